"""Slow clients: how uvicorn is configured so that a client cannot hold a connection open by
sending nothing, or its headers a byte at a time.

- headers: a connection must deliver a request's complete headers within
  `settings.header_timeout` seconds of connecting (or of its previous response), else it is
  closed (`SlowHeaderH11Protocol`; uvicorn itself only times idle keep-alive connections);
- body: `service.guard` answers 408 when a body pauses longer than `settings.body_timeout` or
  trickles slower than `settings.min_body_rate`;
- idle keep-alive connections close after KEEP_ALIVE seconds (uvicorn's own timer);
- headers are capped at MAX_HEADER_BYTES with 431: by h11's limit on an incomplete event while
  they arrive (answered here), by `service.guard` once they are complete.
"""

from __future__ import annotations

import asyncio
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from .errors import error_body
from .guard import ANSWER_HEADERS, MAX_HEADER_BYTES
from .settings import Settings

KEEP_ALIVE = 5


class SlowHeaderH11Protocol(H11Protocol):
    """uvicorn's h11 protocol, plus a deadline for the headers of every request and 431 for too many."""

    header_timeout = 10.0

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._header_timer: asyncio.TimerHandle | None = None
        self._arm()

    def data_received(self, data: bytes) -> None:
        idle = self.cycle is None or self.cycle.response_complete
        if idle and self._header_timer is None:
            self._arm()                      # the first bytes of a new request on a kept-alive connection
        super().data_received(data)
        if self.cycle is not None and not self.cycle.response_complete:
            self._disarm()                   # its headers are complete: a request is running

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _arm(self) -> None:
        self._header_timer = self.loop.call_later(self.header_timeout, self._too_slow)

    def _disarm(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def send_400_response(self, msg: str) -> None:
        """uvicorn answers every request h11 refuses with 400; one whose head outgrew the cap gets 431."""
        if len(self.conn.trailing_data[0]) <= MAX_HEADER_BYTES:   # h11's only reason to buffer that much
            super().send_400_response(msg)
            return
        body = error_body("headers_too_large", f"the request headers exceed the cap of {MAX_HEADER_BYTES} bytes")
        headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                   (b"connection", b"close"), *ANSWER_HEADERS]
        for event in (h11.Response(status_code=431, headers=headers), h11.Data(data=body), h11.EndOfMessage()):
            self.transport.write(self.conn.send(event))
        self.transport.close()

    def _too_slow(self) -> None:
        self._header_timer = None
        if self.cycle is None or self.cycle.response_complete:
            self.transport.close()


def uvicorn_options(settings: Settings) -> dict[str, Any]:
    """Keyword arguments for uvicorn.Config / uvicorn.run that enforce the timeouts above."""
    protocol = type("SlowHeaderH11Protocol", (SlowHeaderH11Protocol,), {"header_timeout": settings.header_timeout})
    return {"http": protocol, "timeout_keep_alive": KEEP_ALIVE, "h11_max_incomplete_event_size": MAX_HEADER_BYTES}
