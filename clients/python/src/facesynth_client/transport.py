"""The sync client's HTTP transport: keep-alive HTTP/1.1 connections behind httpx's
transport interface (issue 23, per-frame requests).

httpx's own transport (httpcore over h11) writes a request's headers and body in two
socket writes and reads a response in 64 KiB pieces, each passed through h11's event
parser. For a per-frame synthesis (a few kB up, a 0.5-9 MB NPZ down) on a loaded machine
that is where the client's time goes: the server wakes once for the headers and again
for the body, and the answer is re-assembled from ~9-140 pieces. Measured against the app
with its synthesis stubbed (``benchmarks/http_overhead.py``: uvicorn + httptools, 2 cores,
load 5-6, medians of interleaved calls), per call, wall / client CPU in ms:

=====================  ====================  =====================
client                 538 kB (mesh) answer  8.9 MB (maps) answer
=====================  ====================  =====================
httpx's transport      1.80 / 1.03           25.6 / 10.1
this transport (then)  1.24 / 0.58           12.7 / 2.9
``http.client`` alone  1.32 / 0.45           14.2 / 4.5
=====================  ====================  =====================

:class:`OnePieceTransport` sends plain-``http`` requests whose body is in memory (what
every JSON and NPZ call of the SDK sends) itself: headers and body in one write (a body up
to :data:`ONE_WRITE_MAX`; ``http.client`` writes them in two), and an answer with a
``Content-Length`` up to :data:`ONE_PIECE_MAX` read in one piece before the response is
returned (one buffer, no per-chunk parsing). Answers without a length (chunked, or until
the server closes), or longer ones (job event streams, artifact downloads), are read as they
arrive in pieces of at most :data:`CHUNK`, so streaming works as before. The answer's
status line and headers are read from a buffered reader the connection keeps (RFC 9112:
interim 1xx answers skipped; no body for HEAD, 1xx, 204 and 304; chunked before
``Content-Length``; keep-alive by version and ``Connection``), as ``http.client`` reads
them but without its per-answer reader and its e-mail header parser. Everything else —
``https`` URLs, request bodies that stream (multipart file uploads from disk) — goes to
httpx's own transport. Connections are kept per host and port and reused while the server keeps them
open; an idle one that became readable (the server closed it) is dropped before reuse, as
httpcore does, and a request whose reused connection turns out closed before any answer
(the server's keep-alive timeout raced it) is sent once more on a new connection. Socket
and protocol errors are raised as httpx's exception classes (``ConnectError``,
``ReadTimeout``, ``RemoteProtocolError``, ...), so the client's retry rules are unchanged.

A :class:`~facesynth_client.Client` that made its httpx client with this transport (the
default) hands it each request directly (``Client._send``): ``httpx.Client.send`` would
add only what that client does not use (auth flows, cookies, event hooks, redirects; a
client given a transport mounts no proxies), and the request is the one ``build_request``
made, its URL parsed once per path and query (``Core.request_url``). Measured against the
stubbed app (``http_overhead.py``'s lean server; the SDK before these changes and after,
interleaved in one process, 500 calls; ``--busy 12``: the server first streams memory for
12 ms, as a frame does), per one-frame ``synthesize``, wall / client CPU in ms:

=============================  ===============  ===============  ================
SDK                            mesh             mesh, busy 12    maps, busy 12
=============================  ===============  ===============  ================
before                         1.079 / 0.696    14.167 / 1.205   18.712 / 3.719
after                          0.803 / 0.407    13.784 / 0.817   18.163 / 3.259
``http.client`` alone          0.643 / 0.252    13.367 / 0.417   17.708 / 2.756
=============================  ===============  ===============  ================

(before: this transport over ``http.client``'s connections and answers, through
``httpx.Client.send``; the last row a bare ``http.client`` loop, no SDK.)
"""

from __future__ import annotations

import re
import select
import socket
import threading
from typing import Iterator

import httpx

__all__ = ["OnePieceTransport", "ONE_PIECE_MAX", "ONE_WRITE_MAX", "CHUNK"]

