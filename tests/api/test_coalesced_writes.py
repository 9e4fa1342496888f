"""service.api.coalesced_writes: a response's writes of one loop iteration go out together."""

from __future__ import annotations

import asyncio
import time

import pytest

from service.api.coalesced_writes import CoalescedWrites, coalesced
from service.api.connections import GuardedHttpToolsProtocol


class RecordingTransport:
    """Records what reaches it: ``calls`` as ("write", data) / ("writelines", [data…]) / ("close",)."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []
        self.closing = False

    def write(self, data) -> None:
        self.calls.append(("write", bytes(data)))

    def writelines(self, lines) -> None:
        self.calls.append(("writelines", [bytes(d) for d in lines]))

    def close(self) -> None:
        self.closing = True
        self.calls.append(("close",))

    def is_closing(self) -> bool:
        return self.closing

    def get_extra_info(self, name, default=None):
        return {"peername": ("127.0.0.1", 1234)}.get(name, default)


def _wrapped() -> tuple[RecordingTransport, CoalescedWrites]:
    """A recording transport and its wrapper on the running loop."""
    inner = RecordingTransport()
    return inner, CoalescedWrites(inner, asyncio.get_running_loop())


def test_writes_of_one_iteration_go_out_in_one_writelines_in_order():
    async def run():
        inner, t = _wrapped()
        t.write(b"HTTP/1.1 200 OK\r\n\r\n")
        t.write(b"")                                     # nothing to send: nothing kept
        t.writelines([b"body-1", memoryview(b"body-2")])
        assert inner.calls == []                         # kept until the iteration ends
        await asyncio.sleep(0)
        assert inner.calls == [("writelines", [b"HTTP/1.1 200 OK\r\n\r\n", b"body-1", b"body-2"])]
        t.write(b"next")                                 # a later iteration: its own write
        await asyncio.sleep(0)
        assert inner.calls[-1] == ("write", b"next")
        assert t.get_extra_info("peername") == ("127.0.0.1", 1234)   # the rest is the transport's
    asyncio.run(run())


def test_close_hands_over_what_is_kept_first_and_a_closing_transport_gets_nothing():
    async def run():
        inner, t = _wrapped()
        t.write(b"408")
        t.close()
        assert inner.calls == [("write", b"408"), ("close",)]
        t.write(b"late")
        await asyncio.sleep(0)
        assert inner.calls == [("write", b"408"), ("close",)]
    asyncio.run(run())


def test_only_uvloop_transports_are_wrapped():
    inner, loop = RecordingTransport(), asyncio.new_event_loop()
    try:
        assert coalesced(inner, loop) is inner
    finally:
        loop.close()
    uvloop = pytest.importorskip("uvloop")

    async def run():
        server = await asyncio.start_server(lambda r, w: None, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        _, writer = await asyncio.open_connection("127.0.0.1", port)
        assert isinstance(coalesced(writer.transport, asyncio.get_running_loop()), CoalescedWrites)
        writer.close()
        server.close()
    uvloop.run(run())


async def _pieces_app(scope, receive, send):
    """Answers a multi-piece body at once (``/pieces``) or a stream whose second piece
    follows 0.5 s after the first (``/stream``)."""
    if scope["type"] != "http":
        return
    while (await receive()).get("more_body"):
        pass
    if scope["path"] == "/pieces":
        pieces = [bytes([65 + k]) * (100_000 * (k + 1)) for k in range(3)]
        await send({"type": "http.response.start", "status": 200,
                    "headers": [(b"content-length", str(sum(map(len, pieces))).encode())]})
        for k, piece in enumerate(pieces):
            await send({"type": "http.response.body", "body": memoryview(piece), "more_body": k < 2})
        return
    await send({"type": "http.response.start", "status": 200, "headers": []})
    await send({"type": "http.response.body", "body": b"first", "more_body": True})
    await asyncio.sleep(0.5)
    await send({"type": "http.response.body", "body": b"second"})


@pytest.mark.skipif(GuardedHttpToolsProtocol is None, reason="uvicorn[standard] is not installed")
def test_a_real_server_sends_whole_answers_and_streams_without_holding_pieces_back():
    """uvicorn + httptools on uvloop with the guarded protocol: a 600 kB answer in three
    pieces arrives byte for byte; a stream's first piece arrives before its second is
    written (kept no longer than one loop iteration)."""
    import http.client

    from service.api.connections import protocol_class
    from tests.servers import uvicorn_thread

    http_class = protocol_class(5.0, 100.0, 1.0, 8, http="httptools")
    with uvicorn_thread(_pieces_app, http=http_class, loop="uvloop") as port:
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        conn.request("GET", "/pieces")
        body = conn.getresponse().read()
        assert body == b"A" * 100_000 + b"B" * 200_000 + b"C" * 300_000
        conn.request("GET", "/stream")             # the same kept-alive connection
        response = conn.getresponse()
        start = time.monotonic()
        first = response.read1(64)
        waited = time.monotonic() - start
        assert first.endswith(b"first") and waited < 0.4, (first, waited)
        assert response.read().endswith(b"second") and time.monotonic() - start > 0.4
        conn.close()
