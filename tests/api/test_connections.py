"""service.api.connections: slow headers, slow bodies and too many connections per client
are cut off within their bounds (issue 16, defect 10). A real uvicorn server on loopback."""

from __future__ import annotations

import socket
import time

import pytest

from service.api.connections import (ConnectionGuard, GuardedH11Protocol,
                                      GuardedHttpToolsProtocol, protocol_class, resolve_http)
from tests.servers import uvicorn_thread

HEADER_TIMEOUT, MIN_RATE, GRACE, PER_CLIENT = 1.0, 200.0, 1.0, 4


async def app(scope, receive, send):
    if scope["type"] != "http":
        return
    size = 0
    while True:
        message = await receive()
        size += len(message.get("body", b""))
        if not message.get("more_body"):
            break
    body = str(size).encode()
    await send({"type": "http.response.start", "status": 200,
                "headers": [(b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})


#: every guarded implementation installed here (httptools with uvicorn[standard])
IMPLEMENTATIONS = ["h11"] + (["httptools"] if GuardedHttpToolsProtocol is not None else [])


@pytest.fixture(scope="module", params=IMPLEMENTATIONS)
def server(request):
    http = protocol_class(HEADER_TIMEOUT, MIN_RATE, GRACE, PER_CLIENT, http=request.param)
    assert issubclass(http, ConnectionGuard)
    with uvicorn_thread(app, http=http, timeout_keep_alive=5) as port:
        yield port


def connect(port) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=10)
    return s


def closed_after(s: socket.socket, trickle: bytes, every: float, limit: float) -> tuple[float, bytes]:
    """Send ``trickle`` one byte every ``every`` s until the server closes; (seconds, reply)."""
    start = time.monotonic()
    reply = b""
    s.settimeout(every)
    for byte in trickle:
        try:
            s.sendall(bytes([byte]))
        except OSError:
            break
        try:
            chunk = s.recv(4096)
            reply += chunk
            if not chunk:
                break
        except socket.timeout:
            pass
        except OSError:
            break
        assert time.monotonic() - start < limit, "the server kept the connection open"
    return time.monotonic() - start, reply


def test_a_normal_request_is_answered(server):
    with connect(server) as s:
        s.sendall(b"POST / HTTP/1.1\r\nhost: x\r\ncontent-length: 5\r\n\r\nhello")
        reply = b""
        while not reply.endswith(b"\r\n\r\n5"):
            chunk = s.recv(4096)
            assert chunk, reply
            reply += chunk
        assert reply.startswith(b"HTTP/1.1 200 ")


def test_slow_headers_of_a_kept_alive_connection_s_next_request_are_cut_off(server):
    with connect(server) as s:
        s.sendall(b"POST / HTTP/1.1\r\nhost: x\r\ncontent-length: 5\r\n\r\nhello")
        reply = b""
        while not reply.endswith(b"\r\n\r\n5"):
            chunk = s.recv(4096)
            assert chunk, reply
            reply += chunk
        took, reply = closed_after(s, b"GET / HTTP/1.1\r\nhost: x\r\n" + b"x" * 100, 0.2, 5)
    assert HEADER_TIMEOUT <= took < HEADER_TIMEOUT + 1.0
    assert reply.startswith(b"HTTP/1.1 408 ")


def test_a_body_at_a_good_rate_after_the_grace_is_read(server):
    """1 kB in 20 chunks over ~1.4 s (above GRACE) at ~700 B/s >= MIN_RATE: answered."""
    with connect(server) as s:
        s.sendall(b"POST / HTTP/1.1\r\nhost: x\r\ncontent-length: 1000\r\n\r\n")
        for _ in range(20):
            s.sendall(b"z" * 50)
            time.sleep(0.07)
        reply = b""
        while not reply.endswith(b"\r\n\r\n1000"):
            chunk = s.recv(4096)
            assert chunk, reply
            reply += chunk
        assert reply.startswith(b"HTTP/1.1 200 ")


def test_the_implementation_setting():
    assert resolve_http("h11") == "h11"
    assert resolve_http("auto") == ("httptools" if GuardedHttpToolsProtocol else "h11")
    assert issubclass(protocol_class(1, 1, 1, 1, http="h11"), GuardedH11Protocol)
    with pytest.raises(ValueError, match="unknown HTTP implementation 'h2'"):
        resolve_http("h2")


def test_slow_headers_are_cut_off_with_408(server):
    with connect(server) as s:
        took, reply = closed_after(s, b"GET / HTTP/1.1\r\nhost: x\r\n" + b"x" * 100, 0.2, 5)
    assert HEADER_TIMEOUT <= took < HEADER_TIMEOUT + 1.0
    assert reply.startswith(b"HTTP/1.1 408 ")


def test_a_silent_connection_is_cut_off(server):
    with connect(server) as s:
        start = time.monotonic()
        assert s.recv(4096).startswith(b"HTTP/1.1 408 ")
        assert s.recv(4096) == b""
        assert time.monotonic() - start < HEADER_TIMEOUT + 1.0


def test_a_slow_body_is_cut_off(server):
    with connect(server) as s:
        s.sendall(b"POST / HTTP/1.1\r\nhost: x\r\ncontent-length: 100000\r\n\r\n")
        took, reply = closed_after(s, b"y" * 1000, 0.1, 6)
    assert GRACE <= took < GRACE + 1.5
    assert reply == b""


def test_connections_per_client_are_bounded(server):
    held = [connect(server) for _ in range(PER_CLIENT)]
    try:
        time.sleep(0.2)
        with connect(server) as extra:
            assert extra.recv(4096).startswith(b"HTTP/1.1 503 ")
    finally:
        for s in held:
            s.close()
    time.sleep(0.2)
    with connect(server) as s:           # the count went down with the closed connections
        s.sendall(b"GET / HTTP/1.1\r\nhost: x\r\n\r\n")
        assert s.recv(4096).startswith(b"HTTP/1.1 200 ")


def test_the_h11_connection_hands_a_content_length_body_back_as_given():
    """BodyPassthroughConnection.send writes the same bytes as h11's own send, and a
    Content-Length body is the very object given (no copy); chunked framing is joined."""
    import h11

    from service.api.connections import BodyPassthroughConnection

    body = memoryview(bytes(range(256)) * 40)
    written = {}
    for cls in (h11.Connection, BodyPassthroughConnection):
        conn = cls(h11.SERVER)
        conn.receive_data(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
        assert isinstance(conn.next_event(), h11.Request)
        out = [conn.send(h11.Response(status_code=200,
                                      headers=[("content-length", str(len(body)))]))]
        data = conn.send(h11.Data(data=body))
        out += [data, conn.send(h11.EndOfMessage())]
        written[cls] = b"".join(bytes(x) for x in out)
        if cls is BodyPassthroughConnection:
            assert data is body
        chunked = cls(h11.SERVER)
        chunked.receive_data(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
        chunked.next_event()
        chunked.send(h11.Response(status_code=200, headers=[("transfer-encoding", "chunked")]))
        written[cls, "chunked"] = chunked.send(h11.Data(data=b"abc"))
    assert written[h11.Connection] == written[BodyPassthroughConnection]
    assert written[h11.Connection, "chunked"] == written[BodyPassthroughConnection, "chunked"] \
        == b"3\r\nabc\r\n"
