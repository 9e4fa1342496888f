"""Family b actors: deterministic, family a's layout and schema, different on every axis, units exact."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.samples.uploads import sample_actor_uploads
from service.io.markers import read_marker_layout
from service.samples import dataset
from service.samples.actor import build_sample_actor
from service.samples.family_b.actor import build_family_b

SMALL = dict(level=0, map_resolution=128)
VARIANTS = ("heldout_combinations_noisy", "heldout_combinations_occluded")


@pytest.fixture(scope="module")
def b_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("family_b")
    build_family_b(out, seed=1, performance_names=("train_smile", "heldout_combinations") + VARIANTS, **SMALL)
    return out


@pytest.fixture(scope="module")
def a_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("family_a")
    build_sample_actor(out, seed=1, with_tracking=False, performance_names=("train_smile",), **SMALL)
    return out


def _manifest(d):
    return json.loads((d / "manifest.json").read_text())


def test_build_is_deterministic_per_seed(b_dir, tmp_path):
    again = build_family_b(tmp_path / "again", seed=1, performance_names=("train_smile",), **SMALL)
    other = build_family_b(tmp_path / "other", seed=2, performance_names=("train_smile",), **SMALL)
    first = _manifest(b_dir)["files"]
    for name in ("neutral.npz", "markers.json", "input_rig.npz", "performances/train_smile.npz"):
        assert again["files"][name]["sha256"] == first[name]["sha256"], name
        assert other["files"][name]["sha256"] != first[name]["sha256"], name


def test_layout_and_manifest_follow_family_a_schema(a_dir, b_dir):
    ma, mb = _manifest(a_dir), _manifest(b_dir)
    assert set(ma) <= set(mb) and mb["family"] == "b" and mb["units"] == "mm"
    assert all(type(ma[k]) is type(mb[k]) for k in ma)
    with np.load(a_dir / "neutral.npz") as na, np.load(b_dir / "neutral.npz") as nb:
        assert {k: na[k].dtype for k in na.files} == {k: nb[k].dtype for k in nb.files}
        assert 0 <= nb["uv"].min() and nb["uv"].max() <= 1 and set(np.unique(nb["region"])) == {0, 1, 2}
    for d, m in ((a_dir, ma), (b_dir, mb)):
        with np.load(d / "input_rig.npz") as r:
            assert set(r.files) == {"vertices", "faces", "uv", "uv_faces"} and len(r["vertices"]) == m["rig_vertices"]
        assert len(read_marker_layout(d / "markers.json").names) == m["markers"]
    with np.load(a_dir / "performances/train_smile.npz") as pa, np.load(b_dir / "performances/train_smile.npz") as pb:
        assert {k: (pa[k].dtype, pa[k].ndim) for k in pa.files} == {k: (pb[k].dtype, pb[k].ndim) for k in pb.files}
        assert pb["displacement"].shape[1:] == (128, 128) and pb["albedo"].shape[1:] == (64, 64, 3)
        assert np.isfinite(pb["vertices"]).all() and len(pb["map_frames"]) == len(pb["vertices"])
    # the variants are the base performance with other markers and the clean ones beside them
    with np.load(b_dir / "performances/heldout_combinations.npz") as base:
        for name in VARIANTS:
            with np.load(b_dir / f"performances/{name}.npz") as v:
                assert set(v.files) == set(base.files) | {"markers_clean"}
                np.testing.assert_array_equal(v["markers_clean"], base["markers"])
                np.testing.assert_array_equal(v["vertices"], base["vertices"])
                np.testing.assert_array_equal(v["map_frames"], np.arange(0, len(base["vertices"]), 5))
            assert mb["performances"][name]["base"] == "heldout_combinations"
    # every consumer path reads both families the same way
    for d in (a_dir, b_dir):
        actor = dataset.load_actor(d)
        clip = dataset.load_clip(d, "train_smile", actor)
        assert clip.markers.shape == (clip.vertices.shape[0], actor.n_markers, 3)
        assert set(actor.regions) == {"narrow_face", "face", "head"}
        neutral, layout, clips = sample_actor_uploads(d, ["train_smile"])
        assert neutral and layout and set(clips) == {"train_smile"}


def test_the_two_families_differ_on_every_axis(a_dir, b_dir):
    ma, mb = _manifest(a_dir), _manifest(b_dir)
    assert ma["vertices"] != mb["vertices"] and ma["triangles"] != mb["triangles"]
    assert (ma["markers"], mb["markers"]) == (150, 118)
    assert ma["fps"] != mb["fps"] and ma["wrinkle_sites"] != mb["wrinkle_sites"]
    with np.load(a_dir / "neutral.npz") as na, np.load(b_dir / "neutral.npz") as nb:
        # family a's high-resolution mesh starts with the rig's vertices; family b's does not
        assert np.abs(nb["vertices"][: len(nb["rig_vertices"])] - nb["rig_vertices"]).max() > 10
        # non-uniform density: family b's face edges are much shorter than its head's
        E = np.sort(nb["faces"][:, [0, 1]], axis=1)
        L = np.linalg.norm(nb["vertices"][E[:, 0]] - nb["vertices"][E[:, 1]], axis=1)
        reg = nb["region"][E[:, 0]]
        assert np.median(L[reg == 2]) > 4 * np.median(L[reg == 0])
        # another identity of the rig (same topology): centimetres apart, not millimetres
        rms = np.sqrt(((na["rig_vertices"] - nb["rig_vertices"]) ** 2).sum(-1).mean())
        assert rms > 5.0

    def stats(d):
        with np.load(d / "performances/train_smile.npz") as p:
            D, A = p["displacement"], p["albedo"].astype(np.float64)
            peak = int(np.argmax(p["weights"].sum(axis=1)))
        covered = A[0].sum(-1) > 0
        texels = np.kron(covered, np.ones((2, 2))).astype(bool)
        x = D[peak] - D[0]
        return {"pores": float((D[0][texels] < -0.02).mean()),          # pore coverage at neutral
                "ridge_floor": float(x.max() / -x.min()),                # crease asymmetry
                "red_green": float(A[0][covered][:, 0].mean() / A[0][covered][:, 1].mean())}

    sa, sb = stats(a_dir), stats(b_dir)
    # measured (seed 1, level 0, 128² maps): pores 0.13 / 0.08, ridge/floor 0.69 / 0.19, R/G 1.45 / 1.40
    assert sa["pores"] > 1.25 * sb["pores"]
    assert sa["ridge_floor"] > 2 * sb["ridge_floor"]
    assert abs(sa["red_green"] - sb["red_green"]) > 0.02


@pytest.mark.parametrize("units", ["cm", "m"])
def test_the_unit_option_scales_every_length_exactly(b_dir, tmp_path, units):
    scale = {"cm": 0.1, "m": 0.001}[units]
    m = build_family_b(tmp_path / units, seed=1, units=units, performance_names=("train_smile",), **SMALL)
    assert m["units"] == units and m["unit_per_mm"] == scale
    # float32 of (mm value × scale) against float32 mm × scale: one rounding apart at most
    tol = dict(rtol=2 * np.finfo(np.float32).eps, atol=0)
    with np.load(b_dir / "neutral.npz") as a, np.load(tmp_path / units / "neutral.npz") as b:
        for k in a.files:
            if k in ("vertices", "rig_vertices"):
                np.testing.assert_allclose(b[k], a[k] * scale, **tol)
            else:
                np.testing.assert_array_equal(b[k], a[k])
    with np.load(b_dir / "performances/train_smile.npz") as a, \
            np.load(tmp_path / units / "performances/train_smile.npz") as b:
        for k in ("markers", "lowres", "vertices_medium", "vertices", "head_translation", "displacement"):
            np.testing.assert_allclose(b[k], a[k] * scale, atol=1e-6 * scale, rtol=2 * np.finfo(np.float32).eps)
        for k in ("weights", "head_rotation", "albedo", "map_frames", "fps"):
            np.testing.assert_array_equal(b[k], a[k])
    with pytest.raises(ValueError, match="units"):
        build_family_b(tmp_path / "x", units="inch", **SMALL)
    with pytest.raises(ValueError, match="mm cameras"):
        build_family_b(tmp_path / "y", units=units, with_tracking=True, **SMALL)


def test_cli_sample_actor_family_option_refuses_what_a_family_does_not_have(tmp_path, capsys):
    from service.cli import build_parser, main

    args = build_parser().parse_args(["sample-actor", "--out", str(tmp_path)])
    assert (args.family, args.units) == ("a", "mm")                 # the default stays family a, mm
    assert main(["sample-actor", "--out", str(tmp_path), "--family", "b", "--level", "2"]) == 2
    assert main(["sample-actor", "--out", str(tmp_path), "--units", "cm"]) == 2
    err = capsys.readouterr().err
    assert "family b has levels 0 and 1" in err and "family a is written in mm only" in err
    assert not any(tmp_path.iterdir())
