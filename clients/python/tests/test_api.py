"""Every route of API.md through the sync :class:`Client`, against the real app served on a
loopback port with an embedded worker (see conftest.py)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from facesynth_client import (Actor, Artifact, ClipFrame, Conflict, Job, JobAccepted,
                              KindInfo, MapInfo, Model, ModelAccepted, NeutralInfo, NotFound,
                              PayloadTooLarge, Readiness, RigAccepted, Unprocessable, load_npz)

from conftest import PDM_PARAMS, SHEET_MARKERS, sheet, sheet_motion, upload_sheet_actor


def obj_text(V, F, uv=None) -> str:
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in V]
    if uv is not None:
        lines += [f"vt {u:.9g} {v:.9g}" for u, v in uv]
        lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in F]
    else:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in F]
    return "\n".join(lines) + "\n"


def markers_csv(markers: np.ndarray) -> str:
    """(F,M,3) as a marker CSV with the layout's names M0, M1, ..."""
    names = [f"M{k}" for k in range(markers.shape[1])]
    header = ["frame"] + [f"{n}_{axis}" for n in names for axis in "xyz"]
    rows = [",".join(header)]
    for f, frame in enumerate(markers):
        rows.append(",".join([str(f + 1)] + [repr(float(v)) for v in frame.ravel()]))
    return "\n".join(rows) + "\n"


# ---------------------------------------------------------------------------- health
def test_health_readiness_and_metrics(client):
    assert client.health() == {"status": "ok"}
    ready = client.ready()
    assert isinstance(ready, Readiness) and ready.ready, ready.checks
    assert set(ready.checks) >= {"database"}
    text = client.metrics()
    assert isinstance(text, str) and "# TYPE" in text


# ---------------------------------------------------------------------------- actors
def test_actor_create_list_get_delete(client):
    actor = client.actors.create("Ada", {"session": "2025-01"})
    assert isinstance(actor, Actor) and actor.name == "Ada"
    assert actor.metadata == {"session": "2025-01"} and actor.vertex_count is None
    assert actor.created_at is not None and actor.created_at.tzinfo is not None
    assert actor.id in [a.id for a in client.actors.list()]
    assert client.actors.get(actor.id) == actor
    assert client.actors.delete(actor.id) is None
    with pytest.raises(NotFound) as caught:
        client.actors.get(actor.id)
    error = caught.value
    assert error.status == 404 and error.title and actor.id in error.detail
    assert error.problem["type"].startswith("urn:facesynth:problem:")


def test_invalid_actor_name_is_unprocessable_with_field_errors(client):
    with pytest.raises(Unprocessable) as caught:
        client.actors.create("")
    assert caught.value.status == 422 and caught.value.errors


def test_neutral_from_arrays_obj_file_and_trimesh_like_object(client, tmp_path):
    V, F, uv = sheet(16, 13)
    actor = client.actors.create("Neutral")
    info = client.actors.upload_neutral(actor.id, vertices=V, faces=F, uv=uv)
    assert isinstance(info, NeutralInfo)
    assert (info.vertex_count, info.triangle_count, info.uv_seams) == (208, 360, 0)

    path = tmp_path / "neutral.obj"
    path.write_text(obj_text(V, F, uv))
    info = client.actors.upload_neutral(actor.id, path)
    assert (info.vertex_count, info.triangle_count) == (208, 360)

    mesh = SimpleNamespace(vertices=V, faces=F, visual=SimpleNamespace(uv=uv))
    assert client.actors.upload_neutral(actor.id, mesh).vertex_count == 208
    assert client.actors.get(actor.id).vertex_count == 208

    bad = V.copy()
    bad[5, 1] = np.nan
    with pytest.raises(Unprocessable) as caught:
        client.actors.upload_neutral(actor.id, vertices=bad, faces=F, uv=uv)
    assert caught.value.status == 422
    client.actors.delete(actor.id)


def test_marker_layout_by_vertex_position_and_barycentric(client):
    V, F, uv = sheet(16, 13)
    actor = client.actors.create("Layout")
    client.actors.upload_neutral(actor.id, vertices=V, faces=F, uv=uv)
    info = client.actors.set_markers(actor.id, {
        "A": 0, "B": V[40] + [0.0, 0.0, 0.5], "C": {"triangle": 3, "barycentric": [0.2, 0.3, 0.5]}})
    assert info.marker_count == 3 and info.snapped == 1 and info.max_snap_distance > 0
    info = client.actors.set_markers(actor.id, [{"name": "A", "vertex": 1}])
    assert info.marker_count == 1
    assert client.actors.get(actor.id).marker_count == 1
    client.actors.delete(actor.id)


