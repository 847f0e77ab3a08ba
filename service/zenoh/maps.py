"""The map lifecycle over Zenoh: the same operations and errors as HTTP.

Keys (``@`` makes a verbatim chunk: the robots' ``{prefix}/*/...`` keys never match it, so a
robot may even be called "maps"):

- ``{prefix}/@maps``          query: the loaded maps (list of MapSummary JSON)
- ``{prefix}/@maps/{name}``   query; the attachment is JSON ``{"action": "get" | "put" |
                              "delete" | "build", "if_match", "if_none_match", "force"}``
                              (default: ``put`` with a payload, else ``get``); the payload is
                              the .swmap file (put) or the round archive (build).
                              Replies: MapSummary (+ ``"created"``), MapDeleted or JobInfo JSON.
- ``{prefix}/@jobs``          query: every build job; ``{prefix}/@jobs/{id}``: one JobInfo.

Errors are reply_err with ``{"error", "status"}``, the HTTP message and status code.

Map queries are answered on ``MAP_WORKERS`` threads of their own, a map's in the order they
came (service/zenoh/workers.py): all but the job queries wait for the map admin, which a build
or a learning session's images hold through a whole map write, so answered on the frame
workers they took the workers robots' frames need. At most ``MAP_BACKLOG`` wait per map and
``MAP_NAMES`` maps have queries waiting; beyond, 503 at once. Job queries wait for nothing and
are answered at once.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import zenoh

from service.api.errors import BadRequest, ServiceError
from service.api.models import DEFAULT_FEATURES
from service.engine.localization_service import LocalizationService
from service.engine.map_admin import payload_to_file
from service.zenoh.replies import answer, error_body, internal_error, parse_json_object
from service.zenoh.workers import KeyedWorkers

log = logging.getLogger("swarmloc.zenoh")
MAP_WORKERS = 2  # threads answering map queries (each map's one at a time)
MAP_BACKLOG = 8  # a map's queries waiting at once; more are refused (503)
MAP_NAMES = 16  # maps with queries waiting at once; a query for another is refused (503)


def _reply(query: zenoh.Query, fn: Callable[[], Any]) -> None:
    try:
        body, ok = fn(), True
    except ServiceError as exc:
        body, ok = error_body(exc), False
    except Exception as exc:  # never let a bad request reach the Zenoh threads
        log.exception("map query %s failed", query.key_expr)
        body, ok = error_body(internal_error(exc)), False
    answer(query, body, ok)


_OPTION_TYPES: dict[str, type] = {"action": str, "if_match": str, "if_none_match": str,
                                   "force": bool, "features": str, "max_features": int,
                                   "width": int, "height": int}


_KIND_NAMES = {bool: "true or false", str: "a string", int: "an integer"}


def _options(raw: bytes) -> dict[str, Any]:
    """The attachment of a map query: a JSON object of the options above (each a string,
    ``force`` a boolean, ``max_features``, ``width`` and ``height`` integers, any of them
    null or left out), else 400 as HTTP's header errors."""
    opts = parse_json_object(raw, "attachment", '{"action": "put"}')
    for key, value in opts.items():
        want = _OPTION_TYPES.get(key)
        if want is None:
            raise BadRequest(f"attachment has an unknown option '{str(key)[:40]}'; use "
                             f"{', '.join(_OPTION_TYPES)}")
        if value is not None and type(value) is not want:
            raise BadRequest(f"attachment option '{key}' must be "
                             f"{_KIND_NAMES[want]}")
    return opts


def declare_map_queryables(session: zenoh.Session, prefix: str, service: LocalizationService,
                           workers: KeyedWorkers) -> list[Any]:
    admin = service.admin
    s = service.settings

    def maps(name: str, data: bytes, opts: dict[str, Any]) -> Any:
        if not name:
            return [s.model_dump(mode="json") for s in service.map_summaries()]
        action = opts.get("action") or ("put" if data else "get")
        match_, none_match = opts.get("if_match"), opts.get("if_none_match")
        if action == "get":
            return service.map_summary(name).model_dump(mode="json")
        if action == "delete":
            return admin.delete(name, bool(opts.get("force")), match_).model_dump(mode="json")
        if action == "put":
            admin.check_preconditions(name, match_, none_match)
            path = payload_to_file(admin, data, "upload", s.max_map_bytes, name)
            summary, created = admin.install_upload(name, path, match_, none_match)
            return {**summary.model_dump(mode="json"), "created": created}
        if action == "build":
            admin.check_preconditions(name, match_, none_match)
            path = payload_to_file(admin, data, "archive", s.max_archive_bytes, name)
            job = admin.submit_build(name, path, match_, none_match,
                                     opts.get("features") or DEFAULT_FEATURES,
                                     opts.get("max_features"), opts.get("width"),
                                     opts.get("height"))
            return job.model_dump(mode="json")
        raise BadRequest(f"unknown action '{action}'; use get, put, delete or build")

    def on_maps(query: zenoh.Query) -> None:
        tail = str(query.key_expr).split("/@maps", 1)[1].strip("/")
        data = query.payload.to_bytes() if query.payload else b""
        raw = query.attachment.to_bytes() if query.attachment else b""
        workers.submit(tail, lambda: _reply(query, lambda: maps(tail, data, _options(raw))),
                       lambda exc: answer(query, error_body(exc)))

    def on_jobs(query: zenoh.Query) -> None:
        tail = str(query.key_expr).split("/@jobs", 1)[1].strip("/")
        _reply(query, lambda: admin.job(tail).model_dump(mode="json") if tail
               else [j.model_dump(mode="json") for j in admin.jobs()])

    return [session.declare_queryable(f"{prefix}/@maps/**", on_maps),
            session.declare_queryable(f"{prefix}/@jobs/**", on_jobs)]
