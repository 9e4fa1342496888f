"""The sync client's transport (facesynth_client.transport.OnePieceTransport) against a small
HTTP/1.1 server on a loopback port: the same answers as httpx's own transport, a sized
answer in one piece, streams in pieces, kept-alive connections reused and stale ones
replaced, httpx's exception classes, and httpx's transport for what it does not take."""

from __future__ import annotations

import hashlib
import http.server
import json
import threading
import time

import httpx
import pytest

from facesynth_client import Client
from facesynth_client.transport import CHUNK, ONE_WRITE_MAX, OnePieceTransport

BIG = bytes(range(256)) * 4099          # 1,049,344 bytes: several of httpx's 64 KiB reads


class Handler(http.server.BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    connections: list[int] = []

    def setup(self) -> None:
        super().setup()
        self.connections.append(id(self.connection))

    def log_message(self, *args) -> None:
        pass

    def _answer(self, body: bytes, status: int = 200, headers: dict | None = None) -> None:
        self.send_response(status)
        for name, value in {"Content-Length": str(len(body)), **(headers or {})}.items():
            self.send_header(name, value)
        self.end_headers()
        self.wfile.write(body)

    def do_GET(self) -> None:
        if self.path == "/big":
            self._answer(BIG, headers={"Content-Type": "application/octet-stream"})
        elif self.path == "/chunked":
            self.send_response(200)
            self.send_header("Transfer-Encoding", "chunked")
            self.end_headers()
            for part in (b"data: 1\n\n", b"data: 2\n\n", BIG):
                self.wfile.write(b"%x\r\n%s\r\n" % (len(part), part))
                self.wfile.flush()
            self.wfile.write(b"0\r\n\r\n")
        elif self.path == "/close":
            self._answer(b"bye", headers={"Connection": "close"})
            self.close_connection = True
        elif self.path == "/slow":
            time.sleep(1.0)
            self._answer(b"late")
        elif self.path == "/missing":
            self._answer(b'{"detail": "no"}', 404, {"Content-Type": "application/problem+json"})
        else:
            self._answer(b"")

    def do_POST(self) -> None:
        body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
        echo = {"path": self.path, "sha256": hashlib.sha256(body).hexdigest(),
                "headers": {k.lower(): v for k, v in self.headers.items()}}
        self._answer(json.dumps(echo).encode(), headers={"Content-Type": "application/json"})


@pytest.fixture(scope="module")
def origin():
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}", Handler.connections
    server.shutdown()
    server.server_close()


@pytest.fixture
def one_piece(origin):
    with httpx.Client(base_url=origin[0], transport=OnePieceTransport(), timeout=5) as client:
        yield client


def test_answers_equal_httpx_transport(origin, one_piece):
    with httpx.Client(base_url=origin[0], timeout=5) as plain:
        for method, path, kwargs in (("GET", "/big", {}), ("GET", "/chunked", {}),
                                     ("GET", "/missing", {}), ("GET", "/empty", {}),
                                     ("POST", "/echo?outputs=mesh&half=true",
                                      {"content": BIG[:5000],
                                       "headers": {"Content-Type": "application/x-npz"}})):
            a, b = (c.request(method, path, **kwargs) for c in (plain, one_piece))
            assert a.status_code == b.status_code and a.content == b.content
            assert [h for h in a.headers.multi_items() if h[0] != "date"] == \
                [h for h in b.headers.multi_items() if h[0] != "date"]
            assert a.http_version == b.http_version and a.reason_phrase == b.reason_phrase
    echo = one_piece.post("/echo?x=1", content=b"abc").json()
    assert echo["path"] == "/echo?x=1" and echo["sha256"] == hashlib.sha256(b"abc").hexdigest()
    assert echo["headers"]["content-length"] == "3" and "host" in echo["headers"]


