"""``GET /events``: the estimate stream of ``service.engine.events`` as Server-Sent Events."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Iterable
from typing import Annotated

from fastapi import APIRouter, Depends, Query
from fastapi.responses import StreamingResponse

from service.engine.events import KEEPALIVE_S, estimate_message
from service.engine.localization_service import LocalizationService
from service.http.auth import require_token_or_query
from service.http.deps import ServiceDep
from service.http.openapi import API_ERRORS


async def sse_stream(service: LocalizationService, map_name: str | None,
                     particles: Iterable[str], keepalive_s: float = KEEPALIVE_S
                     ) -> AsyncIterator[str]:
    """The SSE body: the current state first, then every flush; a comment as keep-alive.

    The subscription lives exactly as long as this generator (closed when the client goes).
    """
    hub = service.events
    sub = hub.subscribe(asyncio.get_running_loop(), map_name, particles)
    try:
        yield "retry: 2000\n\n"
        initial = initial_messages(service, map_name)
        if initial:
            yield _frame(initial)
        while True:
            msgs = await sub.take(keepalive_s)
            if msgs is None:
                return
            if msgs:
                hub.metrics.events_sent.inc(len(msgs))
                yield _frame(msgs)
            else:
                yield ": keep-alive\n\n"
    finally:
        hub.unsubscribe(sub)


def _frame(msgs: list[str]) -> str:
    return f'data: {{"now":{time.time():.3f},"m":[{",".join(msgs)}]}}\n\n'


def initial_messages(service: LocalizationService, map_name: str | None) -> list[str]:
    """The last estimate of every session (on the map), so a new viewer starts complete."""
    out = []
    for info in service.sessions():
        est = info.last_estimate
        if est is not None and (map_name is None or est.frame_id == map_name):
            est = est.model_copy(update={"robot_id": info.robot_id})
            out.append(estimate_message(est, info.last_used, None))
    return out


events_router = APIRouter()


@events_router.get(
    "/events", tags=["viewer"], dependencies=[Depends(require_token_or_query)],
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {"schema": {"type": "string"}}},
                     "description": "Server-Sent Events, see the README"},
               401: API_ERRORS[401], 404: API_ERRORS[404], 422: API_ERRORS[422]})
async def stream_events(
    service: ServiceDep,
    map: Annotated[str | None, Query(description="only estimates on this map")] = None,
    particles: Annotated[str, Query(description="robots whose particles to stream, "
                                    "comma-separated, or '*'")] = "",
    token: Annotated[str | None, Query(description="bearer token, for browsers' "
                                       "EventSource (which cannot send headers)")] = None,
) -> StreamingResponse:
    """The estimates of every robot as they come (auth: bearer header, or ``?token=`` for
    browsers)."""
    if map is not None:
        service.get_map(map)  # 404 with the list of maps
    robots = [p for p in (s.strip() for s in particles.split(",")) if p]
    return StreamingResponse(sse_stream(service, map, robots),
                             media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
