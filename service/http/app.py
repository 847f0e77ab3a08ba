"""HTTP API (FastAPI): thin routes over ``LocalizationService``; schemas from models.py."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import weakref
from collections.abc import AsyncIterator, Callable
from typing import Annotated, Any
from urllib.parse import urlencode

import anyio
from fastapi import APIRouter, Depends, FastAPI, Path, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse, PlainTextResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

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
    pose_prior,
)
from service.engine.localization_service import LocalizationService
from service.http.auth import bearer_guard
from service.http.events import events_router
from service.http.maps import map_router
from service.http.viewer import add_viewer

log = logging.getLogger("swarmloc")
_ERRORS: dict[int | str, dict[str, Any]] = {
    code: {"model": ErrorBody} for code in (400, 401, 404, 409, 413, 415, 422, 503)}
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
_IMAGE_BODY = {
    "requestBody": {
        "required": True,
        "content": {t: {"schema": {"type": "string", "format": "binary"}}
                    for t in ("image/png", "image/jpeg")},
    }
}


def create_app(service: LocalizationService, *, expire_every_s: float | None = None,
               lifespan_hooks: list | None = None) -> FastAPI:
    """The FastAPI application for one service instance.

    ``lifespan_hooks`` are async context managers entered at start-up (the Zenoh bridge).
    Every route but the probes is on a router whose dependency checks the bearer token
    (``/openapi.json`` and ``/docs`` included), and every error answers ``{"error": ...}``.
    """
    settings = service.settings

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        async with contextlib.AsyncExitStack() as stack:
            for hook in lifespan_hooks or []:
                await stack.enter_async_context(hook)
            period = expire_every_s or max(1.0, min(30.0, settings.session_idle_s / 4))
            task = asyncio.create_task(_expire_loop(service, period))
            try:
                yield
            finally:
                task.cancel()

    app = FastAPI(title="swarmloc", version=__version__, lifespan=lifespan,
                  openapi_url=None, docs_url=None, redoc_url=None,
                  description="Visual localization of robots against SIFT route maps with "
                              "Dynamic Particle Swarm Optimization (Kronfeld, Weiss, Zell).")
    app.state.service = service
    add_error_handlers(app, service)

    auth = bearer_guard(settings, service.metrics)
    guarded = [Depends(auth)]
    browser_auth = bearer_guard(settings, service.metrics, allow_query=True)
    app.include_router(health_router(service))
    app.include_router(docs_router(app, browser_auth))
    app.include_router(events_router(service, browser_auth))
    add_viewer(app, browser_auth)
    app.include_router(api_router(service), dependencies=guarded, responses=_ERRORS)
    app.include_router(map_router(service, guarded))  # upload, build, replace, delete, jobs
    return app


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


def health_router(service: LocalizationService) -> APIRouter:
    """The probes: always open."""
    router = APIRouter(tags=["health"])

    @router.get("/healthz")
    async def healthz() -> dict:
        return {"status": "ok", "version": __version__}

    @router.get("/readyz", responses={503: {"model": ErrorBody}})
    async def readyz() -> JSONResponse:
        if service.draining:
            return JSONResponse({"error": "shutting down"}, 503)
        if service.ready:
            return JSONResponse({"status": "ready", "maps": sorted(service.maps)})
        return JSONResponse({"error": f"no maps loaded from {service.settings.maps_dir}",
                             "detail": service.load_errors}, 503)

    return router


def docs_router(app: FastAPI, guard: Callable[..., Any]) -> APIRouter:
    """``/openapi.json`` and ``/docs`` behind the token (header, or ``?token=`` so that a
    browser can open the page; the page passes it on to the schema)."""
    router = APIRouter(dependencies=[Depends(guard)], include_in_schema=False)

    @router.get("/openapi.json")
    async def openapi() -> JSONResponse:
        return JSONResponse(app.openapi())

    @router.get("/docs")
    async def docs(request: Request) -> HTMLResponse:
        token = request.query_params.get("token")
        url = "/openapi.json" + (f"?{urlencode({'token': token})}" if token else "")
        return get_swagger_ui_html(openapi_url=url, title="swarmloc API")

    return router


def api_router(service: LocalizationService) -> APIRouter:
    """Metrics, maps and sessions; the caller adds the auth dependency to the router."""
    settings = service.settings
    router = APIRouter()
    limiter = anyio.CapacityLimiter(settings.frame_workers)
    # sessions over heavy_particles share a quarter of the workers: they cannot take the
    # light robots' threads (fair scheduling)
    heavy_limiter = anyio.CapacityLimiter(max(1, settings.frame_workers // 4))
    gates: weakref.WeakValueDictionary[str, asyncio.Lock] = weakref.WeakValueDictionary()

    def gate(robot_id: str) -> asyncio.Lock:
        """One frame of a robot at a time holds a worker; the others wait without one."""
        lock = gates.get(robot_id)
        if lock is None:
            lock = gates[robot_id] = asyncio.Lock()
        return lock

    @router.get("/metrics", tags=["health"], response_class=PlainTextResponse)
    async def metrics() -> PlainTextResponse:
        """Prometheus text format."""
        return PlainTextResponse(service.metrics.render(),
                                 media_type="text/plain; version=0.0.4")

    @router.get("/maps", tags=["maps"])
    async def list_maps() -> list[MapSummary]:
        return [service.map_summary(n) for n in sorted(service.maps)]

    @router.get("/maps/{map_id}", tags=["maps"])
    async def get_map(map_id: str, response: Response) -> MapDetail:
        detail = service.map_detail(map_id)
        response.headers["ETag"] = f'"{detail.checksum}"'
        return detail

    @router.put("/sessions/{robot_id}", tags=["sessions"],
                responses={201: {"model": SessionInfo, "links": _SESSION_LINKS},
                           200: {"links": _SESSION_LINKS}})
    async def put_session(robot_id: RobotId, config: SessionConfig, response: Response
                          ) -> SessionInfo:
        info, created = service.put_session(robot_id, config)
        response.status_code = 201 if created else 200
        return info

    @router.get("/sessions", tags=["sessions"])
    async def list_sessions() -> list[SessionInfo]:
        return service.sessions()

    @router.get("/sessions/{robot_id}", tags=["sessions"])
    async def get_session(robot_id: RobotId) -> SessionInfo:
        return service.session(robot_id).info()

    @router.delete("/sessions/{robot_id}", tags=["sessions"], status_code=204)
    async def delete_session(robot_id: RobotId) -> Response:
        service.delete_session(robot_id)
        return Response(status_code=204)

    @router.post("/sessions/{robot_id}/reset", tags=["sessions"])
    async def reset_session(robot_id: RobotId, body: ResetRequest | None = None) -> SessionInfo:
        return service.reset_session(robot_id, body.near() if body is not None else None)

    @router.post("/sessions/{robot_id}/frames", tags=["frames"], openapi_extra=_IMAGE_BODY,
                 response_model=Estimate)
    async def post_frame(
        robot_id: RobotId,
        request: Request,
        t: Annotated[float | None, Query(description="frame timestamp, s")] = None,
        seq: Annotated[int | None, Query(description="robot's frame sequence number",
                                         ge=-(2**63), lt=2**63)] = None,
        prior_x: Annotated[float | None, Query(description="pose prior, m east")] = None,
        prior_y: Annotated[float | None, Query(description="pose prior, m north")] = None,
        prior_radius: Annotated[float | None, Query(
            gt=0, le=MAX_PRIOR_RADIUS_M, description="prior radius, m")] = None,
    ) -> Response:
        if service.draining:
            raise Unavailable("the service is shutting down; retry after the restart")
        session = service.session(robot_id)
        prior = pose_prior(prior_x, prior_y, prior_radius)
        body = await _read_body(request, settings.max_body_bytes, service)
        async with gate(robot_id):
            lim = heavy_limiter if service.is_heavy(robot_id) else limiter
            return await anyio.to_thread.run_sync(
                lambda: Response(estimate_json(service.process_frame(
                    robot_id, body, content_type=request.headers.get("content-type"), t=t,
                    prior=prior, transport="http", session=session, input_seq=seq)),
                    media_type="application/json"),
                limiter=lim)

    return router


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


async def _expire_loop(service: LocalizationService, period: float) -> None:
    while True:
        await asyncio.sleep(period)
        service.expire_idle()