# ---------------------------------------------------------------------------- clips
def test_clips_from_arrays_npz_file_and_per_frame_objs(client, sheet_actor, tmp_path):
    fs, actor = client, sheet_actor
    frames = sheet_motion(actor.V, 3, 0.1).astype(np.float32)
    markers = frames[:, list(SHEET_MARKERS)]

    path = tmp_path / "clip.npz"
    np.savez(path, vertices=frames, markers=markers, fps=np.float64(24))
    from_file = fs.clips.upload_file(actor.actor_id, path, name="from-file")
    assert from_file.frames == 3 and from_file.name == "from-file"

    objs: list = []
    for k, frame in enumerate(frames[:2]):
        obj = tmp_path / f"f{k}.obj"
        obj.write_text(obj_text(frame, actor.F))
        objs.append(obj)
    objs.append(SimpleNamespace(vertices=frames[2], faces=actor.F))  # a mesh object, as OBJ
    csv = tmp_path / "take.csv"
    csv.write_text(markers_csv(markers))
    multipart = fs.clips.upload_frames(actor.actor_id, objs, csv, fps=24, name="multipart")
    assert multipart.frames == 3 and multipart.notes == []

    listed = {c.clip_id for c in fs.clips.list(actor.actor_id)}
    assert {from_file.clip_id, multipart.clip_id} <= listed
    assert fs.clips.get(actor.actor_id, multipart.clip_id).frames == 3
    for clip in (from_file, multipart):
        fs.clips.delete(actor.actor_id, clip.clip_id)
    with pytest.raises(NotFound):
        fs.clips.get(actor.actor_id, from_file.clip_id)

    with pytest.raises(Unprocessable) as caught:
        fs.clips.upload(actor.actor_id, frames[:, :100], markers)
    assert "100 vertices" in caught.value.detail and "208" in caught.value.detail


# ---------------------------------------------------------------------------- models
def test_train_wait_and_model_records(client, sheet_actor, shape_model, pdm_model):
    model = client.models.get(shape_model)
    assert isinstance(model, Model) and model.ready and model.kind == "shape_space"
    assert model.metrics["database_frames"] == 24
    listed = client.models.list(sheet_actor.actor_id, status="ready")
    assert {shape_model, pdm_model} <= {m.id for m in listed}
    kinds = client.models.kinds()
    assert all(isinstance(k, KindInfo) for k in kinds)
    assert {"pdm", "shape_space"} <= {k.name for k in kinds}
    assert client.models.kind("pdm").params_schema["properties"]["medium_resolution"]
    with pytest.raises(NotFound):
        client.models.kind("nope")
    job = client.jobs.list(model_id=pdm_model, kind="train")[0]
    assert job.status == "succeeded" and job.result.model_id == pdm_model


def test_training_with_a_misspelt_parameter_is_unprocessable(client, sheet_actor):
    with pytest.raises(Unprocessable) as caught:
        client.models.train(sheet_actor.actor_id, "pdm", list(sheet_actor.clips.values()),
                            {"medium_resolutoin": 32})
    assert "medium_resolutoin" in str(caught.value.errors) + caught.value.detail


def test_model_maps_list_and_download(client, pdm_model, tmp_path):
    maps = client.models.maps(pdm_model)
    assert maps and all(isinstance(m, MapInfo) for m in maps)
    first = maps[0]
    path = client.models.download_map(pdm_model, first.name, tmp_path / f"{first.name}.exr")
    assert path.read_bytes()[:4] == b"\x76\x2f\x31\x01"  # the OpenEXR magic number
    assert path.stat().st_size == first.size_bytes
    assert not list(tmp_path.glob("*.part*"))


def test_delete_model_and_actor_with_cascade(client):
    actor = upload_sheet_actor(client, "Doomed")
    accepted = client.models.train(actor.actor_id, "pdm", list(actor.clips.values()), PDM_PARAMS)
    assert isinstance(accepted, ModelAccepted)
    client.wait(accepted, timeout=120)
    with pytest.raises(Conflict):
        client.actors.delete(actor.actor_id)
    second = client.models.train(actor.actor_id, "pdm", [actor.clips["rise"]], PDM_PARAMS)
    client.wait(second, timeout=120)
    client.models.delete(second.model_id)
    with pytest.raises(NotFound):
        client.models.get(second.model_id)
    client.actors.delete(actor.actor_id, cascade=True)
    with pytest.raises(NotFound):
        client.models.get(accepted.model_id)


