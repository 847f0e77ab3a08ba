"""The one Zenoh reply: an answer or an error body, used by the bridge, the map queryables and
ROS 2 alike (the HTTP status and message of ``service.api.errors``)."""

from __future__ import annotations

import json
import logging
from typing import Any

import zenoh

from service.api.errors import ServiceError

log = logging.getLogger("swarmloc.zenoh")


def error_body(exc: ServiceError, robot: str | None = None, seq: int | None = None
               ) -> dict[str, Any]:
    """The JSON an error is reported with on every Zenoh channel (HTTP's status and message);
    robot channels add the robot and the frame's seq."""
    body: dict[str, Any] = {"error": exc.message, "status": exc.status}
    if robot is not None:
        body |= {"robot_id": robot, "input_seq": seq}
    return body


def internal_error(exc: BaseException) -> ServiceError:
    """What a client is told of an unexpected failure (logged in full by the caller)."""
    return ServiceError(f"internal error: {type(exc).__name__}")


def answer(query: zenoh.Query, body: dict[str, Any], ok: bool | None = None) -> None:
    """Reply (or reply_err for an error body: ``ok`` False, or by default a body with an
    ``error`` key) and finish the query, whatever happens."""
    try:
        payload = json.dumps(body).encode()
        if not (ok if ok is not None else "error" not in body):
            query.reply_err(payload, encoding=zenoh.Encoding.APPLICATION_JSON)
        else:
            query.reply(query.key_expr, payload, encoding=zenoh.Encoding.APPLICATION_JSON)
    except Exception:
        log.exception("a Zenoh reply failed")
    finally:
        query.drop()
