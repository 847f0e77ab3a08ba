"""One client interface, three transports: HTTP (sync and async, httpx), Zenoh, in-process.

Every transport returns the service's own pydantic schemas (``Estimate``, ``SessionInfo``,
``MapSummary``) and raises ``SwarmlocError`` carrying the service's status and message.
Frames are sent as encoded PNG/JPEG bytes (a NumPy image is PNG-encoded first, losslessly),
so every transport runs the very same decoding and localizer code.

Retries: connection failures are retried (the request never reached the service, so that is
safe for every call); a frame that reached the service is never sent twice, because a second
copy would advance the robot's estimator a second time.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Protocol

import httpx
import numpy as np

from service.api.models import (
    DEFAULT_FEATURES,
    Estimate,
    JobInfo,
    MapDeleted,
    MapDetail,
    MapSummary,
    Odometry,
    PosePrior,
    SessionConfig,
    SessionInfo,
)


class SwarmlocError(Exception):
    """The service refused a call (status as in HTTP) or could not be reached (status 0)."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(f"[{status}] {message}")
        self.status = status
        self.message = message


def _frame_bytes(image: np.ndarray | bytes) -> bytes:
    if isinstance(image, bytes | bytearray | memoryview):
        return bytes(image)
    from service.vision.imaging import encode_png

    return encode_png(np.asarray(image))


def _config(map_name: str | None, estimator: str | None, params: dict | None, seed: int,
            initial_pose: PosePrior | None, learn: bool = False,
            condition: str | None = None) -> SessionConfig:
    return SessionConfig.model_validate({"map": map_name, "estimator": estimator,
                                         "params": params or {}, "seed": seed,
                                         "initial_pose": initial_pose, "learn": learn,
                                         "condition": condition})


class Client(Protocol):
    """What every transport offers (and all that ``swarmloc replay`` uses)."""

    def maps(self) -> list[MapSummary]: ...

    def map_detail(self, name: str) -> MapDetail: ...

    def create_session(self, robot_id: str, map_name: str | None = None,
                       estimator: str | None = None, params: dict | None = None,
                       seed: int = 0, initial_pose: PosePrior | None = None,
                       learn: bool = False, condition: str | None = None) -> SessionInfo:
        """``learn``: the session's confident frames teach the map an experience tagged with
        ``condition`` (the light, e.g. 'cloudy')."""

    def session(self, robot_id: str) -> SessionInfo: ...

    def delete_session(self, robot_id: str) -> None: ...

    def reset(self, robot_id: str, near: PosePrior | None = None) -> SessionInfo: ...

    def localize(self, robot_id: str, image: np.ndarray | bytes, t: float | None = None,
                 seq: int | None = None, prior: PosePrior | None = None,
                 odom: Odometry | None = None) -> Estimate: ...

    def close(self) -> None: ...


# ---- HTTP --------------------------------------------------------------------------------
def _raise_for(resp: httpx.Response) -> None:
    if resp.status_code < 400:
        return
    try:
        message = resp.json().get("error", resp.text)
    except ValueError:
        message = resp.text
    raise SwarmlocError(resp.status_code, message)


def _conditions(if_match: str | None, if_none_match: str | None) -> dict[str, str]:
    h = {"If-Match": if_match, "If-None-Match": if_none_match}
    return {k: v if v == "*" else f'"{v.strip(chr(34))}"' for k, v in h.items() if v}


def _frame_params(t: float | None, seq: int | None, prior: PosePrior | None,
                  odom: Odometry | None = None) -> dict:
    q: dict[str, Any] = {}
    if t is not None:
        q["t"] = t
    if seq is not None:
        q["seq"] = seq
    if prior is not None:
        q.update(prior_x=prior.x, prior_y=prior.y, prior_radius=prior.radius)
    if odom is not None:
        q.update(odom_x=odom.x, odom_y=odom.y, odom_yaw=odom.yaw)
        if odom.var_xy is not None:
            q["odom_var_xy"] = odom.var_xy
        if odom.var_yaw is not None:
            q["odom_var_yaw"] = odom.var_yaw
    return q


