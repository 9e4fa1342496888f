"""A ready PDM model in the store (the session's trained ``pdm_model``): synchronous
synthesis in every encoding, its refusals, the model's maps, and synthesis jobs."""

from __future__ import annotations

import functools
import io
import json
import zipfile

import numpy as np
import pytest

from models_store import registry
from service.config import Settings
from service.io.exr import read_exr, read_map
from service.io.markers import MarkerSequence, write_markers_csv, write_markers_trc
from service.io.mesh import read_obj
from service.methods.footprint import nbytes
from tests.api.conftest import NPZ, Recorder, assert_problem, load_npz, make_client, npz, upload_sample_actor
from tests.conftest import PDM_TRAINING


@pytest.fixture(scope="module")
def ready(tmp_path_factory, pdm_actor_dir, pdm_model):
    """(client, actor_id, model_id, heldout markers (F,M,3), submitted) with the sample
    actor uploaded through the API and the trained model marked ready."""
    tmp = tmp_path_factory.mktemp("api_ready")
    settings = Settings(data_dir=tmp / "data", max_frames_per_request=4, max_map_resolution=256)
    submitted = Recorder()
    with make_client(settings, submitted) as client:
        actor_id, clip_ids = upload_sample_actor(client, pdm_actor_dir, PDM_TRAINING[:1])
        model_id = client.post(f"/v1/actors/{actor_id}/models", json={
            "kind": "pdm", "clips": [clip_ids[PDM_TRAINING[0]]]}).json()["model_id"]
        pdm_model.save(tmp / "model")
        services = client.app.state.services
        with services.session() as session:
            registry.mark_model_ready(session, services.blobs, model_id, tmp / "model",
                                      metrics=pdm_model.metrics)
        with np.load(pdm_actor_dir / "performances" / "heldout_in_range.npz") as d:
            heldout = d["markers"][:2].astype(np.float64)
        yield client, actor_id, model_id, heldout, submitted


def synth(client, model_id, body, headers=NPZ, **params):
    return client.post(f"/v1/models/{model_id}/synthesize", content=body, headers=headers,
                       params=params)


def test_ready_model_record(ready, pdm_model):
    client, actor_id, model_id, _, _ = ready
    model = client.get(f"/v1/models/{model_id}").json()
    assert model["status"] == "ready" and model["size_bytes"] > 0
    assert model["metrics"]["training_frames"] == pdm_model.metrics["training_frames"]


def test_synthesize_npz_default_outputs(ready, pdm_model):
    client, _, model_id, markers, _ = ready
    response = synth(client, model_id, npz(markers=markers))
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/x-npz"
    out = load_npz(response.content)
    n = pdm_model.n_vertices
    assert out["vertices"].shape == (2, n, 3) and out["faces"].shape[1] == 3
    assert out["displacement"].shape == (2, 128, 128) and "vertices_detailed" not in out
    expected = pdm_model.synthesize(markers, ("mesh", "displacement"))
    np.testing.assert_allclose(out["vertices"], expected["vertices"], atol=1e-5)


def test_synthesize_json_with_outputs_and_map_resolution(ready):
    client, _, model_id, markers, _ = ready
    frames = markers[:1].tolist()
    frames[0][3] = None                                 # an occluded marker
    response = client.post(f"/v1/models/{model_id}/synthesize", json={
        "markers": frames, "outputs": ["mesh_detailed", "normal_map"], "map_resolution": 64})
    assert response.status_code == 200, response.text
    out = load_npz(response.content)
    assert out["vertices_detailed"].shape[0] == 1 and out["normal_map"].shape == (1, 64, 64, 3)
    lengths = np.linalg.norm(out["normal_map"], axis=-1)
    assert np.allclose(lengths[lengths > 0], 1, atol=1e-4)


def test_synthesize_obj_and_exr_for_one_frame(ready, pdm_model):
    client, _, model_id, markers, _ = ready
    obj = synth(client, model_id, npz(markers=markers[:1]), {**NPZ, "Accept": "model/obj"})
    assert obj.status_code == 200 and obj.headers["content-type"] == "model/obj"
    mesh = read_obj(obj.content)
    assert len(mesh.vertices) == pdm_model.n_vertices and mesh.uv is not None
    exr = synth(client, model_id, npz(markers=markers[:1]), {**NPZ, "Accept": "image/x-exr"},
                outputs="displacement")
    assert exr.status_code == 200 and exr.headers["content-type"] == "image/x-exr"
    assert read_map(exr.content).shape == (128, 128)
    half = synth(client, model_id, npz(markers=markers[:1]), {**NPZ, "Accept": "image/x-exr"},
                 outputs="displacement", half="true")
    assert len(half.content) < len(exr.content)


