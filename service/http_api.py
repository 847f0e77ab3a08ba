"""HTTP API (FastAPI): thin routes over ``LocalizationService``; schemas from models.py."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from typing import Annotated, Any

import anyio
from fastapi import Depends, FastAPI, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from service import __version__
from service.auth import bearer_guard
from service.errors import PayloadTooLarge, ServiceError
from service.events import events_router
from service.map_routes import map_router
from service.models import (
    DEFAULT_PRIOR_RADIUS_M,
    ErrorBody,
    Estimate,
    MapDetail,
    MapSummary,
    PosePrior,
    ResetRequest,
    SessionConfig,
    SessionInfo,
)
from service.sessions import LocalizationService
from service.viewer import add_viewer

_ERRORS: dict[int | str, dict[str, Any]] = {
    code: {"model": ErrorBody} for code in (400, 401, 404, 409, 413, 415, 422, 503)}
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
                  description="Visual localization of robots against SIFT route maps with "
                              "Dynamic Particle Swarm Optimization (Kronfeld, Weiss, Zell).")
    app.state.service = service
    limiter = anyio.CapacityLimiter(settings.frame_workers)

    auth = bearer_guard(settings, service.metrics)
    guarded = [Depends(auth)]
    browser_auth = bearer_guard(settings, service.metrics, allow_query=True)
    app.include_router(events_router(service, browser_auth))
    add_viewer(app, browser_auth)

    @app.exception_handler(ServiceError)
    async def service_error(_: Request, exc: ServiceError) -> JSONResponse:
        headers = {"WWW-Authenticate": "Bearer"} if exc.status == 401 else None
        return JSONResponse({"error": exc.message}, exc.status, headers=headers)

    @app.exception_handler(RequestValidationError)
    async def validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
        service.metrics.rejected.labels("invalid_request").inc()
        parts = [f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors()]
        return JSONResponse({"error": "invalid request: " + "; ".join(parts),
                             "detail": jsonable_errors(exc)}, 422)

    @app.get("/healthz", tags=["health"])
    async def healthz() -> dict:
        return {"status": "ok", "version": __version__}

    @app.get("/readyz", tags=["health"], responses={503: {"model": ErrorBody}})
    async def readyz() -> JSONResponse:
        if service.ready:
            return JSONResponse({"status": "ready", "maps": sorted(service.maps)})
        return JSONResponse({"error": f"no maps loaded from {settings.maps_dir}",
                             "detail": service.load_errors}, 503)

    @app.get("/metrics", tags=["health"], dependencies=guarded)
    async def metrics() -> Response:
        return Response(service.metrics.render(), media_type="text/plain; version=0.0.4")

    @app.get("/maps", tags=["maps"], dependencies=guarded)
    async def list_maps() -> list[MapSummary]:
        return [service.map_summary(n) for n in sorted(service.maps)]

    @app.get("/maps/{map_id}", tags=["maps"], dependencies=guarded, responses=_ERRORS)
    async def get_map(map_id: str, response: Response) -> MapDetail:
        detail = service.map_detail(map_id)
        response.headers["ETag"] = f'"{detail.checksum}"'
        return detail

    app.include_router(map_router(service, guarded))  # upload, build, replace, delete, jobs

    @app.put("/sessions/{robot_id}", tags=["sessions"], dependencies=guarded,
             responses={**_ERRORS, 201: {"model": SessionInfo}})
    async def put_session(robot_id: str, config: SessionConfig, response: Response
                          ) -> SessionInfo:
        info, created = service.put_session(robot_id, config)
        response.status_code = 201 if created else 200
        return info

    @app.get("/sessions", tags=["sessions"], dependencies=guarded)
    async def list_sessions() -> list[SessionInfo]:
        return service.sessions()

    @app.get("/sessions/{robot_id}", tags=["sessions"], dependencies=guarded,
             responses=_ERRORS)
    async def get_session(robot_id: str) -> SessionInfo:
        return service.session(robot_id).info()

    @app.delete("/sessions/{robot_id}", tags=["sessions"], dependencies=guarded,
                status_code=204, responses=_ERRORS)
    async def delete_session(robot_id: str) -> Response:
        service.delete_session(robot_id)
        return Response(status_code=204)

    @app.post("/sessions/{robot_id}/reset", tags=["sessions"], dependencies=guarded,
              responses=_ERRORS)
    async def reset_session(robot_id: str, body: ResetRequest | None = None) -> SessionInfo:
        near = None
        if body is not None and (body.x is not None or body.y is not None):
            if body.x is None or body.y is None:
                raise ServiceError("reset near a pose needs both x and y", 422)
            near = PosePrior(x=body.x, y=body.y, radius=body.radius or DEFAULT_PRIOR_RADIUS_M)
        return service.reset_session(robot_id, near)

    @app.post("/sessions/{robot_id}/frames", tags=["frames"], dependencies=guarded,
              responses=_ERRORS, openapi_extra=_IMAGE_BODY)
    async def post_frame(
        robot_id: str,
        request: Request,
        t: Annotated[float | None, Query(description="frame timestamp, s")] = None,
        seq: Annotated[int | None, Query(description="robot's frame sequence number")] = None,
        prior_x: Annotated[float | None, Query(description="pose prior, m east")] = None,
        prior_y: Annotated[float | None, Query(description="pose prior, m north")] = None,
        prior_radius: Annotated[float | None, Query(gt=0, description="prior radius, m")] = None,
    ) -> Estimate:
        session = service.session(robot_id)
        prior = None
        if prior_x is not None or prior_y is not None:
            if prior_x is None or prior_y is None:
                raise ServiceError("a pose prior needs both prior_x and prior_y", 422)
            prior = PosePrior(x=prior_x, y=prior_y, radius=prior_radius or DEFAULT_PRIOR_RADIUS_M)
        body = await _read_body(request, settings.max_body_bytes, service)
        return await anyio.to_thread.run_sync(
            lambda: service.process_frame(
                robot_id, body, content_type=request.headers.get("content-type"), t=t,
                prior=prior, transport="http", session=session, input_seq=seq),
            limiter=limiter)

    return app


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
