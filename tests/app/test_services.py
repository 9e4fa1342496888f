"""service.app.services: what the HTTP API and the gRPC server share in one process."""

from __future__ import annotations

import threading
import time

import grpc
import httpx
import numpy as np
import uvicorn

from service.api import create_app
from service.app.services import LoadedModel, Services
from service.config import Settings
from service.grpc import codec
from service.grpc.facesynth.v1 import synthesis_pb2_grpc as pb_grpc
from service.grpc.server import serve
from service.io.npz import npz_bytes
from service.methods.kinds import get_kind
from tests.servers import free_port

SLOTS = 2
SECONDS = 0.03          # one synthesis


class Counting:
    """A marker-driven stand-in model (2 markers, 1 vertex) whose syntheses take
    :data:`SECONDS` and record how many ran at once, in all and per transport (the gRPC
    frames run on the pool's ``facesynth-synthesis`` threads)."""

    n_markers = 2
    n_vertices = 1

    def __init__(self):
        self.lock = threading.Lock()
        self.running = {"http": 0, "grpc": 0}
        self.most = self.both = self.calls = 0
        self.started = {"http": threading.Event(), "grpc": threading.Event()}

    def synthesize(self, markers, outputs=("mesh",), clamp=True):
        side = "grpc" if threading.current_thread().name.startswith("facesynth-synthesis") else "http"
        other = "http" if side == "grpc" else "grpc"
        with self.lock:
            self.running[side] += 1
            self.calls += 1
            self.most = max(self.most, sum(self.running.values()))
            self.both += all(self.running.values())
            first = not self.started[side].is_set()
            self.started[side].set()
        if first:
            # each transport's first synthesis holds its slot until the other's runs too, so
            # they overlap whatever order the scheduler starts them in (bounded)
            self.started[other].wait(5)
            with self.lock:
                self.both += all(self.running.values())
        time.sleep(SECONDS)
        with self.lock:
            self.running[side] -= 1
        frames = len(np.asarray(markers).reshape(-1, 2, 3))
        return {"vertices": np.zeros((frames, 1, 3), np.float32),
                "faces": np.zeros((1, 3), np.int32), "clamped": np.zeros(frames)}


def test_http_and_grpc_syntheses_share_one_pool_of_slots(tmp_path):
    """issue 23: with HTTP requests and gRPC streams both busy, at most
    ``max_concurrent_syntheses`` syntheses run at once (before: that many per transport);
    every HTTP request is answered (queued, not refused) and each stream's replies come in
    order. Real servers on loopback; bounded: ~40 syntheses of 30 ms on 2 slots."""
    settings = Settings(data_dir=tmp_path, max_concurrent_syntheses=SLOTS, tokens=[],
                        synthesis_queue_seconds=20)
    services = Services.open(settings)
    model = Counting()
    loaded = LoadedModel("m-counting", get_kind("pdm"), model, None, model)
    services.loaded_model = lambda model_id: loaded          # the store: one ready model
    port, grpc_port = free_port(), free_port()
    grpc_server = serve(services.load_model, "127.0.0.1", grpc_port, synthesis=services.synthesis)
    http_server = uvicorn.Server(uvicorn.Config(create_app(settings, services=services),
                                                host="127.0.0.1", port=port, log_config=None))
    thread = threading.Thread(target=http_server.run, daemon=True)
    thread.start()
    statuses: list[int] = []
    streams: list[list[int]] = [[], []]
    try:
        deadline = time.monotonic() + 10
        while not http_server.started:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        body = npz_bytes(markers=np.zeros((1, 2, 3), np.float32))

        def post():
            with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=20) as client:
                for _ in range(6):
                    statuses.append(client.post(
                        "/v1/models/m-counting/synthesize", content=body,
                        params={"outputs": "mesh"},
                        headers={"Content-Type": "application/x-npz"}).status_code)

        def stream(i):
            frames = [codec.encode_markers(np.zeros((2, 3), np.float32), k,
                                           **({"model_id": "m-counting", "outputs": ["mesh"]}
                                              if k == 0 else {}))
                      for k in range(10)]
            with grpc.insecure_channel(f"127.0.0.1:{grpc_port}") as channel:
                replies = pb_grpc.SynthesisStub(channel).StreamSynthesize(iter(frames), timeout=20)
                streams[i] = [codec.decode_reply(r)["frame"] for r in replies]

        workers = ([threading.Thread(target=post) for _ in range(3)]
                   + [threading.Thread(target=stream, args=(i,)) for i in range(2)])
        for t in workers:
            t.start()
        for t in workers:
            t.join(30)
    finally:
        http_server.should_exit = True
        thread.join(10)
        grpc_server.stop(grace=None)
        services.close()
    assert statuses == [200] * 18 and streams == [list(range(10))] * 2
    assert model.calls == 38
    assert model.most == SLOTS          # busy: the slots were full, and never more than full
    assert model.both > 0               # HTTP and gRPC syntheses did run side by side
    assert services.synthesis.running == services.synthesis.waiting == 0
