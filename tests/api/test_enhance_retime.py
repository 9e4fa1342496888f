"""A ready ``shape_space`` model of a tiny actor (a 16×13 sheet) with a registered
low-resolution input rig (a 9×7 sheet of the same surface): ``/enhance`` with ``rig``,
``/retime`` with vertex and clip-frame keyframes, synthesis jobs with ``rig``, and their
refusals.

The model is trained and the rig registered in-process (jobs are not run in the API tests);
the uploads go through the API."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from fastapi.testclient import TestClient

from models_store import registry
from service.methods.shape_space.temporal import keyframe_indices
from service.config import Settings
from service.methods.shape_space.registration import RigRegistration
from tests.api.conftest import (NPZ, Recorder, assert_problem, load_npz, make_client, npz,
                                put_rig, ready_sheet_model, ready_sheet_rig, sheet, sheet_motion,
                                upload_sheet_actor)

#: frames of a synchronous request at most (retime: keyframes and output length)
MAX_FRAMES = 12
#: the tiny actor's and its rig's vertices
N_ACTOR, N_RIG = 16 * 13, 9 * 7


@dataclass
class Tiny:
    """The uploaded tiny actor, its ready model and rigs (see the module docstring)."""

    client: TestClient
    actor_id: str
    model_id: str
    clip_ids: dict[str, str]
    model: object                   # the trained ShapeSpaceModel (in memory)
    registration: RigRegistration   # the "lod" rig's
    rig_vertices: np.ndarray        # (v,3) the rig's neutral
    pending_job: str                # the registration job of the rig left registering
    other_clip: str                 # a clip of another actor
    submitted: Recorder


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("api_shape_space")
    settings = Settings(data_dir=tmp / "data", max_frames_per_request=MAX_FRAMES,
                        max_body_bytes=8 << 20, tokens=[])
    submitted = Recorder()
    with make_client(settings, submitted) as client:
        actor_id, clip_ids = upload_sheet_actor(client, "sheet")
        _, other_clips = upload_sheet_actor(client, "another sheet")
        model_id, model = ready_sheet_model(client, actor_id, list(clip_ids.values()),
                                            tmp / "model")
        _, rig_vertices, registration = ready_sheet_rig(client, actor_id, "lod")
        Vr, Fr, _ = sheet(9, 7)
        pending = put_rig(client, actor_id, "pending", Vr, Fr)
        broken = put_rig(client, actor_id, "broken", Vr, Fr)
        services = client.app.state.services
        with services.session() as session:
            registry.mark_rig_failed(session, broken["rig_id"], "invalid_input",
                                     "the landmarks do not fix an alignment")
        yield Tiny(client, actor_id, model_id, clip_ids, model, registration, rig_vertices,
                   pending["job_id"], next(iter(other_clips.values())), submitted)


def enhance(tiny: Tiny, body: bytes, **params):
    return tiny.client.post(f"/v1/models/{tiny.model_id}/enhance", content=body, headers=NPZ,
                            params=params)


def retime(tiny: Tiny, body: dict | None = None, content: bytes | None = None, **params):
    url = f"/v1/models/{tiny.model_id}/retime"
    if content is not None:
        return tiny.client.post(url, content=content, headers=NPZ, params=params)
    return tiny.client.post(url, json=body, params=params)


def clip_frames(tiny: Tiny, name: str, frames) -> np.ndarray:
    """Frames (k,n,3) float64 of a stored clip (float32 values, as the store keeps them)."""
    V, _, _ = sheet(16, 13)
    phase = {"rise": 0.0, "fall": 0.3}[name]
    return sheet_motion(V, 12, phase).astype(np.float32)[list(frames)].astype(np.float64)


# ---------------------------------------------------------------------------- /enhance
def test_enhance_with_rig_is_the_model_on_the_propagated_frames(tiny):
    frames = sheet_motion(tiny.rig_vertices, 3, 0.15)          # (3,63,3) on the rig
    response = enhance(tiny, npz(vertices=frames), rig="lod")
    assert response.status_code == 200, response.text
    assert response.headers["x-frames"] == "3"
    out = load_npz(response.content)
    expected = tiny.model.enhance(tiny.registration.propagate(frames), ("mesh", "displacement"))
    assert out["vertices"].shape == (3, N_ACTOR, 3) and len(out["displacement"]) == 3
    assert set(out) == set(expected)
    for key in expected:
        np.testing.assert_array_equal(out[key], expected[key], err_msg=key)
    # the registration is loaded once per process and then served from the cache
    services = tiny.client.app.state.services
    hits = services.registrations.hits
    assert enhance(tiny, npz(vertices=frames[:1]), rig="lod").status_code == 200
    assert services.registrations.hits == hits + 1 and len(services.registrations) == 1


def test_enhance_without_rig_still_takes_the_actor_topology(tiny):
    V, _, _ = sheet(16, 13)
    frames = sheet_motion(V, 2, 0.6)
    response = enhance(tiny, npz(vertices=frames))
    assert response.status_code == 200, response.text
    expected = tiny.model.enhance(frames, ("mesh", "displacement"))
    np.testing.assert_array_equal(load_npz(response.content)["vertices"], expected["vertices"])


def test_enhance_with_rig_refusals(tiny):
    frames = sheet_motion(tiny.rig_vertices, 2, 0.15)
    body = assert_problem(enhance(tiny, npz(vertices=frames), rig="nope"), 404,
                          "input rig 'nope' not found", "lod")
    assert body["type"].endswith("not-found")
    assert_problem(enhance(tiny, npz(vertices=frames), rig="pending"), 409,
                   "input rig 'pending' is still registering", tiny.pending_job)
    assert_problem(enhance(tiny, npz(vertices=frames), rig="broken"), 409,
                   "input rig 'broken' failed to register", "invalid_input",
                   "the landmarks do not fix an alignment")
    assert_problem(enhance(tiny, npz(vertices=frames[:, :-1]), rig="lod"), 422,
                   f"input rig 'lod' has {N_RIG} vertices, the frames have {N_RIG - 1}")
    V, _, _ = sheet(16, 13)
    assert_problem(enhance(tiny, npz(vertices=sheet_motion(V, 1, 0.0)), rig="lod"), 422,
                   f"input rig 'lod' has {N_RIG} vertices, the frames have {N_ACTOR}")
    assert_problem(enhance(tiny, npz(vertices=frames[:, :-1])), 422,
                   f"model expects {N_ACTOR} vertices, got {N_RIG - 1}")
    bad = frames.copy()
    bad[1, 5, 2] = np.nan
    assert_problem(enhance(tiny, npz(vertices=bad), rig="lod"), 422, "frame 1 vertex 5")
    assert_problem(enhance(tiny, npz(vertices=np.repeat(frames, 7, axis=0)), rig="lod"), 413,
                   "14 frames", f"limit of {MAX_FRAMES} frames")
    assert_problem(enhance(tiny, npz(vertices=frames), rig="../x"), 422, "rig")


def test_synthesis_job_with_rig_records_the_registration(tiny):
    frames = sheet_motion(tiny.rig_vertices, 20, 0.1)          # more than MAX_FRAMES
    url = f"/v1/models/{tiny.model_id}/synthesis-jobs"
    response = tiny.client.post(url, content=npz(vertices=frames), headers=NPZ,
                                params={"rig": "lod"})
    assert response.status_code == 202, response.text
    job_id = response.json()["job_id"]
    assert job_id in tiny.submitted
    services = tiny.client.app.state.services
    with services.session() as session:
        job = registry.get_job(session, job_id)
        rig = registry.get_input_rig(session, tiny.actor_id, "lod")
        stored = services.blobs.read_bytes(job.payload["vertices_blob"],
                                           job.payload["vertices_sha256"])
    assert (job.payload["rig"], job.payload["rig_id"], job.payload["frames"]) == ("lod", rig.id, 20)
    assert (job.payload["registration_blob"], job.payload["registration_sha256"]) == (
        rig.registration_blob, rig.registration_sha256)
    np.testing.assert_array_equal(load_npz(stored)["vertices"], frames.astype(np.float32))
    assert_problem(tiny.client.post(url, content=npz(vertices=frames[:, :5]), headers=NPZ,
                                    params={"rig": "lod"}), 422, f"input rig 'lod' has {N_RIG}")
    assert_problem(tiny.client.post(url, content=npz(vertices=frames), headers=NPZ,
                                    params={"rig": "pending"}), 409, "still registering")
    assert_problem(tiny.client.post(url, content=npz(vertices=frames[:, :5]), headers=NPZ), 422,
                   f"model expects {N_ACTOR} vertices, got 5")


# ---------------------------------------------------------------------------- /retime
def test_retime_two_keyframes_is_the_model_s_retiming(tiny):
    keyframes = clip_frames(tiny, "rise", (0, 6))
    response = retime(tiny, {"keyframes": keyframes.tolist(), "length": 7})
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/x-npz"
    out = load_npz(response.content)
    expected = tiny.model.retime(keyframes, 7, False)
    assert out["vertices"].shape == (7, N_ACTOR, 3) and out["vertices"].dtype == np.float32
    for key in ("vertices", "timestamps", "progress", "region_progress"):
        np.testing.assert_array_equal(out[key], expected[key], err_msg=key)
    np.testing.assert_array_equal(out["faces"], tiny.model.faces)
    np.testing.assert_array_equal(out["keyframe_indices"], [0, 6])
    np.testing.assert_array_equal(out["segment_sequences"], expected["region_sequences"][None])
    # the same keyframes as clip-frame references, and extended to the full motion
    clip = tiny.clip_ids["rise"]
    refs = [{"clip_id": clip, "frame": 0}, {"clip_id": clip, "frame": 6}]
    by_ref = load_npz(retime(tiny, {"keyframes": refs, "length": 7}).content)
    np.testing.assert_array_equal(by_ref["vertices"], out["vertices"])
    extended = retime(tiny, {"keyframes": refs, "length": 7, "extend_to_full_motion": True})
    np.testing.assert_array_equal(load_npz(extended.content)["vertices"],
                                  tiny.model.retime(keyframes, 7, True)["vertices"])


def test_retime_three_keyframes_places_each_at_its_index(tiny):
    clip = tiny.clip_ids["rise"]
    other = tiny.clip_ids["fall"]
    refs = [{"clip_id": clip, "frame": 0}, {"clip_id": clip, "frame": 6},
            {"clip_id": other, "frame": 11}]
    response = retime(tiny, {"keyframes": refs, "length": 10})
    assert response.status_code == 200, response.text
    out = load_npz(response.content)
    keyframes = np.concatenate([clip_frames(tiny, "rise", (0, 6)), clip_frames(tiny, "fall", (11,))])
    index = keyframe_indices(3, 10)
    np.testing.assert_array_equal(index, [0, 5, 9])          # round(4.5) = 5: halves go up
    np.testing.assert_array_equal(out["keyframe_indices"], index)
    assert out["vertices"].shape == (10, N_ACTOR, 3) and out["timestamps"].shape == (10,)
    np.testing.assert_array_equal(out["vertices"][index], keyframes.astype(np.float32))
    first = tiny.model.retime(keyframes[:2], 6)
    second = tiny.model.retime(keyframes[1:], 5)
    np.testing.assert_array_equal(out["vertices"][:5], first["vertices"][:5])
    np.testing.assert_array_equal(out["vertices"][5:], second["vertices"])
    np.testing.assert_array_equal(out["timestamps"], np.concatenate(
        [first["timestamps"][:5], 5 + second["timestamps"]]))
    np.testing.assert_array_equal(out["progress"], np.concatenate(
        [first["progress"][:5], 1 + second["progress"]]))
    assert out["segment_sequences"].shape == (2, 1) and out["segment_spans"].shape == (2, 1, 2)


def test_retime_npz_body_with_rig_keyframes(tiny):
    keyframes = sheet_motion(tiny.rig_vertices, 4, 0.1)[[0, 3]]   # (2,63,3) on the rig
    response = retime(tiny, content=npz(keyframes=keyframes), length=6, rig="lod",
                      extend_to_full_motion="false")
    assert response.status_code == 200, response.text
    expected = tiny.model.retime(tiny.registration.propagate(keyframes), 6, False)
    out = load_npz(response.content)
    np.testing.assert_array_equal(out["vertices"], expected["vertices"])
    np.testing.assert_array_equal(out["timestamps"], expected["timestamps"])
    # JSON with the rig in the body, mixed with a clip frame (on the actor's topology)
    clip = tiny.clip_ids["fall"]
    mixed = retime(tiny, {"keyframes": [keyframes[0].tolist(), {"clip_id": clip, "frame": 4}],
                          "length": 5, "rig": "lod"})
    assert mixed.status_code == 200, mixed.text
    target = np.stack([tiny.registration.propagate(keyframes[0]), clip_frames(tiny, "fall", (4,))[0]])
    np.testing.assert_array_equal(load_npz(mixed.content)["vertices"],
                                  tiny.model.retime(target, 5)["vertices"])


def test_retime_refusals(tiny):
    clip = tiny.clip_ids["rise"]
    ref = {"clip_id": clip, "frame": 0}
    keyframes = clip_frames(tiny, "rise", (0, 6))
    assert_problem(retime(tiny, {"keyframes": [ref, {"clip_id": "clp_00000000000000000000000000",
                                                     "frame": 1}], "length": 4}), 404,
                   "clip 'clp_00000000000000000000000000' not found")
    assert_problem(retime(tiny, {"keyframes": [ref, {"clip_id": tiny.other_clip, "frame": 1}],
                                 "length": 4}), 404, "another actor")
    assert_problem(retime(tiny, {"keyframes": [ref, {"clip_id": clip, "frame": 12}],
                                 "length": 4}), 422,
                   f"keyframe 1 refers to frame 12 of clip {clip!r}, which has 12 frames")
    assert_problem(retime(tiny, {"keyframes": [ref, ref], "length": MAX_FRAMES + 1}), 413,
                   f"{MAX_FRAMES + 1} output frames", f"limit of {MAX_FRAMES} frames")
    assert_problem(retime(tiny, {"keyframes": [ref] * (MAX_FRAMES + 1), "length": MAX_FRAMES}),
                   413, f"{MAX_FRAMES + 1} keyframes")
    assert_problem(retime(tiny, {"keyframes": [ref] * 4, "length": 3}), 422,
                   "length 3 is less than the 4 keyframes")
    assert_problem(retime(tiny, {"keyframes": [ref], "length": 3}), 422, "keyframes")
    assert_problem(retime(tiny, {"keyframes": [ref, keyframes[1, :-1].tolist()], "length": 3}),
                   422, f"keyframe 1: model expects {N_ACTOR} vertices, got {N_ACTOR - 1}")
    assert_problem(retime(tiny, {"keyframes": [ref, keyframes[1].tolist()], "length": 3,
                                 "rig": "lod"}), 422,
                   f"keyframe 1: input rig 'lod' has {N_RIG} vertices, the frames have {N_ACTOR}")
    bad = keyframes[1].tolist()
    bad[7][1] = float("nan")
    response = tiny.client.post(f"/v1/models/{tiny.model_id}/retime",
                                content=f'{{"keyframes": [{keyframes[0].tolist()}, {bad}], '
                                        f'"length": 3}}'.replace("nan", "NaN"),
                                headers={"Content-Type": "application/json"})
    assert_problem(response, 422, "keyframe 1", "vertex 7", "non-finite")
    assert_problem(retime(tiny, {"keyframes": [ref, ref], "length": 3, "rig": "lod"}, rig="x"),
                   422, "rig is 'lod' in the body but 'x' in the query")
    assert_problem(retime(tiny, {"keyframes": [ref, ref], "length": 3, "rig": "pending"}), 409,
                   "still registering")
    assert_problem(retime(tiny, {"keyframes": [ref, ref], "length": 3, "lenght": 3}), 422,
                   "lenght")
    assert_problem(retime(tiny, content=npz(keyframes=keyframes)), 422, "'length'")
    assert_problem(retime(tiny, content=npz(keyframes=np.repeat(keyframes, 7, axis=0)),
                          length=14), 413, "14 keyframes")
    assert_problem(retime(tiny, content=npz(vertices=keyframes), length=4), 422, "vertices")
    assert_problem(tiny.client.post(f"/v1/models/{tiny.model_id}/retime", content=b"x",
                                    headers={"Content-Type": "text/csv"}), 415)
    assert_problem(tiny.client.post("/v1/models/mdl_00000000000000000000000000/retime",
                                    json={"keyframes": [ref, ref], "length": 3}), 404)


def test_openapi_documents_rig_and_retime(tiny):
    spec = tiny.client.get("/openapi.json").json()
    enhance_params = {p["name"] for p in spec["paths"]["/v1/models/{model_id}/enhance"]["post"]["parameters"]}
    jobs_params = {p["name"] for p in
                   spec["paths"]["/v1/models/{model_id}/synthesis-jobs"]["post"]["parameters"]}
    assert "rig" in enhance_params and "rig" in jobs_params
    operation = spec["paths"]["/v1/models/{model_id}/retime"]["post"]
    body = operation["requestBody"]["content"]["application/json"]["schema"]
    assert {"keyframes", "length", "extend_to_full_motion", "rig"} <= set(body["properties"])
    assert body["examples"] and "application/x-npz" in operation["requestBody"]["content"]
    assert {"422", "413", "404", "409"} <= set(operation["responses"])


def test_enhance_takes_markers_instead_of_vertices(tiny):
    from tests.api.conftest import SHEET_MARKERS

    V, _, _ = sheet(16, 13)
    markers = sheet_motion(V, 2, 0.4)[:, list(SHEET_MARKERS)]
    response = enhance(tiny, npz(markers=markers))
    assert response.status_code == 200, response.text
    expected = tiny.model.enhance(markers, ("mesh", "displacement"))
    np.testing.assert_array_equal(load_npz(response.content)["vertices"], expected["vertices"])
    assert_problem(enhance(tiny, npz(markers=markers[:, :3])), 422, "model expects 4 markers, got 3")
    assert_problem(enhance(tiny, npz(fps=np.float64(30.0))), 422, "neither 'vertices'", "'markers'")


def test_enhance_answers_every_output_of_synthesize(tiny):
    """API.md: /enhance's "response as for synthesize" — mesh_detailed and normal_map too
    (issue 17 item 6: they were refused as unknown outputs)."""
    V, _, _ = sheet(16, 13)
    frames = sheet_motion(V, 2, 0.6)
    response = enhance(tiny, npz(vertices=frames),
                       outputs="mesh,mesh_detailed,displacement,normal_map")
    assert response.status_code == 200, response.text
    out = load_npz(response.content)
    expected = tiny.model.enhance(frames, ("mesh", "mesh_detailed", "displacement", "normal_map"))
    assert {"vertices", "vertices_detailed", "displacement", "normal_map"} <= set(out)
    for key in ("vertices", "vertices_detailed", "displacement", "normal_map"):
        np.testing.assert_array_equal(out[key], expected[key], err_msg=key)
    # the tiny database has no fine maps: its detail is all in the enhanced mesh
    np.testing.assert_array_equal(out["vertices_detailed"], out["vertices"])
    assert out["normal_map"].shape == (2, 32, 32, 3)
    lengths = np.linalg.norm(out["normal_map"], axis=-1)
    np.testing.assert_allclose(lengths, 1.0, atol=1e-5)


def test_the_cache_weighs_a_served_model_without_its_mapped_database(tiny):
    """The database (detail, colours, maps, marker corrections) is memory-mapped at load and
    a request reads only its active frames, so the model cache does not count it (issue 23:
    a level-1 model's 4.4 GB outweighed the 2 GiB budget and reloaded on every request)."""
    from service.methods.footprint import file_mapped, nbytes

    services = tiny.client.app.state.services
    services.models.invalidate(tiny.model_id)
    before = services.models.total_bytes
    model = services.loaded_model(tiny.model_id).model
    data = model.data
    database = [data.detail, *vars(data.marker_database).values()]    # no colours, no maps
    assert data.colors is None and data.fine_maps is None
    assert [file_mapped(a) for a in database] == [True] * len(database)
    weight = services.models.total_bytes - before
    assert weight == nbytes(model, mapped=False)
    assert weight == nbytes(model) - sum(a.nbytes for a in database)
    assert tiny.model_id in services.models
