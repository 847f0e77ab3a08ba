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
``zenoh-bridge-ros2dds`` or ``rmw_zenoh``): see service/zenoh/ros2.py, imported only then.

A session is created on the first frame with the default map if no control message made one.
Frames that arrive while the robot's previous frame is still being processed wait in a
one-frame slot: a newer frame replaces the waiting one (counted as dropped), so a robot always
gets the estimate of its newest frame and never a growing backlog. ``localize`` queries share
the slot: a replaced query is answered at once with 429 (a newer frame of the robot came).
At most ``max_sessions`` robots have a frame waiting; beyond, a frame is refused with 503.

Control queries run on their own few worker threads, a robot's in the order they came (at most
``CONTROL_BACKLOG`` waiting per robot; beyond, 503): Zenoh calls each declaration's callback on
one thread fed by a bounded queue, so a control query answered there (a learning robot's delete
or reset waits for its learner; a put waits for the map admin through a whole map write) held
every robot's control queries, and once that queue was full, every frame on the link. ROS 2
initial poses' resets queue to the same workers, after the robot's control queries. Map
queries (service/zenoh/maps.py) have workers of their own for the same reason, not the frame
workers: they wait for the map admin (service/zenoh/workers.py).
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

from service.api.errors import BadRequest, ServiceError
from service.api.models import (
    FrameMeta,
    Odometry,
    PosePrior,
    ResetRequest,
    SessionConfig,
    check_robot_id,
    validated,
)
from service.engine.localization_service import LocalizationService
from service.settings import Settings
from service.zenoh.config import check_security, service_zenoh_config
from service.zenoh.maps import MAP_BACKLOG, MAP_NAMES, MAP_WORKERS, declare_map_queryables
from service.zenoh.replies import (
    answer,
    error_body,
    internal_error,
    parse_json,
    parse_json_object,
)
from service.zenoh.workers import KeyedWorkers

log = logging.getLogger("swarmloc")
__all__ = ["ZenohBridge", "control", "parse_attachment"]
CONTROL_WORKERS = 4  # threads answering control queries (each robot's one at a time)
CONTROL_BACKLOG = 16  # a robot's control queries waiting at once; more are refused (503)


@dataclass
class _Frame:
    data: bytes | np.ndarray  # encoded image, or grayscale pixels (ROS 2 sensor_msgs/Image)
    meta: dict[str, Any]
    content_type: str | None = None
    reply: Callable[[dict[str, Any]], None] | None = None  # also answer here (ROS 2, query)
    publish: bool = True  # publish the answer on {robot}/estimate (not for queries)


def _superseded(robot: str, frame: _Frame) -> dict[str, Any]:
    return error_body(ServiceError("a newer frame of this robot arrived before this one was "
                                   "processed; only the newest waiting frame is localized",
                                   429), robot, _seq_of(frame.meta))


def parse_attachment(raw: bytes | None) -> dict[str, Any]:
    return parse_json_object(raw, "attachment", '{"t": 12.5, "seq": 3}')


def _frame_args(meta: dict[str, Any]
                ) -> tuple[float | None, int | None, PosePrior | None, Odometry | None]:
    m = validated(FrameMeta, meta, "attachment")
    return m.t, m.seq, m.prior, m.odom


def _seq_of(meta: dict[str, Any]) -> int | None:
    """The frame's seq for an error reply, when it is a plain integer."""
    seq = meta.get("seq")
    return seq if isinstance(seq, int) and not isinstance(seq, bool) and \
        -(2**63) <= seq < 2**63 else None


