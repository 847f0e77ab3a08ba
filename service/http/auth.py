"""Bearer-token check shared by every guarded route (HTTP API, event stream, viewer).

The check is the ``HTTPBearer`` security dependency, so the OpenAPI schema declares the
scheme (``bearerAuth``) and lists it on every operation that needs the token; the probes
(``/healthz``, ``/readyz``) do not use it and stay open.
"""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.api.errors import Unauthorized
from service.http.deps import ServiceDep

SCHEME = "bearerAuth"
_bearer = HTTPBearer(auto_error=False, scheme_name=SCHEME,
                     description="SWARMLOC_AUTH_TOKEN, when the service runs with a token")
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]


async def require_token(service: ServiceDep, credentials: Credentials) -> None:
    """``Authorization: Bearer <token>`` when a token is configured."""
    _check(service, credentials, None, allow_query=False)


async def require_token_or_query(request: Request, service: ServiceDep,
                                 credentials: Credentials) -> None:
    """The header, or a ``?token=`` query parameter: a browser cannot add a header when it
    opens a page or an EventSource. Only the viewer, the event stream and the docs allow it
    (a token in a URL can end up in logs and history)."""
    _check(service, credentials, request.query_params.get("token"), allow_query=True)


def _check(service: ServiceDep, credentials: HTTPAuthorizationCredentials | None,
           query: str | None, *, allow_query: bool) -> None:
    token = service.settings.auth_token
    if not token:
        return
    if credentials is not None and _same(credentials.credentials.strip(), token):
        return
    if query is not None and _same(query, token):
        return
    service.metrics.rejected.labels("unauthorized").inc()
    hint = " or add '?token=<SWARMLOC_AUTH_TOKEN>' to the URL" if allow_query else ""
    raise Unauthorized("missing or wrong bearer token: send 'Authorization: Bearer "
                       f"<SWARMLOC_AUTH_TOKEN>'{hint}")


def _same(given: str, token: str) -> bool:
    """Constant-time comparison of any text (headers arrive as latin-1 text; compare_digest
    refuses non-ASCII str, so compare the bytes)."""
    return hmac.compare_digest(given.encode("utf-8", "surrogateescape"),
                               token.encode("utf-8", "surrogateescape"))
