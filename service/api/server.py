"""The HTTP/1.1 protocol ``bssrdf serve`` runs: uvicorn's httptools protocol with header limits.

    uvicorn.run(app, host=..., port=..., http=limited_protocol(settings))

uvicorn's httptools protocol (the one ``http="auto"`` picks when httptools is installed, a
dependency) has no limit on the request line and headers: one 60 MB header was read for 9 s,
while every other connection of the event loop waited. :class:`LimitedHttpTools` counts the
bytes of a request's head as they arrive and refuses it with 431 once they pass
``max_header_bytes`` (BSSRDF_MAX_HEADER_BYTES), or once it has more than ``max_headers``
fields (BSSRDF_MAX_HEADERS), before any more of it is read, then closes the connection. A head
still incomplete ``read_timeout_seconds`` (BSSRDF_READ_TIMEOUT_SECONDS) after its first byte is
answered 408 and closed; the body's share of that timeout is :class:`service.api.limits.BodyLimit`.

A refusal is a lingering close: the answer is sent and the write side shut, then what the client
still sends is read and dropped, for :data:`LINGER_SECONDS` or :data:`LINGER_BYTES` at most,
before the connection closes, so that a client that writes its whole request before it reads
(most do) gets the 431 rather than a connection reset.

The parser holds at most the limit plus one read of the socket (64 KiB) of a head, and the
check costs a few additions per read. The same limits hold for any other server through
:class:`service.api.limits.HeaderLimit`, which checks the head the server has already read.
"""

from __future__ import annotations

import asyncio
import json
import logging

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from service.api.limits import header_problem
from service.settings import Settings

__all__ = ["LimitedHttpTools", "limited_protocol"]

log = logging.getLogger("uvicorn.error")

LINGER_SECONDS = 2.0
"""How long a refused connection's input is still read (and dropped) before it is closed."""
LINGER_BYTES = 4 << 20
"""How much of it at most."""


class _Refused(Exception):
    """Raised in a parser callback to stop parsing a head that is over a limit."""


def _response(status: int, reason: str, detail: str) -> bytes:
    body = json.dumps({"detail": detail}).encode()
    return (f"HTTP/1.1 {status} {reason}\r\ncontent-type: application/json\r\ncontent-length: {len(body)}\r\n"
            "connection: close\r\n\r\n").encode() + body


class LimitedHttpTools(HttpToolsProtocol):
    """uvicorn's httptools protocol, refusing heads over the class's limits (set by
    :func:`limited_protocol`) with 431, and heads that arrive too slowly with 408."""

    max_header_bytes = 16384
    max_headers = 100
    read_timeout_seconds = 10.0

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._in_head, self._head_bytes, self._fields = True, 0, 0
        self._refusal: bytes | None = None
        self._dropped = 0
        self._head_timer: asyncio.TimerHandle | None = None

    def _refuse(self, status: int, reason: str, detail: str) -> None:
        if self._refusal is None:
            self._refusal = _response(status, reason, detail)
            log.warning("%s:%d - refused: %s", *(self.client or ("?", 0)), detail)
            self._cancel_head_timer()
            if not self.transport.is_closing():
                self.transport.write(self._refusal)
                if self.transport.can_write_eof():
                    self.transport.write_eof()
                    self.loop.call_later(LINGER_SECONDS, self.transport.close)
                else:
                    self.transport.close()

    def _too_large(self, detail: str) -> None:
        self._refuse(431, "Request Header Fields Too Large", detail)

    def _cancel_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_timed_out(self) -> None:
        self._head_timer = None
        self._refuse(408, "Request Timeout", f"the request line and headers did not arrive within "
                     f"{self.read_timeout_seconds:g} s (BSSRDF_READ_TIMEOUT_SECONDS)")

    def data_received(self, data: bytes) -> None:
        if self._refusal is not None:  # refused: lingering, nothing more is parsed
            self._dropped += len(data)
            if self._dropped > LINGER_BYTES and not self.transport.is_closing():
                self.transport.close()
            return
        if self._in_head:
            self._head_bytes += len(data)
            if self._head_timer is None:
                self._head_timer = self.loop.call_later(self.read_timeout_seconds, self._head_timed_out)
        super().data_received(data)
        if self._in_head and self._refusal is None and self._head_bytes > self.max_header_bytes:
            self._too_large(header_problem(self._head_bytes, self._fields, self.max_header_bytes, self.max_headers,
                                           incomplete=True))

    def send_400_response(self, msg: str) -> None:
        if self._refusal is None:  # a head refused in a callback stopped the parser: answered already
            super().send_400_response(msg)

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._fields = 0

    def on_header(self, name: bytes, value: bytes) -> None:
        self._fields += 1
        if self._fields > self.max_headers:
            self._too_large(header_problem(0, self._fields, self.max_header_bytes, self.max_headers, incomplete=True))
            raise _Refused
        super().on_header(name, value)

    def on_headers_complete(self) -> None:
        size = len(self.url) + sum(len(n) + len(v) + 4 for n, v in self.headers)  # "name: value\r\n"
        problem = header_problem(size, len(self.headers), self.max_header_bytes, self.max_headers)
        if problem is not None:
            self._too_large(problem)
            raise _Refused
        self._in_head = False
        self._cancel_head_timer()
        super().on_headers_complete()

    def on_message_complete(self) -> None:
        super().on_message_complete()
        self._in_head, self._head_bytes = True, 0  # the next request on this connection

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_timer()
        super().connection_lost(exc)


def limited_protocol(settings: Settings) -> type[LimitedHttpTools]:
    """:class:`LimitedHttpTools` with the limits of ``settings``."""
    return type("LimitedHttpTools", (LimitedHttpTools,), {
        "max_header_bytes": settings.max_header_bytes, "max_headers": settings.max_headers,
        "read_timeout_seconds": settings.read_timeout_seconds})
