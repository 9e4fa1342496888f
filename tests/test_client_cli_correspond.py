"""``facesynth correspond ACTOR --source ID --target ID --landmarks FILE --out DIR`` against the
real app with a worker, on a small synthetic scan pair related by a known affine warp."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage

from service.cli import main
from service.client_cli import EXIT_OK, EXIT_REJECTED
from service.io.exr import read_exr
from service.io.npz import npz_arrays
from tests.api.conftest import NPZ, npz
from tests.servers import serve_app

N = 64
A = np.array([[0.98, 0.03, 1.75], [-0.02, 1.01, -1.25]])     # source coords = A @ [x, y, 1]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    running = serve_app(tmp_path_factory.mktemp("cli-scans"), worker=True)
    yield running
    running.stop()


def _warp(img, coords):
    return np.stack([ndimage.map_coordinates(img[..., c], [coords[..., 1], coords[..., 0]], order=1)
                     for c in range(img.shape[2])], axis=-1).astype(np.float32)


def test_correspond_writes_the_warped_maps_and_the_metrics(capsys, server, tmp_path):
    import httpx

    rng = np.random.default_rng(3)
    g = 0.5 + 0.6 * ndimage.gaussian_filter(rng.standard_normal((N, N)), 1.0)
    g += 1.2 * ndimage.gaussian_filter(rng.standard_normal((N, N)), 6)
    albedo = (np.repeat(np.clip(g, 0.05, 1.0)[..., None], 3, axis=2) * [1, 0.7, 0.55]).astype(np.float32)
    xs, ys = np.meshgrid(np.arange(N, dtype=float), np.arange(N, dtype=float))
    grid = np.stack([xs, ys], axis=-1)
    position = np.concatenate([grid, np.zeros((N, N, 1))], axis=-1).astype(np.float32)
    coords = grid @ A[:, :2].T + A[:, 2]
    mask = (coords >= 2).all(-1) & (coords <= N - 3).all(-1)
    with httpx.Client(base_url=server.url) as http:
        actor = http.post("/v1/actors", json={"name": "cli"}).json()["id"]
        src = http.post(f"/v1/actors/{actor}/scans", headers=NPZ,
                        content=npz(albedo=albedo, position=position)).json()["scan_id"]
        tgt = http.post(f"/v1/actors/{actor}/scans", headers=NPZ, content=npz(
            albedo=_warp(albedo, coords), position=_warp(position, coords), mask=mask)).json()["scan_id"]
    pts = np.array([[8, 8], [55, 9], [10, 54], [53, 52]], float)

    def uv(xy):
        return np.column_stack([(xy[:, 0] + 0.5) / N, 1 - (xy[:, 1] + 0.5) / N])

    lm = tmp_path / "clicks.json"
    lm.write_text(json.dumps({"landmarks": np.stack([uv(pts @ A[:, :2].T + A[:, 2]), uv(pts)],
                                                    axis=1).tolist()}))
    out = tmp_path / "result"
    code = main(["correspond", actor, "--source", src, "--target", tgt, "--landmarks", str(lm),
                 "--out", str(out), "--server", server.url])
    stdout, stderr = capsys.readouterr()
    assert code == EXIT_OK, stderr
    assert stdout.strip() == str(out) and "coverage" in stderr
    assert sorted(p.name for p in out.iterdir()) == ["albedo.exr", "position.exr", "result.json",
                                                      "warp.npz"]
    result = json.loads((out / "result.json").read_text())
    assert 0.9 < result["metrics"]["coverage"] <= 1.0
    warp = npz_arrays((out / "warp.npz").read_bytes())
    inner = ndimage.binary_erosion(mask, iterations=4)
    err = np.linalg.norm(warp["coords"][inner] - coords[inner], axis=1)
    assert np.median(err) < 0.05
    assert set(read_exr(out / "albedo.exr")) == {"R", "G", "B"}

    bad = tmp_path / "two.json"
    bad.write_text(json.dumps([[[0.1, 0.1], [0.1, 0.1]]] * 2))
    code = main(["correspond", actor, "--source", src, "--target", tgt, "--landmarks", str(bad),
                 "--out", str(tmp_path / "never"), "--server", server.url])
    assert code == EXIT_REJECTED and not (tmp_path / "never").exists()
    bad.write_text("[1, 2]")
    assert main(["correspond", actor, "--source", src, "--target", tgt, "--landmarks", str(bad),
                 "--out", str(tmp_path / "never"), "--server", server.url]) == 2
