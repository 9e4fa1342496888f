"""The PDM's validity region, envelope and falloff (service/methods/pdm/validity.py), by hand."""

from __future__ import annotations

import numpy as np
import pytest

from service.methods.pdm.validity import (
    DIRECTIONS, HULL_FLOOR, gauge, training_envelope, training_hull, valid_values,
)

# one point, one channel, biquadratic a0 d1² + a1 d2² + a2 d1 d2 + a3 d1 + a4 d2 + a5
COEFFS = np.array([[[1.0, 0.0, 0.0, 2.0, 0.0, 0.5]]], np.float32)        # (P=1,C=1,K=6)


def D(d1, d2):
    return d1 * d1 + 2 * d1 + 0.5


def _apply(d1, d2, rho, width=2.0, slope=1.0, envelope=1e9, fallback=0.5):
    d1, d2, rho = (np.array([[x]], np.float32) for x in (d1, d2, rho))
    values = np.array([[[D(d1[0, 0], d2[0, 0])]]], np.float32)
    return valid_values(COEFFS, values, d1, d2, rho, np.array([envelope], np.float32),
                        np.array([[fallback]], np.float32), width, slope)[0, 0, 0]


def test_inside_the_region_is_exactly_the_polynomial():
    assert _apply(0.7, 0.2, 0.9) == np.float32(D(np.float32(0.7), np.float32(0.2)))


def test_between_the_linear_continuation_is_faded_by_the_smoothstep():
    # d = (2, 0) at ρ = 2: d_b = (1, 0); L = a0·(1 + 2·1) + a3·(1 + 1·1) + a5 = 3 + 4 + 0.5;
    # w = falloff(1, width 2) = 1 − (3·0.25 − 2·0.125) = 0.5; fallback a5 = 0.5 + 0.5·7
    assert _apply(2.0, 0.0, 2.0) == pytest.approx(4.0, abs=1e-6)
    # slope 0 holds the boundary's detail: L = 1 + 2 + 0.5, 0.5 + 0.5·3
    assert _apply(2.0, 0.0, 2.0, slope=0.0) == pytest.approx(2.0, abs=1e-6)


def test_far_outside_is_exactly_the_fallback():
    assert _apply(3.0, 0.0, 3.0) == pytest.approx(0.5, abs=0)
    assert _apply(30.0, 5.0, 31.0) == pytest.approx(0.5, abs=0)


def test_detail_is_limited_to_its_training_envelope():
    # inside, D − fallback = 0.49 + 1.4 = 1.89 > 1.25 × envelope 1: scaled to 1.25
    assert _apply(0.7, 0.0, 0.5, envelope=1.0) == pytest.approx(0.5 + 1.25, abs=1e-6)


def test_training_envelope_is_the_largest_detail_of_the_training_frames():
    d1 = np.array([[0.0], [1.0], [-1.0]], np.float32)
    env = training_envelope(COEFFS, lambda: iter([(d1, np.zeros_like(d1))]),
                            np.array([[0.5]], np.float32))
    assert env == pytest.approx([3.0])                     # D(1, 0) − 0.5 = 1 + 2


def test_star_region_of_one_ray_and_its_gauge():
    r = np.linspace(0, 2, 5, dtype=np.float32)[:, None]   # training frames on the +d1 ray
    hull = training_hull(lambda: iter([(r, np.zeros_like(r))]))
    assert hull.shape == (DIRECTIONS, 1)
    rho = gauge(np.array([[1.0, 2.0, 4.0, 0.0]], np.float32), np.array([[0.0, 0.0, 0.0, 1.0]], np.float32),
                np.repeat(hull, 4, axis=1))
    # on the ray: r / 2; across it (a combination): the floor 0.05 · 2
    assert rho[0] == pytest.approx([0.5, 1.0, 2.0, 1.0 / (HULL_FLOOR * 2)], rel=1e-5)


def test_every_training_sample_lies_in_its_region():
    rng = np.random.default_rng(0)
    d1, d2 = rng.normal(size=(2, 50, 7)).astype(np.float32)
    hull = training_hull(lambda: iter([(d1, d2)]))
    assert gauge(d1, d2, hull).max() <= 1 + 1e-5


# --- the sector envelope of the medium band (issue 17, failure mode 1) ------------------


