"""Connection-level limits of the HTTP server: header and body read timeouts, and
connections per client address (issue 16, defect 10).

uvicorn bounds the idle time *between* requests on a kept-alive connection
(``timeout_keep_alive``) and the total number of connections (``limit_concurrency``), but
nothing bounds how long a client may take to send a request's headers or body: a hundred
clients sending one byte every five seconds held a hundred connections open indefinitely.
:class:`GuardedH11Protocol` (uvicorn's pure-Python h11 protocol) and
:class:`GuardedHttpToolsProtocol` (its httptools protocol, the C parser of ``uvicorn[standard]``)
add three more bounds, written once in :class:`ConnectionGuard`:

- **headers**: a request's headers must be complete within ``header_timeout`` seconds of
  its first byte (or of the connection being made); otherwise the connection is closed
  (with ``408 Request Timeout`` when nothing was answered yet);
- **body**: once ``body_grace`` seconds of a body have passed, the body must arrive at an
  average of at least ``min_body_rate`` bytes per second, and never stall for longer than
  ``header_timeout`` seconds; otherwise the connection is closed and the application sees a
  client disconnect;
- **per client**: at most ``max_per_client`` simultaneous connections from one IP address;
  one more is answered ``503`` with ``Retry-After`` and closed.

:func:`protocol_class` makes the class for a :class:`service.config.Settings` (``http``:
``h11``, ``httptools``, or ``auto``, httptools when installed); ``facesynth serve`` passes it
to uvicorn as ``http=``. The guard reads the parser's state through three questions
(:meth:`ConnectionGuard._phase`: before/inside a request's headers, inside its body, or
past it; :meth:`ConnectionGuard._responding`), which each protocol answers from its parser:
h11's connection states, or the httptools callbacks (``on_message_begin``,
``on_headers_complete``, ``on_message_complete``).
"""

from __future__ import annotations

import abc
import asyncio
import logging
import time
from collections import Counter
from typing import Any, Literal

import h11
from uvicorn.protocols.http.h11_impl import DEFAULT_MAX_INCOMPLETE_EVENT_SIZE, H11Protocol

from service.api.coalesced_writes import coalesced

try:                                    # uvicorn[standard]
    import httptools  # noqa: F401
    from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
except ImportError:                     # pragma: no cover - depends on the installation
    HttpToolsProtocol = None

log = logging.getLogger(__name__)

#: how often a body's rate is checked, seconds
CHECK_INTERVAL = 0.5


def _raw_response(status: int, reason: str, detail: str, extra: str = "") -> bytes:
    body = ('{"type":"about:blank","title":"%s","status":%d,"detail":"%s"}'
            % (reason, status, detail)).encode()
    return (f"HTTP/1.1 {status} {reason}\r\ncontent-type: application/problem+json\r\n"
            f"content-length: {len(body)}\r\nconnection: close\r\n{extra}\r\n").encode() + body


#: a request's phase as the guard sees it: waiting for or inside its headers, inside its body,
#: or read completely (the response is the application's business)
Phase = Literal["headers", "body", "done"]
#: the HTTP implementations :func:`protocol_class` can guard
HTTP_IMPLEMENTATIONS = ("h11", "httptools")


