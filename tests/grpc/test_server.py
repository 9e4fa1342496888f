"""StreamSynthesize end to end: a real server on loopback, a trained PDM model, the client helper."""

from __future__ import annotations

import threading
import time

import grpc
import numpy as np
import pytest

from service.grpc.client import stream_synthesize
from service.grpc.facesynth.v1 import synthesis_pb2 as pb
from service.grpc.server import serve
from tests.grpc.conftest import MODEL_ID, TRAINING_ID, running

ALL = ("mesh", "mesh_detailed", "displacement", "albedo", "normal_map")


def _shapes(model) -> dict[str, tuple[int, ...]]:
    """Per-frame array shapes of all outputs: (V,3) meshes, (Hf,Hf) fine maps, (Ha,Ha,3) albedo."""
    V, Hf, Ha = model.n_vertices, model.data.fine.resolution, model.data.albedo.resolution
    return {"vertices": (V, 3), "vertices_detailed": (V, 3), "displacement": (Hf, Hf),
            "albedo": (Ha, Ha, 3), "normal_map": (Hf, Hf, 3)}


def _status(frames_call) -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as e:
        list(frames_call)
    return e.value


def test_stream_equals_direct_synthesis_bit_exactly_in_order(channel, pdm_model, heldout_markers):
    markers = heldout_markers.copy()
    markers[3, [0, 7, 20]] = np.nan                      # occluded markers travel as NaN
    start = time.perf_counter()
    got = list(stream_synthesize(channel, MODEL_ID, markers, ALL))
    streamed = time.perf_counter() - start
    start = time.perf_counter()
    direct = [pdm_model.synthesize(markers[i:i + 1], ALL, True) for i in range(len(markers))]
    print(f"\n{len(markers)} frames, all outputs: streamed {len(markers) / streamed:.1f} frames/s, "
          f"direct synthesize {len(markers) / (time.perf_counter() - start):.1f} frames/s")
    assert [g["frame"] for g in got] == list(range(len(markers)))
    for i, (g, d) in enumerate(zip(got, direct)):
        for key, shape in _shapes(pdm_model).items():
            assert g[key].shape == shape and g[key].dtype == np.float32, key
            np.testing.assert_array_equal(g[key], d[key][0], err_msg=f"frame {i} {key}")
        assert g["clamped"] == np.float32(d["clamped"][0])
        assert g["latency_ms"] > 0
    np.testing.assert_array_equal(got[0]["faces"], pdm_model.faces)
    assert all("faces" not in g for g in got[1:])


def test_only_the_asked_outputs_are_sent(channel, heldout_markers):
    got = list(stream_synthesize(channel, MODEL_ID, heldout_markers[:2]))      # default: mesh
    assert set(got[1]) == {"frame", "clamped", "latency_ms", "vertices"}
    got = list(stream_synthesize(channel, MODEL_ID, heldout_markers[:1], ["displacement"]))
    assert set(got[0]) == {"frame", "clamped", "latency_ms", "faces", "displacement"}


def test_clamp_false_reports_nothing_clamped(channel, pdm_model, heldout_markers):
    far = heldout_markers[:1] * np.float32(1.3)           # well beyond the training range
    clamped = next(stream_synthesize(channel, MODEL_ID, far, ["displacement"]))
    free = next(stream_synthesize(channel, MODEL_ID, far, ["displacement"], clamp=False))
    assert clamped["clamped"] > 0 and free["clamped"] == 0
    np.testing.assert_array_equal(free["displacement"],
                                  pdm_model.synthesize(far, ["displacement"], False)["displacement"][0])


def test_unknown_model_is_not_found(channel, heldout_markers):
    e = _status(stream_synthesize(channel, "no-such-model", heldout_markers[:1]))
    assert e.code() == grpc.StatusCode.NOT_FOUND and "no-such-model" in e.details()


def test_model_not_ready_is_failed_precondition(channel, heldout_markers):
    e = _status(stream_synthesize(channel, TRAINING_ID, heldout_markers[:1]))
    assert e.code() == grpc.StatusCode.FAILED_PRECONDITION and "training" in e.details()


