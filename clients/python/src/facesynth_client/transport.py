"""The sync client's HTTP transport: ``http.client`` keep-alive connections behind httpx's
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
this transport         1.24 / 0.58           12.7 / 2.9
``http.client`` alone  1.32 / 0.45           14.2 / 4.5
=====================  ====================  =====================

:class:`OnePieceTransport` sends plain-``http`` requests whose body is in memory (what
every JSON and NPZ call of the SDK sends) through ``http.client``: headers and body in one
write (a body up to :data:`ONE_WRITE_MAX`; ``http.client`` itself writes them in two), and an answer with a ``Content-Length`` up to :data:`ONE_PIECE_MAX` read in one piece
when httpx reads the response (one buffer, no per-chunk parsing). Answers without a
length, or longer ones (job event streams, artifact downloads), are read as they arrive in
:data:`CHUNK` pieces, so streaming works as before. Everything else — ``https`` URLs,
request bodies that stream (multipart file uploads from disk) — goes to httpx's own
transport. Connections are kept per host and port and reused while the server keeps them
open; an idle one that became readable (the server closed it) is dropped before reuse, as
httpcore does, and a request whose reused connection turns out closed before any answer
(the server's keep-alive timeout raced it) is sent once more on a new connection. Socket
errors are raised as httpx's exception classes (``ConnectError``,
``ReadTimeout``, ...), so the client's retry rules are unchanged.

A :class:`~facesynth_client.Client` that made its httpx client with this transport (the
default) hands it each request directly (``Client._send``): ``httpx.Client.send`` would
add only what that client does not use (auth flows, cookies, event hooks, redirects; a
client given a transport mounts no proxies), and the request is the one ``build_request``
made, its URL parsed once per path and query (``Core.request_url``). Per one-frame mesh
synthesis against the stubbed app (``http_overhead.py``'s lean server, 538 kB answers, 300
interleaved calls, the previous SDK beside this one), wall / client CPU in ms:
0.958 / 0.574 → 0.827 / 0.442; with ``--busy 12`` (the server streams memory for 12 ms
first, as a frame does) 14.187 / 1.165 → 13.955 / 0.966 (``http.client`` alone: 13.395 /
0.400).
"""

from __future__ import annotations

import http.client
import select
import socket
import threading
from typing import Iterator

import httpx

__all__ = ["OnePieceTransport", "ONE_PIECE_MAX", "ONE_WRITE_MAX", "CHUNK"]

#: answers with a Content-Length up to this many bytes are read in one piece (a streamed
#: download of that size is then held in memory once; larger ones stream in pieces)
ONE_PIECE_MAX = 64 << 20
#: the piece size of other answers (streams, larger downloads)
CHUNK = 64 << 10


def _timeout(request: httpx.Request, kind: str) -> float | None:
    return (request.extensions.get("timeout") or {}).get(kind)


def _is_closed(connection: http.client.HTTPConnection) -> bool:
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


#: a request body up to this many bytes goes out in the headers' write (one copy of it)
ONE_WRITE_MAX = 64 << 10


class _Connection(http.client.HTTPConnection):
    """``http.client``'s connection writing the headers and a body of up to
    :data:`ONE_WRITE_MAX` bytes in one ``sendall``: Python 3's ``endheaders(body)`` writes
    them in two, so the server is woken for the headers and again for the body (a per-frame
    synthesis request: 0.3 kB of headers, 3.6 kB of markers)."""

    def _send_output(self, message_body=None, encode_chunked=False):   # noqa: ANN001
        if (isinstance(message_body, (bytes, bytearray)) and not encode_chunked
                and len(message_body) <= ONE_WRITE_MAX):
            self._buffer.extend((b"", b""))
            head = b"\r\n".join(self._buffer)
            del self._buffer[:]
            self.send(head + message_body)
            return
        super()._send_output(message_body, encode_chunked)


class _Body(httpx.SyncByteStream):
    """A response body read from ``http.client``; on close the connection goes back to the
    transport's idle pool if the answer was read to its end and the server keeps the
    connection, else it is closed."""

    def __init__(self, transport: "OnePieceTransport", key: tuple[str, int],
                 connection: http.client.HTTPConnection, response: http.client.HTTPResponse,
                 request: httpx.Request):
        self.transport, self.key = transport, key
        self.connection, self.response, self.request = connection, response, request

    def __iter__(self) -> Iterator[bytes]:
        response = self.response
        try:
            if not response.chunked and response.length is not None \
                    and response.length <= ONE_PIECE_MAX:
                data = response.read()     # exactly Content-Length bytes, or IncompleteRead
                if data:
                    yield data
                return
            while True:
                chunk = response.read1(CHUNK)
                if not chunk:
                    return
                yield chunk
        except Exception as error:
            raise _mapped(error, self.request, "read") from error

    def close(self) -> None:
        response, connection = self.response, self.connection
        reusable = response.isclosed() and not response.will_close
        response.close()
        if reusable:
            self.transport._check_in(self.key, connection)
        else:
            connection.close()