class ConnectionGuard(abc.ABC):
    """Header/body timeouts and a per-client bound for a uvicorn HTTP protocol (see the
    module docstring), mixed in before the protocol class. The limits are class
    attributes, set by :func:`protocol_class`; the protocol supplies :meth:`_phase` and
    :meth:`_responding` from its parser and calls :meth:`_count_body` with body bytes."""

    header_timeout: float = 10.0
    min_body_rate: float = 1024.0
    body_grace: float = 10.0
    max_per_client: int = 32
    #: open connections per client address, shared by every connection of the process
    per_client: Counter[str] = Counter()

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._header_timer: asyncio.TimerHandle | None = None
        self._header_deadline = 0.0               # time.monotonic() the headers are due by
        self._body_timer: asyncio.TimerHandle | None = None
        self._body_started = 0.0
        self._body_bytes = 0
        self._last_data = 0.0
        self._address: str | None = None

    # -- what the parser says ---------------------------------------------------------------
    @abc.abstractmethod
    def _phase(self) -> Phase:
        """Where the client's side of the connection is: headers, body or between requests."""

    @abc.abstractmethod
    def _responding(self) -> bool:
        """Whether a request is being answered (not between requests)."""

    def _count_body(self, n: int) -> None:
        """``n`` bytes of a chunk received inside a body."""
        self._body_bytes += n

    def _start_body_count(self) -> None:
        self._body_bytes = 0

    # -- connection ------------------------------------------------------------------------
    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)  # type: ignore[misc]
        # a response's head and body in one write (service/api/coalesced_writes.py)
        self.transport = coalesced(transport, self.loop)  # type: ignore[attr-defined]
        self._address = self.client[0] if self.client else None  # type: ignore[attr-defined]
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
        super().connection_lost(exc)  # type: ignore[misc]

    def data_received(self, data: bytes) -> None:
        now = time.monotonic()
        self._last_data = now
        super().data_received(data)  # type: ignore[misc]
        if self.transport.is_closing():  # type: ignore[attr-defined]
            return
        phase = self._phase()
        if phase == "headers":                          # between requests or inside headers
            if self._header_timer is None and not self._responding():
                self._arm_header_timer()
            self._cancel_body_timer()
        else:                                           # the headers are complete
            self._cancel_header_timer()
            if phase == "body":
                if self._body_timer is None:
                    self._body_started = now
                    self._start_body_count()
                    self._body_timer = self.loop.call_later(  # type: ignore[attr-defined]
                        CHECK_INTERVAL, self._check_body)
                self._count_body(len(data))
            else:
                self._cancel_body_timer()

    # uvicorn's keep-alive timer bounds the wait for the next request's first byte

    # -- timers ----------------------------------------------------------------------------
    def _arm_header_timer(self) -> None:
        self._cancel_header_timer()
        self._header_deadline = time.monotonic() + self.header_timeout
        self._header_timer = self.loop.call_later(  # type: ignore[attr-defined]
            self.header_timeout, self._headers_too_slow)

    def _headers_too_slow(self) -> None:
        self._header_timer = None
        early = self._header_deadline - time.monotonic()
        if early > 0:       # uvloop's timers round to the millisecond: not before the bound
            self._header_timer = self.loop.call_later(early, self._headers_too_slow)  # type: ignore[attr-defined]
            return
        transport = self.transport  # type: ignore[attr-defined]
        if transport.is_closing() or self._phase() != "headers":
            return
        if self._responding():                    # a response is in progress: not our turn
            return
        log.warning("closed a connection from %s: request headers not complete within %.0f s",
                    self._address, self.header_timeout)
        cycle = self.cycle  # type: ignore[attr-defined]
        if cycle is None or cycle.response_complete:
            transport.write(_raw_response(
                408, "Request Timeout",
                f"the request headers did not arrive within {self.header_timeout:g} s"))
        transport.close()

    def _check_body(self) -> None:
        self._body_timer = None
        transport = self.transport  # type: ignore[attr-defined]
        if transport.is_closing() or self._phase() != "body":
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
            transport.close()
            return
        self._body_timer = self.loop.call_later(  # type: ignore[attr-defined]
            CHECK_INTERVAL, self._check_body)

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


class BodyPassthroughConnection(h11.Connection):
    """h11's server connection whose :meth:`send` hands a body back as the object it was
    given when it is all there is to write (a ``Content-Length`` response's ``Data``), not
    as ``b"".join`` of it: h11's :meth:`~h11.Connection.send` copies every response body
    once more before the transport writes it (a 9 MB maps answer: ~2-3 ms). Whatever else
    (headers, chunk framing) is joined as h11 does; the bytes written are the same."""

    def send(self, event: h11.Event) -> bytes | None:   # type: ignore[override]
        data = self.send_with_data_passthrough(event)
        if data is None:
            return None
        return data[0] if len(data) == 1 else b"".join(data)