def test_wrong_marker_count_is_invalid_argument_with_the_models_message(channel, heldout_markers):
    M = heldout_markers.shape[1]
    e = _status(stream_synthesize(channel, MODEL_ID, heldout_markers[:3, :-1]))
    assert e.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert e.details() == f"frame 0: model expects markers (F,{M},3), got (1, {M - 1}, 3)"


def test_a_frame_with_too_few_visible_markers_is_named(channel, heldout_markers):
    markers = heldout_markers[:6].copy()
    markers[4, 2:] = np.nan
    replies = stream_synthesize(channel, MODEL_ID, markers)
    got = [next(replies) for _ in range(4)]               # the frames before it are answered
    with pytest.raises(grpc.RpcError) as e:
        next(replies)
    assert [g["frame"] for g in got] == [0, 1, 2, 3]
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert e.value.details().startswith("frame 4 has 2 visible markers, at least")


@pytest.mark.parametrize("model_id, outputs, message", [
    ("", ["mesh"], "the first MarkerFrame of a stream must name a model_id"),
    (MODEL_ID, ["mesh", "wrinkles"], "unknown outputs ['wrinkles']; choose from"),
])
def test_an_invalid_first_message_is_invalid_argument(channel, heldout_markers, model_id, outputs, message):
    e = _status(stream_synthesize(channel, model_id, heldout_markers[:1], outputs))
    assert e.code() == grpc.StatusCode.INVALID_ARGUMENT and e.details().startswith(message)


def test_a_reply_over_the_message_limit_is_resource_exhausted(load_model, heldout_markers):
    with running(load_model, max_message_bytes=32 * 1024) as small:         # a 128² map is 64 KiB
        e = _status(stream_synthesize(small, MODEL_ID, heldout_markers[:1], ["displacement"]))
    assert e.code() == grpc.StatusCode.RESOURCE_EXHAUSTED


def test_tokens_are_required_when_configured(load_model, heldout_markers):
    with running(load_model, tokens=["s3cret", "other"]) as secured:
        for token in (None, "wrong", "s3cret2"):
            e = _status(stream_synthesize(secured, MODEL_ID, heldout_markers[:1], token=token))
            assert e.code() == grpc.StatusCode.UNAUTHENTICATED, token
        assert len(list(stream_synthesize(secured, MODEL_ID, heldout_markers[:2], token="other"))) == 2


def test_serve_listens_beyond_loopback_only_with_tokens(load_model):
    with pytest.raises(ValueError, match="without tokens"):
        serve(load_model, host="0.0.0.0", port=0)


def test_streams_beyond_max_workers_are_refused_not_queued(load_model, heldout_markers):
    release = threading.Event()

    def held_open():                                       # a live source that pauses
        yield heldout_markers[0]
        release.wait(10)

    with running(load_model) as channel:                   # max_workers=2
        open_streams = [stream_synthesize(channel, MODEL_ID, held_open()) for _ in range(2)]
        try:
            assert [next(s)["frame"] for s in open_streams] == [0, 0]
            e = _status(stream_synthesize(channel, MODEL_ID, heldout_markers[:1]))
            assert e.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        finally:
            release.set()
        assert [list(s) for s in open_streams] == [[], []]


def test_each_call_is_scoped_to_its_tokens_tenant(load_model, heldout_markers):
    """issue 16, defect 13: the stream sees only its tenant's models (the registry scope is
    set for the call and reset after it); an admin token sees every tenant."""
    from models_store.registry import TENANT_SCOPE

    seen = []

    def scoped_load(model_id):
        seen.append(TENANT_SCOPE.get())
        if TENANT_SCOPE.get() not in (None, "studio-a"):
            from service.errors import NotFound

            raise NotFound("model", model_id)
        return load_model(model_id)

    with running(scoped_load, tokens=["studio-a:tok-a", "studio-b:tok-b", "ops:tok-o:admin"]) as ch:
        assert len(list(stream_synthesize(ch, MODEL_ID, heldout_markers[:1], token="tok-a"))) == 1
        e = _status(stream_synthesize(ch, MODEL_ID, heldout_markers[:1], token="tok-b"))
        assert e.code() == grpc.StatusCode.NOT_FOUND
        assert len(list(stream_synthesize(ch, MODEL_ID, heldout_markers[:1], token="tok-o"))) == 1
    assert seen == ["studio-a", "studio-b", None]
    assert TENANT_SCOPE.get() is None


