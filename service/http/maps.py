"""HTTP routes of the map lifecycle (thin: the work is in ``map_admin``).

``PUT /maps/{name}`` (a .swmap body), ``GET /maps/{name}/file``, ``DELETE /maps/{name}``,
``POST /maps/{name}/build`` (a zip or tar(.gz) of a round), ``GET /jobs``, ``GET /jobs/{id}``,
``DELETE /maps/{name}/experiences/{id}`` (one learned experience).
Bodies are streamed to a hidden temporary file in the maps directory under a size limit.
"""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Depends, Header, Query, Request, Response
from fastapi.responses import StreamingResponse

from service.api.errors import BadRequest, PayloadTooLarge, UnsupportedMediaType
from service.api.models import (
    DEFAULT_FEATURES,
    MAX_FEATURES_CAP,
    WORKING_SIDE,
    ErrorBody,
    FeatureTypeName,
    JobInfo,
    MapDeleted,
    MapSummary,
)
from service.engine.localization_service import LocalizationService
from service.engine.map_admin import check_map_name, writing
from service.http.auth import require_token
from service.http.deps import ServiceDep
from service.http.openapi import API_ERRORS, binary_body

MAP_ERRORS: dict[int | str, dict[str, Any]] = API_ERRORS | {
    412: {"model": ErrorBody, "description": "If-Match / If-None-Match not met"},
    507: {"model": ErrorBody, "description": "no space left in the maps directory"}}
MAP_TYPES = ("application/octet-stream", "application/x-swarmloc-map")
ARCHIVE_TYPES = ("application/zip", "application/x-zip-compressed", "application/x-tar",
                  "application/gzip", "application/x-gzip", "application/x-compressed-tar",
                  "application/x-bzip2", "application/x-xz", "application/octet-stream")
IfMatch = Annotated[str | None, Header(description="only if the map is at this version (ETag)")]
IfNoneMatch = Annotated[str | None, Header(description="'*': only if there is no such map")]


def _check_type(request: Request, allowed: tuple[str, ...], what: str) -> None:
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype and ctype not in allowed:
        raise UnsupportedMediaType(f"content type '{ctype}' is not accepted for {what}; send "
                                   f"{' or '.join(allowed[:2])}")


async def _stage(request: Request, path: Path, limit: int, what: str) -> None:
    """Stream the body into ``path``, refusing more than ``limit`` bytes."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise PayloadTooLarge(f"{what} is {declared} bytes; the limit is {limit} bytes")
    size = 0
    fh = await anyio.open_file(path, "wb")
    async with fh:
        async for chunk in request.stream():
            size += len(chunk)
            if size > limit:
                raise PayloadTooLarge(f"{what} is over the limit of {limit} bytes")
            await fh.write(chunk)
    if size == 0:
        raise BadRequest(f"empty body: send the {what}")


@contextlib.asynccontextmanager
async def _staged(request: Request, service: LocalizationService, kind: str, limit: int,
                  what: str, name: str) -> AsyncIterator[Path]:
    """The body, staged for map ``name``: 503 / 507 where the maps directory cannot take it."""
    path: Path | None = None
    try:
        try:
            with writing(name, f"receiving the {what}"):
                path = service.admin.staging_file(kind)
                await _stage(request, path, limit, what)
        except Exception as exc:
            label = "uploads" if kind == "upload" else "builds"
            getattr(service.metrics, f"map_{label}").labels("rejected").inc()
            service.metrics.rejected.labels(type(exc).__name__).inc()
            raise
        yield path
    finally:
        if path is not None:
            path.unlink(missing_ok=True)


map_router = APIRouter(dependencies=[Depends(require_token)], responses=MAP_ERRORS)


@map_router.put("/maps/{name}", tags=["maps"],
                openapi_extra=binary_body(MAP_TYPES, "a .swmap file"),
                responses={201: {"model": MapSummary, "description": "uploaded"},
                           200: {"description": "replaced"}})
async def upload_map(name: str, request: Request, response: Response, service: ServiceDep,
                     if_match: IfMatch = None, if_none_match: IfNoneMatch = None
                     ) -> MapSummary:
    """Upload (201) or replace (200) a map: a .swmap file built by `swarmloc map build`."""
    admin = service.admin
    check_map_name(name)
    _check_type(request, MAP_TYPES, "a map")
    # fail before the upload; the map admin's lock, which a map write holds throughout: off
    # the event loop (as every call into the admin here)
    await anyio.to_thread.run_sync(admin.check_preconditions, name, if_match, if_none_match)
    async with _staged(request, service, "upload", service.settings.max_map_bytes,
                       "map", name) as path:
        summary, created = await anyio.to_thread.run_sync(
            admin.install_upload, name, path, if_match, if_none_match)
    response.status_code = 201 if created else 200
    response.headers["ETag"] = f'"{summary.checksum}"'
    response.headers["Location"] = f"/maps/{name}"
    return summary


@map_router.get("/maps/{name}/file", tags=["maps"], response_class=Response,
                responses={200: {"content": {"application/octet-stream": {"schema": {
                    "type": "string", "format": "binary"}}}, "description": "the .swmap file"},
                    304: {"description": "the map is at the version of If-None-Match"}})
async def download_map(name: str, service: ServiceDep, if_none_match: IfNoneMatch = None
                       ) -> Response:
    """The map's .swmap file (its current version), with its ETag."""
    fh, etag, size = await anyio.to_thread.run_sync(service.admin.open_file, name)
    headers = {"ETag": f'"{etag}"'}
    if if_none_match is not None and etag in [t.strip().strip('"')
                                              for t in if_none_match.split(",")]:
        fh.close()  # type: ignore[attr-defined]
        return Response(status_code=304, headers=headers)

    def chunks() -> Any:
        with fh:  # type: ignore[attr-defined]
            while data := fh.read(1 << 20):  # type: ignore[attr-defined]
                yield data

    headers["Content-Length"] = str(size)
    headers["Content-Disposition"] = f'attachment; filename="{name}.swmap"'
    return StreamingResponse(chunks(), media_type="application/octet-stream",
                             headers=headers)


