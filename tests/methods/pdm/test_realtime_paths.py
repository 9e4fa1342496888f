"""The faster per-frame paths of issue 23 against the implementations they replaced.

``_old_valid_values`` is the gathered, float64 continuation of commit 7543b2b
(service/methods/pdm/validity.py), kept here verbatim as the reference: the dense float32
evaluation (:func:`~service.methods.pdm.validity.valid_polynomial`, the continuation inside
the polynomial's own pass) must give the same values bit for bit wherever ρ ≤ 1, and
within a stated float32 bound where ρ > 1 (the continuation and the falloff, which the old
code evaluated in float64 on the gathered points).
"""

from __future__ import annotations

import numpy as np
import pytest

from service.methods.confidence import falloff
from service.methods.pdm.polynomial import TERM_POWERS
from service.methods.pdm.validity import valid_polynomial, valid_values
from tests.methods.pdm.beyond import beyond

#: |new − old| at ρ > 1, relative to the largest |old| detail of the band's frame (measured
#: 4.5e-6 on the albedo, ≤ 2e-6 on the vertex and fine bands of this model; float32
#: evaluation of the continuation and of the falloff against the old float64 ones)
CONTINUATION_RTOL = 1e-5


def _old_valid_values(coeffs, values, d1, d2, rho, envelope, fallback, width, slope, margin=0.25):
    f, p = np.nonzero(rho > 1)
    if len(f):
        powers = np.array(next(t for t in TERM_POWERS.values() if len(t) == coeffs.shape[-1]))
        r = rho[f, p].astype(np.float64)
        b1, b2 = d1[f, p] / r, d2[f, p] / r
        mono = b1[:, None] ** powers[:, 0] * b2[:, None] ** powers[:, 1]           # (N,K)
        mono *= 1 + slope * powers.sum(axis=1) * (r - 1)[:, None]
        values[f, p] = np.einsum("nck,nk->nc", coeffs[p].astype(np.float64), mono).astype(values.dtype)
    const = np.ascontiguousarray(fallback, dtype=values.dtype)                   # (P,C)
    detail = values - const
    norm = np.sqrt(np.einsum("fpc,fpc->fp", detail, detail))
    w = np.minimum(1.0, (1 + margin) * envelope / np.maximum(norm, 1e-30)) * falloff(rho - 1.0, width)
    f, p = np.nonzero(w < 1)
    values[f, p] = const[p] + w[f, p, None].astype(values.dtype) * detail[f, p]
    return values


@pytest.fixture(scope="module")
def frames(pdm_model, pdm_data):
    """S of frames inside (two training peaks), beyond (2.5× and 6× the peaks' motion)."""
    _, clips = pdm_data
    ev = pdm_model.evaluator
    peak = clips[3].markers[[10, 12]]
    return ev.deformation(np.concatenate([peak, *(beyond(ev, peak, s) for s in (2.5, 6.0))]))[2]


@pytest.mark.parametrize("name", ["vertex", "fine", "albedo"])
def test_dense_continuation_is_the_gathered_one(pdm_model, frames, name):
    ev = pdm_model.evaluator
    band = ev.bands[name]
    v = ev.validity
    d1, d2, _ = ev.vertex_band.parameters(frames, None)
    rho_uv = v.gauge(d1, d2)
    if name == "vertex":
        t1, t2, rho = d1, d2, rho_uv
    else:
        t1, t2, _ = band.parameters(frames, None)
        rho = v.texels(name, rho_uv)
    args = (rho, v.envelope[name], v.fallback(name, band.coeffs), v.width, v.slope)
    old = _old_valid_values(band.coeffs, band.evaluate(t1, t2), t1, t2, *args)
    new = valid_polynomial(band.coeffs, t1, t2, *args)
    kept = valid_values(band.coeffs, band.evaluate(t1, t2), t1, t2, *args)
    assert new.dtype == np.float32 and new.flags.c_contiguous
    inside = rho <= 1
    assert inside[:2].mean() > 0.9 and (~inside[2:]).mean() > 0.1      # both cases are exercised
    assert np.array_equal(new[inside], old[inside])                    # bit for bit inside
    assert np.array_equal(kept, new)
    scale = np.abs(old - v.fallback(name, band.coeffs)).max(axis=(1, 2), keepdims=True)
    err = np.abs(new - old) / np.maximum(scale, 1e-12)
    assert err.max() <= CONTINUATION_RTOL, err.max()