class HttpClient:
    """Synchronous HTTP client (httpx)."""

    def __init__(self, base_url: str, token: str | None = None, timeout: float = 30.0,
                 retries: int = 2) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(base_url=base_url, headers=headers, timeout=timeout,
                                  transport=httpx.HTTPTransport(retries=retries))

    def _call(self, method: str, url: str, **kw: Any) -> httpx.Response:
        try:
            resp = self._http.request(method, url, **kw)
        except httpx.HTTPError as exc:
            raise SwarmlocError(0, f"cannot reach the service: {exc}") from None
        _raise_for(resp)
        return resp

    def maps(self) -> list[MapSummary]:
        return [MapSummary(**m) for m in self._call("GET", "/maps").json()]

    def map_detail(self, name: str) -> MapDetail:
        return MapDetail(**self._call("GET", f"/maps/{name}").json())

    def create_session(self, robot_id: str, map_name: str | None = None,
                       estimator: str | None = None, params: dict | None = None,
                       seed: int = 0, initial_pose: PosePrior | None = None,
                       learn: bool = False, condition: str | None = None) -> SessionInfo:
        cfg = _config(map_name, estimator, params, seed, initial_pose, learn, condition)
        resp = self._call("PUT", f"/sessions/{robot_id}", json=cfg.model_dump(mode="json"))
        return SessionInfo(**resp.json())

    def session(self, robot_id: str) -> SessionInfo:
        return SessionInfo(**self._call("GET", f"/sessions/{robot_id}").json())

    def delete_session(self, robot_id: str) -> None:
        self._call("DELETE", f"/sessions/{robot_id}")

    def reset(self, robot_id: str, near: PosePrior | None = None) -> SessionInfo:
        body = near.model_dump() if near else None
        return SessionInfo(**self._call("POST", f"/sessions/{robot_id}/reset", json=body).json())

    def localize(self, robot_id: str, image: np.ndarray | bytes, t: float | None = None,
                 seq: int | None = None, prior: PosePrior | None = None,
                 odom: Odometry | None = None) -> Estimate:
        data = _frame_bytes(image)
        ctype = "image/jpeg" if data[:2] == b"\xff\xd8" else "image/png"
        resp = self._call("POST", f"/sessions/{robot_id}/frames", content=data,
                          params=_frame_params(t, seq, prior, odom),
                          headers={"Content-Type": ctype})
        return Estimate(**resp.json())

    # ---- map lifecycle (PUT/DELETE /maps/NAME, POST /maps/NAME/build, GET /jobs/ID) ------
    def push_map(self, path: str | Path, name: str, if_match: str | None = None,
                 if_none_match: str | None = None) -> tuple[MapSummary, bool]:
        """Upload a .swmap file (streamed); True when the map is new. The map's version
        (``checksum``) is its ETag: pass it as ``if_match`` to replace only that version."""
        headers = {"Content-Type": "application/octet-stream",
                   **_conditions(if_match, if_none_match)}
        with Path(path).open("rb") as fh:
            resp = self._call("PUT", f"/maps/{name}", content=fh, headers=headers)
        return MapSummary(**resp.json()), resp.status_code == 201

    def pull_map(self, name: str, out: str | Path) -> Path:
        """Download the map's current .swmap into ``out`` (a file or a folder), atomically."""
        out = Path(out)
        out = out / f"{name}.swmap" if out.is_dir() else out
        tmp = out.with_name(f".{out.name}.part")
        try:
            with self._http.stream("GET", f"/maps/{name}/file") as resp:
                if resp.status_code >= 400:
                    resp.read()
                    _raise_for(resp)
                with tmp.open("wb") as fh:
                    for chunk in resp.iter_bytes(1 << 20):
                        fh.write(chunk)
                    fh.flush()
                    os.fsync(fh.fileno())
            os.replace(tmp, out)
        except httpx.HTTPError as exc:
            raise SwarmlocError(0, f"cannot reach the service: {exc}") from None
        finally:
            tmp.unlink(missing_ok=True)
        return out

    def delete_map(self, name: str, force: bool = False, if_match: str | None = None
                   ) -> MapDeleted:
        resp = self._call("DELETE", f"/maps/{name}", params={"force": force} if force else None,
                          headers=_conditions(if_match, None))
        return MapDeleted(**resp.json())

    def delete_experience(self, name: str, exp_id: str, if_match: str | None = None
                          ) -> MapSummary:
        """Remove one experience the fleet taught map ``name`` (a new map version)."""
        resp = self._call("DELETE", f"/maps/{name}/experiences/{exp_id}",
                          headers=_conditions(if_match, None))
        return MapSummary(**resp.json())

    def build_map_remote(self, name: str, archive: str | Path | bytes,
                         if_none_match: str | None = None,
                         features: str = DEFAULT_FEATURES,
                         max_features: int | None = None, width: int = 320,
                         height: int = 240) -> JobInfo:
        """Post a zip/tar(.gz) of a round; the service builds the map (of feature type
        ``features`` at the working size ``width`` x ``height``, SIFT keeping
        ``max_features`` per image; None: the default) as a job."""
        headers = {"Content-Type": "application/octet-stream",
                   **_conditions(None, if_none_match)}
        url = f"/maps/{name}/build"
        params = {"features": features, "width": str(width), "height": str(height)}
        if max_features is not None:
            params["max_features"] = str(max_features)
        if isinstance(archive, bytes):
            resp = self._call("POST", url, content=archive, headers=headers, params=params)
        else:
            with Path(archive).open("rb") as fh:
                resp = self._call("POST", url, content=fh, headers=headers, params=params)
        return JobInfo(**resp.json())

    def job(self, job_id: str) -> JobInfo:
        return JobInfo(**self._call("GET", f"/jobs/{job_id}").json())

    def jobs(self) -> list[JobInfo]:
        return [JobInfo(**j) for j in self._call("GET", "/jobs").json()]

    def close(self) -> None:
        self._http.close()


