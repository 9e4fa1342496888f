"""The SDK's gRPC stream (facesynth_client.streaming) against the real Synthesis server started
in this process on a loopback port, serving the models of the real app: the sheet's PDM,
trained over HTTP by the SDK.

A stream gives what HTTP ``synthesize`` gives for the same markers; frames are sent ahead of
the replies and never more than ``max_in_flight`` are unanswered; the server's statuses
arrive as the SDK's errors.
"""

from __future__ import annotations

import asyncio
import socket
import threading
from typing import Iterator

import numpy as np
import pytest

pytest.importorskip("grpc")

from facesynth_client import Conflict, NotFound, Unprocessable  # noqa: E402
from facesynth_client.streaming import AsyncStreamingClient, StreamingClient  # noqa: E402

from conftest import SHEET_MARKERS, sheet_motion  # noqa: E402

OUTPUTS = ("mesh", "mesh_detailed", "displacement")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def grpc_target(server) -> Iterator[str]:
    """``service.grpc.server.serve`` on a free loopback port with the app's own model store
    (as ``facesynth serve`` wires them), stopped afterwards."""
    from service.grpc.server import serve

    services = server.uvicorn.config.app.state.services
    port = _free_port()
    grpc_server = serve(services.load_model, "127.0.0.1", port, max_workers=4)
    yield f"127.0.0.1:{port}"
    grpc_server.stop(grace=None)


@pytest.fixture(scope="module")
def take(sheet_actor) -> np.ndarray:
    """8 frames (8,M,3) float32 of a motion the model did not see, mm (8: the test server's
    max_frames_per_request, so HTTP synthesizes them in one request)."""
    return sheet_motion(sheet_actor.V, 8, 0.15)[:, list(SHEET_MARKERS)].astype(np.float32)


def test_a_stream_gives_what_http_synthesize_gives(client, grpc_target, pdm_model, take):
    expected = client.synthesize(pdm_model, take, outputs=list(OUTPUTS))
    with StreamingClient(grpc_target) as stream:
        results = list(stream.synthesize(pdm_model, take, OUTPUTS, start_frame=100))
    assert [r["frame"] for r in results] == list(range(100, 108))
    assert results[0]["faces"].tolist() == expected["faces"].tolist()
    assert all("faces" not in r for r in results[1:])            # the topology comes once
    for key in ("vertices", "vertices_detailed", "displacement"):
        got = np.stack([r[key] for r in results])
        assert got.shape == expected[key].shape
        np.testing.assert_allclose(got, expected[key], rtol=0, atol=1e-4)
    assert all(r["latency_ms"] > 0 for r in results)


def test_half_maps_over_the_stream_and_the_async_client(client, grpc_target, pdm_model, take):
    """``half=True``: float16 maps within 2^-11 relative (+2^-25) of the float32 stream's,
    meshes bit-exact, in order, sync and async alike."""
    outputs = ("mesh", "displacement", "normal_map")
    with StreamingClient(grpc_target) as stream:
        full = list(stream.synthesize(pdm_model, take[:3], outputs))
        half = list(stream.synthesize(pdm_model, take[:3], outputs, half=True, max_in_flight=3))

    async def run():
        async with AsyncStreamingClient(grpc_target) as stream:
            return [out async for out in stream.synthesize(pdm_model, take[:3], outputs,
                                                           half=True)]

    for results in (half, asyncio.run(run())):
        assert [r["frame"] for r in results] == [0, 1, 2]
        for f, h in zip(full, results):
            np.testing.assert_array_equal(h["vertices"], f["vertices"])
            for key in ("displacement", "normal_map"):
                assert h[key].dtype == np.float16
                ref = f[key].astype(np.float64)
                assert np.all(np.abs(h[key] - ref) <= 2.0 ** -11 * np.abs(ref) + 2.0 ** -25)


def test_frames_go_ahead_of_the_replies_at_most_max_in_flight(grpc_target, pdm_model, take):
    received = 0
    ahead: list[int] = []          # frames taken and not yet seen answered, at each take
    lock = threading.Lock()

    def frames():
        for k, markers in enumerate(np.repeat(take, 4, axis=0)):
            with lock:
                ahead.append(k + 1 - received)
            yield markers

    with StreamingClient(grpc_target) as stream:
        for out in stream.synthesize(pdm_model, frames(), ("mesh",), max_in_flight=3):
            with lock:
                received += 1
    assert received == 32
    # a frame is taken only once it has one of the 3 slots (+1: a reply whose slot was
    # freed while the loop above has not counted it yet); unbounded, the source would be
    # drained at once (ahead up to 32)
    assert max(ahead) <= 3 + 1
    assert max(ahead) >= 2                   # and frames did go ahead of the replies


def test_the_server_statuses_are_the_sdk_errors(client, grpc_target, pdm_model, take,
                                                 sheet_actor):
    with StreamingClient(grpc_target) as stream:
        with pytest.raises(NotFound) as unknown:
            list(stream.synthesize("mdl_00000000000000000000000000", take))
        assert unknown.value.problem["grpc_status"] == "NOT_FOUND"
        with pytest.raises(Unprocessable) as wrong:
            list(stream.synthesize(pdm_model, take[:, :3]))           # 3 markers, not 4
        assert "marker" in wrong.value.detail
        with pytest.raises(ValueError, match=r"frame 0: markers must be \(M,3\)"):
            list(stream.synthesize(pdm_model, [np.zeros(12)]))
        training = client.models.train(sheet_actor.actor_id, "pdm",
                                       list(sheet_actor.clips.values()),
                                       {"medium_resolution": 256, "fine_resolution": 512})
        try:
            with pytest.raises(Conflict):                              # still training
                list(stream.synthesize(training.model_id, take))
        finally:
            client.cancel(training)


def test_the_async_stream_gives_the_same_frames(grpc_target, pdm_model, take):
    async def run() -> list[dict]:
        async def frames():
            for markers in take:
                await asyncio.sleep(0)
                yield markers

        async with AsyncStreamingClient(grpc_target) as stream:
            return [out async for out in stream.synthesize(pdm_model, frames(), ("mesh",),
                                                            max_in_flight=2)]

    results = asyncio.run(run())
    with StreamingClient(grpc_target) as stream:
        sync = list(stream.synthesize(pdm_model, take, ("mesh",)))
    assert [r["frame"] for r in results] == list(range(8))
    np.testing.assert_array_equal(np.stack([r["vertices"] for r in results]),
                                  np.stack([r["vertices"] for r in sync]))


def test_the_sdk_never_imports_the_server_for_streaming():
    import subprocess
    import sys

    code = ("import sys; from facesynth_client.streaming import StreamingClient; "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'service', 'models_store'}))")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                         text=True, timeout=60).stdout.strip()
    assert out == "[]"