def test_the_continuation_inside_the_polynomial_pass_is_the_plain_polynomial_inside(pdm_model, frames):
    from service.methods.pdm import polynomial

    band = pdm_model.evaluator.fine
    t1, t2, _ = band.parameters(frames, None)
    plain = band.evaluate(t1, t2)
    assert np.array_equal(polynomial.evaluate(band.coeffs, t1, t2, np.full_like(t1, 0.5)), plain)
    rho = np.where(np.arange(t1.shape[1]) % 2, 2.0, 1.0).astype(np.float32)[None].repeat(len(t1), 0)
    got = polynomial.evaluate(band.coeffs, t1, t2, rho, slope=0.0)
    assert np.array_equal(got[:, ::2], plain[:, ::2])
    # slope 0 at ρ = 2: the polynomial at d/2
    half = polynomial.evaluate(band.coeffs[1::2], t1[:, 1::2] / 2, t2[:, 1::2] / 2)
    np.testing.assert_allclose(got[:, 1::2], half, rtol=1e-6, atol=1e-6 * np.abs(half).max())


def _old_gauge(d1, d2, hull):
    K = len(hull)
    d1, d2 = np.broadcast_arrays(np.asarray(d1, np.float32), np.asarray(d2, np.float32))
    x = (np.arctan2(d2, d1) % (2 * np.pi)) * (K / (2 * np.pi))
    k0 = np.floor(x).astype(np.int64) % K
    t = (x - np.floor(x)).astype(np.float32)
    cols = np.broadcast_to(np.arange(d1.shape[-1]), d1.shape)
    h = (1 - t) * hull[k0, cols] + t * hull[(k0 + 1) % K, cols]
    return (np.hypot(d1, d2) / h).astype(np.float32)


def test_point_major_gauge_is_the_old_gauge_bit_for_bit(pdm_model, frames):
    from service.methods.pdm.validity import gauge

    v = pdm_model.evaluator.validity
    d1, d2, _ = pdm_model.evaluator.vertex_band.parameters(frames, None)
    old = _old_gauge(d1, d2, v.hull)
    assert np.array_equal(v.gauge(d1, d2), old) and np.array_equal(gauge(d1, d2, v.hull), old)
    assert old.min() < 1 < old.max()


def test_one_sector_lookup_serves_the_gauge_and_the_sector_envelope(pdm_model, frames):
    """The frame's :class:`SectorLookup` (made once) reads the hull and the sector envelope
    as the per-table lookups did (the old gauge, the old sector values), bit for bit."""
    from service.methods.pdm.validity import SectorLookup

    v = pdm_model.evaluator.validity
    d1, d2, _ = pdm_model.evaluator.vertex_band.parameters(frames, None)
    lookup = v.lookup(d1, d2)
    assert np.array_equal(v.gauge(d1, d2, lookup), _old_gauge(d1, d2, v.hull))
    assert v.sector_points is not None
    assert np.array_equal(lookup.values(v.sector_points), _old_sector_values(d1, d2, v.sectors))
    rho = v.gauge(d1, d2, lookup)
    coeffs = pdm_model.evaluator.vertex_band.coeffs
    assert np.array_equal(v.evaluate("vertex", coeffs, d1, d2, rho, lookup), v.evaluate("vertex", coeffs, d1, d2, rho))
    # the sector box's bounds (K,Q,3) as stored (sector-major) through the same lookup, as
    # the point-major (Q,K,3) gather of each bound and of both at once (Q,K,2,3)
    assert v.sector_box is not None
    both = lookup.values(_point_major_box(v))                                   # (F,Q,2,3)
    for i, bound in enumerate(v.sector_box):                                    # (K,Q,3) each
        got = lookup.sector_values(bound)
        assert np.array_equal(got, SectorLookup.of(d1, d2, lookup.K).values(np.ascontiguousarray(bound.transpose(1, 0, 2))))
        assert np.array_equal(got, both[..., i, :])
    fallback = pdm_model.evaluator.shell_fallback(frames[..., :3], None)
    shared = v.evaluate("vertex", coeffs, d1, d2, rho, lookup, fallback)
    assert np.array_equal(shared, v.evaluate("vertex", coeffs, d1, d2, rho, fallback=fallback))
    assert not np.array_equal(shared, v.evaluate("vertex", coeffs, d1, d2, rho, lookup))    # the box and fallback act
    with pytest.raises(ValueError):
        SectorLookup.of(d1, d2, 8).values(v.sector_points)


def _point_major_box(v):
    """The sector box point-major (Q,K,2,3), as Validity held it before (frozen layout)."""
    return np.ascontiguousarray(v.sector_box.transpose(2, 1, 0, 3))