class AsyncHttpClient:
    """Asynchronous HTTP client (httpx), the same calls as ``HttpClient``."""

    def __init__(self, base_url: str, token: str | None = None, timeout: float = 30.0,
                 retries: int = 2) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.AsyncClient(base_url=base_url, headers=headers, timeout=timeout,
                                       transport=httpx.AsyncHTTPTransport(retries=retries))

    async def _call(self, method: str, url: str, **kw: Any) -> httpx.Response:
        try:
            resp = await self._http.request(method, url, **kw)
        except httpx.HTTPError as exc:
            raise SwarmlocError(0, f"cannot reach the service: {exc}") from None
        _raise_for(resp)
        return resp

    async def maps(self) -> list[MapSummary]:
        return [MapSummary(**m) for m in (await self._call("GET", "/maps")).json()]

    async def create_session(self, robot_id: str, map_name: str | None = None,
                             estimator: str | None = None, params: dict | None = None,
                             seed: int = 0, initial_pose: PosePrior | None = None,
                             learn: bool = False, condition: str | None = None
                             ) -> SessionInfo:
        cfg = _config(map_name, estimator, params, seed, initial_pose, learn, condition)
        resp = await self._call("PUT", f"/sessions/{robot_id}", json=cfg.model_dump(mode="json"))
        return SessionInfo(**resp.json())

    async def session(self, robot_id: str) -> SessionInfo:
        return SessionInfo(**(await self._call("GET", f"/sessions/{robot_id}")).json())

    async def delete_session(self, robot_id: str) -> None:
        await self._call("DELETE", f"/sessions/{robot_id}")

    async def reset(self, robot_id: str, near: PosePrior | None = None) -> SessionInfo:
        body = near.model_dump() if near else None
        resp = await self._call("POST", f"/sessions/{robot_id}/reset", json=body)
        return SessionInfo(**resp.json())

    async def localize(self, robot_id: str, image: np.ndarray | bytes, t: float | None = None,
                       seq: int | None = None, prior: PosePrior | None = None,
                 odom: Odometry | None = None) -> Estimate:
        data = _frame_bytes(image)
        ctype = "image/jpeg" if data[:2] == b"\xff\xd8" else "image/png"
        resp = await self._call("POST", f"/sessions/{robot_id}/frames", content=data,
                                params=_frame_params(t, seq, prior, odom),
                                headers={"Content-Type": ctype})
        return Estimate(**resp.json())

    async def close(self) -> None:
        await self._http.aclose()


