"""Tests for service.methods.shape_space.maps: database maps blended per texel (eq. 4)."""

import numpy as np
import pytest

from service.methods.inputs import ActorData, Clip, InvalidInput
from service.methods.shape_space.maps import DatabaseMaps, MapBlender
from service.methods.shape_space.regions import normalize_region_weights
from tests.methods.shape_space.conftest import grid_mesh

H = 32


@pytest.fixture(scope="module")
def sheet_maps():
    """A UV-mapped sheet, three frames of random maps, and two regions split at x = 20 mm."""
    V, F = grid_mesh()
    uv = (V[:, :2] - V[:, :2].min(0)) / np.ptp(V[:, :2], axis=0).max() * 0.9 + 0.05
    actor = ActorData(vertices=V, faces=F, uv=uv, uv_faces=F, marker_triangle=np.zeros(0, int),
                      marker_barycentric=np.zeros((0, 3)), marker_names=())
    rng = np.random.default_rng(3)
    maps = rng.normal(0.0, 0.1, (3, H, H)).astype(np.float32)
    clip = Clip("db", np.repeat(V[None], 3, axis=0), np.zeros((3, 0, 3)), displacement=maps)
    left = (V[:, 0] < 20.0).astype(float)
    omega_hat = normalize_region_weights(np.stack([left, 1.0 - left]))        # (2,n)
    fm = MapBlender.build(DatabaseMaps.from_clips(actor, [clip], stride=1), uv, F, F, omega_hat)
    return fm, maps, actor, omega_hat


def test_maps_are_kept_at_the_covered_texels(sheet_maps):
    fm, maps, _, _ = sheet_maps
    assert fm.maps.shape == (3, len(fm.texels), 1) and fm.maps.dtype == np.float16
    assert fm.maps.flags.c_contiguous          # frame-major: a request reads whole frames
    assert fm.shape == (H, H) and 0 < len(fm.texels) < H * H
    stored = maps[1].astype(np.float16).astype(np.float32)           # the store's rounding ...
    np.testing.assert_array_equal(fm.image(fm.maps)[1].ravel()[fm.texels],
                                  stored.ravel()[fm.texels])
    assert np.abs(stored - maps[1]).max() <= 2.0 ** -12                  # ... half a step at |d| < 0.5


def test_blend_follows_the_region_weights_per_texel(sheet_maps):
    fm, maps, _, _ = sheet_maps
    W = np.array([[1.0, 0.0, 0.0], [0.0, 0.25, 0.75]])     # region 0: frame 0; region 1: a mix
    m = fm.blend(W)[:, 0]
    flat = maps.reshape(3, -1)[:, fm.texels].astype(np.float16).astype(np.float64)
    a = fm.omega_hat                                         # (2,P), columns sum to 1
    np.testing.assert_allclose(a.sum(axis=0), 1.0, atol=1e-12)
    expected = a[0] * flat[0] + a[1] * (0.25 * flat[1] + 0.75 * flat[2])
    np.testing.assert_allclose(m, expected, atol=1e-5)
    one = fm.blend(np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]]))[:, 0]
    np.testing.assert_allclose(one, flat[1], atol=1e-6)


def test_resampling_keeps_a_constant_map_on_the_covered_texels(sheet_maps):
    fm, _, actor, _ = sheet_maps
    from service.geometry.uv_raster import rasterize_uv

    out = fm.image(np.full((1, len(fm.texels), 1), 0.3), H=48)[0]
    covered = rasterize_uv(actor.uv, actor.uv_faces, 48, 48).mask
    np.testing.assert_allclose(out[covered], 0.3, atol=1e-6)
    assert np.all(out[~covered] == 0.0)


def test_clips_without_maps_give_none_and_mixed_sizes_are_refused(sheet_maps):
    _, maps, actor, _ = sheet_maps
    V = actor.vertices
    plain = Clip("db", V[None], np.zeros((1, 0, 3)))
    assert DatabaseMaps.from_clips(actor, [plain], 1) is None
    a = Clip("a", V[None], np.zeros((1, 0, 3)), displacement=maps[:1])
    b = Clip("b", V[None], np.zeros((1, 0, 3)), displacement=np.zeros((1, 16, 16), np.float32))
    with pytest.raises(InvalidInput, match="one size"):
        DatabaseMaps.from_clips(actor, [a, b], 1)


def test_albedo_maps_keep_their_channels(sheet_maps):
    fm, _, actor, omega_hat = sheet_maps
    rgb = np.random.default_rng(4).uniform(0, 1, (2, 16, 16, 3)).astype(np.float32)
    clip = Clip("db", np.repeat(actor.vertices[None], 2, axis=0), np.zeros((2, 0, 3)), albedo=rgb)
    am = MapBlender.build(DatabaseMaps.from_clips(actor, [clip], 1, "albedo"), actor.uv, actor.faces,
                          actor.faces, omega_hat)
    assert am.maps.shape == (2, len(am.texels), 3) and am.shape == (16, 16)
    assert am.maps.flags.c_contiguous
    img = am.image(am.blend(np.array([[0.0, 1.0], [0.0, 1.0]]))[None])
    assert img.shape == (1, 16, 16, 3)
    stored = rgb[1].astype(np.float16).astype(np.float32).reshape(-1, 3)[am.texels]
    np.testing.assert_allclose(img[0].reshape(-1, 3)[am.texels], stored, atol=1e-6)
    assert am.image(am.maps[:1], H=24).shape == (1, 24, 24, 3)