# ---------------------------------------------------------------------------- synthesis
def test_synthesize_arrays_json_obj_and_exr(client, sheet_actor, pdm_model):
    markers = sheet_actor.motions["rise"][:2, list(SHEET_MARKERS)]
    out = client.synthesize(pdm_model, markers)
    assert out["vertices"].shape == (2, 208, 3) and out["faces"].shape == (360, 3)
    assert out["displacement"].shape[0] == 2

    out = client.synthesis.synthesize(pdm_model, markers[0], outputs=["mesh_detailed"],
                                      map_resolution=16)
    assert out["vertices_detailed"].shape == (1, 208, 3)
    out = client.synthesis.synthesize(pdm_model, markers, outputs="displacement",
                                      map_resolution=16)
    assert out["displacement"].shape == (2, 16, 16)

    text = client.synthesis.synthesize_obj(pdm_model, markers[0], detailed=True)
    assert text.count("\nv ") + text.startswith("v ") >= 208 and "vt " in text
    exr = client.synthesis.synthesize_exr(pdm_model, markers[0], "displacement")
    assert exr[:4] == b"\x76\x2f\x31\x01"

    with pytest.raises(Unprocessable) as caught:
        client.synthesize(pdm_model, markers[:, :3])
    assert "model expects 4 markers, got 3" in caught.value.detail
    with pytest.raises(PayloadTooLarge) as caught:
        client.synthesize(pdm_model, sheet_actor.motions["rise"][:, list(SHEET_MARKERS)])
    assert "max_frames_per_request" in caught.value.detail


def test_repeated_synthesis_sends_the_topology_once_and_half_maps(server, sheet_actor, pdm_model):
    """The second call asks with ``topology=false`` and gets the kept ``faces`` back; the
    result equals the first call's bit for bit, and so does ``copy=False``'s (read-only views
    of the body); ``half`` maps are float16 within 2^-11
    relative (+2^-25) of float32; ``topology()`` revalidates with its ETag (304)."""
    import httpx

    from facesynth_client import Client

    seen: list[httpx.Request] = []
    statuses: list[int] = []
    markers = sheet_actor.motions["rise"][:2, list(SHEET_MARKERS)]
    outputs = ["mesh", "displacement", "normal_map"]
    with httpx.Client(timeout=60, event_hooks={
            "request": [seen.append],
            "response": [lambda r: statuses.append(r.status_code)]}) as http, \
            Client(server.url, http_client=http) as fs:
        first = fs.synthesize(pdm_model, markers, outputs=outputs)
        second = fs.synthesize(pdm_model, markers, outputs=outputs)
        assert "topology" not in seen[0].url.params
        assert seen[1].url.params["topology"] == "false"
        assert set(first) == set(second)
        for key in first:
            np.testing.assert_array_equal(second[key], first[key])
        viewed = fs.synthesize(pdm_model, markers, outputs=outputs, copy=False)
        assert set(viewed) == set(first)
        for key in first:        # views of the body: the same bytes, dtype and shape
            assert viewed[key].dtype == first[key].dtype and viewed[key].shape == first[key].shape
            assert viewed[key].tobytes() == first[key].tobytes(), key
        assert not viewed["vertices"].flags.writeable
        half = fs.synthesize(pdm_model, markers, outputs=outputs, half=True)
        assert seen[-1].url.params["half"] == "true"
        for key in ("displacement", "normal_map"):
            assert half[key].dtype == np.float16
            f = first[key].astype(np.float64)
            assert np.all(np.abs(half[key] - f) <= 2.0 ** -11 * np.abs(f) + 2.0 ** -25)
        np.testing.assert_array_equal(half["vertices"], first["vertices"])
        np.testing.assert_array_equal(half["faces"], first["faces"])

        topology = fs.synthesis.topology(pdm_model)
        np.testing.assert_array_equal(topology["faces"], first["faces"])
        assert topology["uv"].shape == (208, 2) and topology["uv_faces"].shape == (360, 3)
        again = fs.synthesis.topology(pdm_model)
        assert seen[-1].headers["if-none-match"].startswith('"') and statuses[-1] == 304
        np.testing.assert_array_equal(again["faces"], topology["faces"])