class GuardedH11Protocol(ConnectionGuard, H11Protocol):
    """uvicorn's :class:`H11Protocol` with the :class:`ConnectionGuard` bounds; the phase is
    h11's state of the client's side (IDLE: between requests or inside headers; SEND_BODY)
    and a response is in progress unless our side is IDLE. Its h11 connection is a
    :class:`BodyPassthroughConnection` (made as uvicorn makes its own)."""

    def __init__(self, config: Any, *args: Any, **kwargs: Any) -> None:
        super().__init__(config, *args, **kwargs)
        self.conn = BodyPassthroughConnection(
            h11.SERVER, config.h11_max_incomplete_event_size
            if config.h11_max_incomplete_event_size is not None
            else DEFAULT_MAX_INCOMPLETE_EVENT_SIZE)

    def _phase(self) -> Phase:
        state = self.conn.their_state
        return "headers" if state is h11.IDLE else "body" if state is h11.SEND_BODY else "done"

    def _responding(self) -> bool:
        return self.conn.our_state is not h11.IDLE


if HttpToolsProtocol is not None:
    class GuardedHttpToolsProtocol(ConnectionGuard, HttpToolsProtocol):
        """uvicorn's :class:`HttpToolsProtocol` (the httptools C parser) with the
        :class:`ConnectionGuard` bounds. httptools has no connection state to ask, so the
        phase follows its callbacks: ``headers`` from the connection (or the previous
        response) until ``on_headers_complete``, then ``body`` until
        ``on_message_complete``, then ``done`` until the response completes; body bytes
        are counted in ``on_body`` (the body alone, not the chunk's headers)."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self._request_phase: Phase = "headers"

        def _phase(self) -> Phase:
            return self._request_phase

        def _responding(self) -> bool:
            return self.cycle is not None and not self.cycle.response_complete

        def _count_body(self, n: int) -> None:
            pass                                         # counted in on_body

        def _start_body_count(self) -> None:
            pass                                         # reset in on_headers_complete

        def on_message_begin(self) -> None:
            super().on_message_begin()
            self._request_phase = "headers"

        def on_headers_complete(self) -> None:
            super().on_headers_complete()
            self._request_phase, self._body_bytes = "body", 0

        def on_body(self, body: bytes) -> None:
            super().on_body(body)
            self._body_bytes += len(body)

        def on_message_complete(self) -> None:
            super().on_message_complete()
            self._request_phase = "done"

        def on_response_complete(self) -> None:
            if self._request_phase == "done" and not self.pipeline:
                self._request_phase = "headers"          # the next request's, if any
            super().on_response_complete()
else:                                                    # pragma: no cover
    GuardedHttpToolsProtocol = None  # type: ignore[assignment,misc]


def resolve_http(http: str) -> str:
    """The HTTP implementation for a setting: ``h11``, ``httptools``, or ``auto``
    (httptools when ``uvicorn[standard]`` is installed, else h11). ``ValueError`` for
    httptools when it is not installed, or an unknown name."""
    if http == "auto":
        return "httptools" if GuardedHttpToolsProtocol is not None else "h11"
    if http not in HTTP_IMPLEMENTATIONS:
        raise ValueError(f"unknown HTTP implementation {http!r}; expected auto, "
                         + ", ".join(HTTP_IMPLEMENTATIONS))
    if http == "httptools" and GuardedHttpToolsProtocol is None:
        raise ValueError("http 'httptools' needs httptools: pip install 'uvicorn[standard]'")
    return http


def protocol_class(header_timeout: float, min_body_rate: float, body_grace: float,
                   max_per_client: int, http: str = "h11") -> type[ConnectionGuard]:
    """A guarded protocol subclass (of :class:`GuardedH11Protocol` or
    :class:`GuardedHttpToolsProtocol`, by :func:`resolve_http`) with these limits and its
    own per-client counter (pass it to uvicorn as ``http=``)."""
    base = (GuardedHttpToolsProtocol if resolve_http(http) == "httptools"
            else GuardedH11Protocol)
    return type(base.__name__, (base,), {
        "header_timeout": float(header_timeout), "min_body_rate": float(min_body_rate),
        "body_grace": float(body_grace), "max_per_client": int(max_per_client),
        "per_client": Counter()})
