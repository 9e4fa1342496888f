"""Connection-level limits of the HTTP server: header and body read timeouts, and
connections per client address (issue 16, defect 10).

uvicorn bounds the idle time *between* requests on a kept-alive connection
(``timeout_keep_alive``) and the total number of connections (``limit_concurrency``), but
nothing bounds how long a client may take to send a request's headers or body: a hundred
clients sending one byte every five seconds held a hundred connections open indefinitely.
:class:`GuardedH11Protocol` is uvicorn's h11 protocol with three more bounds:

- **headers**: a request's headers must be complete within ``header_timeout`` seconds of
  its first byte (or of the connection being made); otherwise the connection is closed
  (with ``408 Request Timeout`` when nothing was answered yet);
- **body**: once ``body_grace`` seconds of a body have passed, the body must arrive at an
  average of at least ``min_body_rate`` bytes per second, and never stall for longer than
  ``header_timeout`` seconds; otherwise the connection is closed and the application sees a
  client disconnect;
- **per client**: at most ``max_per_client`` simultaneous connections from one IP address;
  one more is answered ``503`` with ``Retry-After`` and closed.

:func:`protocol_class` makes the class for a :class:`service.config.Settings`; ``facesynth
serve`` passes it to uvicorn as ``http=``.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import Counter
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

log = logging.getLogger(__name__)

#: how often a body's rate is checked, seconds
CHECK_INTERVAL = 0.5


def _raw_response(status: int, reason: str, detail: str, extra: str = "") -> bytes:
    body = ('{"type":"about:blank","title":"%s","status":%d,"detail":"%s"}'
            % (reason, status, detail)).encode()
    return (f"HTTP/1.1 {status} {reason}\r\ncontent-type: application/problem+json\r\n"
            f"content-length: {len(body)}\r\nconnection: close\r\n{extra}\r\n").encode() + body


class GuardedH11Protocol(H11Protocol):
    """uvicorn's :class:`H11Protocol` with header/body timeouts and a per-client bound (see
    the module docstring). The limits are class attributes, set by :func:`protocol_class`."""

    header_timeout: float = 10.0
    min_body_rate: float = 1024.0
    body_grace: float = 10.0
    max_per_client: int = 32
    #: open connections per client address, shared by every connection of the process
    per_client: Counter[str] = Counter()

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._header_timer: asyncio.TimerHandle | None = None
        self._body_timer: asyncio.TimerHandle | None = None
        self._body_started = 0.0
        self._body_bytes = 0
        self._last_data = 0.0
        self._address: str | None = None

    # -- connection ------------------------------------------------------------------------
    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._address = self.client[0] if self.client else None
        if self._address is not None:
            self.per_client[self._address] += 1
            if self.per_client[self._address] > self.max_per_client:
                log.warning("refused a connection from %s: %d open, at most %d per client",
                            self._address, self.per_client[self._address] - 1,
                            self.max_per_client)
                transport.write(_raw_response(
                    503, "Service Unavailable",
                    f"too many connections from this address (at most {self.max_per_client})",
                    "retry-after: 1\r\n"))
                transport.close()
                return
        self._arm_header_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_timers()
        if self._address is not None:
            self.per_client[self._address] -= 1
            if self.per_client[self._address] <= 0:
                del self.per_client[self._address]
            self._address = None
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        now = time.monotonic()
        self._last_data = now
        super().data_received(data)
        if self.transport.is_closing():
            return
        if self.conn.their_state is h11.IDLE:          # between requests or inside headers
            if self._header_timer is None and self.conn.our_state is h11.IDLE:
                self._arm_header_timer()
            self._cancel_body_timer()
        else:                                           # the headers are complete
            self._cancel_header_timer()
            if self.conn.their_state is h11.SEND_BODY:
                if self._body_timer is None:
                    self._body_started, self._body_bytes = now, 0
                    self._body_timer = self.loop.call_later(CHECK_INTERVAL, self._check_body)
                self._body_bytes += len(data)
            else:
                self._cancel_body_timer()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        # uvicorn's keep-alive timer now bounds the wait for the next request's first byte

    # -- timers ----------------------------------------------------------------------------
    def _arm_header_timer(self) -> None:
        self._cancel_header_timer()
        self._header_timer = self.loop.call_later(self.header_timeout, self._headers_too_slow)

    def _headers_too_slow(self) -> None:
        self._header_timer = None
        if self.transport.is_closing() or self.conn.their_state is not h11.IDLE:
            return
        if self.conn.our_state is not h11.IDLE:   # a response is in progress: not our turn
            return
        log.warning("closed a connection from %s: request headers not complete within %.0f s",
                    self._address, self.header_timeout)
        if self.cycle is None or self.cycle.response_complete:
            self.transport.write(_raw_response(
                408, "Request Timeout",
                f"the request headers did not arrive within {self.header_timeout:g} s"))
        self.transport.close()

    def _check_body(self) -> None:
        self._body_timer = None
        if self.transport.is_closing() or self.conn.their_state is not h11.SEND_BODY:
            return
        now = time.monotonic()
        elapsed = now - self._body_started
        stalled = now - self._last_data
        slow = elapsed > self.body_grace and self._body_bytes / elapsed < self.min_body_rate
        if slow or stalled > self.header_timeout:
            log.warning("closed a connection from %s: request body at %.0f B/s after %.1f s "
                        "(at least %.0f B/s required), %.1f s since its last bytes",
                        self._address, self._body_bytes / max(elapsed, 1e-9), elapsed,
                        self.min_body_rate, stalled)
            self.transport.close()
            return
        self._body_timer = self.loop.call_later(CHECK_INTERVAL, self._check_body)

    def _cancel_header_timer(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _cancel_body_timer(self) -> None:
        if self._body_timer is not None:
            self._body_timer.cancel()
            self._body_timer = None

    def _cancel_timers(self) -> None:
        self._cancel_header_timer()
        self._cancel_body_timer()


def protocol_class(header_timeout: float, min_body_rate: float, body_grace: float,
                   max_per_client: int) -> type[GuardedH11Protocol]:
    """A :class:`GuardedH11Protocol` subclass with these limits and its own per-client
    counter (pass it to uvicorn as ``http=``)."""
    return type("GuardedH11Protocol", (GuardedH11Protocol,), {
        "header_timeout": float(header_timeout), "min_body_rate": float(min_body_rate),
        "body_grace": float(body_grace), "max_per_client": int(max_per_client),
        "per_client": Counter()})