def test_enhance_and_retime(client, sheet_actor, shape_model):
    frames = sheet_actor.motions["fall"][:3]
    out = client.enhance(shape_model, frames)
    assert out["vertices"].shape == (3, 208, 3)

    clip = sheet_actor.clips["rise"]
    out = client.retime(shape_model, [ClipFrame(clip, 0), (clip, 11)], length=6)
    assert out["vertices"].shape == (6, 208, 3) and out["timestamps"].shape == (6,)
    keys = sheet_actor.motions["rise"][[0, 11]]
    out = client.synthesis.retime(shape_model, keys, 5, extend_to_full_motion=True)
    assert out["vertices"].shape == (5, 208, 3)
    np.testing.assert_allclose(out["vertices"][0], keys[0], atol=1e-3)
    out = client.retime(shape_model, list(keys), length=4)
    assert out["vertices"].shape == (4, 208, 3)
    with pytest.raises(Unprocessable):
        client.enhance(shape_model, frames[:, :50])


def test_input_rig_registration_and_enhance_with_rig(client, sheet_actor, shape_model):
    Vr, Fr, _ = sheet(9, 7)
    accepted = client.rigs.upload(sheet_actor.actor_id, "lod", vertices=Vr, faces=Fr)
    assert isinstance(accepted, RigAccepted) and accepted.vertex_count == 63
    client.wait(accepted, timeout=120)
    rig = client.rigs.get(sheet_actor.actor_id, "lod")
    assert rig.status == "ready" and rig.rig_id == accepted.rig_id
    assert "lod" in [r.name for r in client.rigs.list(sheet_actor.actor_id)]
    out = client.enhance(shape_model, np.repeat(Vr[None], 2, axis=0), rig="lod")
    assert out["vertices"].shape == (2, 208, 3)

    with_landmarks = client.rigs.upload(sheet_actor.actor_id, "lod-guided",
                                        SimpleNamespace(vertices=Vr, faces=Fr),
                                        landmarks=[[0, 0], [8, 15]])
    assert with_landmarks.landmarks == 2
    client.wait(with_landmarks, timeout=120)


# ---------------------------------------------------------------------------- jobs
def test_synthesis_job_download_and_job_routes(client, sheet_actor, pdm_model, tmp_path):
    markers = sheet_actor.motions["fall"][:, list(SHEET_MARKERS)]  # 12 frames: over the limit
    accepted = client.synthesis.submit_job(pdm_model, markers=markers, fps=30.0)
    assert isinstance(accepted, JobAccepted) and accepted.location.endswith(accepted.job_id)
    states = []
    job = client.wait(accepted, timeout=120, progress=states.append)
    assert isinstance(job, Job) and job.status == "succeeded" and states[-1].done
    artifacts = client.jobs.artifacts(job)
    assert artifacts and all(isinstance(a, Artifact) for a in artifacts)
    result = next(a for a in artifacts if a.id in job.artifact_ids)
    path = client.download_artifact(result.id, tmp_path / "take.npz")
    assert path.stat().st_size == result.size_bytes
    arrays = load_npz(path.read_bytes())
    assert arrays["vertices"].shape == (12, 208, 3)
    np.testing.assert_array_equal(client.artifacts.arrays(result.id)["vertices"],
                                  arrays["vertices"])
    assert client.artifacts.read(result.id) == path.read_bytes()

    # the job routes
    assert client.jobs.get(accepted.job_id) == job
    assert accepted.job_id in [j.id for j in client.jobs.list(status="succeeded",
                                                              actor_id=sheet_actor.actor_id)]
    events = list(client.jobs.events(job))
    assert len(events) == 1 and events[0].status == "succeeded"
    assert client.cancel(job).status == "succeeded"  # a finished job is left as it is

    # format="usd": one point cache whose points are the npz result's vertices, bit for bit
    from pxr import Usd, UsdGeom
    usd_job = client.wait(client.synthesis.submit_job(pdm_model, markers=markers, fps=24.0,
                                                      outputs=["mesh"], format="usd"),
                          timeout=120)
    cache = client.download_artifact(usd_job.artifact_ids[0], tmp_path / "take.usd")
    stage = Usd.Stage.Open(str(cache))
    points = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Mesh")).GetPointsAttr()
    assert points.GetTimeSamples() == [float(k) for k in range(12)]
    assert stage.GetTimeCodesPerSecond() == 24.0
    np.testing.assert_array_equal(np.stack([np.asarray(points.Get(k)) for k in range(12)]),
                                  arrays["vertices"])

    csv = tmp_path / "perf.csv"
    csv.write_text(markers_csv(markers[:5]))
    from_file = client.synthesis.submit_job(pdm_model, csv, outputs=["mesh"])
    done = client.wait(from_file, timeout=120)
    assert client.artifacts.arrays(done.artifact_ids[0])["vertices"].shape == (5, 208, 3)
    with pytest.raises(NotFound):
        client.jobs.get("job_0000000000000000000000000")