def test_half_maps_and_topology_false_against_the_float32_response(ready, pdm_model):
    """``half=true`` gives float16 maps within the stated bound of the float32 response
    (|h - f| <= 2^-11 |f| + 2^-25), everything else bit-exact; ``topology=false`` leaves out
    only ``faces``; the float32 default is bit-exact with the in-process model."""
    from service.app.synthesis import HALF_ABSOLUTE_ERROR, HALF_RELATIVE_ERROR

    client, _, model_id, markers, _ = ready
    outputs = "mesh,displacement,normal_map"
    full = load_npz(synth(client, model_id, npz(markers=markers), outputs=outputs).content)
    expected = pdm_model.synthesize(markers, outputs.split(","))
    for key in ("vertices", "faces", "displacement", "normal_map", "clamped"):
        assert full[key].dtype == expected[key].dtype
        np.testing.assert_array_equal(full[key], expected[key])     # bit-exact, float32
    response = synth(client, model_id, npz(markers=markers), outputs=outputs, half="true",
                     topology="false")
    assert response.status_code == 200, response.text
    half = load_npz(response.content)
    assert set(half) == set(full) - {"faces"}
    for key in ("displacement", "normal_map"):
        assert half[key].dtype == np.float16 and half[key].shape == full[key].shape
        f = full[key].astype(np.float64)
        error = np.abs(half[key].astype(np.float64) - f)
        assert np.all(error <= HALF_RELATIVE_ERROR * np.abs(f) + HALF_ABSOLUTE_ERROR)
        assert error.max() > 0                                     # it is rounded
        # the model's own float16 kernels (Synthesizer.run(half=True)): NumPy's rounding
        np.testing.assert_array_equal(half[key], full[key].astype(np.float16))
    for key in set(half) - {"displacement", "normal_map"}:
        np.testing.assert_array_equal(half[key], full[key])
    assert len(response.content) < 0.6 * len(
        synth(client, model_id, npz(markers=markers), outputs=outputs).content)


def test_topology_resource_with_etag_and_304(ready, pdm_model):
    client, _, model_id, _, _ = ready
    response = client.get(f"/v1/models/{model_id}/topology")
    assert response.status_code == 200 and response.headers["content-type"] == "application/x-npz"
    etag = response.headers["etag"]
    assert etag.startswith('"') and len(etag) == 66
    out = load_npz(response.content)
    np.testing.assert_array_equal(out["faces"], pdm_model.faces)
    assert out["faces"].dtype == np.int32
    np.testing.assert_array_equal(out["uv"], pdm_model.uv)
    np.testing.assert_array_equal(out["uv_faces"], pdm_model.uv_faces)
    again = client.get(f"/v1/models/{model_id}/topology", headers={"If-None-Match": etag})
    assert again.status_code == 304 and again.headers["etag"] == etag and not again.content
    listed = client.get(f"/v1/models/{model_id}/topology",
                        headers={"If-None-Match": f'"other", W/{etag}'})
    assert listed.status_code == 304
    stale = client.get(f"/v1/models/{model_id}/topology", headers={"If-None-Match": '"x"'})
    assert stale.status_code == 200 and stale.headers["etag"] == etag
    assert stale.content == response.content
    assert_problem(client.get("/v1/models/mdl_00000000000000000000000000/topology"), 404)


