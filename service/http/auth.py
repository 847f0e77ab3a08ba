"""Bearer-token check shared by every guarded route (HTTP API, event stream, viewer)."""

from __future__ import annotations

import hmac
from collections.abc import Awaitable, Callable

from fastapi import Request

from service.api.errors import Unauthorized
from service.engine.metrics import Metrics
from service.settings import Settings


def bearer_guard(settings: Settings, metrics: Metrics, allow_query: bool = False
                 ) -> Callable[[Request], Awaitable[None]]:
    """A FastAPI dependency: ``Authorization: Bearer <token>`` when a token is configured.

    With ``allow_query`` a ``?token=`` query parameter is accepted too: a browser cannot add
    a header when it opens a page or an EventSource. Only the viewer and the event stream
    allow it (a token in a URL can end up in logs and history).
    """

    async def guard(request: Request) -> None:
        token = settings.auth_token
        if not token:
            return
        scheme, _, given = request.headers.get("authorization", "").partition(" ")
        if scheme.lower() == "bearer" and _same(given.strip(), token):
            return
        query = request.query_params.get("token") if allow_query else None
        if query is not None and _same(query, token):
            return
        metrics.rejected.labels("unauthorized").inc()
        hint = " or add '?token=<SWARMLOC_AUTH_TOKEN>' to the URL" if allow_query else ""
        raise Unauthorized("missing or wrong bearer token: send 'Authorization: Bearer "
                           f"<SWARMLOC_AUTH_TOKEN>'{hint}")

    return guard


def _same(given: str, token: str) -> bool:
    """Constant-time comparison of any text (headers arrive as latin-1 text; compare_digest
    refuses non-ASCII str, so compare the bytes)."""
    return hmac.compare_digest(given.encode("utf-8", "surrogateescape"),
                               token.encode("utf-8", "surrogateescape"))