def test_sector_envelope_is_the_training_detail_in_each_direction():
    from service.methods.pdm.validity import SectorLookup, sector_envelope

    r = np.linspace(0, 2, 5, dtype=np.float32)[:, None]          # training on the +d1 ray
    env = sector_envelope(COEFFS, lambda: iter([(r, np.zeros_like(r))]), np.array([[0.0]], np.float32))
    assert env.shape == (DIRECTIONS, 1)
    assert env[0, 0] == pytest.approx(D(2.0, 0.0))                # 8.5: the largest on the ray
    assert env[1, 0] == pytest.approx(8.5) and env[-1, 0] == pytest.approx(8.5)   # one sector away
    # never trained: the rest sample's detail D(0, 0) = 0.5 (every sector holds the neutral's)
    assert env[DIRECTIONS // 2, 0] == pytest.approx(0.5) and env[DIRECTIONS // 4, 0] == pytest.approx(0.5)
    # linear between sectors: halfway between sector 1 (full) and 2 (κ = 0)
    half = 2 * np.pi * 1.5 / DIRECTIONS
    v = SectorLookup.of(np.array([[np.cos(half)]], np.float32), np.array([[np.sin(half)]], np.float32),
                        DIRECTIONS).values(np.ascontiguousarray(env.T))
    assert v[0, 0] == pytest.approx(4.5, rel=1e-5)


def test_vertex_band_uses_the_sector_envelope_and_others_the_scalar_one():
    """Along the trained ray the polynomial is kept; in a direction training never moved the
    point (45°, inside the floored region), the detail is limited to 1.25 × that direction's
    envelope (0: the fallback), where the scalar envelope keeps it."""
    import scipy.sparse as sp

    from service.methods.pdm.validity import Validity, sector_envelope

    r = np.linspace(0, 2, 5, dtype=np.float32)[:, None]
    chunks = lambda: iter([(r, np.zeros_like(r))])            # noqa: E731
    coeffs = COEFFS.copy()
    coeffs[..., -1] = 0.0                                     # D = d1² + 2 d1; vertex fallback 0
    fb = np.zeros((1, 1), np.float32)
    hull, env = training_hull(chunks), training_envelope(coeffs, chunks, fb)
    args = ({"vertex": env, "fine": env}, 1.0, 1.0, {}, sp.csr_matrix((1, 1)), np.ones(1))
    points = np.ascontiguousarray(hull.T)                     # Validity keeps the hull point-major
    v = Validity(points, *args, np.ascontiguousarray(sector_envelope(coeffs, chunks, fb).T))
    scalar = Validity(points, *args)

    def apply(val, name, d1, d2):
        d1, d2 = np.array([[d1]], np.float32), np.array([[d2]], np.float32)
        D_ = d1 * d1 + 2 * d1
        return val.evaluate(name, coeffs, d1, d2, val.gauge(d1, d2))[0, 0, 0], D_[0, 0]

    got, want = apply(v, "vertex", 1.5, 0.0)                  # on the ray, inside: the polynomial
    assert got == want
    got, want = apply(v, "vertex", 0.05, 0.05)                # 45°: inside (ρ 0.71), untrained direction
    assert want > 0.1 and got == 0.0
    assert apply(scalar, "vertex", 0.05, 0.05)[0] == want     # the scalar envelope (8) keeps it
    assert apply(v, "fine", 0.05, 0.05)[0] == want            # texel bands: the scalar envelope


# --- the sector box and the per-frame shell fallback (issue 17, step 1) -------------------


def test_sector_box_is_the_training_detail_per_channel_against_each_frames_fallback():
    from service.methods.pdm.validity import sector_envelope

    r = np.linspace(0, 2, 5, dtype=np.float32)[:, None]          # training on the +d1 ray
    fb = np.linspace(0, 1, 5, dtype=np.float32)[:, None, None]    # each frame's fallback (t,P,C)
    coeffs = np.concatenate([COEFFS, -COEFFS], axis=1)            # channels D and −D
    env, box = sector_envelope(coeffs, lambda: iter([(r, np.zeros_like(r), fb)]), None, box=True)
    assert box.shape == (2, DIRECTIONS, 1, 2)
    detail = np.stack([D(r[:, 0], 0) - fb[:, 0, 0], -D(r[:, 0], 0) - fb[:, 0, 0]], -1)   # (t,C)
    # on the ray: the channels' extremes over the frames, with 0 (the fallback) always inside
    assert box[0, 0, 0] == pytest.approx(np.minimum(detail.min(0), 0))
    assert box[1, 0, 0] == pytest.approx(np.maximum(detail.max(0), 0))
    assert env[0, 0] == pytest.approx(np.linalg.norm(detail, axis=1).max())
    # opposite the ray only the rest sample (d = 0: D − fb = 0.5, −0.5) counts
    assert box[:, DIRECTIONS // 2, 0].ravel() == pytest.approx([0.0, -0.5, 0.5, 0.0])


def test_a_sector_lookup_of_channels_is_each_channels_lookup():
    from service.methods.pdm.validity import SectorLookup

    rng = np.random.default_rng(1)
    table = rng.normal(size=(4, DIRECTIONS, 3)).astype(np.float32)
    d1, d2 = rng.normal(size=(2, 2, 4)).astype(np.float32)
    lookup = SectorLookup.of(d1, d2, DIRECTIONS)
    got = lookup.values(table)
    assert got.shape == (2, 4, 3)
    for c in range(3):
        assert np.array_equal(got[..., c], lookup.values(np.ascontiguousarray(table[..., c])))


def test_the_box_clips_each_channel_and_the_fade_reaches_each_frames_fallback():
    from service.methods.pdm.validity import fade_detail

    fb = np.array([[[1.0, -1.0]], [[2.0, 0.0]]], np.float32)      # per frame (F=2,P=1,C=2)
    box = np.array([[[[-1.0, -1.0]]] * 2, [[[1.0, 0.5]]] * 2], np.float32)   # (2,F,P,C)
    big = np.float32(1e9)
    # inside the region: (1 + margin) × box = [−1.25, 1.25] × [−1.25, 0.625] per channel
    values = fb + np.array([[[0.5, 3.0]], [[-3.0, 0.1]]], np.float32)
    out = fade_detail(values.copy(), np.full((2, 1), 0.5, np.float32), np.full((2, 1), big), fb, 1.0, 0.25, box)
    assert out[0, 0] == pytest.approx(fb[0, 0] + [0.5, 0.625])
    assert out[1, 0] == pytest.approx(fb[1, 0] + [-1.25, 0.1])
    # detail within the box, inside the region: the values unchanged, bit for bit
    inside = fb + np.float32(0.1)
    assert np.array_equal(fade_detail(inside.copy(), np.full((2, 1), 0.5, np.float32), np.full((2, 1), big),
                                      fb, 1.0, 0.25, box), inside)
    # far outside (ρ ≥ 1 + width): exactly each frame's fallback
    far = fade_detail(values.copy(), np.full((2, 1), 2.5, np.float32), np.full((2, 1), big), fb, 1.0, 0.25, box)
    assert np.array_equal(far, fb)