#: answers with a Content-Length up to this many bytes are read in one piece (a streamed
#: download of that size is then held in memory once; larger ones stream in pieces)
ONE_PIECE_MAX = 64 << 20
#: the largest piece of other answers (streams, larger downloads)
CHUNK = 64 << 10
#: a request body up to this many bytes goes out in the headers' write (one copy of it)
ONE_WRITE_MAX = 64 << 10
#: the longest status or header line, and the most header lines, of an answer (as
#: ``http.client``)
MAX_LINE = 65536
MAX_HEADERS = 100

#: a header name as it may be, and what a value must not hold (``http.client``'s checks:
#: no injected lines)
_LEGAL_NAME = re.compile(rb"[^:\s][^:\r\n]*").fullmatch
_ILLEGAL_VALUE = re.compile(rb"\n(?![ \t])|\r(?![ \t\n])").search


def _timeout(request: httpx.Request, kind: str) -> float | None:
    return (request.extensions.get("timeout") or {}).get(kind)


class _Connection:
    """One keep-alive connection: its socket and the buffered reader its answers are read
    from (kept across answers: nothing read ahead is lost)."""

    def __init__(self, sock: socket.socket):
        self.sock = sock
        self.reader = sock.makefile("rb")
        self.fresh = True

    def close(self) -> None:
        sock, self.sock = self.sock, None
        if sock is not None:
            self.reader.close()
            sock.close()


def _is_closed(connection: _Connection) -> bool:
    """Whether an idle keep-alive connection can no longer be used: no socket, or one that
    is readable while no request is in flight (the server closed it, or sent something
    unasked)."""
    sock = connection.sock
    if sock is None:
        return True
    try:
        if hasattr(select, "poll"):      # any descriptor number (select.select: < 1024)
            poller = select.poll()
            poller.register(sock, select.POLLIN)
            return bool(poller.poll(0))
        readable, _, _ = select.select([sock], [], [], 0)
    except (OSError, ValueError):
        return True
    return bool(readable)


def _request_head(request: httpx.Request) -> bytes:
    """The request line and headers, ending in the blank line; a header that would inject a
    line is refused (``httpx.LocalProtocolError``)."""
    lines = [b"%s %s HTTP/1.1" % (request.method.encode("ascii"), request.url.raw_path)]
    for name, value in request.headers.raw:
        if not _LEGAL_NAME(name) or _ILLEGAL_VALUE(value):
            raise httpx.LocalProtocolError(f"invalid header {name!r}: {value!r}", request=request)
        lines.append(name + b": " + value)
    lines += (b"", b"")
    return b"\r\n".join(lines)


class _Closed(Exception):
    """The server closed the connection before an answer's status line."""


class _Head:
    """An answer's status line and headers, and how its body is framed."""

    __slots__ = ("version", "status", "reason", "headers", "length", "chunked", "keep_alive")

    def __init__(self, reader, method: str):
        while True:
            line = reader.readline(MAX_LINE + 1)
            if not line:
                raise _Closed("the server closed the connection without an answer")
            version, _, rest = line.rstrip(b"\r\n").partition(b" ")
            code, _, reason = rest.partition(b" ")
            if not version.startswith(b"HTTP/1.") or len(code) != 3 or not code.isdigit():
                raise httpx.RemoteProtocolError(f"malformed status line {line[:80]!r}")
            headers = _read_headers(reader)
            status = int(code)
            if not 100 <= status < 200:
                break
        self.version, self.status, self.reason, self.headers = version, status, reason, headers
        fields: dict[bytes, bytes] = {}
        for name, value in headers:
            key = name.lower()
            fields[key] = fields[key] + b"," + value if key in fields else value
        connection = fields.get(b"connection", b"").lower()
        self.keep_alive = b"close" not in connection if version == b"HTTP/1.1" \
            else b"keep-alive" in connection
        self.chunked = False
        self.length: int | None = None
        if method == "HEAD" or status in (204, 304):
            self.length = 0
        elif b"chunked" in fields.get(b"transfer-encoding", b"").lower():
            self.chunked = True
        elif b"content-length" in fields:
            values = {v.strip() for v in fields[b"content-length"].split(b",")}
            if len(values) != 1 or not next(iter(values)).isdigit():
                raise httpx.RemoteProtocolError(f"bad Content-Length {fields[b'content-length']!r}")
            self.length = int(values.pop())
        else:                               # read until the server closes
            self.keep_alive = False