def _old_sector_values(d1, d2, table):
    """The (K,P) table at d's direction, linear between sectors (the old column gather)."""
    K = len(table)
    x = (np.arctan2(d2, d1) % (2 * np.pi)) * (K / (2 * np.pi))
    k0 = np.floor(x).astype(np.int64) % K
    t = (x - np.floor(x)).astype(np.float32)
    cols = np.broadcast_to(np.arange(d1.shape[-1]), d1.shape)
    return (1 - t) * table[k0, cols] + t * table[(k0 + 1) % K, cols]


def _flat_channel_values(lookup, table):
    """The channel-table lookup before items (frozen copy): C scalars gathered per point by
    the flat indices ``lower · C + c``."""
    flat = np.ascontiguousarray(table).ravel()
    channels = table.shape[2:]
    C = int(np.prod(channels))
    chan = np.arange(C)
    t = lookup.t[..., None]
    out = ((1 - t) * np.take(flat, lookup.lower[..., None] * C + chan)
           + t * np.take(flat, lookup.upper[..., None] * C + chan))
    return out.reshape(*out.shape[:-1], *channels)


def test_the_item_gather_of_a_channel_table_is_the_flat_gather_bit_for_bit(pdm_model, frames):
    from service.methods.pdm.validity import SectorLookup

    v = pdm_model.evaluator.validity
    d1, d2, _ = pdm_model.evaluator.vertex_band.parameters(frames, None)
    lookup = v.lookup(d1, d2)
    got = lookup.values(_point_major_box(v))
    assert got.shape == d1.shape + (2, 3) and got.dtype == np.float32
    assert np.array_equal(got, _flat_channel_values(lookup, _point_major_box(v)))
    assert np.abs(got).max() > 0
    # a table that is not contiguous, float64, one frame of 1-D parameters
    rng = np.random.default_rng(4)
    table = rng.normal(size=(5, 3, 16, 4)).transpose(0, 2, 1, 3)              # (P,K,3,4) view
    a, b = rng.normal(size=(2, 5)).astype(np.float32)
    one = SectorLookup.of(a, b, 16)
    assert np.array_equal(one.values(table), _flat_channel_values(one, table))


def _any_axis_fade(values, rho, envelope, fallback, width, margin, box):
    """:func:`~service.methods.pdm.validity.fade_detail` with the box's clip found by
    ``np.any(…, axis=-1)`` (frozen copy of the code before the per-channel OR)."""
    dtype = values.dtype
    const = np.ascontiguousarray(fallback, dtype=dtype)
    detail = values - const
    bound = np.asarray(box, dtype) * dtype.type(1 + margin)
    inside = np.clip(detail, bound[0], bound[1])
    clipped = np.any(inside != detail, axis=-1)
    detail = inside
    norm = np.sqrt(np.einsum("fpc,fpc->fp", detail, detail))
    np.maximum(norm, 1e-30, out=norm)
    w = np.divide((1 + margin) * np.asarray(envelope, dtype), norm, out=norm)
    np.minimum(w, 1.0, out=w)
    outside = rho > 1
    if np.any(outside):
        w *= np.where(outside, falloff(np.asarray(rho, dtype) - dtype.type(1), width, dtype), dtype.type(1))
    fading = (w < 1) | clipped
    detail *= w[..., None]
    detail += const
    np.copyto(values, detail, where=fading[..., None])
    return values


def test_the_medium_fade_toward_the_shell_is_the_old_one_bit_for_bit(pdm_model, frames):
    """The vertex band's fade to the per-frame shell fallback through the item gather of
    the sector box and the per-channel clip test, against the old flat gather and
    ``np.any``: frames inside the hull and far outside (2.5×, 6× the peaks)."""
    from service.methods.pdm import polynomial
    from service.methods.pdm.validity import fade_detail

    ev = pdm_model.evaluator
    v = ev.validity
    d1, d2, _ = ev.vertex_band.parameters(frames, None)
    lookup = v.lookup(d1, d2)
    rho = v.gauge(d1, d2, lookup)
    fallback = ev.shell_fallback(frames[..., :3], None)
    L = np.ascontiguousarray(polynomial.evaluate(ev.vertex_band.coeffs, d1, d2, rho, v.slope))
    env = lookup.values(v.sector_points)
    old_box = np.moveaxis(_flat_channel_values(lookup, _point_major_box(v)), -2, 0)
    old = _any_axis_fade(L.copy(), rho, env, fallback, v.width, 0.25, old_box)
    new = fade_detail(L.copy(), rho, env, fallback, v.width, 0.25,
                      np.stack([lookup.sector_values(bound) for bound in v.sector_box]))
    assert np.array_equal(new, old)
    assert np.array_equal(v.evaluate("vertex", ev.vertex_band.coeffs, d1, d2, rho, lookup, fallback), old)
    changed = np.any(old != L, axis=-1)
    assert not changed[:2].any() and changed[2:].mean() > 0.3     # training peaks kept; far frames faded


