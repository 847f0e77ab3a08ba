"""The fleet viewer: a static page at ``/viewer`` (plain ES modules, canvas, no CDN).

``GET /viewer`` needs the API's bearer token (header, or ``?token=`` since a browser opening
a page cannot add a header); the page then sends the token as a header to ``/maps`` and
``/events``. The files under ``/viewer/static/`` are the page's code and style only, no
data, and are open like ``/docs``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Depends, FastAPI, Query
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from service.api.models import ErrorBody

STATIC = Path(__file__).resolve().parent / "static"


def add_viewer(app: FastAPI, guard: Callable[..., Any]) -> None:
    """Serve the page at ``/viewer`` (guarded) and its code at ``/viewer/static``."""
    router = APIRouter()

    @router.get("/viewer", tags=["viewer"], dependencies=[Depends(guard)],
                response_class=FileResponse,
                responses={200: {"content": {"text/html": {}}}, 401: {"model": ErrorBody}})
    async def viewer(
        token: Annotated[str | None, Query(description="bearer token (browsers)")] = None,
    ) -> FileResponse:
        return FileResponse(STATIC / "index.html", media_type="text/html",
                            headers={"Cache-Control": "no-store",
                                     "Referrer-Policy": "no-referrer"})

    app.include_router(router)
    app.mount("/viewer/static", StaticFiles(directory=STATIC), name="viewer-static")