def _read_headers(reader) -> list[tuple[bytes, bytes]]:
    """The header (or trailer) lines up to the blank line, as (name, value) stripped."""
    headers = []
    while True:
        line = reader.readline(MAX_LINE + 1)
        if len(line) > MAX_LINE:
            raise httpx.RemoteProtocolError("header line too long")
        if not line:
            raise httpx.RemoteProtocolError("the answer ended inside its headers")
        if line in (b"\r\n", b"\n"):
            return headers
        name, colon, value = line.partition(b":")
        if not colon:
            raise httpx.RemoteProtocolError(f"malformed header line {line[:80]!r}")
        headers.append((name.strip(), value.strip()))
        if len(headers) > MAX_HEADERS:
            raise httpx.RemoteProtocolError(f"more than {MAX_HEADERS} headers")


def _read_exactly(reader, n: int) -> bytes:
    data = reader.read(n)
    if len(data) < n:
        raise httpx.RemoteProtocolError(f"the answer ended after {len(data)} of {n} bytes")
    return data


def _pieces(reader, n: int) -> Iterator[bytes]:
    """The next ``n`` bytes as they arrive, in pieces of at most :data:`CHUNK`."""
    while n:
        piece = reader.read1(min(n, CHUNK))
        if not piece:
            raise httpx.RemoteProtocolError(f"the answer ended {n} bytes short")
        n -= len(piece)
        yield piece


class _Body(httpx.SyncByteStream):
    """A streamed answer's body: chunked, of a length above :data:`ONE_PIECE_MAX`, or until
    the server closes; on close the connection goes back to the transport's idle pool if
    the body was read to its end and the server keeps the connection, else it is closed."""

    def __init__(self, transport: "OnePieceTransport", key: tuple[str, int],
                 connection: _Connection, head: _Head, request: httpx.Request):
        self.transport, self.key, self.connection = transport, key, connection
        self.head, self.request = head, request
        self.done = False

    def __iter__(self) -> Iterator[bytes]:
        reader, head = self.connection.reader, self.head
        try:
            if head.chunked:
                while True:
                    size_line = reader.readline(MAX_LINE + 1)
                    size = size_line.split(b";", 1)[0].strip()
                    try:
                        left = int(size, 16)
                    except ValueError:
                        raise httpx.RemoteProtocolError(f"bad chunk size {size_line[:80]!r}") from None
                    if left == 0:
                        _read_headers(reader)            # trailers
                        break
                    yield from _pieces(reader, left)
                    if reader.readline(MAX_LINE + 1) not in (b"\r\n", b"\n"):
                        raise httpx.RemoteProtocolError("a chunk did not end in CRLF")
            elif head.length is not None:
                yield from _pieces(reader, head.length)
            else:
                while piece := reader.read1(CHUNK):
                    yield piece
            self.done = True
        except Exception as error:
            raise _mapped(error, self.request, "read") from error

    def close(self) -> None:
        self.transport._release(self.key, self.connection, self.done and self.head.keep_alive)


def _mapped(error: Exception, request: httpx.Request, phase: str) -> Exception:
    """The httpx exception for a socket error in ``phase`` (``connect``, ``write``, ``read``)."""
    if isinstance(error, httpx.HTTPError):
        return error
    text = f"{type(error).__name__}: {error}"
    if isinstance(error, (socket.timeout, TimeoutError)):
        kind = {"connect": httpx.ConnectTimeout, "write": httpx.WriteTimeout}.get(
            phase, httpx.ReadTimeout)
        return kind(text, request=request)
    if phase == "connect" and isinstance(error, OSError):
        return httpx.ConnectError(text, request=request)
    if isinstance(error, (_Closed, ConnectionResetError, ConnectionAbortedError)):
        return httpx.RemoteProtocolError(text, request=request)
    if isinstance(error, OSError):
        return (httpx.WriteError if phase == "write" else httpx.ReadError)(text, request=request)
    return error