def test_headers_and_a_small_body_go_out_in_one_write(one_piece, monkeypatch):
    """issue 23: http.client writes them in two (the server woken twice per request)."""
    import socket

    writes: list[bytes] = []
    sendall = socket.socket.sendall
    client = threading.get_ident()          # the origin's answers are written by its threads

    def spy(sock, data, *args):
        if threading.get_ident() == client:
            writes.append(bytes(data))
        return sendall(sock, data, *args)

    monkeypatch.setattr(socket.socket, "sendall", spy)
    for size in (3600, ONE_WRITE_MAX, ONE_WRITE_MAX + 1):
        writes.clear()
        body = BIG[:size]
        echo = one_piece.post("/echo", content=body).json()
        assert echo["sha256"] == hashlib.sha256(body).hexdigest()
        assert len(writes) == (1 if size <= ONE_WRITE_MAX else 2)
        assert writes[-1].endswith(body) and writes[0].startswith(b"POST /echo HTTP/1.1\r\n")


def test_a_sized_answer_is_read_in_one_piece_and_a_stream_in_pieces(one_piece):
    with one_piece.stream("GET", "/big") as response:
        pieces = list(response.iter_raw())
    assert [len(p) for p in pieces] == [len(BIG)] and pieces[0] == BIG
    with one_piece.stream("GET", "/chunked") as response:
        pieces = list(response.iter_raw())
    assert pieces[:2] == [b"data: 1\n\n", b"data: 2\n\n"]
    assert b"".join(pieces[2:]) == BIG and max(len(p) for p in pieces) <= CHUNK


def test_connections_are_kept_alive_and_a_closed_one_is_replaced(origin, one_piece):
    connections = origin[1]
    one_piece.get("/empty")
    before = len(connections)
    for _ in range(5):
        assert one_piece.get("/big").content == BIG
    assert len(connections) == before                  # one connection for all five
    assert one_piece.get("/close").content == b"bye"   # the server closes this one
    assert one_piece.get("/big").content == BIG
    assert len(connections) == before + 1


class ShortKeepAlive(Handler):
    """Closes a kept-alive connection after 0.2 s without a request."""

    timeout = 0.2
    connections: list[int] = []


@pytest.fixture(scope="module")
def short_origin():
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), ShortKeepAlive)
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_address[1]}", ShortKeepAlive.connections
    server.shutdown()
    server.server_close()


@pytest.mark.parametrize("noticed", [True, False])
def test_a_kept_connection_the_server_closed_is_replaced(short_origin, monkeypatch, noticed):
    """Closed while idle: dropped when it is checked out (noticed), or — when the server
    closes it between that check and the request — the request is sent once more on a new
    connection."""
    import facesynth_client.transport as transport_module

    if not noticed:
        monkeypatch.setattr(transport_module, "_is_closed", lambda connection: False)
    url, connections = short_origin
    transport = OnePieceTransport()
    exchanges = []
    exchange = transport._exchange
    monkeypatch.setattr(transport, "_exchange", lambda *a: exchanges.append(1) or exchange(*a))
    with httpx.Client(base_url=url, transport=transport, timeout=5) as client:
        assert client.get("/big").content == BIG
        before = len(connections)
        time.sleep(0.6)                    # the server closes the idle connection
        exchanges.clear()
        assert client.post("/echo", content=b"again").json()["sha256"] == \
            hashlib.sha256(b"again").hexdigest()
        assert len(connections) == before + 1
        assert len(exchanges) == (1 if noticed else 2)


def test_errors_are_httpx_exceptions():
    import socket

    with socket.socket() as unused:
        unused.bind(("127.0.0.1", 0))
        port = unused.getsockname()[1]
    with httpx.Client(transport=OnePieceTransport(), timeout=2) as client:
        with pytest.raises(httpx.ConnectError):
            client.get(f"http://127.0.0.1:{port}/")


def test_a_slow_answer_is_a_read_timeout(origin):
    with httpx.Client(base_url=origin[0], transport=OnePieceTransport(),
                      timeout=httpx.Timeout(5, read=0.2)) as client:
        with pytest.raises(httpx.ReadTimeout):
            client.get("/slow")
        assert client.get("/big").content == BIG       # the timed-out connection was dropped


