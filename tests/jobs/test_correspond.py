"""service.jobs.tasks.correspond: the ``correspond`` job on small synthetic scans (identity
and an exact affine warp), its artifacts, cancellation at progress points, a deleted scan,
and the per-vertex UVs of a neutral."""

from __future__ import annotations

import io

import numpy as np
import pytest
from scipy import ndimage

from models_store import registry
from service.geometry import optical_flow as of
from service.io.exr import read_exr
from service.io.npz import npz_arrays, npz_bytes
from service.jobs.queue import submit
from service.jobs.running import JobCancelled, RunningJob
from service.jobs.tasks.correspond import correspond_scans, map_exr, vertex_uv

N = 64
A = np.array([[0.98, 0.03, 1.75], [-0.02, 1.01, -1.25]])     # source coords = A @ [x, y, 1]


def skin(seed=0, n=N):
    rng = np.random.default_rng(seed)
    g = 0.5 + 0.6 * ndimage.gaussian_filter(rng.standard_normal((n, n)), 1.0)
    g += 1.2 * ndimage.gaussian_filter(rng.standard_normal((n, n)), 6)
    return (np.repeat(np.clip(g, 0.05, 1.0)[..., None], 3, axis=2) * [1.0, 0.7, 0.55]).astype(np.float32)


def grid(n=N):
    xs, ys = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    return np.stack([xs, ys], axis=-1)


def uv(xy, n=N):
    return np.column_stack([(xy[:, 0] + 0.5) / n, 1 - (xy[:, 1] + 0.5) / n])


@pytest.fixture(scope="module")
def scans():
    """A source scan and the target it becomes under the affine A (target texel x shows
    source point A x), with landmarks at 6 target points."""
    albedo = skin()
    position = np.concatenate([grid(), np.zeros((N, N, 1))], axis=-1).astype(np.float32)
    src = {"albedo": albedo, "position": position}
    coords = (grid() @ A[:, :2].T + A[:, 2]).astype(np.float32)
    tgt = {k: of.remap(v, coords, border=0.0) for k, v in src.items()}
    tgt["mask"] = (coords >= 2).all(-1) & (coords <= N - 3).all(-1)
    pts = np.array([[8, 8], [55, 9], [10, 54], [53, 52], [30, 20], [25, 45]], float)
    lm = np.stack([uv(pts @ A[:, :2].T + A[:, 2]), uv(pts)], axis=1)
    return src, tgt, lm, coords


def add_scans(deployment, scans):
    src, tgt, _, _ = scans
    ids = []
    with deployment.session() as session:
        for maps in (src, tgt):
            ids.append(registry.add_scan(session, deployment.store.blobs, deployment.actor_id,
                                         npz_bytes(**maps), width=N, height=N,
                                         maps=list(maps)).id)
    return ids


def create_job(deployment, scans, **payload) -> str:
    src_id, tgt_id = add_scans(deployment, scans)
    with deployment.session() as session:
        return registry.create_job(session, "correspond", deployment.actor_id, payload={
            "source_scan_id": src_id, "target_scan_id": tgt_id,
            "landmarks": scans[2].tolist(), **payload}).id


def running(deployment, job_id, progress) -> RunningJob:
    job = deployment.job(job_id)
    return RunningJob(job.id, job.kind, job.actor_id, None, dict(job.payload), 1,
                      deployment.store, progress)