@pytest.mark.parametrize("name", ["fine", "albedo"])
def test_texel_rho_per_frame_is_the_multi_vector_product_bit_for_bit(pdm_model, frames, name):
    v = pdm_model.evaluator.validity
    d1, d2, _ = pdm_model.evaluator.vertex_band.parameters(frames, None)
    rho = v.gauge(d1, d2)
    old = np.ascontiguousarray((v.texel_rho[name] @ rho.T).T, dtype=np.float32)    # frozen: before
    got = v.texels(name, rho)
    assert got.dtype == np.float32 and got.flags.c_contiguous and got.shape == old.shape
    assert np.array_equal(got, old) and old.max() > 1
    assert np.array_equal(v.texels(name, rho[1:2]), old[1:2])


def _dense_valid(coeffs, d1, d2, rho, envelope, fallback, width, slope):
    """The dense continuation and fade every band took before (one pass over all points)."""
    from service.methods.pdm import polynomial
    from service.methods.pdm.validity import fade_detail

    values = np.ascontiguousarray(polynomial.evaluate(coeffs, d1, d2, rho, slope))
    return fade_detail(values, rho, envelope, fallback, width)


def test_the_scalar_band_path_is_the_dense_one_bit_for_bit(pdm_model, frames):
    """The fine band (one channel) continued and faded only where a value can change is
    the dense pass bit for bit, per block as synthesis runs it, inside the hull and far out."""
    from service.methods.pdm.validity import valid_polynomial

    ev = pdm_model.evaluator
    v = ev.validity
    band = ev.fine
    d1, d2, _ = ev.vertex_band.parameters(frames, None)
    bv = v.band("fine", band.coeffs, v.gauge(d1, d2))
    assert bv.sure is not None
    t1, t2, _ = band.parameters(frames, None)
    args = (bv.rho, bv.envelope, bv.fallback, v.width, v.slope)
    dense = _dense_valid(band.coeffs, t1, t2, *args)
    assert np.array_equal(valid_polynomial(band.coeffs, t1, t2, *args), dense)
    P = len(band.index)
    cuts = [0, P // 3, P // 3 + 1, P]                                      # blocks, one of one point
    got = np.concatenate([bv.evaluate(t1[:, a:b], t2[:, a:b], a, b) for a, b in zip(cuts, cuts[1:])], axis=1)
    assert np.array_equal(got, dense)
    assert np.array_equal(band.synthesize(frames, None, bv)[0], dense)
    outside = bv.rho > 1
    assert outside[2:].mean() > 0.1 and np.any(dense != band.evaluate(t1, t2))      # continued and faded


def test_the_scalar_band_path_keeps_the_dense_zeros_signs_and_edge_envelopes():
    """Synthetic one-channel points where the dense pass's arithmetic has corner cases: values
    ±0 inside (the dense continuation adds 0 · Σ k a_k m_k), envelopes 0, subnormal and
    huge, NaN coefficients, ρ exactly 1, and details at the envelope: bit for bit."""
    from service.methods.pdm.validity import valid_scalar_polynomial

    rng = np.random.default_rng(7)
    P = 400
    coeffs = rng.normal(size=(P, 1, 6)).astype(np.float32)
    coeffs[:40] = 0.0
    coeffs[20:40] = -0.0                                                 # D = −0 where d > 0
    coeffs[40:60, 0, :5] = 0.0
    coeffs[40:60, 0, -1] = -0.0
    coeffs[40:50, 0, 0] = -1e-30                                        # −0 after rounding, sum < 0
    coeffs[60, 0, 2] = np.nan
    d1, d2 = rng.normal(size=(2, 3, P)).astype(np.float32) * 3
    d1[:, 20:40], d2[:, 20:40] = np.abs(d1[:, 20:40]), np.abs(d2[:, 20:40])
    rho = np.abs(rng.normal(size=(3, P))).astype(np.float32) * 1.3
    rho[:, ::7] = 1.0
    fallback = coeffs[:, :, -1].copy()
    envelope = np.abs(rng.normal(size=P)).astype(np.float32)
    envelope[100:110] = 0.0
    envelope[110:120] = 1e-40
    envelope[120:130] = 3e38
    plain = np.ascontiguousarray(
        __import__("service.methods.pdm.polynomial", fromlist=["evaluate"]).evaluate(coeffs, d1, d2))
    detail = np.abs(plain[..., 0] - fallback[:, 0])
    envelope[130:200] = (detail[0, 130:200] / np.float32(1.25)).astype(np.float32)   # at the bound
    for width, slope in ((1.0, 1.0), (0.5, 0.0)):
        with np.errstate(over="ignore"):                     # 1.25 × 3e38 is inf in float32
            dense = _dense_valid(coeffs, d1, d2, rho, envelope, fallback, width, slope)
            got = valid_scalar_polynomial(coeffs, d1, d2, rho, envelope, fallback, width, slope)
        same = (got == dense) | (np.isnan(got) & np.isnan(dense))
        assert same.all() and np.array_equal(np.signbit(got), np.signbit(dense))
        assert (dense == 0).sum() > 30 and np.isnan(dense).any()
        zero = dense[..., 0] == 0
        assert np.signbit(plain[..., 0][zero]).any() and not np.signbit(dense[..., 0][zero]).all()


def test_the_shell_fallback_gathered_by_items_is_the_strided_gather_bit_for_bit(pdm_model, frames):
    from service.geometry.thin_shell import apply_basis

    ev = pdm_model.evaluator
    u_H = frames[..., :3]
    X = ev.base.deform(u_H)
    world = (ev.shell_offset + apply_basis(ev.shell_correction, u_H)).astype(np.float32)
    local = ev.base.frame_field.to_frame(X, world) - ev.data.neutral_offset             # frozen: before
    old = np.ascontiguousarray(local[:, ev.uv_vertex], dtype=np.float32)
    got = ev.shell_fallback(u_H, X)
    assert got.dtype == np.float32 and got.flags.c_contiguous and np.array_equal(got, old)
    assert np.abs(old).max() > 0.1


@pytest.mark.parametrize("outputs", [("mesh", "displacement", "normal_map", "albedo"), ("normal_map",),
                                     ("displacement",)])
def test_half_maps_are_the_float32_maps_rounded_by_numpy_bit_for_bit(pdm_model, pdm_data, outputs):
    """Issue 23: ``synthesize(half=True)`` writes the maps as float16 in the map kernels;
    each is ``astype(np.float16)`` of the float32 call's map bit for bit, the rest of the
    result (meshes, clamped, confidence) is the float32 call's, two frames in one chunk."""
    _, clips = pdm_data
    markers = clips[2].markers[[3, 9]]
    full = pdm_model.synthesize(markers, outputs)
    half = pdm_model.synthesize(markers, outputs, half=True)
    assert sorted(full) == sorted(half)
    maps = [k for k in ("displacement", "normal_map", "albedo") if k in outputs]
    for key, value in full.items():
        if key in maps:
            assert value.dtype == np.float32 and half[key].dtype == np.float16 and half[key].shape == value.shape
            assert np.array_equal(half[key].view(np.uint16), value.astype(np.float16).view(np.uint16)), key
        else:
            assert np.array_equal(half[key], value), key
    if "displacement" in outputs:
        assert np.abs(full["displacement"]).max() > 1e-4          # a real map, not zeros
    if outputs == ("normal_map",):                               # the map alone is the full call's
        both = pdm_model.synthesize(markers, ("displacement", "normal_map"))
        assert np.array_equal(both["normal_map"], full["normal_map"])


def test_without_confidence_the_rest_of_the_result_is_the_same_bit_for_bit(pdm_model, pdm_data):
    """``confidence=False`` (the gRPC stream, whose MeshFrame has none) leaves out the two
    confidence arrays and their computation; every other array is the full call's."""
    _, clips = pdm_data
    markers = clips[4].markers[[2, 7]].copy()
    markers[1, :5] = np.nan                                   # occlusion moves the input factor
    outputs = ("mesh", "displacement", "normal_map")
    full = pdm_model.synthesize(markers, outputs)
    lean = pdm_model.synthesize(markers, outputs, confidence=False)
    assert sorted(lean) == sorted(set(full) - {"confidence", "confidence_vertices"})
    for key, value in lean.items():
        assert np.array_equal(value, full[key]), key
    assert full["confidence"][1] < full["confidence"][0] <= 1