class OnePieceTransport(httpx.BaseTransport):
    """httpx transport for plain ``http`` (see the module docstring).

    Parameters
    ----------
    fallback : httpx.BaseTransport, optional   for ``https`` and streamed request bodies
                                               (default ``httpx.HTTPTransport()``)
    max_idle : int     idle keep-alive connections kept per host and port
    """

    def __init__(self, fallback: httpx.BaseTransport | None = None, max_idle: int = 8):
        self.fallback = fallback if fallback is not None else httpx.HTTPTransport()
        self.max_idle = max_idle
        self._idle: dict[tuple[str, int], list[_Connection]] = {}
        self._lock = threading.Lock()
        self._closed = False

    # ------------------------------------------------------------------ the pool
    def _check_out(self, key: tuple[str, int]) -> _Connection | None:
        with self._lock:
            idle = self._idle.get(key, [])
            while idle:
                connection = idle.pop()
                if not _is_closed(connection):
                    return connection
                connection.close()
        return None

    def _release(self, key: tuple[str, int], connection: _Connection, reusable: bool) -> None:
        """A connection whose answer is done: back to the idle pool if ``reusable`` (and the
        pool has room), else closed."""
        if reusable:
            with self._lock:
                idle = self._idle.setdefault(key, [])
                if not self._closed and len(idle) < self.max_idle:
                    idle.append(connection)
                    return
        connection.close()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            connections = [c for idle in self._idle.values() for c in idle]
            self._idle.clear()
        for connection in connections:
            connection.close()
        self.fallback.close()

    # ------------------------------------------------------------------ a request
    def handle_request(self, request: httpx.Request) -> httpx.Response:
        if request.url.scheme != "http" or not isinstance(request.stream, httpx.ByteStream):
            return self.fallback.handle_request(request)
        key = (request.url.host, request.url.port or 80)
        head = _request_head(request)
        body = request.read()
        connection = self._check_out(key)
        if connection is not None:
            try:
                return self._exchange(key, connection, request, head, body)
            except _Stale:   # closed by the server meanwhile: once more, on a new connection
                pass
        return self._exchange(key, self._connect(key, request), request, head, body)

    def _connect(self, key: tuple[str, int], request: httpx.Request) -> _Connection:
        try:
            sock = socket.create_connection(key, timeout=_timeout(request, "connect"))
        except Exception as error:
            raise _mapped(error, request, "connect") from error
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return _Connection(sock)

    def _exchange(self, key: tuple[str, int], connection: _Connection, request: httpx.Request,
                  head: bytes, body: bytes) -> httpx.Response:
        """Send ``request`` on ``connection`` and read the status line and headers, and a
        sized body up to :data:`ONE_PIECE_MAX`; :class:`_Stale` if a reused connection
        turns out closed before any answer."""
        reused, connection.fresh = not connection.fresh, False
        phase = "write"
        try:
            sock = connection.sock
            sock.settimeout(_timeout(request, "write"))
            if body and len(body) <= ONE_WRITE_MAX:
                sock.sendall(head + body)                # headers and body in one write
            else:
                sock.sendall(head)
                if body:
                    sock.sendall(body)
            phase = "read"
            sock.settimeout(_timeout(request, "read"))
            answer = _Head(connection.reader, request.method)
            data = None
            if not answer.chunked and answer.length is not None and answer.length <= ONE_PIECE_MAX:
                data = _read_exactly(connection.reader, answer.length)
        except Exception as error:
            connection.close()
            if reused and isinstance(error, (_Closed, BrokenPipeError, ConnectionResetError)):
                raise _Stale() from error
            raise _mapped(error, request, phase) from error
        extensions = {"http_version": answer.version, "reason_phrase": answer.reason}
        if data is None:
            return httpx.Response(answer.status, headers=answer.headers, extensions=extensions,
                                  stream=_Body(self, key, connection, answer, request))
        self._release(key, connection, answer.keep_alive)
        return httpx.Response(answer.status, headers=answer.headers, extensions=extensions,
                              stream=httpx.ByteStream(data))


class _Stale(Exception):
    """A kept-alive connection was closed by the server before it answered."""