def _mapped(error: Exception, request: httpx.Request, phase: str) -> Exception:
    """The httpx exception for a socket or ``http.client`` error in ``phase`` (``connect``,
    ``write``, ``read``)."""
    if isinstance(error, httpx.HTTPError):
        return error
    text = f"{type(error).__name__}: {error}"
    if isinstance(error, (socket.timeout, TimeoutError)):
        kind = {"connect": httpx.ConnectTimeout, "write": httpx.WriteTimeout}.get(
            phase, httpx.ReadTimeout)
        return kind(text, request=request)
    if phase == "connect" and isinstance(error, OSError):
        return httpx.ConnectError(text, request=request)
    if isinstance(error, (http.client.HTTPException, ConnectionError)) and not isinstance(
            error, (BrokenPipeError,)):
        return httpx.RemoteProtocolError(text, request=request)
    if isinstance(error, OSError):
        return (httpx.WriteError if phase == "write" else httpx.ReadError)(text, request=request)
    return error


class OnePieceTransport(httpx.BaseTransport):
    """httpx transport over ``http.client`` for plain ``http`` (see the module docstring).

    Parameters
    ----------
    fallback : httpx.BaseTransport, optional   for ``https`` and streamed request bodies
                                               (default ``httpx.HTTPTransport()``)
    max_idle : int     idle keep-alive connections kept per host and port
    """

    def __init__(self, fallback: httpx.BaseTransport | None = None, max_idle: int = 8):
        self.fallback = fallback if fallback is not None else httpx.HTTPTransport()
        self.max_idle = max_idle
        self._idle: dict[tuple[str, int], list[http.client.HTTPConnection]] = {}
        self._lock = threading.Lock()
        self._closed = False

    # ------------------------------------------------------------------ the pool
    def _check_out(self, key: tuple[str, int]) -> http.client.HTTPConnection | None:
        with self._lock:
            idle = self._idle.get(key, [])
            while idle:
                connection = idle.pop()
                if not _is_closed(connection):
                    return connection
                connection.close()
        return None

    def _check_in(self, key: tuple[str, int], connection: http.client.HTTPConnection) -> None:
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
        body = request.read()
        connection = self._check_out(key)
        if connection is not None:
            try:
                return self._exchange(key, connection, request, body)
            except _Stale:   # closed by the server meanwhile: once more, on a new connection
                pass
        return self._exchange(key, self._connect(key, request), request, body)

    def _connect(self, key: tuple[str, int], request: httpx.Request
                 ) -> http.client.HTTPConnection:
        connection = _Connection(*key, timeout=_timeout(request, "connect"))
        try:
            connection.connect()
            connection.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except Exception as error:
            connection.close()
            raise _mapped(error, request, "connect") from error
        connection.fresh = True   # type: ignore[attr-defined]
        return connection

    def _exchange(self, key: tuple[str, int], connection: http.client.HTTPConnection,
                  request: httpx.Request, body: bytes) -> httpx.Response:
        """Send ``request`` on ``connection`` and read the status line and headers;
        :class:`_Stale` if a reused connection turns out closed before any answer."""
        reused = not getattr(connection, "fresh", False)
        connection.fresh = False   # type: ignore[attr-defined]
        phase = "write"
        try:
            connection.sock.settimeout(_timeout(request, "write"))
            connection.putrequest(request.method, request.url.raw_path.decode("ascii"),
                                  skip_host=True, skip_accept_encoding=True)
            for name, value in request.headers.raw:
                connection.putheader(name, value)
            connection.endheaders(body or None)   # headers and body in one write
            phase = "read"
            connection.sock.settimeout(_timeout(request, "read"))
            response = connection.getresponse()
        except Exception as error:
            connection.close()
            if reused and isinstance(error, (BrokenPipeError, ConnectionResetError,
                                             http.client.RemoteDisconnected)):
                raise _Stale() from error
            raise _mapped(error, request, phase) from error
        return httpx.Response(
            response.status, headers=response.getheaders(),
            stream=_Body(self, key, connection, response, request),
            extensions={"http_version": b"HTTP/1.1" if response.version == 11 else b"HTTP/1.0",
                        "reason_phrase": response.reason.encode("ascii", "replace")})


class _Stale(Exception):
    """A kept-alive connection was closed by the server before it answered."""
