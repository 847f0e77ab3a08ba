"""The fleet viewer: a static page at ``/viewer`` (plain ES modules, canvas, no CDN).

``GET /viewer`` needs the API's bearer token (header, or ``?token=`` since a browser opening
a page cannot add a header); the page then sends the token as a header to ``/maps`` and
``/events``. The files under ``/viewer/static/`` are the page's code and style only, no
data, and are open like ``/docs``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Depends, FastAPI, Query
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from service.http.auth import require_token_or_query
from service.http.openapi import API_ERRORS

STATIC = Path(__file__).resolve().parent / "static"


viewer_router = APIRouter()


@viewer_router.get("/viewer", tags=["viewer"], dependencies=[Depends(require_token_or_query)],
                   response_class=FileResponse,
                   responses={200: {"content": {"text/html": {"schema": {"type": "string"}}},
                                    "description": "the viewer page"},
                              401: API_ERRORS[401], 422: API_ERRORS[422]})
async def viewer(
    token: Annotated[str | None, Query(description="bearer token (browsers)")] = None,
) -> FileResponse:
    """The fleet viewer: a page that draws the map and the robots live."""
    return FileResponse(STATIC / "index.html", media_type="text/html",
                        headers={"Cache-Control": "no-store", "Referrer-Policy": "no-referrer"})


@viewer_router.get("/favicon.ico", include_in_schema=False)
async def favicon() -> FileResponse:
    """The viewer's icon, also for pages that do not link one (browsers ask for it)."""
    return FileResponse(STATIC / "favicon.svg", media_type="image/svg+xml",
                        headers={"Cache-Control": "max-age=86400"})


def add_viewer(app: FastAPI) -> None:
    """Serve the page at ``/viewer`` (guarded), its code at ``/viewer/static`` and the icon at
    ``/favicon.ico`` (open, like the code)."""
    app.include_router(viewer_router)
    app.mount("/viewer/static", StaticFiles(directory=STATIC), name="viewer-static")