# ---- Zenoh -------------------------------------------------------------------------------
class ZenohClient:
    """Request/response over the service's Zenoh queryables (``{prefix}/{robot}/...``)."""

    def __init__(self, connect: list[str] | None = None, prefix: str = "swarmloc",
                 timeout: float = 30.0, mode: str = "client",
                 config_file: str | Path | None = None) -> None:
        """``config_file``: a Zenoh JSON5 config (TLS/mTLS certificates, user/password) that
        ``connect`` and ``mode`` are applied on top of."""
        import zenoh

        from service.zenoh.config import zenoh_config

        cfg = zenoh_config(config_file=config_file, mode=mode, connect=connect,
                           multicast_scouting=None if config_file else not connect)
        self._z = zenoh.open(cfg)
        self.prefix = prefix.strip("/")
        self.timeout = timeout

    def _query(self, key: str, payload: bytes, attachment: bytes | None = None) -> Any:
        replies = self._z.get(f"{self.prefix}/{key}", payload=payload, attachment=attachment,
                              timeout=self.timeout)
        for reply in replies:
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
            err = reply.err
            body = json.loads(err.payload.to_bytes()) if err is not None else {}
            raise SwarmlocError(int(body.get("status", 500)), body.get("error", "error"))
        raise SwarmlocError(0, f"no reply on {self.prefix}/{key} within {self.timeout} s: "
                               "is the service running and reachable over Zenoh?")

    def _control(self, robot_id: str, body: dict) -> dict:
        return self._query(f"{robot_id}/control", json.dumps(body).encode())

    def maps(self) -> list[MapSummary]:
        raise SwarmlocError(501, "map listing is served over HTTP (GET /maps)")

    def create_session(self, robot_id: str, map_name: str | None = None,
                       estimator: str | None = None, params: dict | None = None,
                       seed: int = 0, initial_pose: PosePrior | None = None,
                       learn: bool = False, condition: str | None = None) -> SessionInfo:
        cfg = _config(map_name, estimator, params, seed, initial_pose, learn, condition)
        return SessionInfo(**self._control(robot_id, {"action": "put",
                                                      **cfg.model_dump(mode="json")}))

    def session(self, robot_id: str) -> SessionInfo:
        return SessionInfo(**self._control(robot_id, {"action": "get"}))

    def delete_session(self, robot_id: str) -> None:
        self._control(robot_id, {"action": "delete"})

    def reset(self, robot_id: str, near: PosePrior | None = None) -> SessionInfo:
        body: dict[str, Any] = {"action": "reset"}
        if near:
            body.update(near.model_dump())
        return SessionInfo(**self._control(robot_id, body))

    def localize(self, robot_id: str, image: np.ndarray | bytes, t: float | None = None,
                 seq: int | None = None, prior: PosePrior | None = None,
                 odom: Odometry | None = None) -> Estimate:
        meta: dict[str, Any] = {"t": t, "seq": seq}
        if prior is not None:
            meta["prior"] = prior.model_dump()
        if odom is not None:
            meta["odom"] = odom.model_dump(exclude_none=True)
        body = self._query(f"{robot_id}/localize", _frame_bytes(image), json.dumps(meta).encode())
        return Estimate(**body)

    # ---- map lifecycle ({prefix}/@maps/NAME, {prefix}/@jobs/ID) ------------------------
    def _maps(self, name: str, payload: bytes = b"", **opts: Any) -> Any:
        att = json.dumps({k: v for k, v in opts.items() if v is not None}).encode()
        return self._query(f"@maps/{name}", payload, att)

    def map_detail(self, name: str) -> MapDetail:
        raise SwarmlocError(501, "map detail (image positions) is served over HTTP only")

    def map_info(self, name: str) -> MapSummary:
        return MapSummary(**self._maps(name, action="get"))

    def push_map(self, path: str | Path, name: str, if_match: str | None = None,
                 if_none_match: str | None = None) -> tuple[MapSummary, bool]:
        body = self._maps(name, Path(path).read_bytes(), action="put", if_match=if_match,
                          if_none_match=if_none_match)
        created = body.pop("created")
        return MapSummary(**body), created

    def delete_map(self, name: str, force: bool = False, if_match: str | None = None
                   ) -> MapDeleted:
        return MapDeleted(**self._maps(name, action="delete", force=force, if_match=if_match))

    def build_map_remote(self, name: str, archive: str | Path | bytes,
                         if_none_match: str | None = None,
                         features: str = DEFAULT_FEATURES,
                         max_features: int | None = None, width: int = 320,
                         height: int = 240) -> JobInfo:
        data = archive if isinstance(archive, bytes) else Path(archive).read_bytes()
        return JobInfo(**self._maps(name, data, action="build", if_none_match=if_none_match,
                                    features=features, max_features=max_features,
                                    width=width, height=height))

    def job(self, job_id: str) -> JobInfo:
        return JobInfo(**self._query(f"@jobs/{job_id}", b""))

    def close(self) -> None:
        self._z.close()


