"""Errors a client can act on; each carries its HTTP status code and a message saying what
to fix. The Zenoh bridge sends the same status and message."""

from __future__ import annotations


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
