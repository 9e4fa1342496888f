"""Tests for service.methods.correspondence.correspond: identity, affine and sample scans."""

import numpy as np
import pytest
from pydantic import ValidationError
from scipy import ndimage

from service.geometry import optical_flow as of
from service.methods.correspondence import CorrespondenceParams, correspond
from service.methods.correspondence.accuracy import warp_errors
from service.methods.inputs import InvalidInput

N = 128
A = np.array([[0.97, 0.05, 2.75], [-0.04, 1.02, -1.5]])     # source coords = A @ [x, y, 1]


def skin(seed=0, n=N):
    rng = np.random.default_rng(seed)
    g = 0.5 + 0.6 * ndimage.gaussian_filter(rng.standard_normal((n, n)), 1.0)
    g += 1.2 * ndimage.gaussian_filter(rng.standard_normal((n, n)), 10)
    return np.repeat(np.clip(g, 0.05, 1.0)[..., None], 3, axis=2) * [1.0, 0.7, 0.55]


def grid(n=N):
    xs, ys = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    return np.stack([xs, ys], axis=-1)


def landmarks_uv(tgt_xy, src_xy, n=N):
    def uv(xy):
        return np.column_stack([(xy[:, 0] + 0.5) / n, 1 - (xy[:, 1] + 0.5) / n])
    return np.stack([uv(src_xy), uv(tgt_xy)], axis=1)


def test_identity_scans_give_zero_flow_and_the_maps_back():
    maps = {"albedo": skin(), "position": np.dstack([grid(), np.ones((N, N))])}
    pts = np.array([[10, 10], [110, 12], [60, 100], [15, 115], [100, 90.0]])
    r = correspond(maps, maps, landmarks_uv(pts, pts))
    assert np.abs(r.flow).max() < 1e-4
    np.testing.assert_allclose(r.coords, grid(), atol=1e-3)
    np.testing.assert_allclose(r.maps["position"], maps["position"], atol=1e-3)
    assert r.mask.all() and r.confidence[8:-8, 8:-8].min() > 0.99
    assert set(r.maps) == {"albedo", "position"} and r.maps["albedo"].dtype == np.float32


def test_an_exact_affine_scan_is_recovered_by_the_prewarp_and_kept_by_the_flow():
    big = skin(1, 160)
    coords_true = grid() @ A[:, :2].T + A[:, 2] + 12.0                 # inside the 160² source
    target = of.remap(big, coords_true)
    src = {"albedo": big, "position": np.dstack([grid(160), np.zeros((160, 160))])}
    tgt = {"albedo": target}
    pts = np.random.default_rng(2).uniform(5, 120, (10, 2))
    lm = np.stack([of.sample(grid(160), pts @ A[:, :2].T + A[:, 2] + 12.0), pts], axis=1)
    lm_uv = np.stack([(lm[:, :, 0] + 0.5) / [160, N], 1 - (lm[:, :, 1] + 0.5) / [160, N]], axis=-1)
    pre = correspond(src, tgt, lm_uv, CorrespondenceParams(flow="none"))
    np.testing.assert_allclose(pre.coords, coords_true, atol=1e-3)
    np.testing.assert_allclose(pre.maps["position"][..., :2], coords_true, atol=1e-3)
    both = correspond(src, tgt, lm_uv)
    err = np.linalg.norm(both.coords - coords_true, axis=-1)[8:-8, 8:-8]
    assert np.median(err) < 0.05 and np.percentile(err, 95) < 0.15


def test_flow_corrects_clicks_that_are_off(scans512):
    S = scans512
    truth, valid = S.truth(0)
    lm = np.stack([S.source_landmarks[0], S.target_landmarks[0]], axis=1)
    src = S.sources[0]
    errs = {}
    for name, p in {"prewarp": CorrespondenceParams(flow="none"),
                    "both": CorrespondenceParams()}.items():
        r = correspond(src.maps, S.target.maps, lm, p)
        tex, mm = warp_errors(r.coords, truth, valid & r.mask, src.maps["position"])
        errs[name] = np.median(tex), np.median(mm)
        assert (valid & r.mask).sum() > 0.97 * valid.sum()
    assert errs["prewarp"][1] > 0.3                     # clicks are off by 0.3 mm
    assert errs["both"][0] < 0.5 * errs["prewarp"][0] and errs["both"][1] < 0.15


def test_pinned_points_hold_the_warp_at_the_landmark():
    maps = {"albedo": skin(3)}
    pts = np.array([[10, 10], [110, 12], [60, 100], [15, 115], [100, 90.0], [64, 64]])
    r = correspond(maps, maps, landmarks_uv(pts, pts), pinned=[5])
    np.testing.assert_allclose(r.coords[64, 64], [64, 64], atol=0.05)
    with pytest.raises(InvalidInput, match="pinned"):
        correspond(maps, maps, landmarks_uv(pts, pts), pinned=[6])


def test_bad_inputs_and_params_are_rejected():
    maps = {"albedo": skin()}
    pts = np.array([[10, 10], [110, 12], [60, 100.0]])
    with pytest.raises(InvalidInput, match="albedo"):
        correspond({"position": np.zeros((N, N, 3))}, maps, landmarks_uv(pts, pts))
    with pytest.raises(InvalidInput, match="expected"):
        correspond({**maps, "position": np.zeros((64, 64, 3))}, maps, landmarks_uv(pts, pts))
    with pytest.raises(InvalidInput, match="L,2,2"):
        correspond(maps, maps, np.zeros((3, 4)))
    with pytest.raises(InvalidInput, match="source_occlusion"):
        correspond(maps, maps, landmarks_uv(pts, pts), source_occlusion=np.zeros((3, 3), bool))
    with pytest.raises(InvalidInput, match="flow must be one of"):
        CorrespondenceParams(flow="deepflow")
    with pytest.raises(InvalidInput, match="sharpen_sigmaa is not a parameter"):
        CorrespondenceParams(sharpen_sigmaa=2.0)
    p = CorrespondenceParams()
    with pytest.raises(ValidationError):
        p.dis_passes = 3