@pytest.mark.parametrize("errno_, code", [
    (28, grpc.StatusCode.RESOURCE_EXHAUSTED),   # ENOSPC: the data disk is full
    (30, grpc.StatusCode.UNAVAILABLE),          # EROFS: it is read-only
])
def test_a_storage_fault_is_a_status_by_meaning_without_paths(heldout_markers, errno_, code):
    """issue 16: a full or read-only data disk ends a stream as the HTTP API answers it
    (507 / 503 there), never INTERNAL, and names no server path."""
    def load(model_id: str):
        raise OSError(errno_, "storage fault", "/srv/facesynth/blobs/models/x/model.npz")

    with running(load) as channel:
        e = _status(stream_synthesize(channel, MODEL_ID, heldout_markers[:1]))
    assert e.code() == code and "/srv" not in e.details()


# ---------------------------------------------------------------------- pipelining, half maps
class _Recording:
    """A stand-in model: frame k's vertex is (k, 0, 0) (k = the first marker's x); records
    the order of its calls."""

    def __init__(self):
        self.calls: list[int] = []

    def synthesize(self, markers, outputs=("mesh",), clamp=True):
        k = int(markers[0, 0, 0])
        if markers.shape[1] != 2:
            from service.errors import InvalidInput

            raise InvalidInput(f"frame 0: model expects 2 markers, got {markers.shape[1]}")
        self.calls.append(k)
        return {"vertices": np.array([[[k, 0, 0]]], np.float32), "faces": np.zeros((1, 3), np.int32),
                "clamped": np.zeros(1)}


def _frames(n, bad=None):
    from service.grpc import codec

    return [codec.encode_markers(np.full((3 if k == bad else 2, 3), k, np.float32), k,
                                 **({"model_id": "m", "outputs": ["mesh"]} if k == 0 else {}))
            for k in range(n)]


def _pipeline(model, messages, depth, synthesis=None):
    """A pipeline of ``messages`` on ``synthesis`` (default: one thread of its own)."""
    from concurrent.futures import ThreadPoolExecutor

    from service.grpc.server import _Pipeline, _Stream

    stream = _Stream("m", model, ("mesh",), True)
    return _Pipeline(stream, messages[0], iter(messages[1:]), depth,
                     synthesis or ThreadPoolExecutor(1))


def _wait_for(condition, seconds=2.0):
    deadline = time.monotonic() + seconds
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.01)


def test_the_pipeline_synthesizes_the_next_frame_while_one_is_held_and_bounds_the_flight():
    """With depth 2, while reply 0 is held by the serving thread (being sent), frame 1 is
    synthesized and frame 2 is not read; each reply handed on lets one more frame in."""
    model = _Recording()
    pipeline = _pipeline(model, _frames(6), depth=2)
    replies = iter(pipeline)
    try:
        first = next(replies)
        _wait_for(lambda: len(model.calls) >= 2)
        time.sleep(0.2)
        assert model.calls == [0, 1]                     # n+1 done while n is held; no more
        second = next(replies)
        _wait_for(lambda: len(model.calls) >= 3)
        time.sleep(0.2)
        assert model.calls == [0, 1, 2]
        rest = list(replies)
    finally:
        pipeline.close()
    got = [pb.MeshFrame.FromString(r) for r in (first, second, *rest)]
    assert [r.frame for r in got] == list(range(6)) and model.calls == list(range(6))
    assert [np.frombuffer(r.vertices, np.float32)[0] for r in got] == list(range(6))
    assert got[0].faces and not any(r.faces for r in got[1:])


def test_an_invalid_frame_ends_the_stream_after_the_replies_before_it_in_order():
    from service.grpc.server import StreamError

    model = _Recording()
    pipeline = _pipeline(model, _frames(6, bad=3), depth=3)
    got = []
    with pytest.raises(StreamError) as e:
        for reply in pipeline:
            got.append(pb.MeshFrame.FromString(reply).frame)
    pipeline.close()
    assert got == [0, 1, 2]
    assert e.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert e.value.details.startswith("frame 3: model expects 2 markers, got 3")


