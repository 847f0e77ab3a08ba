"""HTTP API (FastAPI): thin routes over ``LocalizationService``; schemas from models.py."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import uuid
import weakref
from collections.abc import AsyncIterator
from typing import Annotated
from urllib.parse import urlencode

import anyio
from fastapi import APIRouter, Depends, FastAPI, Path, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service import __version__
from service.api.errors import PayloadTooLarge, ServiceError, Unavailable, describe_errors
from service.api.models import (
    MAX_PRIOR_RADIUS_M,
    ROBOT_ID_MAX_LENGTH,
    ROBOT_ID_PATTERN,
    ErrorBody,
    Estimate,
    MapDetail,
    MapSummary,
    ResetRequest,
    SessionConfig,
    SessionInfo,
    odometry,
    pose_prior,
)
from service.engine.localization_service import LocalizationService
from service.engine.metrics import PROMETHEUS_TEXT
from service.http.auth import require_token, require_token_or_query
from service.http.deps import ServiceDep
from service.http.events import events_router
from service.http.maps import map_router
from service.http.openapi import API_ERRORS, binary_body, operation_id
from service.http.viewer import add_viewer

log = logging.getLogger("swarmloc")
RobotId = Annotated[str, Path(pattern=ROBOT_ID_PATTERN, max_length=ROBOT_ID_MAX_LENGTH,
                             description=f"1-{ROBOT_ID_MAX_LENGTH} ASCII letters, digits, '-', "
                             "'_' or '.', not dots only")]
# OpenAPI links: what a client (and the stateful fuzzer) can do with a session it created
_SESSION_LINKS = {
    name: {"operationRef": f"#/paths/~1sessions~1{{robot_id}}{path}/{method}",
           "parameters": {"robot_id": "$request.path.robot_id"}}
    for name, path, method in (("GetSession", "", "get"), ("SendFrame", "~1frames", "post"),
                               ("ResetSession", "~1reset", "post"),
                               ("DeleteSession", "", "delete"))}
FRAME_TYPES = ("image/png", "image/jpeg", "application/octet-stream")


def create_app(service: LocalizationService, *, expire_every_s: float | None = None,
               lifespan_hooks: list | None = None) -> FastAPI:
    """The FastAPI application for one service instance.

    ``lifespan_hooks`` are async context managers entered at start-up (the Zenoh bridge).
    Every route but the probes depends on the bearer token check (``/openapi.json`` and
    ``/docs`` included), and every error answers ``{"error": ...}``.
    """
    settings = service.settings

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        async with contextlib.AsyncExitStack() as stack:
            for hook in lifespan_hooks or []:
                await stack.enter_async_context(hook)
            period = expire_every_s or max(1.0, min(30.0, settings.session_idle_s / 4))
            sweeps: list[asyncio.Future[list[str]]] = []
            task = asyncio.create_task(_expire_loop(service, period, sweeps))
            try:
                yield
            finally:
                task.cancel()
                for sweep in sweeps:  # a sweep in flight ends before the service closes
                    with contextlib.suppress(Exception):
                        await sweep

    app = FastAPI(title="swarmloc", version=__version__, lifespan=lifespan,
                  openapi_url=None, docs_url=None, redoc_url=None,
                  generate_unique_id_function=operation_id,
                  description="Visual localization of robots against SIFT route maps with "
                              "Dynamic Particle Swarm Optimization (Kronfeld, Weiss, Zell).")
    app.state.service = service
    app.state.frame_workers = FrameWorkers(settings.frame_workers)
    add_error_handlers(app, service)
    app.add_middleware(InternalErrors)
    app.include_router(health_router)
    app.include_router(docs_router)
    app.include_router(events_router)
    add_viewer(app)
    app.include_router(api_router)
    app.include_router(map_router)  # upload, build, replace, delete, jobs
    return app


class FrameWorkers:
    """The threads that localize frames. One frame of a robot at a time holds a worker (the
    others wait without one); sessions over ``heavy_particles`` share a quarter of the
    workers, so they cannot take the light robots' threads (fair scheduling)."""

    def __init__(self, workers: int) -> None:
        self.light = anyio.CapacityLimiter(workers)
        self.heavy = anyio.CapacityLimiter(max(1, workers // 4))
        self._gates: weakref.WeakValueDictionary[str, asyncio.Lock] = \
            weakref.WeakValueDictionary()

    def gate(self, robot_id: str) -> asyncio.Lock:
        lock = self._gates.get(robot_id)
        if lock is None:
            lock = self._gates[robot_id] = asyncio.Lock()
        return lock


def get_frame_workers(request: Request) -> FrameWorkers:
    return request.app.state.frame_workers


FrameWorkersDep = Annotated[FrameWorkers, Depends(get_frame_workers)]


def add_error_handlers(app: FastAPI, service: LocalizationService) -> None:
    """``{"error": "what to fix"}`` for every error: the service's, validation, and the
    framework's own 400/404/405."""

    @app.exception_handler(ServiceError)
    async def service_error(_: Request, exc: ServiceError) -> JSONResponse:
        headers = {"WWW-Authenticate": "Bearer"} if exc.status == 401 else None
        return JSONResponse({"error": exc.message}, exc.status, headers=headers)

    @app.exception_handler(ClientDisconnect)
    async def client_gone(request: Request, _: ClientDisconnect) -> Response:
        """A client that hung up mid-request (an upload cut off): one warning line; nobody
        is left to read an answer."""
        service.metrics.rejected.labels("ClientDisconnect").inc()
        client = request.client.host if request.client else "a client"
        log.warning("%s disconnected during %s %s; the request was dropped", client,
                    request.method, request.url.path)
        return Response(status_code=400)

    @app.exception_handler(RequestValidationError)
    async def validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
        service.metrics.rejected.labels("invalid_request").inc()
        return JSONResponse({"error": "invalid request: " + describe_errors(exc.errors()),
                             "detail": jsonable_errors(exc)}, 422)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        message = str(exc.detail)
        if exc.status_code == 404 and message == "Not Found":
            message = f"no such route: {request.url.path} (the API is listed at /docs)"
        elif exc.status_code == 405:
            message = f"method {request.method} is not allowed on {request.url.path}"
        elif exc.status_code == 400:
            message = f"the request body could not be read: {message}"
        return JSONResponse({"error": message}, exc.status_code,
                            headers=getattr(exc, "headers", None))


class InternalErrors:
    """The last resort: an exception no handler answered (a defect) is logged once, with its
    traceback and an error id, and answered 500 ``{"error": ...}`` with that id, never the
    traceback. Starlette's own last handler would answer plain text and let uvicorn log the
    traceback again. A response already under way (a stream) cannot be replaced: its
    exception goes on to uvicorn, which logs it and closes the connection."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def sending(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, receive, sending)
        except Exception:
            if started:
                raise
            ref = uuid.uuid4().hex[:12]
            log.exception("internal error %s in %s %s", ref, scope.get("method"),
                          scope.get("path"))
            await JSONResponse({"error": f"internal error; see the service log (error {ref})"},
                               500)(scope, receive, send)


# ---- the probes: always open ------------------------------------------------------------
health_router = APIRouter(tags=["health"])


@health_router.get("/healthz")
async def healthz() -> dict:
    """Liveness: the process answers."""
    return {"status": "ok", "version": __version__}


@health_router.get("/readyz", responses={503: {"model": ErrorBody,
                                               "description": "no maps, or shutting down"}})
async def readyz(service: ServiceDep) -> JSONResponse:
    """Readiness: maps are loaded and the service is not shutting down."""
    if service.draining:
        return JSONResponse({"error": "shutting down"}, 503)
    if service.ready:
        return JSONResponse({"status": "ready", "maps": sorted(service.maps)})
    return JSONResponse({"error": f"no maps loaded from {service.settings.maps_dir}",
                         "detail": service.load_errors}, 503)


# ---- /openapi.json and /docs: behind the token (header, or ?token= so that a browser can
# open the page; the page passes it on to the schema) ----------------------------------
docs_router = APIRouter(dependencies=[Depends(require_token_or_query)], include_in_schema=False)


@docs_router.get("/openapi.json")
async def openapi(request: Request) -> JSONResponse:
    return JSONResponse(request.app.openapi())


@docs_router.get("/docs")
async def docs(request: Request) -> HTMLResponse:
    token = request.query_params.get("token")
    url = "/openapi.json" + (f"?{urlencode({'token': token})}" if token else "")
    return get_swagger_ui_html(openapi_url=url, title="swarmloc API")


# ---- metrics, maps and sessions -----------------------------------------------------------
api_router = APIRouter(dependencies=[Depends(require_token)], responses=API_ERRORS)


@api_router.get("/metrics", tags=["health"], response_class=Response,  # errors: JSON
                responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                                 "description": "Prometheus text format 0.0.4"}})
async def get_metrics(service: ServiceDep) -> Response:
    """Prometheus text format, without ``*_created`` samples."""
    return Response(service.metrics.render(), media_type=PROMETHEUS_TEXT)


@api_router.head("/metrics", include_in_schema=False)
async def head_metrics(service: ServiceDep) -> Response:
    """The headers of ``GET /metrics`` (uvicorn sends no body for HEAD)."""
    return await get_metrics(service)


@api_router.get("/maps", tags=["maps"])
async def list_maps(service: ServiceDep) -> list[MapSummary]:
    """The maps served, by name (with replicas on one maps directory: those any of them
    uploaded, built or learned, less those deleted)."""
    # the map admin's lock, which a map write holds throughout: off the event loop
    return await anyio.to_thread.run_sync(service.map_summaries)


@api_router.get("/maps/{name}", tags=["maps"])
async def get_map(name: str, response: Response, service: ServiceDep) -> MapDetail:
    """One map: its images' positions and names, its version as the ETag."""
    detail = await anyio.to_thread.run_sync(service.map_detail, name)  # as list_maps
    response.headers["ETag"] = f'"{detail.checksum}"'
    return detail


@api_router.put("/sessions/{robot_id}", tags=["sessions"],
                responses={201: {"model": SessionInfo, "links": _SESSION_LINKS,
                                 "description": "created"},
                           200: {"links": _SESSION_LINKS, "description": "replaced"}})
async def create_session(robot_id: RobotId, config: SessionConfig, response: Response,
                         service: ServiceDep) -> SessionInfo:
    """Create (201) or replace (200) the session of a robot."""
    # the map admin's lock, and a replaced learning session's gates: off the event loop
    info, created = await anyio.to_thread.run_sync(service.put_session, robot_id, config)
    response.status_code = 201 if created else 200
    return info


@api_router.get("/sessions", tags=["sessions"])
async def list_sessions(service: ServiceDep) -> list[SessionInfo]:
    """Every open session."""
    return service.sessions()


@api_router.get("/sessions/{robot_id}", tags=["sessions"])
async def get_session(robot_id: RobotId, service: ServiceDep) -> SessionInfo:
    """One session, with its last estimate."""
    # a learning session's progress waits (briefly) for its gates: off the event loop
    return await anyio.to_thread.run_sync(service.session_info, robot_id)


@api_router.delete("/sessions/{robot_id}", tags=["sessions"], status_code=204)
async def delete_session(robot_id: RobotId, service: ServiceDep) -> Response:
    """End a session."""
    # a learning session's end waits for its gates: off the event loop
    await anyio.to_thread.run_sync(service.delete_session, robot_id)
    return Response(status_code=204)


@api_router.post("/sessions/{robot_id}/reset", tags=["sessions"])
async def reset_session(robot_id: RobotId, service: ServiceDep,
                        body: ResetRequest | None = None) -> SessionInfo:
    """Re-initialise the swarm: globally (no body) or near a pose."""
    near = body.near() if body is not None else None
    # the robot's frame in progress, and a learning session's gates: off the event loop
    return await anyio.to_thread.run_sync(service.reset_session, robot_id, near)


@api_router.post("/sessions/{robot_id}/frames", tags=["frames"], response_model=Estimate,
                 openapi_extra=binary_body(FRAME_TYPES, "a camera frame: PNG or JPEG "
                                           "(application/octet-stream: sniffed)"))
async def send_frame(
    robot_id: RobotId,
    request: Request,
    service: ServiceDep,
    workers: FrameWorkersDep,
    t: Annotated[float | None, Query(description="frame timestamp, s")] = None,
    seq: Annotated[int | None, Query(description="robot's frame sequence number",
                                     ge=-(2**63), lt=2**63)] = None,
    prior_x: Annotated[float | None, Query(description="pose prior, m east")] = None,
    prior_y: Annotated[float | None, Query(description="pose prior, m north")] = None,
    prior_radius: Annotated[float | None, Query(
        gt=0, le=MAX_PRIOR_RADIUS_M, description="prior radius, m")] = None,
    odom_x: Annotated[float | None, Query(description="odometry pose (odom->base_link), m; "
                                          "with odom_y and odom_yaw")] = None,
    odom_y: Annotated[float | None, Query(description="odometry pose, m")] = None,
    odom_yaw: Annotated[float | None, Query(description="odometry pose, rad")] = None,
    odom_var_xy: Annotated[float | None, Query(description="odometry position variance per "
                                               "metre travelled, m^2/m")] = None,
    odom_var_yaw: Annotated[float | None, Query(description="odometry heading variance per "
                                                "metre travelled, rad^2/m")] = None,
) -> Response:
    """Localize one frame of the robot's camera: the estimate. With odometry (the robot's
    pose in its odom frame), the estimate moves with the robot between frames."""
    if service.draining:
        raise Unavailable("the service is shutting down; retry after the restart")
    session = service.session(robot_id)
    prior = pose_prior(prior_x, prior_y, prior_radius)
    odom = odometry(odom_x, odom_y, odom_yaw, odom_var_xy, odom_var_yaw)
    body = await _read_body(request, service.settings.max_body_bytes, service)
    async with workers.gate(robot_id):
        lim = workers.heavy if service.is_heavy(robot_id) else workers.light
        return await anyio.to_thread.run_sync(
            lambda: Response(estimate_json(service.process_frame(
                robot_id, body, content_type=request.headers.get("content-type"), t=t,
                prior=prior, transport="http", session=session, input_seq=seq, odom=odom)),
                media_type="application/json"),
            limiter=lim)


def estimate_json(est: Estimate) -> bytes:
    """The answer to a frame, serialised once by pydantic (in the frame's worker thread):
    FastAPI would validate the returned model again and encode it in the event loop."""
    return est.model_dump_json().encode()


def jsonable_errors(exc: RequestValidationError) -> list[dict]:
    return [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in exc.errors()]


async def _read_body(request: Request, limit: int, service: LocalizationService) -> bytes:
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        service.metrics.rejected.labels("PayloadTooLarge").inc()
        raise PayloadTooLarge(f"frame is {declared} bytes; the limit is {limit} bytes")
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            service.metrics.rejected.labels("PayloadTooLarge").inc()
            raise PayloadTooLarge(f"frame is over the limit of {limit} bytes")
        chunks.append(chunk)
    return b"".join(chunks)


async def _expire_loop(service: LocalizationService, period: float,
                       sweeps: list[asyncio.Future[list[str]]]) -> None:
    """Every ``period`` seconds, the sweep (``expire_idle``: idle sessions, idle learners, maps
    other services wrote) on a thread, off the event loop: it may load a map's new version.
    ``sweeps`` holds the one in flight, which a cancelled loop leaves running to its end."""
    loop = asyncio.get_running_loop()
    while True:
        await asyncio.sleep(period)
        sweeps[:] = [loop.run_in_executor(None, service.expire_idle)]
        try:
            await asyncio.shield(sweeps[0])
        except Exception:  # logged; the next sweep runs as usual
            log.exception("the periodic sweep failed")