# ---- in process --------------------------------------------------------------------------
class LocalClient:
    """No network: the service engine in this process (same decoding and localizer code).
    ``close()`` closes the engine it started (not one passed in): its background threads stop
    and what learning sessions collected is written, before the process exits."""

    def __init__(self, maps_dir: str | Path | None = None, service: Any = None) -> None:
        from service.engine.localization_service import LocalizationService
        from service.settings import Settings

        self._owns = service is None
        if service is None:
            # in memory: an in-process client is one run's; it must not take the maps
            # directory's session file from a `swarmloc serve` on the same maps
            settings = Settings(maps_dir=Path(maps_dir or "maps"), zenoh_enabled=False,
                                session_store="memory")
            service = LocalizationService(settings)
        self.service = service

    def _wrap(self, fn: Any, *args: Any) -> Any:
        from service.api.errors import ServiceError

        try:
            return fn(*args)
        except ServiceError as exc:
            raise SwarmlocError(exc.status, exc.message) from None

    def maps(self) -> list[MapSummary]:
        return [self.service.map_summary(n) for n in sorted(self.service.maps)]

    def map_detail(self, name: str) -> MapDetail:
        return self._wrap(self.service.map_detail, name)

    def create_session(self, robot_id: str, map_name: str | None = None,
                       estimator: str | None = None, params: dict | None = None,
                       seed: int = 0, initial_pose: PosePrior | None = None,
                       learn: bool = False, condition: str | None = None) -> SessionInfo:
        cfg = _config(map_name, estimator, params, seed, initial_pose, learn, condition)
        return self._wrap(self.service.put_session, robot_id, cfg)[0]

    def session(self, robot_id: str) -> SessionInfo:
        return self._wrap(lambda: self.service.session_info(robot_id))

    def delete_session(self, robot_id: str) -> None:
        self._wrap(self.service.delete_session, robot_id)
        self.service.writer.wait()  # one run's service: what it learned is in the map now

    def reset(self, robot_id: str, near: PosePrior | None = None) -> SessionInfo:
        return self._wrap(self.service.reset_session, robot_id, near)

    def localize(self, robot_id: str, image: np.ndarray | bytes, t: float | None = None,
                 seq: int | None = None, prior: PosePrior | None = None,
                 odom: Odometry | None = None) -> Estimate:
        data = _frame_bytes(image)
        return self._wrap(lambda: self.service.process_frame(
            robot_id, data, t=t, prior=prior, transport="local", input_seq=seq, odom=odom))

    def close(self) -> None:
        if self._owns:
            self._owns = False  # once
            self.service.close()


def connect(via: str, token: str | None = None, maps_dir: str | Path | None = None,
            prefix: str = "swarmloc") -> Client:
    """``http://HOST:PORT`` | ``zenoh`` | ``zenoh:tcp/HOST:7447`` | ``local`` | ``local:DIR``."""
    if via.startswith(("http://", "https://")):
        return HttpClient(via, token)
    if via == "zenoh" or via.startswith("zenoh:"):
        endpoint = via.partition(":")[2]
        return ZenohClient([endpoint] if endpoint else None, prefix)
    if via == "local" or via.startswith("local:"):
        return LocalClient(via.partition(":")[2] or maps_dir)
    raise ValueError(f"unknown transport '{via}': use http://HOST:PORT, zenoh[:ENDPOINT] "
                     "or local[:MAPS_DIR]")
