"""The limits nginx would set in front of the service, in uvicorn's HTTP protocol itself.

- A request's head (request line and headers) may hold at most ``http_max_header_bytes``
  (like nginx's ``large_client_header_buffers``): a longer one gets 431 and the connection
  is closed before the parser buffers it.
- A request's head must arrive within ``http_read_timeout_s`` of its first byte (or of the
  connection being opened), and a body may pause at most that long between two reads (like
  nginx's ``client_header_timeout`` and ``client_body_timeout``); then the connection is
  closed (408 for a head). A slowloris client holds neither a connection nor a staging file.

uvicorn's own keep-alive timeout still closes idle connections between requests.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

log = logging.getLogger("swarmloc.http")


def _response(status: int, reason: str, message: str) -> bytes:
    body = message.encode()
    return (f"HTTP/1.1 {status} {reason}\r\ncontent-type: text/plain; charset=utf-8\r\n"
            f"content-length: {len(body)}\r\nconnection: close\r\n\r\n").encode() + body


class LimitedHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with a head-size limit and read timeouts."""

    max_head_bytes = 8192
    read_timeout_s = 30.0

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._head_open = True  # the bytes coming in belong to a request's head
        self._head_bytes = 0
        self._in_body = False
        self._deadline: asyncio.TimerHandle | None = None

    # ---- timers ---------------------------------------------------------------------------
    def _arm(self) -> None:
        self._disarm()
        self._deadline = self.loop.call_later(self.read_timeout_s, self._timed_out)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _timed_out(self) -> None:
        self._deadline = None
        if self.transport.is_closing():
            return
        if self.flow.read_paused:  # the app has not taken the body yet: not the client's pause
            self._arm()
            return
        where = "body" if self._in_body else "head"
        log.info("closed a connection from %s: no request %s bytes for %.0f s", self.client,
                 where, self.read_timeout_s)
        if not self._in_body:
            self.transport.write(_response(408, "Request Timeout", "request head timed out"))
        self.transport.close()

    # ---- protocol -------------------------------------------------------------------------
    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()  # the first request's head must come in time

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._head_open:
            end = data.find(b"\r\n\r\n")
            self._head_bytes += len(data) if end < 0 else end + 4
            if self._head_bytes > self.max_head_bytes:
                self._disarm()
                log.info("refused a request head over %d bytes from %s", self.max_head_bytes,
                         self.client)
                self.transport.write(_response(
                    431, "Request Header Fields Too Large",
                    f"the request line and headers exceed {self.max_head_bytes} bytes"))
                self.transport.close()
                return
            if self._deadline is None:
                self._arm()  # a new request's head: its deadline runs from its first byte
        elif self._in_body:
            self._arm()  # the body keeps coming: the pause allowed starts again
        super().data_received(data)

    def on_headers_complete(self) -> None:
        self._head_open, self._in_body = False, True
        self._arm()
        super().on_headers_complete()

    def on_message_complete(self) -> None:
        self._disarm()
        self._head_open, self._in_body, self._head_bytes = True, False, 0
        super().on_message_complete()


def limited_protocol(max_head_bytes: int, read_timeout_s: float
                     ) -> type[LimitedHttpToolsProtocol]:
    """The protocol class for uvicorn's ``http=`` with these limits."""
    return type("SwarmlocHttpProtocol", (LimitedHttpToolsProtocol,),
                {"max_head_bytes": max_head_bytes, "read_timeout_s": read_timeout_s})