@map_router.delete("/maps/{name}", tags=["maps"])
async def delete_map(name: str, service: ServiceDep, force: Annotated[bool, Query(
        description="end the sessions that use the map")] = False,
        if_match: IfMatch = None) -> MapDeleted:
    """Delete a map; 409 names the sessions on it unless ?force=true ends them."""
    return await anyio.to_thread.run_sync(service.admin.delete, name, force, if_match)


@map_router.delete("/maps/{name}/experiences/{exp_id}", tags=["maps"])
async def delete_experience(name: str, exp_id: str, response: Response, service: ServiceDep,
                            if_match: IfMatch = None) -> MapSummary:
    """Remove one experience the fleet taught the map (listed by GET /maps/{name}): a new map
    version, its ETag in the answer."""
    summary = await anyio.to_thread.run_sync(service.admin.delete_experience, name, exp_id,
                                             if_match)
    response.headers["ETag"] = f'"{summary.checksum}"'
    return summary


@map_router.post("/maps/{name}/build", tags=["maps"], status_code=202,
                 openapi_extra=binary_body(ARCHIVE_TYPES, "a zip or tar(.gz) of a round"))
async def build_map(name: str, request: Request, response: Response, service: ServiceDep,
                    if_match: IfMatch = None, if_none_match: IfNoneMatch = None,
                    features: Annotated[FeatureTypeName, Query(
                        description="feature type: clahe-rootsift+xfeat (default: both, "
                        "fused), clahe-rootsift, sift (the papers') or xfeat (learned, holds "
                        "at night)")] = DEFAULT_FEATURES,
                    max_features: Annotated[int | None, Query(
                        ge=0, le=MAX_FEATURES_CAP,
                        description="SIFT's features kept per map image and frame, the "
                        "strongest (default 2,048; 0: all). Above 2,048 the service compares "
                        "the map through its inverted file (SWARMLOC_MATCHER=auto); XFeat keeps "
                        "its own 1,024")] = None,
                    width: Annotated[int, Query(
                        ge=WORKING_SIDE[0], le=WORKING_SIDE[1],
                        description="the map's working width: frames are resized to it (keep "
                        "the camera's aspect)")] = 320,
                    height: Annotated[int, Query(
                        ge=WORKING_SIDE[0], le=WORKING_SIDE[1],
                        description="the map's working height")] = 240,
                    ) -> JobInfo:
    """Build a map from a zip/tar(.gz) of a round (poses.csv + images) in the background;
    follow GET /jobs/{id}. The map appears (or is replaced) when the build is done."""
    admin = service.admin
    check_map_name(name)
    _check_type(request, ARCHIVE_TYPES, "a round archive")
    await anyio.to_thread.run_sync(admin.check_preconditions, name, if_match, if_none_match)
    async with _staged(request, service, "archive", service.settings.max_archive_bytes,
                       "round archive", name) as path:
        job = await anyio.to_thread.run_sync(
            admin.submit_build, name, path, if_match, if_none_match, features, max_features,
            width, height)
    response.headers["Location"] = f"/jobs/{job.id}"
    return job


@map_router.get("/jobs", tags=["jobs"])
async def list_jobs(service: ServiceDep) -> list[JobInfo]:
    """The map builds, running and finished."""
    return service.admin.jobs()


@map_router.get("/jobs/{job_id}", tags=["jobs"])
async def get_job(job_id: str, service: ServiceDep) -> JobInfo:
    """One map build: its state and progress."""
    return service.admin.job(job_id)
