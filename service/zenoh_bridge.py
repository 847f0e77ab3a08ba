"""Zenoh transport: key expressions <-> robot sessions (eclipse-zenoh 1.x, same process).

Keys (prefix ``swarmloc`` by default):

- ``{prefix}/{robot}/frame``     robot publishes an encoded PNG/JPEG; the attachment is JSON
                                 ``{"t": seconds, "seq": n, "prior": {"x", "y", "radius"}}``
                                 (all optional). The estimate, or an error, is published on
- ``{prefix}/{robot}/estimate``  as JSON (the HTTP Estimate schema plus robot_id, input_seq;
                                 errors are ``{"error", "status", "robot_id", "input_seq"}``).
- ``{prefix}/{robot}/localize``  queryable: a frame in the query payload (same attachment),
                                 the estimate as the reply, or an error reply (same JSON).
- ``{prefix}/{robot}/control``   queryable: JSON ``{"action": "put", ...SessionConfig}``,
                                 ``{"action": "reset", "x", "y", "radius"}``,
                                 ``{"action": "delete"}`` or ``{"action": "get"}``.

With ``ros2_enabled`` the same session also speaks ROS 2 (CDR messages on the keys of
``zenoh-bridge-ros2dds`` or ``rmw_zenoh``): see service/ros2.py, imported only then.

A session is created on the first frame with the default map if no control message made one.
Frames that arrive while the robot's previous frame is still being processed wait in a
one-frame slot: a newer frame replaces the waiting one (counted as dropped), so a robot always
gets the estimate of its newest frame and never a growing backlog.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh
from pydantic import ValidationError

from service.errors import BadRequest, InvalidParameters, ServiceError
from service.map_zenoh import declare_map_queryables
from service.models import DEFAULT_PRIOR_RADIUS_M, PosePrior, SessionConfig
from service.sessions import LocalizationService
from service.settings import Settings

log = logging.getLogger("swarmloc")


def zenoh_config(settings: Settings) -> zenoh.Config:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(settings.zenoh_mode))
    if settings.zenoh_connect:
        cfg.insert_json5("connect/endpoints", json.dumps(settings.zenoh_connect))
    if settings.zenoh_listen:
        cfg.insert_json5("listen/endpoints", json.dumps(settings.zenoh_listen))
    cfg.insert_json5("scouting/multicast/enabled",
                     json.dumps(settings.zenoh_multicast_scouting))
    return cfg


@dataclass
class _Frame:
    data: bytes | np.ndarray  # encoded image, or grayscale pixels (ROS 2 sensor_msgs/Image)
    meta: dict[str, Any]
    content_type: str | None = None
    reply: Callable[[dict[str, Any]], None] | None = None  # also answer here (ROS 2)


def parse_attachment(raw: bytes | None) -> dict[str, Any]:
    if not raw:
        return {}
    try:
        meta = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise BadRequest("attachment must be JSON like {\"t\": 12.5, \"seq\": 3}") from None
    if not isinstance(meta, dict):
        raise BadRequest("attachment must be a JSON object")
    return meta


def error_body(exc: ServiceError, robot: str, seq: int | None = None) -> dict[str, Any]:
    """The JSON an error is reported with on every Zenoh channel (HTTP's status and message)."""
    return {"error": exc.message, "status": exc.status, "robot_id": robot, "input_seq": seq}


def _frame_args(meta: dict[str, Any]) -> tuple[float | None, int | None, PosePrior | None]:
    try:
        t = float(meta["t"]) if meta.get("t") is not None else None
        seq = int(meta["seq"]) if meta.get("seq") is not None else None
        prior = PosePrior(**meta["prior"]) if meta.get("prior") else None
    except (TypeError, ValueError, ValidationError) as exc:
        raise InvalidParameters(f"bad attachment field: {exc}") from None
    return t, seq, prior


class ZenohBridge:
    """Owns one Zenoh session and the declarations serving ``service``."""

    def __init__(self, service: LocalizationService, settings: Settings | None = None) -> None:
        self.service = service
        self.settings = settings or service.settings
        self.prefix = self.settings.zenoh_prefix.strip("/")
        self._session: zenoh.Session | None = None
        self._decls: list[Any] = []
        self._pool = ThreadPoolExecutor(max_workers=self.settings.frame_workers,
                                        thread_name_prefix="zenoh-frames")
        self._slots: dict[str, _Frame | None] = {}
        self._busy: set[str] = set()
        self._lock = threading.Lock()

    # ---- lifecycle ----------------------------------------------------------------------
    def start(self) -> ZenohBridge:
        s = zenoh.open(zenoh_config(self.settings))
        self._session = s
        p = self.prefix
        self._decls = [
            s.declare_subscriber(f"{p}/*/frame", self._on_frame),
            s.declare_queryable(f"{p}/*/localize", self._on_localize),
            s.declare_queryable(f"{p}/*/control", self._on_control),
            *declare_map_queryables(s, p, self.service, self._pool),  # {p}/@maps, {p}/@jobs
        ]
        if self.settings.ros2_enabled:
            from service.ros2 import Ros2Endpoints

            ros2 = Ros2Endpoints(self.settings, self.service, self.submit_frame, self._publish)
            self._decls += ros2.declare(s)
        return self

    def close(self) -> None:
        for d in self._decls:
            d.undeclare()
        self._decls = []
        self._pool.shutdown(wait=True)
        if self._session is not None:
            self._session.close()
            self._session = None

    async def __aenter__(self) -> ZenohBridge:
        return self.start()

    async def __aexit__(self, *exc: object) -> None:
        self.close()

    # ---- helpers ------------------------------------------------------------------------
    def _robot(self, key: str) -> str:
        parts = str(key).split("/")
        return parts[-2]

    def _publish(self, robot: str, body: dict[str, Any]) -> None:
        if self._session is not None:
            self._session.put(f"{self.prefix}/{robot}/estimate", json.dumps(body).encode(),
                              encoding=zenoh.Encoding.APPLICATION_JSON)

    def _serves(self, robot: str) -> bool:
        """Several replicas on one Zenoh network all hear a robot; with a shared session
        store exactly one serves it: the one holding the robot's claim (service/store.py)."""
        try:
            return self.service.claim(robot)
        except ServiceError:  # the store is down: answer, the frame's error says why
            return True

    def _localize(self, robot: str, frame: _Frame) -> dict[str, Any] | None:
        """The estimate or error body; None when another replica serves the robot."""
        if not self._serves(robot):
            return None
        seq = frame.meta.get("seq")
        try:
            t, seq, prior = _frame_args(frame.meta)
            session = self.service.ensure_session(robot)
            est = self.service.process_frame(
                robot, frame.data, content_type=frame.content_type, t=t, prior=prior,
                transport="zenoh", session=session, input_seq=seq)
            return est.model_dump(mode="json")
        except ServiceError as exc:
            return error_body(exc, robot, seq)
        except Exception as exc:  # never let one robot's failure reach the others
            return error_body(ServiceError(f"internal error: {exc}"), robot, seq)

    # ---- frames (publish/subscribe) -----------------------------------------------------
    def _on_frame(self, sample: zenoh.Sample) -> None:
        robot = self._robot(str(sample.key_expr))
        data = sample.payload.to_bytes()
        try:
            meta = parse_attachment(sample.attachment.to_bytes() if sample.attachment else None)
        except ServiceError as exc:
            if self._serves(robot):
                self.service.metrics.rejected.labels(type(exc).__name__).inc()
                self._publish(robot, error_body(exc, robot))
            return
        self.submit_frame(robot, data, meta)

    def submit_frame(self, robot: str, data: bytes | np.ndarray, meta: dict[str, Any],
                     content_type: str | None = None,
                     reply: Callable[[dict[str, Any]], None] | None = None) -> None:
        """Queue a frame in the robot's one-frame slot (newest wins) and process it."""
        with self._lock:
            if self._slots.get(robot) is not None:
                self.service.metrics.dropped.inc()  # a newer frame replaces the waiting one
            self._slots[robot] = _Frame(data, meta, content_type, reply)
            if robot in self._busy:
                return
            self._busy.add(robot)
        self._pool.submit(self._drain, robot)

    def _drain(self, robot: str) -> None:
        while True:
            with self._lock:
                frame = self._slots.get(robot)
                self._slots[robot] = None
                if frame is None:
                    self._busy.discard(robot)
                    return
            body = self._localize(robot, frame)
            if body is None:  # another replica serves this robot
                continue
            self._publish(robot, body)
            if frame.reply is not None:
                try:
                    frame.reply(body)
                except Exception:  # a failing ROS answer must not stop this robot's frames
                    log.exception("ROS 2 answer for robot %s failed", robot)

    # ---- request/response ---------------------------------------------------------------
    def _on_localize(self, query: zenoh.Query) -> None:
        robot = self._robot(str(query.key_expr))
        data = query.payload.to_bytes() if query.payload else b""
        att = query.attachment.to_bytes() if query.attachment else None

        def work() -> None:
            try:
                meta = parse_attachment(att)
                body = self._localize(robot, _Frame(data, meta))
            except ServiceError as exc:
                body = error_body(exc, robot) if self._serves(robot) else None
            if body is None:  # another replica serves this robot: no reply from here
                query.drop()
                return
            payload = json.dumps(body).encode()
            if "error" in body:
                query.reply_err(payload, encoding=zenoh.Encoding.APPLICATION_JSON)
            else:
                query.reply(query.key_expr, payload, encoding=zenoh.Encoding.APPLICATION_JSON)
            query.drop()

        self._pool.submit(work)

    def _on_control(self, query: zenoh.Query) -> None:
        robot = self._robot(str(query.key_expr))
        if not self._serves(robot):
            query.drop()
            return
        try:
            body = json.loads(query.payload.to_bytes()) if query.payload else {"action": "get"}
            if not isinstance(body, dict):
                raise BadRequest("control payload must be a JSON object")
            action = body.pop("action", "put")
            if action == "put":
                try:
                    config = SessionConfig(**body)
                except ValidationError as exc:
                    raise InvalidParameters(f"invalid session config: {exc}") from None
                info, _ = self.service.put_session(robot, config)
                reply: dict[str, Any] = info.model_dump(mode="json")
            elif action == "get":
                reply = self.service.session(robot).info().model_dump(mode="json")
            elif action == "delete":
                self.service.delete_session(robot)
                reply = {"deleted": robot}
            elif action == "reset":
                near = None
                if body.get("x") is not None and body.get("y") is not None:
                    near = PosePrior(x=body["x"], y=body["y"],
                                     radius=body.get("radius") or DEFAULT_PRIOR_RADIUS_M)
                reply = self.service.reset_session(robot, near).model_dump(mode="json")
            else:
                raise BadRequest(f"unknown action '{action}'; use put, get, reset or delete")
            query.reply(query.key_expr, json.dumps(reply).encode(),
                        encoding=zenoh.Encoding.APPLICATION_JSON)
        except (ServiceError, json.JSONDecodeError, UnicodeDecodeError, ValidationError) as exc:
            err = exc if isinstance(exc, ServiceError) else BadRequest(
                f"bad control message: {exc}")
            query.reply_err(json.dumps(error_body(err, robot)).encode(),
                            encoding=zenoh.Encoding.APPLICATION_JSON)
