"""What the OpenAPI schema says beyond the routes' types: the error responses, raw binary
bodies, and operation ids that read well as generated function names."""

from __future__ import annotations

from typing import Any

from fastapi.routing import APIRoute

from service.api.models import ErrorBody

#: every 4xx and 5xx an operation may answer, each with the one error body
API_ERRORS: dict[int | str, dict[str, Any]] = {
    code: {"model": ErrorBody, "description": text} for code, text in (
        (400, "the request could not be read"), (401, "missing or wrong bearer token"),
        (404, "no such session, map or route"), (409, "conflict with the current state"),
        (413, "body over the size limit"), (415, "unsupported content type"),
        (422, "invalid parameters"),
        (500, "internal error (a defect): the body names the error id in the service log"),
        (503, "not ready, shutting down, a store unavailable, or the maps directory not "
              "writable"))}


def binary_body(types: tuple[str, ...], description: str) -> dict[str, Any]:
    """``openapi_extra`` of a route whose body is raw bytes of one of ``types``."""
    return {"requestBody": {"required": True, "description": description, "content": {
        t: {"schema": {"type": "string", "format": "binary"}} for t in types}}}


def operation_id(route: APIRoute) -> str:
    """The route function's name (``send_frame``, ``upload_map``): generated clients name
    their functions after the operation ids."""
    return route.name