class _Overlapping(_Recording):
    """A stand-in whose frames take ``seconds[k]`` and record how many ran at once."""

    def __init__(self, seconds):
        super().__init__()
        self.seconds, self.running, self.most = seconds, 0, 0
        self.lock = threading.Lock()

    def synthesize(self, markers, outputs=("mesh",), clamp=True):
        with self.lock:
            self.running += 1
            self.most = max(self.most, self.running)
        time.sleep(self.seconds[int(markers[0, 0, 0])])
        with self.lock:
            self.running -= 1
        return super().synthesize(markers, outputs, clamp)


def test_two_synthesis_threads_overlap_a_streams_frames_and_reply_in_order():
    """Frame 0 takes 0.3 s, the others 0.02 s: on two threads frames 1.. finish before it,
    yet the replies come 0, 1, 2, … and two frames were synthesized at once."""
    from concurrent.futures import ThreadPoolExecutor

    model = _Overlapping([0.3] + [0.02] * 7)
    pipeline = _pipeline(model, _frames(8), depth=3, synthesis=ThreadPoolExecutor(2))
    try:
        got = [pb.MeshFrame.FromString(r).frame for r in pipeline]
    finally:
        pipeline.close()
    assert got == list(range(8)) and model.most == 2
    assert model.calls[0] != 0                        # frame 1 was done before frame 0