class Recording(httpx.BaseTransport):
    def __init__(self):
        self.urls: list[str] = []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        request.read()
        self.urls.append(str(request.url))
        return httpx.Response(200, content=b"fallback")


def test_https_and_streamed_bodies_go_to_httpx_transport(origin):
    fallback = Recording()
    with httpx.Client(transport=OnePieceTransport(fallback=fallback), timeout=5) as client:
        assert client.get("https://fs.test/x").content == b"fallback"
        streamed = client.post(f"{origin[0]}/echo", content=iter([b"a", b"b"]))
        assert streamed.content == b"fallback"
        assert client.post(f"{origin[0]}/echo", content=b"ab").json()["sha256"] == \
            hashlib.sha256(b"ab").hexdigest()
    assert fallback.urls == ["https://fs.test/x", f"{origin[0]}/echo"]


def test_the_client_sends_through_it_by_default(origin):
    with Client(origin[0]) as fs:
        assert isinstance(fs._http._transport, OnePieceTransport)
        assert fs.health is not None
    with Client(origin[0], transport=Recording()) as fs:
        assert isinstance(fs._http._transport, Recording)


def test_the_client_hands_requests_to_it_directly(origin):
    """The SDK's own client skips ``httpx.Client.send`` and sends the same request: the
    same headers, path and body as through httpx with the same transport."""
    from facesynth_client._core import Call

    call = Call("POST", "/echo", params={"outputs": "mesh", "half": None, "topology": "false"},
                content=b"abc", headers={"Content-Type": "application/x-npz"})
    with Client(origin[0], token="t0k") as direct, \
            httpx.Client(transport=OnePieceTransport(), timeout=5) as plain_http, \
            Client(origin[0], token="t0k", http_client=plain_http) as through_httpx:
        assert direct._direct is direct._http._transport and through_httpx._direct is None

        def refused(*args, **kwargs):
            raise AssertionError("httpx.Client.send was called")
        direct._http.send = refused
        a = direct._run(direct._core.call_json(call))
        b = through_httpx._run(through_httpx._core.call_json(call))
        assert a["path"] == b["path"] == "/echo?outputs=mesh&topology=false"
        assert a["sha256"] == b["sha256"] == hashlib.sha256(b"abc").hexdigest()
        assert a["headers"] == b["headers"]
        assert a["headers"]["authorization"] == "Bearer t0k"
        missing = direct._run(direct._core.send(Call("GET", "/missing", accept_statuses=(404,))))
        assert missing.status_code == 404 and missing.request.url.path == "/missing"
        del direct._http.send
    with pytest.raises(RuntimeError, match="closed"):    # as httpx answers a closed client
        direct.health()


def test_request_urls_are_parsed_once_per_path_and_query():
    from facesynth_client._core import URL_CACHE_MAX, Core

    core = Core(base_url="http://fs.test:9/", token=None, timeout=httpx.Timeout(1),
                max_retries=0, backoff=0, backoff_max=0, poll_interval=1,
                build_request=httpx.Client().build_request)
    params = {"outputs": "mesh,normal_map", "clamp": None, "half": "true", "n": 2}
    url = core.request_url("/v1/models/m 1/synthesize", params)
    expected = httpx.Request("POST", "http://fs.test:9/v1/models/m 1/synthesize",
                             params={"outputs": "mesh,normal_map", "half": "true", "n": 2}).url
    assert url == expected and str(url).endswith("synthesize?outputs=mesh%2Cnormal_map&half=true&n=2")
    assert core.request_url("/v1/models/m 1/synthesize", dict(params)) is url
    assert core.request_url("/healthz", None) == httpx.URL("http://fs.test:9/healthz")
    listed = core.request_url("/x", {"outputs": ["mesh", "albedo"]})      # unhashable: not kept
    assert str(listed) == "http://fs.test:9/x?outputs=mesh&outputs=albedo"
    for k in range(URL_CACHE_MAX + 5):
        core.request_url(f"/p{k}", None)
    assert len(core._urls) <= URL_CACHE_MAX


