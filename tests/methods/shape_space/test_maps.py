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
    db = fm.database
    assert fm.maps.shape == (3, len(fm.texels), 1) and fm.maps.dtype == np.int16
    assert fm.maps.flags.c_contiguous          # frame-major: a request reads whole frames
    assert fm.shape == (H, H) and 0 < len(fm.texels) < H * H
    flat = maps.reshape(3, -1)[:, fm.texels]
    # one step per frame: its largest value is ±32767 steps, every value within half a step
    np.testing.assert_allclose(db.scale, np.abs(flat).max(axis=1) / 32767, rtol=1e-6)
    assert np.abs(fm.maps).max(axis=(1, 2)).tolist() == [32767] * 3
    # (and float32's own rounding of the value)
    np.testing.assert_array_less(np.abs(db.values()[..., 0] - flat).max(axis=1), 0.5 * db.scale + 1e-7)
    np.testing.assert_array_equal(fm.image(db.values())[1].ravel()[fm.texels], db.values()[1, :, 0])


def test_quantization_is_exact_on_a_step_grid_and_zero_frames_stay_zero():
    from service.methods.shape_space.maps import quantize

    values = np.array([[[3.0], [-1.5], [0.75]], [[0.0], [0.0], [0.0]]], np.float32)
    q, scale = quantize(values)
    assert q.dtype == np.int16 and scale.tolist() == [np.float32(3.0 / 32767), 1.0]
    assert q[:, :, 0].tolist() == [[32767, -16384, 8192], [0, 0, 0]]   # −16383.5, 8191.75 rounded
    np.testing.assert_allclose(q * scale[:, None, None], values, atol=0.5 * 3.0 / 32767)


def test_blend_follows_the_region_weights_per_texel(sheet_maps):
    fm, maps, _, _ = sheet_maps
    W = np.array([[1.0, 0.0, 0.0], [0.0, 0.25, 0.75]])     # region 0: frame 0; region 1: a mix
    m = fm.blend(W)[:, 0]
    flat = fm.database.values()[..., 0].astype(np.float64)   # the stored values
    a = fm.omega_hat                                         # (2,P), columns sum to 1
    np.testing.assert_allclose(a.sum(axis=0), 1.0, atol=1e-12)
    expected = a[0] * flat[0] + a[1] * (0.25 * flat[1] + 0.75 * flat[2])
    np.testing.assert_allclose(m, expected, atol=1e-6)
    one = fm.blend(np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]]))[:, 0]
    np.testing.assert_allclose(one, flat[1], atol=1e-6)
    # against the float maps the clips gave: within the steps the weights put on them
    raw = maps.reshape(3, -1)[:, fm.texels].astype(np.float64)
    exact = a[0] * raw[0] + a[1] * (0.25 * raw[1] + 0.75 * raw[2])
    bound = 0.5 * (a[0] * fm.database.scale[0] + a[1] * (0.25 * fm.database.scale[1]
                                                          + 0.75 * fm.database.scale[2]))
    assert np.all(np.abs(m - exact) <= bound + 1e-6)


def test_blend_and_image_into_given_arrays_are_the_same_values(sheet_maps):
    """issue 23: /enhance blends into a request's work array and writes the images into its
    outputs; the values are those of the calls that allocate."""
    fm, _, _, _ = sheet_maps
    W = np.array([[0.5, 0.5, 0.0], [0.0, 0.25, 0.75]])
    work = np.full((2, len(fm.texels), 1), np.nan, np.float32)
    assert np.shares_memory(fm.blend(W, out=work[1]), work)
    np.testing.assert_array_equal(work[1], fm.blend(W))
    images = np.zeros((2, H, H), np.float32)
    assert fm.database.image(work[1:], out=images[1:]) is not None
    np.testing.assert_array_equal(images[1:], fm.image(work[1:]))
    assert not images[0].any()
    with pytest.raises(ValueError):
        fm.database.image(work[1:], out=np.zeros((1, H, H), np.float64))


def test_float16_maps_of_older_models_blend_as_stored(sheet_maps):
    """A model stored before the int16 maps holds float16 values and no steps."""
    fm, maps, actor, omega_hat = sheet_maps
    half = DatabaseMaps(fm.database.values().astype(np.float16), fm.texels, fm.shape)
    old = MapBlender.build(half, actor.uv, actor.faces, actor.faces, omega_hat)
    W = np.array([[0.5, 0.5, 0.0], [0.0, 0.25, 0.75]])
    np.testing.assert_allclose(old.blend(W), fm.blend(W), atol=2.0 ** -11)
    np.testing.assert_array_equal(half.values(), half.maps.astype(np.float32))


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
    stored = am.database.values()[1]
    np.testing.assert_allclose(img[0].reshape(-1, 3)[am.texels], stored, atol=1e-6)
    np.testing.assert_allclose(stored, rgb[1].reshape(-1, 3)[am.texels], atol=0.5 / 32767 + 1e-7)
    assert am.image(am.maps[:1], H=24).shape == (1, 24, 24, 3)
