"""``client.scans`` against the real app with a worker: upload, list, delete, and a
correspondence job (sync and async) on a small synthetic scan pair whose warp is a known
affine map."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from scipy import ndimage

from facesynth_client import AsyncClient, JobAccepted, NotFound, load_npz
from facesynth_client.errors import Unprocessable
from facesynth_client.types import Scan

N = 64
A = np.array([[0.98, 0.03, 1.75], [-0.02, 1.01, -1.25]])     # source coords = A @ [x, y, 1]


def _warp(img, coords):
    """``img`` sampled bilinearly at ``coords`` (H,W,2) (column, row)."""
    channels = [ndimage.map_coordinates(img[..., c], [coords[..., 1], coords[..., 0]], order=1)
                for c in range(img.shape[2])]
    return np.stack(channels, axis=-1).astype(np.float32)


@pytest.fixture(scope="module")
def pair():
    rng = np.random.default_rng(7)
    g = 0.5 + 0.6 * ndimage.gaussian_filter(rng.standard_normal((N, N)), 1.0)
    g += 1.2 * ndimage.gaussian_filter(rng.standard_normal((N, N)), 6)
    albedo = (np.repeat(np.clip(g, 0.05, 1.0)[..., None], 3, axis=2) * [1, 0.7, 0.55]).astype(np.float32)
    xs, ys = np.meshgrid(np.arange(N, dtype=float), np.arange(N, dtype=float))
    grid = np.stack([xs, ys], axis=-1)
    position = np.concatenate([grid, np.zeros((N, N, 1))], axis=-1).astype(np.float32)
    coords = grid @ A[:, :2].T + A[:, 2]
    mask = (coords >= 2).all(-1) & (coords <= N - 3).all(-1)
    target = {"albedo": _warp(albedo, coords), "position": _warp(position, coords), "mask": mask}
    pts = np.array([[8, 8], [55, 9], [10, 54], [53, 52], [30, 20]], float)

    def uv(xy):
        return np.column_stack([(xy[:, 0] + 0.5) / N, 1 - (xy[:, 1] + 0.5) / N])

    landmarks = np.stack([uv(pts @ A[:, :2].T + A[:, 2]), uv(pts)], axis=1)
    return {"albedo": albedo, "position": position}, target, landmarks, coords, mask


def test_scans_upload_list_correspond_and_delete(client, pair, tmp_path):
    source, target, landmarks, coords, mask = pair
    actor = client.actors.create("Scanned")
    src = client.scans.upload(actor.id, source["albedo"], source["position"], name="smile")
    tgt = client.scans.upload(actor.id, **target, name="neutral")
    assert isinstance(src, Scan) and (src.width, src.height) == (N, N)
    assert src.maps == ["albedo", "position"] and tgt.maps == ["albedo", "mask", "position"]
    assert [s.id for s in client.scans.list(actor.id)] == [src.id, tgt.id]
    assert client.scans.get(actor.id, tgt.id).name == "neutral"
    with pytest.raises(Unprocessable, match="landmarks"):
        client.scans.correspond(actor.id, src.id, tgt.id, landmarks[:2])
    accepted = client.scans.correspond(actor.id, src.id, tgt.id, landmarks, pinned=[4],
                                       params={"dis_passes": 1})
    assert isinstance(accepted, JobAccepted) and accepted.location == f"/v1/jobs/{accepted.job_id}"
    job = client.wait(accepted, timeout=60)
    assert job.status == "succeeded", job.error
    artifacts = job.result.raw["artifacts"]
    path = client.download_artifact(artifacts["warp.npz"], tmp_path / "warp.npz")
    warp = load_npz(path.read_bytes())
    inner = ndimage.binary_erosion(mask, iterations=4)
    err = np.linalg.norm(warp["coords"][inner] - coords[inner], axis=1)
    assert np.median(err) < 0.05 and err.max() < 0.3
    assert 0.9 < job.result.raw["metrics"]["coverage"] <= 1.0
    client.scans.delete(actor.id, src.id)
    with pytest.raises(NotFound):
        client.scans.get(actor.id, src.id)


def test_async_scans_and_correspondence(server, pair):
    source, target, landmarks, _, _ = pair

    async def main():
        async with AsyncClient(server.url, poll_interval=0.05) as fs:
            actor = await fs.actors.create("Async scans")
            src = await fs.scans.upload(actor.id, source["albedo"], source["position"])
            tgt = await fs.scans.upload(actor.id, **target)
            listed = await fs.scans.list(actor.id)
            accepted = await fs.scans.correspond(actor.id, src.id, tgt.id, landmarks)
            job = await fs.wait(accepted, timeout=60)
            return src, tgt, listed, job

    src, tgt, listed, job = asyncio.run(main())
    assert [s.id for s in listed] == [src.id, tgt.id]
    assert job.status == "succeeded" and set(job.result.raw["artifacts"]) == {
        "albedo.exr", "position.exr", "warp.npz"}