def test_synthesize_refusals(ready, pdm_model):
    client, _, model_id, markers, _ = ready
    M = pdm_model.n_markers
    assert_problem(synth(client, model_id, npz(markers=markers[:, :-1])), 422,
                   f"model expects {M} markers, got {M - 1}")
    assert_problem(synth(client, model_id, npz(markers=np.repeat(markers, 3, axis=0))), 413,
                   "6 frames", "limit of 4 frames", "synthesis-jobs")
    assert_problem(client.post(f"/v1/models/{model_id}/synthesize",
                               json={"markers": np.repeat(markers, 3, axis=0).tolist()}), 413,
                   "limit of 4")
    bad = markers.copy()
    bad[1, 2, 0] = np.inf
    assert_problem(synth(client, model_id, npz(markers=bad)), 422, "frame 1 marker 2")
    assert_problem(synth(client, model_id, npz(markers=markers), outputs="wrinkles"), 422,
                   "unknown outputs ['wrinkles']")
    assert_problem(synth(client, model_id, npz(markers=markers), {**NPZ, "Accept": "model/obj"}),
                   422, "one frame")
    assert_problem(synth(client, model_id, npz(markers=markers[:1]),
                         {**NPZ, "Accept": "image/x-exr"}), 422, "one map")
    assert_problem(synth(client, model_id, npz(markers=markers), {**NPZ, "Accept": "text/html"}),
                   406, "text/html")
    assert_problem(synth(client, model_id, npz(vertices=markers)), 422, "lacks 'markers'")
    assert_problem(synth(client, model_id, b"{}", {"Content-Type": "application/json"}), 422,
                   "markers")
    assert_problem(synth(client, model_id, b"{", {"Content-Type": "application/json"}), 400)
    assert_problem(synth(client, model_id, b"x", {"Content-Type": "text/csv"}), 415)
    assert_problem(client.post(f"/v1/models/{model_id}/synthesize", json={
        "markers": markers[:1].tolist(), "map_resolution": 512}), 413, "max_map_resolution")
    assert_problem(client.post(f"/v1/models/{model_id}/enhance", content=npz(vertices=markers),
                               headers=NPZ), 422, "takes markers", "/synthesize")


def test_synthesis_is_counted_in_metrics(ready):
    client, _, model_id, markers, _ = ready
    synth(client, model_id, npz(markers=markers))
    text = client.get("/metrics").text
    line = next(l for l in text.splitlines() if l.startswith('facesynth_synthesis_frames_total{kind="pdm"}'))
    assert float(line.split()[-1]) >= 2
    assert 'facesynth_synthesis_fps{kind="pdm"}' in text


def test_markers_in_metres_for_a_millimetre_actor_are_a_422_naming_the_unit(ready):
    client, _, model_id, markers, _ = ready
    body = assert_problem(synth(client, model_id, npz(markers=markers / 1000)), 422,
                          "were they sent in metres?", "mm")
    assert "about 1000× smaller" in body["detail"]
    response = client.post(f"/v1/models/{model_id}/synthesis-jobs",
                           content=npz(markers=markers / 10), headers=NPZ)
    assert_problem(response, 422, "were they sent in centimetres?")
    assert synth(client, model_id, npz(markers=markers)).status_code == 200


def _cache_metrics(client) -> dict[str, float]:
    return {line.split()[0].removeprefix("facesynth_model_cache_"): float(line.split()[-1])
            for line in client.get("/metrics").text.splitlines()
            if line.startswith("facesynth_model_cache_")}


def test_preload_and_the_model_cache_in_metrics(ready):
    """Preloading (``Services.preload``, ``facesynth serve --preload``) loads the ready
    model once; each later request is a cache hit; /metrics reports the cache's state."""
    client, _, model_id, markers, _ = ready
    services = client.app.state.services
    services.forget_model(model_id)
    before = _cache_metrics(client)
    assert before["models"] == 0 and before["bytes"] == 0
    assert before["budget_bytes"] == services.settings.model_cache_bytes
    assert services.preload(["all"]) == [model_id]
    loaded = _cache_metrics(client)
    assert loaded["models"] == 1 and loaded["misses_total"] == before["misses_total"] + 1
    assert loaded["bytes"] == services.models.total_bytes > 0
    assert synth(client, model_id, npz(markers=markers)).status_code == 200
    after = _cache_metrics(client)
    assert after["hits_total"] == loaded["hits_total"] + 1
    assert after["misses_total"] == loaded["misses_total"]      # no second load


