import numpy as np

from service.geometry.deformation_gradient import rotation_exp
from service.geometry.surface_strain import StressField
from tests.methods.stress_blend.synthetic import actor


def _field(smoothing=0):
    a = actor()
    return a, StressField.build(a.vertices, a.faces, a.uv, a.uv_faces, smoothing)


def test_stress_zero_at_neutral_and_under_rigid_motion():
    a, sf = _field(3)
    assert np.abs(sf.stress(a.vertices)).max() < 1e-14
    R = rotation_exp([0.3, -1.2, 0.7])
    assert np.abs(sf.stress(a.vertices @ R.T + [10, 20, -5])).max() < 1e-12


def test_uniform_stretch_hand_computed():
    # stretch by λ along u (x): E_TT = ½(λ² − 1), E_BB = 0, E_TB = 0 at every vertex
    a, sf = _field(0)
    lam = 1.2
    X = a.vertices * [lam, 1.0, 1.0]
    s = sf.stress(X)
    np.testing.assert_allclose(s[:, 0], 0.5 * (lam ** 2 - 1), atol=1e-12)
    np.testing.assert_allclose(s[:, 1:], 0.0, atol=1e-12)
    # compression along v (y) by 0.9: E_BB = ½(0.81 − 1) = −0.095
    s = sf.stress(a.vertices * [1.0, 0.9, 1.0])
    np.testing.assert_allclose(s[:, 1], -0.095, atol=1e-12)
    # simple shear x += γ y: C = [[1, γ], [γ, 1 + γ²]] → E_TB = γ/2, stored as √2 γ/2
    g = 0.1
    X = a.vertices.copy()
    X[:, 0] += g * a.vertices[:, 1]
    s = sf.stress(X)
    np.testing.assert_allclose(s[:, 2], np.sqrt(2) * g / 2, atol=1e-12)
    np.testing.assert_allclose(s[:, 1], 0.5 * g * g, atol=1e-12)


def test_smoothing_keeps_uniform_stress_and_batches_frames():
    a, sf = _field(5)
    X = np.stack([a.vertices * [1.1, 1, 1], a.vertices * [1, 0.8, 1]])
    s = sf.stress(X)
    assert s.shape == (2, len(a.vertices), 3)
    np.testing.assert_allclose(s[0, :, 0], 0.5 * (1.21 - 1), atol=1e-12)
    np.testing.assert_allclose(s[1], sf.stress(X[1]), atol=0)


def test_the_compiled_strain_is_the_numpy_strain():
    """stress32 (the compiled kernels, service.geometry.strain_kernels) against stress on a
    random smooth deformation, with and without smoothing: float32 rounding apart; and the
    hand-computed uniform stretch."""
    rng = np.random.default_rng(4)
    for steps in (0, 2):
        a, sf = _field(steps)
        X = a.vertices + 2.0 * np.sin(a.vertices[:, [1, 2, 0]] / 15.0 + rng.normal(size=3))
        want = sf.stress(X)
        np.testing.assert_allclose(sf.stress32(X), want, atol=1e-6 * max(1.0, np.abs(want).max()))
        assert sf.stress32(X).dtype == np.float32 and sf.smoothed == (steps > 0)
    a, sf = _field(0)
    s = sf.stress32(a.vertices * [1.2, 1.0, 1.0])
    np.testing.assert_allclose(s[:, 0], 0.5 * (1.2 ** 2 - 1), atol=1e-6)
    np.testing.assert_allclose(s[:, 1:], 0.0, atol=1e-6)