class Scripted:
    """A one-connection loopback server answering each request with the next of ``answers``
    (raw bytes), then closing (or, with ``keep``, waiting for the next request)."""

    def __init__(self, answers: list[bytes], keep: bool = False):
        import socket

        self.answers, self.keep, self.requests = list(answers), keep, []
        self.server = socket.create_server(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.server.getsockname()[1]}"
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        conn, _ = self.server.accept()
        with conn:
            reader = conn.makefile("rb")
            for answer in self.answers:
                head = b""
                while not head.endswith(b"\r\n\r\n"):
                    line = reader.readline()
                    if not line:
                        return
                    head += line
                length = next((int(v) for k, v in (h.split(b":", 1) for h in head.split(b"\r\n")[1:] if b":" in h)
                               if k.strip().lower() == b"content-length"), 0)
                self.requests.append(head + reader.read(length))
                conn.sendall(answer)
                if not self.keep:
                    break
        self.server.close()


@pytest.mark.parametrize("answer, method, status, content", [
    (b"HTTP/1.1 100 Continue\r\n\r\nHTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\nok", "GET", 200, b"ok"),
    (b"HTTP/1.1 204 No Content\r\n\r\n", "GET", 204, b""),
    (b"HTTP/1.1 200 OK\r\nContent-Length: 9\r\n\r\n", "HEAD", 200, b""),
    (b"HTTP/1.0 200 OK\r\nContent-Type: text/plain\r\n\r\nuntil the end", "GET", 200, b"until the end"),
    (b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n3;x=1\r\nabc\r\n2\r\nde\r\n0\r\nT: 1\r\n\r\n",
     "GET", 200, b"abcde"),
])
def test_answers_are_framed_as_rfc_9112_says(answer, method, status, content):
    origin = Scripted([answer])
    with httpx.Client(transport=OnePieceTransport(), timeout=5) as client:
        response = client.request(method, f"{origin.url}/x")
    assert (response.status_code, response.content) == (status, content)


def test_an_answer_cut_short_or_malformed_is_a_remote_protocol_error():
    for answer in (b"HTTP/1.1 200 OK\r\nContent-Length: 10\r\n\r\nshort",
                   b"ICY 200 OK\r\n\r\n", b"HTTP/1.1 200 OK\r\nno colon here\r\n\r\n",
                   b"HTTP/1.1 200 OK\r\nContent-Length: 2, 3\r\n\r\nab", b"",
                   b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n"):
        origin = Scripted([answer])
        with httpx.Client(transport=OnePieceTransport(), timeout=5) as client:
            with pytest.raises(httpx.RemoteProtocolError):
                client.get(f"{origin.url}/x")


def test_a_header_that_would_inject_a_line_is_refused():
    with httpx.Client(transport=OnePieceTransport(), timeout=5) as client:
        with pytest.raises(httpx.LocalProtocolError):
            client.get("http://127.0.0.1:9/x", headers={"X-A": "1\r\nX-Injected: 2"})


def transport_of(client: httpx.Client) -> OnePieceTransport:
    return client._transport


def test_a_connection_is_kept_only_while_the_server_keeps_it():
    ok = b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\nok"
    origin = Scripted([ok, ok], keep=True)
    with httpx.Client(transport=OnePieceTransport(), timeout=5) as client:
        assert client.get(f"{origin.url}/a").content == b"ok"
        assert sum(map(len, transport_of(client)._idle.values())) == 1
        assert client.post(f"{origin.url}/b", content=b"xyz").content == b"ok"   # same connection
    assert [r.split(b"\r\n", 1)[0] for r in origin.requests] == [b"GET /a HTTP/1.1", b"POST /b HTTP/1.1"]
    assert origin.requests[1].endswith(b"\r\n\r\nxyz")
    closing = Scripted([b"HTTP/1.1 200 OK\r\nConnection: close\r\nContent-Length: 2\r\n\r\nok"])
    transport = OnePieceTransport()
    with httpx.Client(transport=transport, timeout=5) as client:
        assert client.get(f"{closing.url}/a").content == b"ok"
        assert not any(transport._idle.values())           # closed, not kept