@pytest.mark.parametrize("damage", ["manifest", "cache"])
def test_a_model_file_altered_on_disk_is_refused_as_corrupt_and_never_cached(ready, damage):
    """The files are hashed while the model loads (``BlobStore.open_dir(background=True)``):
    one flipped byte, in the manifest (read first) or in the largest file (mapped, read
    last), still fails the load as corrupt (500, the checksum detail) and caches nothing."""
    client, _, model_id, markers, _ = ready
    services = client.app.state.services
    services.forget_model(model_id)
    with services.session() as session:
        blob = registry.get_model(session, model_id).blob
    target = services.blobs.path(blob) / ("manifest.json" if damage == "manifest" else "cache.npz")
    original = target.read_bytes()
    altered = bytearray(original)
    altered[len(altered) // 2] ^= 0x01
    target.chmod(0o644)
    target.write_bytes(bytes(altered))
    try:
        response = synth(client, model_id, npz(markers=markers))
        assert_problem(response, 500, "stored data failed its checksum")
        assert model_id not in services.models
    finally:
        target.write_bytes(original)
    assert synth(client, model_id, npz(markers=markers)).status_code == 200


def test_a_corrupt_model_is_never_warmed_up_streamed_or_cached(ready, monkeypatch):
    """The integrity rule of a load (``Services._load``): nothing read from a model's files
    is synthesized with before they match their sha256. One flipped byte in the largest file
    (hashed in a thread while the kind reads it): the preload fails and /readyz names the
    corrupt blob, the warm-up frame never runs, the gRPC path's loader raises what the stream
    ends with as DATA_LOSS, and nothing is cached."""
    import grpc

    from service.app.services import Services
    from service.errors import Corrupt
    from service.grpc.server import code_of

    client, _, model_id, markers, _ = ready
    services = client.app.state.services
    services.forget_model(model_id)
    with services.session() as session:
        blob = registry.get_model(session, model_id).blob
    target = services.blobs.path(blob) / "cache.npz"
    original = target.read_bytes()
    altered = bytearray(original)
    altered[len(altered) // 3] ^= 0x10
    warmed: list[str] = []
    monkeypatch.setattr(Services, "warm_up", lambda self, loaded: warmed.append(loaded.id))
    target.write_bytes(bytes(altered))
    try:
        state = services.start_preload([model_id])
        assert state.done.wait(60) and state.loaded == []
        assert "BlobCorrupt" in state.error and "is corrupt: sha256" in state.error
        checks = client.get("/readyz").json()["checks"]
        assert checks["models"].startswith(f"preload failed: {model_id}: BlobCorrupt")
        with pytest.raises(Corrupt) as error:
            services.load_model(model_id)
        assert code_of(error.value) == grpc.StatusCode.DATA_LOSS
        assert warmed == [] and model_id not in services.models
    finally:
        target.write_bytes(original)
        services.preloading = None
    assert services.load_model(model_id) is not None and model_id in services.models


def test_background_preload_holds_readiness_until_loaded_and_names_a_failed_load(ready, monkeypatch):
    """``Services.start_preload`` (``facesynth serve --preload`` / ``FACESYNTH_PRELOAD``)
    checks the ids at once, loads in a thread, and /readyz answers 503 (check ``models``)
    until the models are in the cache; a load that fails keeps it 503 and names the model."""
    import threading

    from service.app.services import Preload
    from service.errors import NotFound

    client, _, model_id, markers, _ = ready
    services = client.app.state.services
    services.forget_model(model_id)
    with pytest.raises(NotFound):
        services.start_preload(["mdl_00000000000000000000000000"])
    assert services.preloading is None                  # nothing started for a bad id
    assert Preload([model_id, "mdl_x"], loaded=[model_id]).status() == "loading: 1 of 2 preloaded"
    gate = threading.Event()
    load = services.loaded_model

    def slow_load(mid):
        gate.wait(30)
        return load(mid)

    monkeypatch.setattr(services, "loaded_model", slow_load)
    try:
        state = services.start_preload([model_id])
        response = client.get("/readyz")
        assert response.status_code == 503
        assert response.json()["checks"]["models"] == "loading: 0 of 1 preloaded"
        gate.set()
        assert state.done.wait(60) and state.loaded == [model_id]
        response = client.get("/readyz")
        assert response.status_code == 200 and response.json()["checks"]["models"] == "ok"
        assert model_id in services.models
        loaded = services.loaded_model(model_id)
        calls, real = [], loaded.model.synthesize

        @functools.wraps(real)                 # the model's signature: it takes half
        def recorded(*args, **options):
            calls.append(options.get("half", False))
            return real(*args, **options)

        monkeypatch.setattr(loaded.model, "synthesize", recorded)
        assert services.warm_up(loaded) is True and calls == [False]
        # the float16 map kernels (issue 23), which start_preload runs once the model is ready
        assert services.warm_up(loaded, half=True) is True and calls == [False, True]

        def broken(mid):
            raise OSError("disk on fire")

        monkeypatch.setattr(services, "loaded_model", broken)
        assert services.start_preload([model_id]).done.wait(60)
        response = client.get("/readyz")
        assert response.status_code == 503
        assert response.json()["checks"]["models"] == f"preload failed: {model_id}: OSError: disk on fire"
    finally:
        services.preloading = None


def test_settings_preload_from_the_environment(monkeypatch):
    monkeypatch.setenv("FACESYNTH_PRELOAD", " mdl_a, mdl_b ,")
    assert Settings().preload == ["mdl_a", "mdl_b"]
    monkeypatch.setenv("FACESYNTH_PRELOAD", "all")
    assert Settings().preload == ["all"]


def test_model_maps_list_and_download(ready):
    client, _, model_id, _, _ = ready
    maps = {m["name"]: m for m in client.get(f"/v1/models/{model_id}/maps").json()["items"]}
    assert {"medium", "fine", "neutral"} <= set(maps)
    assert maps["fine"]["channels"][:2] == ["n.a0", "n.a1"] and maps["fine"]["width"] == 128
    response = client.get(maps["fine"]["url"])
    assert response.status_code == 200 and response.headers["content-type"] == "image/x-exr"
    channels = read_exr(response.content)
    assert set(channels) == set(maps["fine"]["channels"])
    half = client.get(maps["fine"]["url"], params={"half": "true"})
    assert len(half.content) < len(response.content)
    ranged = client.get(maps["fine"]["url"], headers={"Range": "bytes=0-3"})
    assert ranged.status_code == 206 and ranged.content == response.content[:4]
    assert_problem(client.get(f"/v1/models/{model_id}/maps/wrinkles.exr"), 404, "fine")
    assert_problem(client.get(f"/v1/models/{model_id}/maps/..%2Fmanifest.exr"), 404)


def _csv(markers, names):
    buffer = io.BytesIO()
    write_markers_csv(buffer, MarkerSequence(markers, names))
    return buffer.getvalue()


def test_synthesis_job_from_npz_and_marker_files(ready):
    client, actor_id, model_id, markers, submitted = ready
    url = f"/v1/models/{model_id}/synthesis-jobs"
    response = client.post(url, content=npz(markers=np.repeat(markers, 5, axis=0)), headers=NPZ,
                           params={"outputs": "mesh,normal_map"})
    assert response.status_code == 202, response.text
    job_id = response.json()["job_id"]
    assert response.headers["location"] == f"/v1/jobs/{job_id}" and job_id in submitted
    services = client.app.state.services
    with services.session() as session:
        job = registry.get_job(session, job_id)
        data = services.blobs.read_bytes(job.payload["markers_blob"], job.payload["markers_sha256"])
    assert (job.kind, job.model_id, job.payload["frames"]) == ("synthesize", model_id, 10)
    assert job.payload["outputs"] == ["mesh", "normal_map"] and job.payload["format"] == "npz"
    np.testing.assert_allclose(load_npz(data)["markers"], np.repeat(markers, 5, axis=0), rtol=1e-6)

    names = json.loads(client.app.state.services.blobs.read_bytes(
        *_layout_key(services, actor_id)))["names"]
    reversed_csv = _csv(markers[:, ::-1], names[::-1])   # named columns in another order
    response = client.post(url, content=reversed_csv, headers={"Content-Type": "text/csv"})
    assert response.status_code == 202, response.text
    trc = io.BytesIO()
    write_markers_trc(trc, MarkerSequence(markers, names), fps=60)
    response = client.post(url, files={"file": ("take.trc", trc.getvalue(), "text/plain")})
    assert response.status_code == 202, response.text


def test_synthesis_job_marker_filter_option_reaches_the_payload(ready):
    client, _, model_id, markers, _ = ready
    url = f"/v1/models/{model_id}/synthesis-jobs"
    services = client.app.state.services

    def payload(**params):
        response = client.post(url, content=npz(markers=markers), headers=NPZ, params=params)
        assert response.status_code == 202, response.text
        with services.session() as session:
            return registry.get_job(session, response.json()["job_id"]).payload

    assert "marker_filter_frames" not in payload()
    assert payload(marker_filter_frames=3)["marker_filter_frames"] == 3.0
    assert payload(marker_filter_frames="auto")["marker_filter_frames"] == "auto"
    assert_problem(client.post(url, content=npz(markers=markers), headers=NPZ,
                               params={"marker_filter_frames": -1}), 422)
    refused = client.post(url, content=npz(markers=markers), headers=NPZ,
                          params={"marker_filter_frames": "smooth"})
    assert_problem(refused, 422)
    assert "marker_filter_frames" in refused.text and "auto" in refused.text
    assert_problem(client.post(url, content=npz(markers=markers), headers=NPZ,
                               params={"marker_filter_frames": 1000}), 422)


def _layout_key(services, actor_id):
    with services.session() as session:
        actor = registry.get_actor(session, actor_id)
        return actor.markers_blob, actor.markers_sha256


def test_synthesis_job_refusals(ready, pdm_model):
    client, _, model_id, markers, _ = ready
    url = f"/v1/models/{model_id}/synthesis-jobs"
    M = pdm_model.n_markers
    assert_problem(client.post(url, content=npz(markers=markers[:, :5]), headers=NPZ), 422,
                   f"model expects {M} markers, got 5")
    assert_problem(client.post(url, content=npz(markers=markers), headers=NPZ,
                               params={"format": "usd", "outputs": "displacement"}), 422,
                   "format 'usd' is a point cache and needs a mesh output")
    assert_problem(client.post(url, content=_csv(markers[:, :3], ["a", "b", "c"]),
                               headers={"Content-Type": "text/csv"}), 422, "lacks")
    assert_problem(client.post(url, content=b"x", headers={"Content-Type": "image/png"}), 415)
    assert_problem(client.post("/v1/models/mdl_00000000000000000000000000/synthesis-jobs",
                               content=npz(markers=markers), headers=NPZ), 404)


def test_services_load_model_serves_the_grpc_path(ready):
    client, _, model_id, markers, _ = ready
    services = client.app.state.services
    model = services.load_model(model_id)
    assert model is services.load_model(model_id)        # cached
    # weighed by the memory it held when loaded (mapped arrays included: a PDM reads its
    # coefficient maps on every frame), not by its files; what it builds lazily while
    # synthesizing can only add to that
    weight = services.models.total_bytes
    assert nbytes(model, mapped=False) < weight <= nbytes(model)
    assert model.synthesize(markers[:1], ["mesh"])["vertices"].shape[0] == 1


def test_accept_negotiation():
    from service.app.synthesis import negotiate
    from service.errors import NotAcceptable

    assert negotiate(None) == negotiate("*/*") == "application/x-npz"
    assert negotiate("model/obj") == "model/obj"
    assert negotiate("image/x-exr;q=0.5, model/obj;q=0.9") == "model/obj"
    assert negotiate("text/html, image/*") == "image/x-exr"
    assert negotiate("model/obj;q=0, application/*") == "application/x-npz"
    with pytest.raises(NotAcceptable):
        negotiate("text/html")


def test_synthesis_slots_answer_503_when_busy():
    from types import SimpleNamespace

    from service.api.errors import status_of
    from service.errors import Unavailable
    from service.app.metrics import Metrics
    from service.app.synthesis import SynthesisInput, Synthesizer

    synthesizer = Synthesizer(Metrics(), limit=1, wait_seconds=0.0)
    model = SimpleNamespace(synthesize=lambda frames, outputs, clamp: {"faces": np.zeros((1, 3))})
    loaded = SimpleNamespace(model=model, kind=SimpleNamespace(name="fake"))
    request = SynthesisInput(np.zeros((1, 2, 3)), ("mesh",))
    assert "faces" in synthesizer.run(loaded, request)
    synthesizer.pool.acquire()
    with pytest.raises(Unavailable) as error:
        synthesizer.run(loaded, request)
    status, headers = status_of(error.value)
    assert status == 503 and headers["Retry-After"] == "1"


def test_half_is_passed_to_a_model_that_takes_it_unless_maps_are_resampled():
    """issue 23: an NPZ ``half=true`` answer has the model write float16 maps itself where
    its ``synthesize`` takes ``half``; a model without it, or a resampled map, is converted
    after (service.app.synthesis.encode)."""
    from types import SimpleNamespace

    from service.app.metrics import Metrics
    from service.app.synthesis import SynthesisInput, Synthesizer

    calls = []

    def takes_half(frames, outputs, clamp, half=False):
        calls.append(half)
        return {"faces": np.zeros((1, 3))}

    synthesizer = Synthesizer(Metrics(), limit=1, wait_seconds=0.0)
    plain = SimpleNamespace(model=SimpleNamespace(synthesize=lambda frames, outputs, clamp: {}),
                            kind=SimpleNamespace(name="fake"))
    loaded = SimpleNamespace(model=SimpleNamespace(synthesize=takes_half), kind=SimpleNamespace(name="fake"))
    request = SynthesisInput(np.zeros((1, 2, 3)), ("mesh",))
    synthesizer.run(loaded, request, half=True)
    synthesizer.run(loaded, request)
    synthesizer.run(loaded, SynthesisInput(request.frames, ("mesh",), map_resolution=64), half=True)
    synthesizer.run(plain, request, half=True)                    # no half parameter: not passed
    assert calls == [True, False, False]


def test_busy_syntheses_queue_for_a_bounded_wait_and_the_depth_is_a_metric():
    """issue 16, defect 12: excess requests were refused at once (77 % 503s with 16 clients);
    now they wait up to ``wait_seconds`` for a slot, and /metrics shows how many wait."""
    import threading
    import time
    from types import SimpleNamespace

    from service.app.metrics import Metrics
    from service.app.synthesis import SynthesisInput, Synthesizer
    from service.errors import Unavailable

    metrics = Metrics()
    synthesizer = Synthesizer(metrics, limit=1, wait_seconds=5.0, max_queue=2)
    release = threading.Event()

    def slow(frames, outputs, clamp):
        release.wait(10)
        return {"faces": np.zeros((1, 3))}

    loaded = SimpleNamespace(model=SimpleNamespace(synthesize=slow),
                             kind=SimpleNamespace(name="fake"))
    request = SynthesisInput(np.zeros((1, 2, 3)), ("mesh",))
    results: list[object] = []

    def call():
        try:
            results.append(synthesizer.run(loaded, request))
        except Unavailable as error:
            results.append(error)

    threads = [threading.Thread(target=call) for _ in range(3)]    # 1 runs, 2 wait
    for t in threads:
        t.start()
    deadline = time.monotonic() + 5
    while synthesizer.waiting < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert (synthesizer.running, synthesizer.waiting) == (1, 2)
    text = metrics.render().decode()
    assert "facesynth_synthesis_queue_depth 2.0" in text
    assert "facesynth_synthesis_running 1.0" in text
    with pytest.raises(Unavailable, match="2 requests are waiting"):    # the queue is full
        synthesizer.run(loaded, request)
    release.set()
    for t in threads:
        t.join(10)
    assert len(results) == 3 and all(isinstance(r, dict) for r in results)   # none refused
    assert synthesizer.waiting == 0 and "facesynth_synthesis_queue_depth 0.0" in \
        metrics.render().decode()
    # a wait that runs out is a 503
    short = Synthesizer(Metrics(), limit=1, wait_seconds=0.2)
    short.pool.acquire()
    start = time.monotonic()
    with pytest.raises(Unavailable, match="waited 0.2 s"):
        short.run(loaded, request)
    assert 0.2 <= time.monotonic() - start < 1.0


def test_per_vertex_displacement_is_refused_as_a_map_not_a_500():
    """A kind that gives 'displacement' per vertex (shape_space: (F,n)) cannot be resampled
    or sent as EXR: 422 naming the shape, never a crash."""
    from service.app.synthesis import resample_maps
    from service.methods.inputs import InvalidInput

    with pytest.raises(InvalidInput, match=r"'displacement' per vertex, shape \(1, 10\)"):
        resample_maps({"displacement": np.zeros((1, 10), np.float32)}, 64)


def test_retime_is_refused_for_a_pdm_model(ready):
    client, _, model_id, _, _ = ready
    response = client.post(f"/v1/models/{model_id}/retime",
                           json={"keyframes": [[[0.0, 0.0, 0.0]], [[1.0, 0.0, 0.0]]], "length": 3})
    assert_problem(response, 422, "a pdm model cannot retime", "supported by the kinds shape_space")
    assert_problem(client.post(f"/v1/models/{model_id}/enhance", content=npz(vertices=np.zeros((1, 4, 3))),
                               headers=NPZ, params={"rig": "lod"}), 422, "takes markers")


def test_a_usd_synthesis_job_through_the_api_is_a_zip_of_the_cache_and_its_maps(ready, tmp_path):
    """Submitted over HTTP, run by the job runner in this process (jobs are only recorded
    here), downloaded over HTTP: the cache's points are the npz job's vertices, bit for bit."""
    from pxr import Usd, UsdGeom, UsdShade

    from service.jobs import runner

    client, _, model_id, markers, submitted = ready
    services = client.app.state.services
    body = npz(markers=markers, fps=np.float64(25.0))
    results = {}
    for fmt in ("usd", "npz"):
        response = client.post(f"/v1/models/{model_id}/synthesis-jobs", content=body,
                               headers=NPZ, params={"outputs": "mesh,displacement",
                                                    "format": fmt})
        assert response.status_code == 202, response.text
        job_id = response.json()["job_id"]
        assert job_id in submitted
        assert runner.execute(services.settings, job_id, "test-host:1:MainThread") == "succeeded"
        job = client.get(f"/v1/jobs/{job_id}").json()
        (artifact_id,) = job["result"]["artifact_ids"]
        results[fmt] = client.get(f"/v1/artifacts/{artifact_id}")
        assert results[fmt].status_code == 200
    assert results["usd"].headers["content-type"] == "application/zip"
    with zipfile.ZipFile(io.BytesIO(results["usd"].content)) as z:
        assert sorted(z.namelist()) == ["clamped.csv", "confidence.json", "frame_0000_displacement.exr",
                                        "frame_0001_displacement.exr", "performance.usd"]
        z.extractall(tmp_path)
    expected = load_npz(results["npz"].content)
    stage = Usd.Stage.Open(str(tmp_path / "performance.usd"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Mesh"))
    points = np.stack([np.asarray(mesh.GetPointsAttr().Get(t)) for t in (0, 1)])
    assert mesh.GetPointsAttr().GetTimeSamples() == [0.0, 1.0]
    assert points.dtype == expected["vertices"].dtype == np.float32
    np.testing.assert_array_equal(points, expected["vertices"])
    np.testing.assert_array_equal(np.asarray(mesh.GetFaceVertexIndicesAttr().Get()),
                                  expected["faces"].ravel())
    assert stage.GetTimeCodesPerSecond() == 25.0
    texture = UsdShade.Shader(stage.GetPrimAtPath("/Face/Looks/Material/displacementTexture"))
    resolved = texture.GetInput("file").GetAttr().Get(1).resolvedPath
    np.testing.assert_array_equal(read_map(open(resolved, "rb").read()),
                                  expected["displacement"][1])


def test_the_grpc_path_refuses_markers_in_another_unit(ready):
    """issue 22 item 11 on the stream: metres sent to a millimetre model are refused with
    the likely unit named, as /synthesize refuses them."""
    from service.methods.inputs import InvalidInput

    client, _, model_id, markers, _ = ready
    model = client.app.state.services.load_model(model_id)
    assert model.synthesize(markers[:1], ["mesh"])["vertices"].shape == (1, model.n_vertices, 3)
    with pytest.raises(InvalidInput, match="metres"):
        model.synthesize(markers[:1] / 1000.0, ["mesh"])


def test_synthesize_answers_the_per_frame_confidence_in_a_header_and_the_npz(ready, pdm_model):
    client, _, model_id, markers, _ = ready
    rest = pdm_model.evaluator.base.rest_markers
    pose = pdm_model.evaluator.deformation(markers[:1])[0]
    far = pose.restore(rest + 6.0 * (pose.remove(markers[:1]) - rest))      # 6× the expression
    frames = np.concatenate([markers[:1], far])
    response = synth(client, model_id, npz(markers=frames))
    assert response.status_code == 200, response.text
    expected = pdm_model.synthesize(frames, ("mesh", "displacement"))["confidence"]
    header = [float(x) for x in response.headers["X-Facesynth-Confidence"].split(",")]
    np.testing.assert_allclose(header, expected, atol=5e-5)
    out = load_npz(response.content)
    np.testing.assert_allclose(out["confidence"], expected, atol=0)
    assert out["confidence_vertices"].shape == (2, pdm_model.n_vertices)
    spec = client.get("/openapi.json").json()
    ok = spec["paths"]["/v1/models/{model_id}/synthesize"]["post"]["responses"]["200"]
    assert "X-Facesynth-Confidence" in ok["headers"]
