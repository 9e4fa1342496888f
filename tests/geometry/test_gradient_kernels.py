"""service.geometry.gradient_kernels: the compiled Newton iteration of the polar
decomposition and the decoding, against the vectorized NumPy passes they replaced (written
out here as the references)."""

from __future__ import annotations

import numpy as np

from service.geometry.deformation_gradient import POLAR_MAX_ITERATIONS, POLAR_TOLERANCE
from service.geometry.gradient_kernels import decode_rows, newton_rotations


def _numpy_steps(G: np.ndarray, iterations: int = POLAR_MAX_ITERATIONS):
    """The vectorized iteration as ``polar_decomposition`` ran it before: (k,9) R, fallback."""
    X = G.reshape(-1, 9).T.copy()

    def cofactors(X):
        return np.stack([
            X[4] * X[8] - X[5] * X[7], X[5] * X[6] - X[3] * X[8], X[3] * X[7] - X[4] * X[6],
            X[2] * X[7] - X[1] * X[8], X[0] * X[8] - X[2] * X[6], X[1] * X[6] - X[0] * X[7],
            X[1] * X[5] - X[2] * X[4], X[2] * X[3] - X[0] * X[5], X[0] * X[4] - X[1] * X[3]])

    out = X
    proper = (X[0] * (X[4] * X[8] - X[5] * X[7]) - X[1] * (X[3] * X[8] - X[5] * X[6])
              + X[2] * (X[3] * X[7] - X[4] * X[6])) > 0
    out[:, ~proper] = np.eye(3).reshape(9, 1)
    active = np.arange(out.shape[1])
    for _ in range(iterations):
        cof = cofactors(X)
        det = X[0] * cof[0] + X[1] * cof[1] + X[2] * cof[2]
        zeta = np.cbrt(det)
        Y = 0.5 * (X / zeta + cof * (zeta / det))
        going = np.abs(Y - X).max(axis=0) > POLAR_TOLERANCE
        out[:, active] = Y
        if not going.any():
            active = active[:0]
            break
        if not going.all():
            active, Y = active[going], Y[:, going]
        X = Y
    fallback = ~proper
    fallback[active] = True
    return np.ascontiguousarray(out.T), fallback


def _run(G: np.ndarray, iterations: int = POLAR_MAX_ITERATIONS):
    R = np.empty((len(G), 9))
    fallback = newton_rotations(np.ascontiguousarray(G.reshape(-1, 9)), POLAR_TOLERANCE, iterations, R)
    return R, fallback


def test_the_compiled_iteration_is_the_numpy_steps_within_two_ulp():
    """Random, ill-conditioned (condition up to 1e8), singular-row, negative-determinant and
    NaN matrices: the same fallbacks, and the rotations within 4.4e-16 (2 ulp of 1; NumPy's
    SIMD cube root is up to 3 ulp from libm's, so not bit for bit); identity where det <= 0."""
    rng = np.random.default_rng(0)
    G = np.eye(3) + 0.3 * rng.standard_normal((20000, 3, 3))
    G[:300] = rng.standard_normal((300, 3, 3)) * np.array([1, 1e-5, 1e3])[None, :, None]
    G[300:320, 0] = 0.0                                   # singular: det 0
    G[320:340, 0, 0] = np.nan
    reference, expected = _numpy_steps(G)
    R, fallback = _run(G)
    np.testing.assert_array_equal(fallback, expected)
    assert 0 < fallback.sum() < len(G) // 4
    ok = ~fallback
    assert np.abs(R[ok] - reference[ok]).max() <= 2 * np.spacing(1.0)
    negative = np.flatnonzero(np.linalg.det(G) <= 0)
    np.testing.assert_array_equal(R[negative], np.broadcast_to(np.eye(3).ravel(), (len(negative), 9)))


def test_a_matrix_not_converged_in_the_allowed_steps_falls_back():
    G = np.diag([100.0, 1.0, 0.01])[None]
    R, fallback = _run(G, iterations=2)
    assert fallback.tolist() == [True]
    R, fallback = _run(G)
    assert fallback.tolist() == [False]
    np.testing.assert_allclose(R.reshape(3, 3), np.eye(3), rtol=0, atol=1e-15)


def _numpy_decode(w: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``decode``'s vectorized passes as they were: (k,9)."""
    x, y, z = w.T
    th2 = x * x + y * y + z * z
    th = np.sqrt(th2)
    small = th < 1e-4
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - np.cos(ths)) / (ths * ths))
    c = 1.0 - b * th2
    bx, by, bz = b * x, b * y, b * z
    ax, ay, az = a * x, a * y, a * z
    R = ((c + bx * x, bx * y - az, bx * z + ay),
         (bx * y + az, c + by * y, by * z - ax),
         (bx * z - ay, by * z + ax, c + bz * z))
    e = s.T
    S = ((e[0], e[1], e[2]), (e[1], e[3], e[4]), (e[2], e[4], e[5]))
    return np.stack([R[i][0] * S[0][j] + R[i][1] * S[1][j] + R[i][2] * S[2][j]
                     for i in range(3) for j in range(3)], axis=1)


def test_the_compiled_decoding_is_the_numpy_passes_bit_for_bit():
    """Rotations of every size (small-angle series below 1e-4, near π) and stretches."""
    rng = np.random.default_rng(1)
    w = rng.standard_normal((30000, 3)) * np.repeat([1e-6, 0.3, 1.0, 3.0], 7500)[:, None]
    s = 1.0 + 0.2 * rng.standard_normal((30000, 6))
    out = np.empty((len(w), 9))
    decode_rows(w, s, out)
    np.testing.assert_array_equal(out, _numpy_decode(w, s))
