"""Errors a client can act on; each carries its HTTP status code and a message saying what
to fix. The Zenoh bridge sends the same status and message."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any


class ServiceError(Exception):
    status = 500

    def __init__(self, message: str, status: int | None = None) -> None:
        super().__init__(message)
        self.message = message
        if status is not None:
            self.status = status


class BadRequest(ServiceError):
    status = 400


class Unauthorized(ServiceError):
    status = 401


class NotFound(ServiceError):
    status = 404


class Conflict(ServiceError):
    status = 409


class UnreadableSession(Conflict):
    """A stored session state that this version cannot continue (written by another version
    of swarmloc, or damaged): the robot replaces or deletes it; everyone else is served."""


class PreconditionFailed(ServiceError):
    status = 412


class PayloadTooLarge(ServiceError):
    status = 413


class UnsupportedMediaType(ServiceError):
    status = 415


class InvalidParameters(ServiceError):
    status = 422


class Unavailable(ServiceError):
    status = 503


class InsufficientStorage(ServiceError):
    """The maps directory's disk (or the service's quota on it) is full."""

    status = 507


def describe_errors(errors: Iterable[Mapping[str, Any]]) -> str:
    """pydantic / FastAPI validation errors as one line: ``where: what (got value)``. The
    leading ``body`` of FastAPI's locations is dropped, so HTTP and Zenoh read the same."""
    parts = []
    for e in errors:
        loc = [str(p) for p in e.get("loc", ())]
        if loc and loc[0] == "body":
            loc = loc[1:]
        msg = str(e.get("msg", "invalid")).removeprefix("Value error, ")
        given = e.get("input")
        shown = f" (got {given!r})" if isinstance(given, int | float | str) and \
            not isinstance(given, bool) and len(repr(given)) <= 40 else ""
        parts.append(f"{'.'.join(loc) or 'value'}: {msg}{shown}")
    return "; ".join(parts)