def test_streams_share_the_servers_synthesis_threads():
    """Two streams on one server with one synthesis thread never synthesize two frames at
    once (the threads are the server's slots, not each stream's); each gets its replies."""
    from service.grpc.server import SynthesisServicer

    model = _Overlapping([0.01] * 6)
    servicer = SynthesisServicer(lambda _: model, depth=3, synthesis_threads=1)
    streams = [servicer._replies(iter(_frames(6))) for _ in range(2)]
    got: list[list[int]] = [[], []]
    threads = [threading.Thread(target=lambda i=i: got[i].extend(
        pb.MeshFrame.FromString(r).frame for r in streams[i]))
               for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert got == [list(range(6))] * 2 and model.most == 1


def test_closing_a_pipeline_cancels_its_waiting_frames_only():
    """A closed stream's frames not yet started are cancelled; a frame of another stream
    waiting on the same thread still runs."""
    from concurrent.futures import ThreadPoolExecutor

    model = _Overlapping([0.2] * 6)
    pool = ThreadPoolExecutor(1)
    pipeline = _pipeline(model, _frames(6), depth=4, synthesis=pool)
    _wait_for(lambda: model.running == 1)
    other = pool.submit(lambda: "other")
    pipeline.close()
    assert other.result(2) == "other"                 # after frame 0, on the one thread
    assert model.calls == [0]                          # frames 1-3 were submitted, never run


def test_all_outputs_on_two_threads_equal_one_thread_bit_for_bit_in_order(
        load_model, pdm_model, heldout_markers):
    """The same 12 frames streamed (all outputs, float32 and half maps) with one synthesis
    thread and with two, four frames in flight: the same replies in the same order, and
    each that of ``synthesize`` on its frame alone."""
    got = {}
    for n in (1, 2):
        with running(load_model, pipeline_depth=4, synthesis_threads=n) as channel:
            got[n] = [list(stream_synthesize(channel, MODEL_ID, heldout_markers, ALL, half=half))
                      for half in (False, True)]
    for half, (one, many) in enumerate(zip(got[1], got[2])):
        assert [g["frame"] for g in many] == list(range(len(heldout_markers)))
        for i, (a, b) in enumerate(zip(one, many)):
            assert a.keys() == b.keys()
            for key in a:
                if key != "latency_ms":
                    np.testing.assert_array_equal(b[key], a[key], err_msg=f"frame {i} {key}")
            if not half:
                direct = pdm_model.synthesize(heldout_markers[i:i + 1], ALL, True)
                for key in _shapes(pdm_model):
                    np.testing.assert_array_equal(b[key], direct[key][0], err_msg=f"frame {i} {key}")


@pytest.mark.parametrize("depth", [1, 4])
def test_streams_at_any_depth_equal_direct_synthesis_in_order(load_model, pdm_model, heldout_markers,
                                                              depth):
    outputs = ("mesh", "displacement")
    with running(load_model, pipeline_depth=depth) as channel:
        got = list(stream_synthesize(channel, MODEL_ID, heldout_markers[:6], outputs))
    assert [g["frame"] for g in got] == list(range(6))
    for i, g in enumerate(got):
        d = pdm_model.synthesize(heldout_markers[i:i + 1], outputs, True)
        np.testing.assert_array_equal(g["vertices"], d["vertices"][0])
        np.testing.assert_array_equal(g["displacement"], d["displacement"][0])


def test_half_maps_are_float16_within_the_bound_and_meshes_stay_exact(channel, pdm_model,
                                                                      heldout_markers):
    """MarkerFrame.half: maps as binary16, |h - f| <= 2^-11 |f| + 2^-25; meshes bit-exact."""
    outputs = ("mesh", "displacement", "normal_map")
    got = list(stream_synthesize(channel, MODEL_ID, heldout_markers[:3], outputs, half=True))
    for i, g in enumerate(got):
        d = pdm_model.synthesize(heldout_markers[i:i + 1], outputs, True)
        np.testing.assert_array_equal(g["vertices"], d["vertices"][0])
        for key in ("displacement", "normal_map"):
            assert g[key].dtype == np.float16 and g[key].shape == d[key][0].shape
            f = d[key][0].astype(np.float64)
            error = np.abs(g[key].astype(np.float64) - f)
            assert np.all(error <= 2.0 ** -11 * np.abs(f) + 2.0 ** -25) and error.max() > 0


def test_half_maps_written_by_the_model_are_the_converted_float32_maps_bit_for_bit(load_model, pdm_model,
                                                                                   heldout_markers):
    """Issue 23: a model whose ``synthesize`` takes ``half`` writes the float16 maps itself
    (``takes``), and skips the confidence with ``confidence=False``; a half stream's replies
    are then those of a model without those parameters (its float32 maps converted as the
    reply is written), bit for bit."""
    from service.grpc.server import stream_options
    from service.methods.kinds import takes

    class Float32Maps:           # synthesize without ``half``: the maps are converted after
        def synthesize(self, markers, outputs=("mesh",), clamp=True):
            return pdm_model.synthesize(markers, outputs, clamp)

    class PassesOn:              # a wrapper passing its keyword options on to .model
        def __init__(self, model):
            self.model = model

        def synthesize(self, markers, outputs=("mesh",), clamp=True, **options):
            return self.model.synthesize(markers, outputs, clamp, **options)

    assert takes(pdm_model, "half") and not takes(Float32Maps(), "half") and not takes(object(), "half")
    assert takes(PassesOn(pdm_model), "half") and not takes(PassesOn(Float32Maps()), "half")
    assert stream_options(pdm_model, True) == {"half": True, "confidence": False}
    assert stream_options(PassesOn(pdm_model), False) == {"confidence": False}
    assert stream_options(Float32Maps(), True) == {}
    got = {}
    for name, model in (("model", pdm_model), ("after", Float32Maps())):
        with running(lambda model_id, model=model: model) as channel:
            got[name] = list(stream_synthesize(channel, MODEL_ID, heldout_markers[:3], ALL, half=True))
    for a, b in zip(got["model"], got["after"]):
        assert a.keys() == b.keys()
        for key in set(a) - {"latency_ms"}:
            assert np.array_equal(np.atleast_1d(a[key]).view(np.uint8), np.atleast_1d(b[key]).view(np.uint8)), key
        assert a["normal_map"].dtype == np.float16


def test_a_later_message_changing_half_is_invalid_argument(channel, heldout_markers):
    from service.grpc import codec
    from service.grpc.facesynth.v1 import synthesis_pb2_grpc as pb_grpc

    messages = [codec.encode_markers(heldout_markers[0], 0, model_id=MODEL_ID, outputs=["mesh"]),
                codec.encode_markers(heldout_markers[1], 1, half=True)]
    with pytest.raises(grpc.RpcError) as e:
        list(pb_grpc.SynthesisStub(channel).StreamSynthesize(iter(messages)))
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "half True differs from the first message's False" in e.value.details()
