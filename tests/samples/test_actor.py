"""The sample actor: deterministic by seed, detail zero at neutral and growing with compression."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.samples import detail, performances
from service.samples.actor import build_sample_actor, render_performance


def _clip(actor, name):
    clips = performances.training_clips(actor.rig.expression_names, actor.seed)
    return next(c for c in clips if c.name == name)


def test_detail_is_zero_at_neutral(actor0):
    out = render_performance(actor0, _clip(actor0, "train_brow_raise"), np.array([0]))
    np.testing.assert_array_equal(out["weights"][0], 0)
    # wrinkles vanish exactly at neutral; only pores remain in the displacement map
    assert np.abs(out["vertices"][0] - out["vertices_medium"][0]).max() < 1e-5
    assert -0.21 < out["displacement"][0].min() < -0.04          # pore depth, mm
    assert out["displacement"][0].max() <= 0.0


@pytest.mark.parametrize("clip, site", [("train_brow_raise", "forehead"),
                                        ("train_brow_furrow", "glabella"),
                                        ("train_smile", "crows_feet_L")])
def test_wrinkles_grow_with_compression_at_their_site(actor0, clip, site):
    perf = _clip(actor0, clip)
    out = render_performance(actor0, perf, np.arange(0))
    i = [s.name for s in actor0.sites].index(site)
    idx, pattern, _ = actor0.vertex_patterns[i]
    idx = idx[np.abs(pattern) > 0.3 * np.abs(pattern).max()]
    depth = np.linalg.norm(out["vertices"][:, idx] - out["vertices_medium"][:, idx], axis=2).max(axis=1)
    rise = np.argmax(perf.weights.sum(axis=1))
    # monotone growth while the expression eases in, and a real wrinkle at the peak
    assert np.all(np.diff(depth[: rise + 1]) >= -1e-6)
    assert depth[rise] > 0.15
    assert depth[0] == 0.0


def test_buckling_response_is_nonlinear():
    site = detail.WrinkleSite("t", "lines", np.zeros(3), np.eye(3)[0], np.eye(3)[1],
                              (10.0, 10.0), 5.0, 1.5, threshold=0.05, scale=0.15)
    c = np.array([0.0, 0.05, 0.10, 0.20, 0.40, 1.0])
    a = site.response(c)
    assert a[0] == 0 and a[1] == 0                      # below the buckling threshold
    assert np.all(np.diff(a[1:]) > 0) and a[-1] < 1.5  # grows, saturates below A_max
    # √-onset: the first 5 % of compression past threshold gives more than a linear share
    assert a[2] / a[3] > (0.05 / 0.15) * 1.3


def test_pores_flatten_when_stretched_and_deepen_when_compressed():
    offset = np.array([[0.1], [0.0], [0.0]])
    pores = detail.PoreField(offset, np.array([0.1]), np.array([0.25]), np.array([[0.0], [0], [1]]))

    def tangent_stretch(lam):                   # Voigt (6,1): diag(λ², λ², 0)
        return np.array([[lam ** 2], [lam ** 2], [0.0], [0], [0], [0]])

    rest = tangent_stretch(1.0)
    h0, J0 = detail.pore_height(pores, rest, rest)
    hs, Js = detail.pore_height(pores, tangent_stretch(1.2), rest)
    hc, Jc = detail.pore_height(pores, tangent_stretch(0.85), rest)
    np.testing.assert_allclose([J0[0], Js[0], Jc[0]], [1.0, 1.44, 0.7225], rtol=1e-12)
    assert abs(hs[0]) < abs(h0[0]) < abs(hc[0])


def test_surface_strain_of_uniform_scaling(rig):
    Q = detail.surface_strain(rig.neutral, 1.1 * rig.neutral, rig.triangles).T
    Q0 = detail.surface_strain(rig.neutral, rig.neutral, rig.triangles).T
    a = np.tile([[1.0], [0.0], [0.0]], (1, Q.shape[1]))
    ratio = detail.quadratic_form(Q, a) / detail.quadratic_form(Q0, a)
    np.testing.assert_allclose(ratio[detail.quadratic_form(Q0, a) > 0.5], 1.21, rtol=1e-9)


def test_area_ratio_matches_the_triangle_areas(rig):
    """J from det(Q + nnᵀ) is the area change: an in-plane stretch by (1.3, 0.8) gives 1.04."""
    from service.geometry.normals import vertex_normals
    V1 = rig.neutral * [1.3, 0.8, 1.0]
    Q = detail.surface_strain(rig.neutral, V1, rig.triangles).T
    Q0 = detail.surface_strain(rig.neutral, rig.neutral, rig.triangles).T
    N = vertex_normals(rig.neutral, rig.triangles).T
    J = detail.area_ratio(Q, N, Q0)
    facing = np.abs(N[2]) > 0.99                 # where the surface lies in the stretched plane
    np.testing.assert_allclose(np.median(J[facing]), 1.04, rtol=0.01)


def test_build_is_deterministic_by_seed(tmp_path):
    m1 = build_sample_actor(tmp_path / "a", seed=5, level=0, with_tracking=False, map_resolution=128,
                            performance_names=("train_smile", "heldout_in_range"))
    m2 = build_sample_actor(tmp_path / "b", seed=5, level=0, with_tracking=False, map_resolution=128,
                            performance_names=("train_smile", "heldout_in_range"))
    m3 = build_sample_actor(tmp_path / "c", seed=6, level=0, with_tracking=False, map_resolution=128,
                            performance_names=("train_smile",))
    digests = lambda m: {k: v["sha256"] for k, v in m["files"].items()}
    assert digests(m1) == digests(m2)
    assert digests(m1)["performances/train_smile.npz"] != digests(m3)["performances/train_smile.npz"]
    manifest = json.loads((tmp_path / "a" / "manifest.json").read_text())
    assert manifest["files"] == m1["files"]
    with np.load(tmp_path / "a" / "performances/train_smile.npz") as d:
        assert d["vertices"].shape == (20, 11248, 3) and d["markers"].shape == (20, 150, 3)
        assert d["displacement"].shape == (20, 128, 128) and d["albedo"].shape == (20, 64, 64, 3)
        assert np.isfinite(d["vertices"]).all()


def test_gallery_shows_detail_only_away_from_neutral(tmp_path):
    from PIL import Image

    from service.samples.gallery import SIZE, write_gallery

    build_sample_actor(tmp_path / "actor", seed=2, level=0, with_tracking=False, map_resolution=128,
                       performance_names=("train_brow_raise", "train_brow_furrow", "train_smile",
                                          "train_squint"))
    shaded, maps, albedo = write_gallery(tmp_path / "actor", tmp_path / "gallery")
    img = np.asarray(Image.open(shaded)).astype(int)
    assert img.shape == (2 * SIZE, 5 * SIZE, 3)
    detail, plain = img[:SIZE], img[SIZE:]
    panel = lambda rows, k: rows[40:, k * SIZE:(k + 1) * SIZE]      # below the label
    assert np.array_equal(panel(detail, 0), panel(plain, 0))         # neutral: no detail at all
    # each expression wrinkles: a visible share of the panel changes by more than 2 levels
    # (measured at level 0, seed 2: 1.0 %, 0.16 %, 1.6 %, 0.5 % for raise, furrow, smile, squint)
    changed = [np.mean(np.abs(panel(detail, k) - panel(plain, k)).max(axis=-1) > 2) for k in range(1, 5)]
    assert min(changed) > 0.0008
    assert Image.open(maps).size == (5 * 512, 2 * 512) and Image.open(albedo).size == (3 * 512, 2 * 512)


def test_marker_variants_keep_the_truth_and_are_written_only_when_asked(tmp_path):
    m = build_sample_actor(tmp_path / "v", seed=1, level=0, with_tracking=False, map_resolution=64,
                           performance_names=("heldout_amplified_occluded",))
    assert list(m["performances"]) == ["heldout_amplified_occluded"]          # the base is not written
    info = m["performances"]["heldout_amplified_occluded"]
    assert info["base"] == "heldout_amplified" and info["kind"] == "heldout_out_of_range"
    with np.load(tmp_path / "v" / "performances/heldout_amplified_occluded.npz") as d:
        missing = np.isnan(d["markers"]).all(axis=-1)
        assert np.array_equal(missing, np.isnan(d["markers"]).any(axis=-1))   # whole markers go missing
        np.testing.assert_allclose(missing.mean(), info["occluded_fraction"], atol=1e-4)
        assert not np.isnan(d["markers_clean"]).any()
        np.testing.assert_array_equal(d["markers"][~missing], d["markers_clean"][~missing])
        assert np.all(np.diff(d["map_frames"]) == 5) and d["weights"].max() > 1.25
