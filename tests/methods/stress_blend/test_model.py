import numpy as np
import pytest

from service.methods.inputs import InvalidInput
from service.methods.stress_blend.model import StressBlendModel, train
from service.methods.stress_blend.params import StressBlendParams
from tests.methods.stress_blend.synthetic import H, clips
from tests.methods.verified import load_verified_without_hashing

PARAMS = StressBlendParams(regions=3, stress_smoothing=2, mask_smoothing=2)


@pytest.fixture(scope="module")
def trained():
    actor, cl = clips()
    return actor, cl, train(actor, cl, PARAMS)


def test_scans_are_the_neutral_and_each_clip_peak(trained):
    _, _, model = trained
    assert model.scan_names[1:] == ["train_stretch:2", "train_squeeze:2"]
    assert model.scan_names[0].endswith(":0") or model.scan_names[0].endswith(":4")
    assert model.metrics["scan_reproduction_max_abs_mm"] == 0.0


def test_frame_equal_to_a_scan_blends_to_that_scan(trained):
    actor, cl, model = trained
    c, f = cl[1], 2
    out = model.synthesize(c.vertices[f:f + 1], ("displacement", "albedo", "blend_weights"))
    mask = model.disp_band.mask()
    np.testing.assert_array_equal(out["displacement"][0][mask], c.displacement[f][mask])
    am = model.albedo_band.mask()
    np.testing.assert_array_equal(out["albedo"][0][am], c.albedo[f][am])
    np.testing.assert_array_equal(out["blend_weights"][0][:, 2], 1.0)


def test_intermediate_frame_is_a_convex_blend(trained):
    actor, cl, model = trained
    out = model.synthesize(cl[0].vertices[1], ("displacement", "blend_weights", "wrinkle_weights"))
    w = out["blend_weights"][0]
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
    assert np.all(w >= 0)
    # the stretched half leans to the stretch scan, part way
    moved = actor.vertices[:, 0] < 10
    assert 0.2 < w[moved, 1].mean() < 0.99
    ww = out["wrinkle_weights"]
    assert ww.shape == (1, model.masks.shape[1], 2)
    assert np.all(ww >= 0) and np.all(ww.sum(axis=-1) <= 1 + 1e-6)
    # texel maps are inside the per-texel range of the scans' maps
    mask = model.disp_band.mask()
    lo, hi = model.displacement.min(axis=0), model.displacement.max(axis=0)
    d = out["displacement"][0]
    assert np.all((d[mask] >= lo[mask] - 1e-6) & (d[mask] <= hi[mask] + 1e-6))


def test_masks_partition_of_unity_and_engine_maps_at_scans(trained):
    _, cl, model = trained
    np.testing.assert_allclose(model.masks.sum(axis=1), 1.0, atol=1e-12)
    # engine weights (masks × region weights) of the neutral scan give the neutral map
    out = model.synthesize(cl[0].vertices[0], ("wrinkle_weights",))
    eng = model.engine_maps(np.zeros_like(out["wrinkle_weights"]))
    mask = model.disp_band.mask()
    np.testing.assert_allclose(eng[0][mask], model.displacement[0][mask], atol=1e-6)


def test_save_load_round_trip_is_identical(trained, tmp_path):
    _, cl, model = trained
    model.save(tmp_path / "m")
    back = StressBlendModel.load(tmp_path / "m")
    X = cl[0].vertices[1:4]
    a = model.synthesize(X, ("displacement", "albedo", "normal_map", "wrinkle_weights"))
    b = back.synthesize(X, ("displacement", "albedo", "normal_map", "wrinkle_weights"))
    for k in ("displacement", "albedo", "normal_map", "wrinkle_weights"):
        np.testing.assert_array_equal(a[k], b[k])
    assert a["normal_map"].shape == (3, 32, 32, 3)


def test_bad_input_is_refused(trained):
    actor, cl, model = trained
    with pytest.raises(InvalidInput, match="expects vertices"):
        model.synthesize(np.zeros((2, 5, 3)))
    X = cl[0].vertices[:2].copy()
    X[1, 3, 0] = np.nan
    with pytest.raises(InvalidInput, match="frame 1"):
        model.synthesize(X)
    with pytest.raises(InvalidInput, match="unknown outputs"):
        model.synthesize(cl[0].vertices[0], ("wrinkles",))
    import dataclasses
    with pytest.raises(InvalidInput, match="displacement maps"):
        train(actor, [dataclasses.replace(c, displacement=None, albedo=None) for c in cl], PARAMS)


def test_region_masks_separate_the_two_expressions():
    actor, cl = clips()
    model = train(actor, cl, StressBlendParams(regions=2, stress_smoothing=2, mask_smoothing=0))
    V = actor.vertices
    left_bottom = np.flatnonzero((V[:, 0] < 8) & (V[:, 1] < 8))
    right_top = np.flatnonzero((V[:, 0] > 22) & (V[:, 1] > 22))
    a = np.argmax(model.masks[left_bottom], axis=1)
    b = np.argmax(model.masks[right_top], axis=1)
    assert len(set(a)) == 1 and len(set(b)) == 1 and a[0] != b[0]


def test_mesh_detailed_is_the_input_mesh_with_the_blended_displacement_along_the_normals(trained):
    """/enhance answers ``mesh_detailed`` as /synthesize does (issue 17 item 6): at a scan's
    own frame the blend is that scan's map, sampled bilinearly at the vertices' UVs."""
    from service.geometry.normals import vertex_normals
    from service.geometry.uv_raster import map_to_vertices

    actor, cl, model = trained
    c, f = cl[1], 2
    out = model.synthesize(c.vertices[f:f + 1], ("mesh_detailed",))
    assert set(out) == {"faces", "vertices_detailed"}
    X = c.vertices[f]
    normals = vertex_normals(X, actor.faces)
    offset = out["vertices_detailed"][0].astype(np.float64) - X
    h = np.einsum("nd,nd->n", offset, normals)
    np.testing.assert_allclose(offset, h[:, None] * normals, atol=1e-5)     # along the normals
    expected = map_to_vertices(c.displacement[f].astype(np.float64), actor.uv, actor.uv_faces,
                               actor.faces, actor.n_vertices)
    # away from the chart's border, where every texel of the bilinear footprint is covered
    inner = np.all((actor.uv > 0.05 + 2 / H) & (actor.uv < 0.95 - 2 / H), axis=1)
    assert inner.sum() > 50
    np.testing.assert_allclose(h[inner], expected[inner], atol=1e-5)
    assert np.abs(h).max() > 0.05                                          # the map's noise, 0.1 mm


def test_a_directory_the_blob_store_verified_is_not_hashed_again(trained, tmp_path, monkeypatch):
    _, cl, model = trained
    model.save(tmp_path / "m")
    back = load_verified_without_hashing(StressBlendModel.load, tmp_path / "m", monkeypatch)
    X = cl[0].vertices[1:3]
    np.testing.assert_array_equal(back.synthesize(X, ("displacement",))["displacement"],
                                  model.synthesize(X, ("displacement",))["displacement"])
