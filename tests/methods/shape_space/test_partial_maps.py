"""Shape-space training on clips of which only some carry maps (issue 17 item 6), and the
outputs ``mesh_detailed`` / ``normal_map`` that /enhance answers as /synthesize does: a
small UV-mapped sheet, a 4-frame 'scans' clip with maps and a 6-frame 'performance' clip
without (a database captured partly as meshes only)."""

import numpy as np
import pytest

from service.methods.inputs import ActorData, Clip
from service.methods.shape_space import ShapeSpaceModel, ShapeSpaceParams, train
from tests.methods.shape_space.conftest import grid_mesh

#: the scans' fine displacement, one constant per frame (exact in float16), mm
SCAN_MM = np.array([0.125, 0.25, 0.375, 0.5])
H = 16
PARAMS = ShapeSpaceParams(regions="whole", smoothing="rest", patch_size=10, lam_dt=5.0,
                          map_resolution=32)


def _motion(V, amplitudes, phase):
    """Frames (k,n,3): a bump of the given amplitudes with ripples, shifted by ``phase``."""
    bump = np.exp(-((V[:, 0] - 20.0) ** 2 + (V[:, 1] - 16.0) ** 2) / 60.0)
    out = np.repeat(V[None], len(amplitudes), axis=0)
    for k, a in enumerate(amplitudes):
        out[k, :, 2] += a * (4.0 * bump + 0.2 * np.sin(2.0 * V[:, 0] + phase) * bump)
        out[k, :, 0] += 0.5 * a * bump
    return out


@pytest.fixture(scope="module")
def partial():
    V, F = grid_mesh()
    uv = (V[:, :2] - V[:, :2].min(0)) / np.ptp(V[:, :2], axis=0).max() * 0.9 + 0.05
    actor = ActorData(vertices=V, faces=F, uv=uv, uv_faces=F, marker_triangle=np.zeros(0, np.int64),
                      marker_barycentric=np.zeros((0, 3)), marker_names=())
    scans = _motion(V, [0.2, 0.5, 0.8, 1.1], 0.0)
    perf = _motion(V, [0.1, 0.35, 0.65, 0.95, 1.25, 0.45], 1.0)
    disp = np.broadcast_to(SCAN_MM[:, None, None], (4, H, H)).astype(np.float32)
    albedo = np.random.default_rng(5).uniform(0.2, 0.8, (4, H, H, 3)).astype(np.float32)
    clips = [Clip("scans", scans, np.zeros((4, 0, 3)), disp, albedo),
             Clip("performance", perf, np.zeros((6, 0, 3)))]
    return actor, clips, train(actor, clips, PARAMS)


def test_clips_without_maps_keep_the_maps_of_the_clips_that_have_them(partial):
    """Before the fix: InvalidInput 'displacement maps must be given for every clip or for none'."""
    _, _, m = partial
    for maps in (m.fine_maps, m.albedo_maps):
        assert maps.frames.tolist() == [0, 1, 2, 3] and len(maps.maps) == 4
    assert m.n_frames == 10
    note = m.metrics["maps_partial"]
    assert set(note) == {"displacement", "albedo"}
    assert note["displacement"]["clips_without"] == ["performance"]
    assert note["displacement"]["database_frames_with_maps"] == 4
    assert note["displacement"]["database_frames"] == 10
    assert m.colors is None                       # colours need albedo in every clip


def test_a_frame_with_maps_gets_its_own_and_one_without_gets_the_mean(partial):
    _, clips, m = partial
    covered = m.fine_maps.image(np.ones((1, len(m.fine_maps.texels), 1)))[0] > 0
    scan = m.enhance(clips[0].vertices[2], ("displacement", "albedo"))
    assert scan["weights"][0, 0, 2] > 1 - 1e-6
    np.testing.assert_allclose(scan["fine_displacement"][0][covered], 0.375, atol=1e-6)
    lit = m.albedo_maps.image(np.ones((1, len(m.albedo_maps.texels), 3)))[0] > 0
    np.testing.assert_allclose(scan["albedo"][0][lit], clips[0].albedo[2][lit], atol=2e-3)
    # all weight on a frame without maps: the mean of the scans' maps (0.3125 mm)
    perf = m.enhance(clips[1].vertices[3], ("displacement", "albedo"))
    assert perf["weights"][0, 0, 4 + 3] > 1 - 1e-6
    np.testing.assert_allclose(perf["fine_displacement"][0][covered], SCAN_MM.mean(), atol=1e-6)
    mean_albedo = clips[0].albedo.astype(np.float16).astype(np.float64).mean(axis=0)
    np.testing.assert_allclose(perf["albedo"][0][lit], mean_albedo[lit], atol=1e-3)


def test_weights_split_between_frames_with_and_without_maps_blend_continuously(partial):
    _, _, m = partial
    W = np.zeros((1, 10))
    W[0, 1], W[0, 6] = 0.25, 0.75              # scan 1 (0.25 mm) and a frame without maps
    values = m.evaluator.fine_maps.blend(W)
    np.testing.assert_allclose(values, 0.25 * 0.25 + 0.75 * SCAN_MM.mean(), atol=1e-6)


def test_mesh_detailed_bakes_the_fine_map_along_the_normals(partial):
    from service.geometry.normals import vertex_normals

    _, clips, m = partial
    out = m.enhance(clips[0].vertices[1:3], ("mesh_detailed",))
    assert "displacement" not in out and "fine_displacement" not in out
    offset = out["vertices_detailed"].astype(np.float64) - out["vertices"]
    normals = vertex_normals(out["vertices"].astype(np.float64), m.faces)
    # float32 vertices of a 40 mm sheet: a step of 3.8e-6 mm
    np.testing.assert_allclose(offset, SCAN_MM[1:3, None, None] * normals, atol=1e-5)


def test_normal_map_is_unit_and_flat_for_a_constant_detail(partial):
    _, clips, m = partial
    out = m.enhance(clips[0].vertices[1], ("normal_map",))
    N = out["normal_map"]
    assert N.shape == (1, 32, 32, 3) and "displacement" not in out
    np.testing.assert_allclose(np.linalg.norm(N, axis=-1), 1.0, atol=1e-5)
    from service.geometry.uv_raster import rasterize_uv
    covered = rasterize_uv(m.uv, m.uv_faces, 32, 32).mask
    assert np.abs(N[0][covered] - [0.0, 0.0, 1.0]).max() < 0.02   # the database frame's own detail


def test_partial_maps_round_trip_bit_exact(partial, tmp_path):
    _, clips, m = partial
    m.save(tmp_path / "m")
    with np.load(tmp_path / "m" / "maps.npz") as z:
        assert z["displacement_frames"].tolist() == [0, 1, 2, 3]
    loaded = ShapeSpaceModel.load(tmp_path / "m")
    frames = np.stack([clips[0].vertices[1], clips[1].vertices[2]])
    outputs = ("mesh", "mesh_detailed", "displacement", "albedo", "normal_map")
    a, b = m.enhance(frames, outputs), loaded.enhance(frames, outputs)
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
