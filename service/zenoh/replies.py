"""The one Zenoh reply: an answer or an error body, used by the bridge, the map queryables and
ROS 2 alike (the HTTP status and message of ``service.api.errors``); and the one JSON parser
of the Zenoh channels' payloads and attachments (bad JSON of any shape is a 400, as on HTTP)."""

from __future__ import annotations

import json
import logging
from typing import Any

import zenoh

from service.api.errors import BadRequest, ServiceError

log = logging.getLogger("swarmloc.zenoh")


def parse_json(raw: bytes, what: str) -> Any:
    """``raw`` as JSON, or BadRequest (400) saying why: not UTF-8 or not JSON, nested too
    deeply (100 000 '['), or an integer of more digits than Python converts (5 000)."""
    try:
        return json.loads(raw)
    except UnicodeDecodeError:
        raise BadRequest(f"{what} is not UTF-8 JSON") from None
    except json.JSONDecodeError as exc:
        raise BadRequest(f"{what} is not JSON: {exc}") from None
    except RecursionError:
        raise BadRequest(f"{what} is JSON nested too deeply") from None
    except ValueError:  # int_max_str_digits: a number of thousands of digits
        raise BadRequest(f"{what} holds a number with too many digits") from None


def parse_json_object(raw: bytes | None, what: str, example: str) -> dict[str, Any]:
    """A JSON object (``{}`` when ``raw`` is empty), or BadRequest naming ``example``."""
    if not raw:
        return {}
    value = parse_json(raw, what)
    if not isinstance(value, dict):
        raise BadRequest(f"{what} must be a JSON object like {example}")
    return value


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