def test_the_job_recovers_an_affine_warp_and_stores_its_artifacts(deployment, scans):
    settings = deployment.settings.model_copy(update={"queue_url": "memory://"})
    job_id = create_job(deployment, scans, pinned=[4])
    submit(settings, job_id)
    job = deployment.job(job_id)
    assert job.status == "succeeded", job.error
    names = job.result["artifacts"]
    assert set(names) == {"albedo.exr", "position.exr", "warp.npz"}
    assert sorted(names.values()) == sorted(job.result["artifact_ids"])
    with deployment.session() as session:
        files = {}
        for name, artifact_id in names.items():
            artifact, stream = registry.open_artifact(session, deployment.store.blobs, artifact_id)
            with stream:
                files[name] = (artifact.media_type, stream.read())
    assert files["albedo.exr"][0] == "image/x-exr" and files["warp.npz"][0] == "application/x-npz"
    warp = npz_arrays(files["warp.npz"][1])
    _, tgt, _, coords = scans
    inner = ndimage.binary_erosion(tgt["mask"], iterations=4)
    err = np.linalg.norm(warp["coords"][inner] - coords[inner], axis=1)
    # the pre-warp alone is exact for an affine warp; the flow adds < 0.1 texel
    assert np.median(err) < 0.05 and err.max() < 0.3
    position = read_exr(files["position.exr"][1])
    assert set(position) == {"R", "G", "B"}
    # the position map of the source was its texel grid: warped, it is the warp itself
    np.testing.assert_allclose(np.stack([position["R"], position["G"]], -1)[inner],
                               warp["coords"][inner], atol=1e-3)
    assert warp["confidence"].shape == (N, N) and warp["confidence"][inner].mean() > 0.9
    metrics = job.result["metrics"]
    assert metrics["coverage"] == pytest.approx(warp["mask"].sum() / tgt["mask"].sum())
    assert metrics["mean_confidence"] == pytest.approx(warp["confidence"][warp["mask"]].mean(),
                                                       rel=1e-5)
    assert (metrics["width"], metrics["height"]) == (N, N)
    assert {"prewarp", "flow", "warp", "store", "total"} <= set(metrics["seconds"])


def test_cancellation_at_a_progress_point_stores_nothing(deployment, scans):
    job_id = create_job(deployment, scans)
    stages = []

    def progress(fraction, stage):
        stages.append((fraction, stage))
        if stage.startswith("flow ("):
            raise JobCancelled()

    with pytest.raises(JobCancelled):
        correspond_scans(running(deployment, job_id, progress))
    assert [s for _, s in stages] == ["loading the scans", "pre-warp", "flow textures",
                                      "flow (refined)"]
    fractions = [f for f, _ in stages]
    assert fractions == sorted(fractions) and 0.0 <= fractions[0] and fractions[-1] < 0.85
    with deployment.session() as session:
        assert registry.list_artifacts(session, job_id) == []


def test_a_retry_reuses_the_artifacts_of_an_earlier_attempt(deployment, scans):
    job_id = create_job(deployment, scans)
    first = correspond_scans(running(deployment, job_id, lambda f, s: None))
    again = correspond_scans(running(deployment, job_id, lambda f, s: None))
    assert again["artifacts"] == first["artifacts"]
    with deployment.session() as session:
        assert len(registry.list_artifacts(session, job_id)) == 3


def test_a_scan_deleted_after_submission_fails_the_job(deployment, scans):
    settings = deployment.settings.model_copy(update={"queue_url": "memory://"})
    job_id = create_job(deployment, scans)
    with deployment.session() as session:
        registry.delete_scan(session, deployment.store.blobs,
                             deployment.job(job_id).payload["source_scan_id"])
    submit(settings, job_id)
    job = deployment.job(job_id)
    assert job.status == "failed" and job.error["code"] == "invalid_input"
    assert "no longer exists" in job.error["message"]


def test_vertex_uv_takes_each_vertex_corner_uv():
    neutral = {"vertices": np.zeros((5, 3)), "faces": np.array([[0, 1, 2], [2, 1, 3]]),
               "uv": np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]),
               "uv_faces": np.array([[0, 1, 2], [2, 1, 3]])}
    out = vertex_uv(neutral)
    np.testing.assert_array_equal(out[:4], neutral["uv"])
    assert np.isnan(out[4]).all()                    # in no triangle


def test_map_exr_channels():
    m = np.arange(12, dtype=np.float32).reshape(2, 2, 3)
    back = read_exr(io.BytesIO(map_exr(m)))
    np.testing.assert_array_equal(np.stack([back[c] for c in "RGB"], -1), m)
    assert set(read_exr(io.BytesIO(map_exr(m[..., 0])))) == {"Y"}
