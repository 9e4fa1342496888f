"""Family b's detail: strain, direction-selective creases, pores, albedo response."""

import numpy as np

from service.samples.family_b import detail as D
from tests.samples.family_b.test_mesh import _grid


def _sheet():
    V, T = _grid(6)
    return V * 5.0, T                      # a flat 30 mm sheet facing +z


def test_strain_is_the_identity_at_rest_and_exact_for_a_uniaxial_stretch():
    V, T = _sheet()
    op = D.StrainOperator.build(V, T)
    c0 = op.tensors(V[None])[:, 0]
    np.testing.assert_allclose(c0, np.array([[1.0], [1.0], [0.0]]) * np.ones(len(V)), atol=1e-12)
    # t1 = t2 × n with t2 = up (y), n = z: t1 = x; squeeze y by 0.8, stretch x by 1.1
    c = op.tensors((V * [1.1, 0.8, 1.0])[None])[:, 0]
    np.testing.assert_allclose(c, np.array([[1.21], [0.64], [0.0]]) * np.ones(len(V)), atol=1e-12)
    l1, l2, psi = D.principal(c)
    np.testing.assert_allclose([l1[0], l2[0], psi[0]], [1.1, 0.8, np.pi / 2], atol=1e-12)
    np.testing.assert_allclose(D.area_ratio(c), 0.88, atol=1e-12)


def test_creases_vanish_at_rest_and_follow_the_compression_direction():
    V, T = _sheet()
    P = V + [0, 0, 60.0]
    lm = D.Landmarks(np.zeros((68, 3)), np.zeros(3), 80.0)
    patterns = D.bank_patterns(P, lm, seed=1)
    amp = np.full(len(P), 1.0)
    rest = np.array([[1.0], [1.0], [0.0]]) * np.ones(len(P))
    h0, a0 = D.crease_height(rest, patterns, amp)
    assert np.abs(h0).max() == 0 and np.abs(a0).max() == 0
    vertical = np.array([[1.0], [0.75 ** 2], [0.0]]) * np.ones(len(P))      # squeezed along y
    horizontal = np.array([[0.75 ** 2], [1.0], [0.0]]) * np.ones(len(P))    # squeezed along x
    for c, bank in ((vertical, D.BANKS // 2), (horizontal, 0)):
        w = D.bank_weights(D.principal(c)[2])
        # 30° apart, cos^12: the bank across the compression takes 1 / (1 + 2 cos¹²30° + 2 cos¹²60°)
        expected = 1 / (1 + 2 * np.cos(np.pi / 6) ** 12 + 2 * np.cos(np.pi / 3) ** 12)
        assert np.all(np.argmax(w, axis=0) == bank)
        np.testing.assert_allclose(w[bank], expected, rtol=1e-9)
        h, _ = D.crease_height(c, patterns, amp)
        r = D.response(np.array(0.25))
        np.testing.assert_allclose(h, r * np.einsum("bk,bk->k", w, patterns), rtol=1e-5, atol=1e-6)
    assert not np.allclose(D.crease_height(vertical, patterns, amp)[0],
                           D.crease_height(horizontal, patterns, amp)[0], atol=0.05)


def test_response_has_a_threshold_and_a_convex_onset():
    k = np.array([0.0, D.ONSET, D.ONSET + 0.01, D.ONSET + 0.02, 0.2])
    r = D.response(k)
    assert r[0] == 0 and r[1] == 0 and np.all(np.diff(r[1:]) > 0) and r[-1] < 1
    assert r[3] > 2 * r[2]                        # exponent 1.5: doubling the excess more than doubles R


def test_cusp_profile_floor_and_ridge():
    np.testing.assert_allclose(D.cusp(np.array([0.0, 3.0, -2.0])), -1.0)
    e = np.exp(-0.5 / D.CREASE_DECAY)
    np.testing.assert_allclose(D.cusp(np.array([0.5, 2.5])), -e + D.RIDGE * (1 - e))


def test_pores_deepen_under_compression_and_open_slower_than_the_skin():
    p = D.Pores(np.array([[0.2], [0.0]], np.float32), np.array([[1.0], [0.0]], np.float32),
                np.array([0.3], np.float32), np.array([0.1], np.float32))
    iso = lambda s: np.array([[s * s], [s * s], [0.0]])
    h1, J1 = D.pore_height(p, iso(1.0))
    # at rest: r² = (0.2/ (1.7·0.3))², h = −0.1 (1 − r²)²
    r2 = (0.2 / (D.PORE_ELONGATION * 0.3)) ** 2
    np.testing.assert_allclose(h1, -0.1 * (1 - r2) ** 2, rtol=1e-6)
    hs, Js = D.pore_height(p, iso(1.2))
    # stretched by 1.2: J = 1.44, distances grow 1.2×, the footprint only 1.2^0.5×
    r2s = r2 * 1.2 ** (2 * (1 - D.PORE_BETA))
    np.testing.assert_allclose(hs, -0.1 / 1.44 * (1 - r2s) ** 2, rtol=1e-5)
    hc, _ = D.pore_height(p, iso(0.85))
    assert abs(hs[0]) < abs(h1[0]) < abs(hc[0])


def test_albedo_darkens_with_compression_and_blanches_with_stretch():
    base = np.tile(D.SKIN_BASE, (3, 1))
    out = D.skin_albedo(base, np.array([0.7, 1.0, 1.4]), np.zeros(3), np.zeros(3))
    np.testing.assert_allclose(out[1], D.SKIN_BASE)
    assert np.all(out[0] < out[1]) and np.all(out[2] > out[1])
    np.testing.assert_allclose(out[0] / out[1], 0.7 ** 0.35)             # hue kept: darker only
