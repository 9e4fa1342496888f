"""Scans (POST/GET/DELETE /v1/actors/{id}/scans) and correspondence jobs
(POST /v1/actors/{id}/correspondence-jobs), on sample scans of the level-0 sample actor
(service/samples/uv_scans.py, 256²) with their known correspondence; jobs run in the
immediate (``memory://``) queue."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.api import create_app
from service.io.exr import read_exr
from service.methods.correspondence import (CorrespondenceParams, blendshape_vertices,
                                            correspond)
from tests.api.conftest import NPZ, assert_problem, load_npz, npz

RES = 256


@pytest.fixture(scope="module")
def uv_scans(pdm_actor_dir):
    from service.samples.uv_scans import build_uv_scans

    return build_uv_scans(pdm_actor_dir, resolution=RES, expressions=["train_smile"],
                          landmarks=24, seed=0)


@pytest.fixture
def live(settings):
    """A client whose jobs run when they are submitted (the immediate queue)."""
    with TestClient(create_app(settings.model_copy(update={"queue_url": "memory://"}))) as client:
        yield client


def scan_body(scan, **extra) -> bytes:
    return npz(albedo=scan.maps["albedo"], position=scan.maps["position"], mask=scan.mask,
               **extra)


def upload(client, actor_id, scan, name=None, **extra):
    response = client.post(f"/v1/actors/{actor_id}/scans", content=scan_body(scan, **extra),
                           headers=NPZ, params={"name": name} if name else None)
    assert response.status_code == 201, response.text
    return response.json()


def landmarks(S, i=0) -> list:
    return np.stack([S.source_landmarks[i], S.target_landmarks[i]], axis=1).tolist()


def new_actor(client, name="Ada") -> str:
    return client.post("/v1/actors", json={"name": name}).json()["id"]


# ---------------------------------------------------------------------------- scans
def test_upload_answers_201_and_is_listed_then_deleted(client, actor_id, uv_scans):
    scan = uv_scans.target
    body = upload(client, actor_id, scan, name="neutral")
    assert body["scan_id"].startswith("scn_")
    assert (body["name"], body["width"], body["height"]) == ("neutral", RES, RES)
    assert body["maps"] == ["albedo", "mask", "position"]
    listed = client.get(f"/v1/actors/{actor_id}/scans").json()["items"]
    assert [s["scan_id"] for s in listed] == [body["scan_id"]]
    one = client.get(f"/v1/actors/{actor_id}/scans/{body['scan_id']}")
    assert one.status_code == 200 and one.json()["size_bytes"] == body["size_bytes"]
    other = new_actor(client, "Bo")
    assert_problem(client.get(f"/v1/actors/{other}/scans/{body['scan_id']}"), 404, "another actor")
    assert client.delete(f"/v1/actors/{actor_id}/scans/{body['scan_id']}").status_code == 204
    assert client.get(f"/v1/actors/{actor_id}/scans").json()["items"] == []
    assert_problem(client.delete(f"/v1/actors/{actor_id}/scans/{body['scan_id']}"), 404)


def test_stored_scan_is_the_upload_in_float32(client, actor_id, uv_scans):
    from models_store import registry

    scan = uv_scans.target
    body = upload(client, actor_id, scan, normal=np.zeros((RES, RES, 3), np.float64))
    services = client.app.state.services
    with services.session() as session:
        stored = load_npz(registry.read_scan(session, services.blobs, body["scan_id"]))
    assert stored["albedo"].dtype == np.float32 and stored["mask"].dtype == bool
    np.testing.assert_array_equal(stored["position"], scan.maps["position"])
    np.testing.assert_array_equal(stored["mask"], scan.mask)
    assert body["maps"] == ["albedo", "mask", "normal", "position"]


def test_scan_uploads_are_validated(client, actor_id):
    url = f"/v1/actors/{actor_id}/scans"
    a = np.full((16, 16, 3), 0.5, np.float32)
    assert_problem(client.post(url, content=npz(albedo=a), headers=NPZ), 422, "'position'")
    assert_problem(client.post(url, content=npz(albedo=a, position=a[:, :8]), headers=NPZ),
                   422, "'position'", "'albedo'")
    bad = a.copy()
    bad[3, 5, 1] = np.nan
    assert_problem(client.post(url, content=npz(albedo=a, position=bad), headers=NPZ), 422,
                   "'position' has 1 texels", "row 3, column 5")
    inside = np.ones((16, 16), bool)
    assert_problem(client.post(url, content=npz(albedo=a, position=bad, mask=inside),
                               headers=NPZ), 422, "'position' has 1 covered texels")
    inside[3, 5] = False                       # NaN outside the mask is stored as 0
    body = client.post(url, content=npz(albedo=a, position=bad, mask=inside), headers=NPZ)
    assert body.status_code == 201, body.text
    from models_store import registry

    services = client.app.state.services
    with services.session() as session:
        stored = load_npz(registry.read_scan(session, services.blobs, body.json()["scan_id"]))
    assert stored["position"][3, 5].tolist() == [0.0, 0.0, 0.0]
    np.testing.assert_array_equal(stored["position"][inside], a[inside])
    assert_problem(client.post(url, content=npz(albedo=a, position=a.astype(int)), headers=NPZ),
                   422, "dtype")
    assert_problem(client.post(url, content=npz(albedo=a, position=a, mask=np.ones((16, 16))),
                               headers=NPZ), 422, "'mask'")
    assert_problem(client.post(url, content=npz(albedo=a[:4, :4], position=a[:4, :4]),
                               headers=NPZ), 422, "4×4")
    assert_problem(client.post(url, content=npz(albedo=a, position=a, extra=a), headers=NPZ),
                   422, "unexpected array 'extra'")
    assert_problem(client.post(url, content=b"not a zip", headers=NPZ), 422, "not a readable")
    big = np.zeros((1024, 1024, 3), np.float32)          # 12 MiB each, over the 8 MiB body limit
    assert client.post(url, content=npz(albedo=big, position=big), headers=NPZ).status_code == 413
    assert_problem(client.post("/v1/actors/act_00000000000000000000000000/scans",
                               content=npz(albedo=a, position=a), headers=NPZ), 404)


# ---------------------------------------------------------------------------- refusals
def test_correspondence_refusals(client, actor_id, uv_scans, submitted):
    S = uv_scans
    src = upload(client, actor_id, S.sources[0])["scan_id"]
    tgt = upload(client, actor_id, S.target)["scan_id"]
    url = f"/v1/actors/{actor_id}/correspondence-jobs"
    lm = landmarks(S)
    ok = {"source_scan_id": src, "target_scan_id": tgt, "landmarks": lm}
    # unknown scan, and a scan of another actor
    assert_problem(client.post(url, json={**ok, "source_scan_id": "scn_00000000000000000000000000"}),
                   404)
    other = new_actor(client, "Bo")
    foreign = upload(client, other, S.target)["scan_id"]
    assert_problem(client.post(url, json={**ok, "target_scan_id": foreign}), 404, "another actor")
    assert_problem(client.post(f"/v1/actors/{other}/correspondence-jobs", json=ok), 404)
    # landmarks: fewer than 3, out of [0, 1], malformed; pinned past the end
    assert_problem(client.post(url, json={**ok, "landmarks": lm[:2]}), 422, "landmarks")
    outside = [row[:] for row in lm]
    outside[1] = [[1.2, 0.5], [0.5, 0.5]]
    assert_problem(client.post(url, json={**ok, "landmarks": outside}), 422, "landmarks")
    assert_problem(client.post(url, json={**ok, "landmarks": [[[0.1, 0.2, 0.3], [0.1, 0.2]]] * 3}),
                   422, "landmarks")
    assert_problem(client.post(url, json={**ok, "pinned": [len(lm)]}), 422, "pinned")
    # parameters are CorrespondenceParams: unknown or out of range
    assert_problem(client.post(url, json={**ok, "params": {"patch_size": 2}}), 422, "patch_size")
    assert_problem(client.post(url, json={**ok, "params": {"typo": 1}}), 422, "typo")
    # mismatched map sets
    with_normal = upload(client, actor_id, S.sources[0],
                         normal=np.zeros((RES, RES, 3), np.float32))["scan_id"]
    assert_problem(client.post(url, json={**ok, "source_scan_id": with_normal}), 422,
                   "different maps", "normal")
    # artist_uv without a neutral
    assert_problem(client.post(url, json={**ok, "artist_uv": True}), 409, "neutral")
    assert submitted == []
    # a valid request is queued, with a Location header
    response = client.post(url, json={**ok, "pinned": [0, 2]})
    assert response.status_code == 202, response.text
    job_id = response.json()["job_id"]
    assert response.headers["Location"] == f"/v1/jobs/{job_id}" and submitted == [job_id]
    job = client.get(f"/v1/jobs/{job_id}").json()
    assert (job["kind"], job["status"]) == ("correspond", "queued")


def test_another_tenants_scan_is_an_unknown_id(tmp_path, uv_scans):
    from tests.api.conftest import Recorder, make_client
    from tests.api.test_health_auth import TENANT_TOKENS, bearer
    from service.config import Settings

    settings = Settings(data_dir=tmp_path, max_body_bytes=8 << 20, tokens=TENANT_TOKENS)
    with make_client(settings, Recorder()) as c:
        a, b = bearer("token-a"), bearer("token-b")
        actor_a = c.post("/v1/actors", json={"name": "A"}, headers=a).json()["id"]
        actor_b = c.post("/v1/actors", json={"name": "B"}, headers=b).json()["id"]
        body = scan_body(uv_scans.target)
        scan_a = c.post(f"/v1/actors/{actor_a}/scans", content=body, headers={**NPZ, **a}).json()["scan_id"]
        scan_b = c.post(f"/v1/actors/{actor_b}/scans", content=body, headers={**NPZ, **b}).json()["scan_id"]
        unknown = "scn_" + "0" * 26
        crossed = c.get(f"/v1/actors/{actor_b}/scans/{scan_a}", headers=b)
        twin = c.get(f"/v1/actors/{actor_b}/scans/{unknown}", headers=b)
        assert crossed.status_code == twin.status_code == 404
        assert crossed.json()["detail"].replace(scan_a, unknown) == twin.json()["detail"]
        job = {"source_scan_id": scan_a, "target_scan_id": scan_b, "landmarks": landmarks(uv_scans)}
        crossed = c.post(f"/v1/actors/{actor_b}/correspondence-jobs", json=job, headers=b)
        twin = c.post(f"/v1/actors/{actor_b}/correspondence-jobs",
                      json={**job, "source_scan_id": unknown}, headers=b)
        assert crossed.status_code == twin.status_code == 404
        assert crossed.json()["detail"].replace(scan_a, unknown) == twin.json()["detail"]
        assert c.get(f"/v1/actors/{actor_a}/scans", headers=b).status_code == 404
        assert c.delete(f"/v1/actors/{actor_b}/scans/{scan_a}", headers=b).status_code == 404
        assert [s["scan_id"] for s in c.get(f"/v1/actors/{actor_a}/scans", headers=a).json()["items"]] == [scan_a]


# ---------------------------------------------------------------------------- the job
def _artist_neutral(S):
    """The scanned part of the actor's neutral with the *target scan's* UV layout as its
    UVs (an artist mesh whose UVs are the neutral scan's): vertices, faces, uv, and the
    mesh vertex of each."""
    used = np.unique(S.faces)
    faces = np.searchsorted(used, S.faces)
    return S.mesh_vertices[used], faces, S.target.layout[used], used


def test_correspondence_job_warps_the_source_onto_the_target(live, uv_scans):
    S = uv_scans
    actor_id = new_actor(live)
    V, F, uv, used = _artist_neutral(S)
    assert live.put(f"/v1/actors/{actor_id}/neutral", content=npz(vertices=V, faces=F, uv=uv),
                    headers=NPZ).status_code == 200
    src = upload(live, actor_id, S.sources[0], name="smile")["scan_id"]
    tgt = upload(live, actor_id, S.target, name="neutral")["scan_id"]
    response = live.post(f"/v1/actors/{actor_id}/correspondence-jobs", json={
        "source_scan_id": src, "target_scan_id": tgt, "landmarks": landmarks(S),
        "artist_uv": True})
    assert response.status_code == 202, response.text
    job = live.get(response.headers["Location"]).json()
    assert job["status"] == "succeeded", job
    result = job["result"]
    assert set(result["artifacts"]) == {"albedo.exr", "position.exr", "warp.npz",
                                        "blendshape.npz"}
    metrics = result["metrics"]
    assert 0.5 < metrics["mean_confidence"] <= 1.0 and 0.9 < metrics["coverage"] <= 1.0
    assert metrics["seconds"]["flow"] > 0 and metrics["seconds"]["total"] > 0

    def artifact(name):
        r = live.get(f"/v1/artifacts/{result['artifacts'][name]}")
        assert r.status_code == 200
        return r.content

    coords_true, valid = S.truth(0)
    warp = load_npz(artifact("warp.npz"))
    # the job ran the library's correspond on exactly the uploaded maps
    direct = correspond({**S.sources[0].maps, "mask": S.sources[0].mask},
                        {**S.target.maps, "mask": S.target.mask},
                        np.asarray(landmarks(S)), CorrespondenceParams())
    np.testing.assert_allclose(warp["coords"], direct.coords, atol=1e-3)
    np.testing.assert_array_equal(warp["mask"], direct.mask)
    valid &= warp["mask"]
    error = np.linalg.norm(warp["coords"][valid] - coords_true[valid], axis=1)
    pre = correspond(S.sources[0].maps, S.target.maps, np.asarray(landmarks(S)),
                     CorrespondenceParams(flow="none"))
    pre_error = np.linalg.norm(pre.coords[valid] - coords_true[valid], axis=1)
    # measured (level 0, seed 0, 256², 24 clicks): median 0.19 texel (the pre-warp alone
    # 0.77), p95 5.4 (pre-warp 3.9: at 256² pores do not resolve and the flow's tail is
    # worse than the pre-warp's; see the report)
    assert np.median(error) < 0.3 and np.median(error) < 0.4 * np.median(pre_error)
    assert np.percentile(error, 95) < 7.0

    albedo = read_exr(artifact("albedo.exr"))
    warped = np.stack([albedo[c] for c in "RGB"], axis=-1)
    np.testing.assert_allclose(warped, direct.maps["albedo"], atol=1e-6)
    target = S.target.maps["albedo"]
    scale = np.abs(target[valid]).mean()
    rel = np.abs(warped[valid] - target[valid]).mean() / scale
    raw = np.abs(S.sources[0].maps["albedo"][valid] - target[valid]).mean() / scale
    rel_pre = np.abs(pre.maps["albedo"][valid] - target[valid]).mean() / scale
    # measured: mean |warped - target| / mean |target| = 0.017 (un-warped source 0.024)
    assert rel < 0.022 and rel < 0.8 * raw and rel <= rel_pre

    blend = load_npz(artifact("blendshape.npz"))
    truth = S.sources[0].vertices[used]
    H = S.resolution
    seen = valid[np.clip(np.rint((1 - uv[:, 1]) * H - 0.5).astype(int), 0, H - 1),
                 np.clip(np.rint(uv[:, 0] * H - 0.5).astype(int), 0, H - 1)]
    assert blend["vertices"].shape == (len(used), 3) and blend["valid"].all()
    err_mm = np.linalg.norm(blend["vertices"] - truth, axis=1)[seen]
    moved = np.linalg.norm(truth - V, axis=1)[seen]
    np.testing.assert_allclose(blend["vertices"],
                               blendshape_vertices(direct.maps["position"], direct.mask, uv),
                               atol=1e-4)
    # measured (256²): median 0.35 mm over the vertices the source sees, 68 % within 1 mm,
    # while the smile moves 10 % of them by more than 11 mm
    assert np.percentile(moved, 90) > 5.0
    assert np.median(err_mm) < 0.5 and np.mean(err_mm < 1.0) > 0.6