def control(service: LocalizationService, robot: str, body: Any) -> dict[str, Any]:
    """One control message (``{robot}/control``): the same validation and answers as the
    HTTP session routes. Raises ServiceError."""
    check_robot_id(robot)
    if not isinstance(body, dict):
        raise BadRequest("control payload must be a JSON object")
    body = dict(body)
    action = body.pop("action", "put")
    if action == "put":
        config = validated(SessionConfig, body, "request")
        info, _ = service.put_session(robot, config)
        return info.model_dump(mode="json")
    if action == "get":
        return service.session_info(robot).model_dump(mode="json")
    if action == "delete":
        service.delete_session(robot)
        return {"deleted": robot}
    if action == "reset":
        near = validated(ResetRequest, body, "request").near()
        return service.reset_session(robot, near).model_dump(mode="json")
    raise BadRequest(f"unknown action {action!r}; use put, get, reset or delete")


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
        # sessions over heavy_particles get their own quarter of the workers (fairness)
        self._heavy_pool = ThreadPoolExecutor(
            max_workers=max(1, self.settings.frame_workers // 4),
            thread_name_prefix="zenoh-heavy")
        self._slots: dict[str, _Frame] = {}  # the frame waiting per robot
        self._busy: set[str] = set()
        self._lock = threading.Lock()
        unavailable = self.service.metrics.rejected.labels("Unavailable").inc
        # control queries, off Zenoh's callback thread, a robot's in order
        self._controls = KeyedWorkers("zenoh-control", CONTROL_WORKERS, CONTROL_BACKLOG,
                                      self.settings.max_sessions, "control queries",
                                      unavailable)
        # map queries wait for the map admin: neither on a frame worker nor a control worker
        self._maps = KeyedWorkers("zenoh-maps", MAP_WORKERS, MAP_BACKLOG, MAP_NAMES,
                                  "map queries", unavailable)

    # ---- lifecycle ----------------------------------------------------------------------
    def start(self) -> ZenohBridge:
        check_security(self.settings)
        s = zenoh.open(service_zenoh_config(self.settings))
        self._session = s
        p = self.prefix
        self._decls = [
            s.declare_subscriber(f"{p}/*/frame", self._on_frame),
            s.declare_queryable(f"{p}/*/localize", self._on_localize),
            s.declare_queryable(f"{p}/*/control", self._on_control),
            *declare_map_queryables(s, p, self.service, self._maps),  # {p}/@maps, {p}/@jobs
        ]
        if self.settings.ros2_enabled:
            from service.zenoh.ros2 import Ros2Endpoints

            ros2 = Ros2Endpoints(self.settings, self.service, self.submit_frame, self._publish,
                                 self._controls.submit)
            self._decls += ros2.declare(s)
        return self

    def close(self) -> None:
        """Stop taking queries and frames; frames in flight get the shutdown deadline."""
        for d in self._decls:
            d.undeclare()
        self._decls = []
        self.service.begin_shutdown()
        for pool in (self._pool, self._heavy_pool):
            pool.shutdown(wait=False, cancel_futures=True)
        for workers in (self._controls, self._maps):  # queries not started: answered 503
            workers.close()
        if not self.service.wait_idle(self.settings.shutdown_deadline_s):
            log.warning("Zenoh frames still running after the %.1f s shutdown deadline",
                        self.settings.shutdown_deadline_s)
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
        store exactly one serves it: the one holding the robot's claim (service/engine/store.py)."""
        try:
            return self.service.claim(robot)
        except ServiceError:  # the store is down: answer, the frame's error says why
            return True

    def _localize(self, robot: str, frame: _Frame) -> dict[str, Any] | None:
        """The estimate or error body; None when another replica serves the robot."""
        if not self._serves(robot):
            return None
        seq = _seq_of(frame.meta)
        try:
            check_robot_id(robot)
            t, seq, prior, odom = _frame_args(frame.meta)
            est = self.service.process_frame(
                robot, frame.data, content_type=frame.content_type, t=t, prior=prior,
                transport="zenoh", input_seq=seq, create=self.settings.zenoh_creates_sessions,
                odom=odom)
            return est.model_dump(mode="json")
        except ServiceError as exc:
            return error_body(exc, robot, seq)
        except Exception as exc:  # never let one robot's failure reach the others
            return error_body(internal_error(exc), robot, seq)

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
                     reply: Callable[[dict[str, Any]], None] | None = None,
                     publish: bool = True) -> None:
        """Queue a frame in the robot's one-frame slot (newest wins) and process it; a
        replaced frame's ``reply`` is told so (429)."""
        frame = _Frame(data, meta, content_type, reply, publish)
        refused = start = False
        with self._lock:
            replaced = self._slots.get(robot)
            if replaced is None and len(self._slots) >= self.settings.max_sessions:
                refused = True
            else:
                if replaced is not None:
                    self.service.metrics.dropped.inc()  # a newer frame replaces the waiting one
                self._slots[robot] = frame
                start = robot not in self._busy
                self._busy.add(robot)
        if refused:
            self.service.metrics.rejected.labels("Unavailable").inc()
            self._answer(robot, frame, error_body(ServiceError(
                f"{self.settings.max_sessions} robots have a frame waiting; retry later", 503),
                robot, _seq_of(meta)))
            return
        if replaced is not None and replaced.reply is not None and not replaced.publish:
            self._answer(robot, replaced, _superseded(robot, replaced))
        if not start:
            return
        pool = self._heavy_pool if self.service.is_heavy(robot) else self._pool
        try:
            pool.submit(self._drain, robot)
        except RuntimeError:  # shutting down: the pool takes no more work
            with self._lock:
                self._busy.discard(robot)
                waiting = self._slots.pop(robot, None)
            if waiting is not None:
                self._answer(robot, waiting, error_body(
                    ServiceError("the service is shutting down", 503), robot))

    def _answer(self, robot: str, frame: _Frame, body: dict[str, Any]) -> None:
        if frame.publish:
            self._publish(robot, body)
        if frame.reply is not None:
            try:
                frame.reply(body)
            except Exception:  # a failing answer must not stop this robot's frames
                log.exception("the answer to robot %s failed", robot)

    def _drain(self, robot: str) -> None:
        while True:
            with self._lock:
                frame = self._slots.pop(robot, None)
                if frame is None:
                    self._busy.discard(robot)
                    return
            body = self._localize(robot, frame)
            if body is None:  # another replica serves this robot
                if frame.reply is not None and not frame.publish:
                    frame.reply({})  # a query: finish it without an answer
                continue
            self._answer(robot, frame, body)

    # ---- request/response ---------------------------------------------------------------
    def _on_localize(self, query: zenoh.Query) -> None:
        """A frame as a query: it waits in the robot's slot like a published frame (newest
        wins), and is answered with the estimate or an error."""
        robot = self._robot(str(query.key_expr))
        data = query.payload.to_bytes() if query.payload else b""
        att = query.attachment.to_bytes() if query.attachment else None
        try:
            meta = parse_attachment(att)
        except ServiceError as exc:
            if self._serves(robot):
                self.service.metrics.rejected.labels(type(exc).__name__).inc()
                answer(query, error_body(exc, robot))
            else:
                query.drop()
            return

        def reply(body: dict[str, Any]) -> None:
            if body:
                answer(query, body)
            else:  # another replica serves this robot: no reply from here
                query.drop()

        self.submit_frame(robot, data, meta, reply=reply, publish=False)

    def _on_control(self, query: zenoh.Query) -> None:
        """Queue a control query for the control workers (the robot's after its earlier ones)
        and return: Zenoh's callback thread never waits for the service."""
        robot = self._robot(str(query.key_expr))

        def refuse(exc: ServiceError) -> None:
            if self._serves(robot):
                answer(query, error_body(exc, robot))
            else:
                query.drop()

        self._controls.submit(robot, lambda: self._control(robot, query), refuse)

    def _control(self, robot: str, query: zenoh.Query) -> None:
        """Every control query gets an answer: the reply, or an error reply (from the replica
        that serves the robot; the others stay silent)."""
        try:
            if not self._serves(robot):
                query.drop()
                return
            raw = query.payload.to_bytes() if query.payload else b""
            body = parse_json(raw, "control payload") if raw else {"action": "get"}
            reply: dict[str, Any] = control(self.service, robot, body)
        except ServiceError as exc:
            reply = error_body(exc, robot)
        except Exception as exc:  # never leave a query open
            log.exception("control query for robot %s failed", robot)
            reply = error_body(internal_error(exc), robot)
        answer(query, reply)
