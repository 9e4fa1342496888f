"""The per-matrix work of :mod:`service.geometry.deformation_gradient`'s encoding, compiled
(issue 23: the shape-space ``/enhance`` frame): the Newton iteration of
:func:`~service.geometry.deformation_gradient.polar_decomposition` and the decoding of
:func:`~service.geometry.deformation_gradient.decode`.

Newton iteration (:func:`newton_rotations`).
Higham's scaled Newton iteration ``X ← ½(ζX + ζ⁻¹X⁻ᵀ)``, ``ζ = |det X|^(-1/3)`` (Higham
1986, §3), one 3×3 matrix at a time in registers: the same float64 operations in the same
order as the vectorized NumPy steps it replaces (the cofactors, ``det = X₀c₀ + X₁c₁ + X₂c₂``,
``ζ = cbrt(det)``, ``Y = 0.5 (X/ζ + c (ζ/det))``, stopped when no entry moved by more than
the tolerance, or when a NaN appeared — NumPy's ``max`` then is NaN and ``NaN > tol`` is
false), compiled without fast-math. Not bit for bit: ζ's cube root is libm's, where NumPy's
``cbrt`` is its AVX-512 SIMD one (up to 3 ulp apart), so the rotations are within 4.4e-16
(2 ulp of 1) of the NumPy steps' (tests/geometry/test_gradient_kernels.py). The NumPy steps made a (9,k) temporary per
operation and step over all k matrices still iterating; on the 89k triangles of a level-1
frame the iteration was the largest item of a shape-space enhancement (cProfile: 4.3 of
20.3 s for 30 frames with the cofactors' stacks and the maxima).

Decoding (:func:`decode_rows`): ``exp(w) S`` per matrix, the entry-by-entry Rodrigues
formula and product of ``decode``'s NumPy passes (the same float64 operations in the same
order, libm's sin and cos, which NumPy's float64 passes use too here): bit for bit, 89k
matrices 47 → 4.5 ms under load 8 (the NumPy passes wrote ~40 (k,) temporaries).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(nogil=True, cache=True, error_model="numpy")
def newton_rotations(G, tolerance, max_iterations, R):
    """Rotation factors of the proper matrices among ``G`` (k,9) float64 (row-major entries).

    Writes R (k,9): the converged Newton iterate of each matrix with ``det G > 0``, the
    identity for the others; returns (k,) bool, True where the caller must use the SVD
    instead (``det G <= 0``, or not converged in ``max_iterations`` steps).
    """
    k = G.shape[0]
    fallback = np.zeros(k, np.bool_)
    for i in range(k):
        x0, x1, x2, x3, x4, x5, x6, x7, x8 = (G[i, 0], G[i, 1], G[i, 2], G[i, 3], G[i, 4],
                                              G[i, 5], G[i, 6], G[i, 7], G[i, 8])
        det0 = (x0 * (x4 * x8 - x5 * x7) - x1 * (x3 * x8 - x5 * x6)
                + x2 * (x3 * x7 - x4 * x6))
        if not det0 > 0:
            R[i, 0], R[i, 1], R[i, 2] = 1.0, 0.0, 0.0
            R[i, 3], R[i, 4], R[i, 5] = 0.0, 1.0, 0.0
            R[i, 6], R[i, 7], R[i, 8] = 0.0, 0.0, 1.0
            fallback[i] = True
            continue
        converged = False
        for _ in range(max_iterations):
            c0 = x4 * x8 - x5 * x7
            c1 = x5 * x6 - x3 * x8
            c2 = x3 * x7 - x4 * x6
            c3 = x2 * x7 - x1 * x8
            c4 = x0 * x8 - x2 * x6
            c5 = x1 * x6 - x0 * x7
            c6 = x1 * x5 - x2 * x4
            c7 = x2 * x3 - x0 * x5
            c8 = x0 * x4 - x1 * x3
            det = x0 * c0 + x1 * c1 + x2 * c2
            zeta = np.cbrt(det)
            q = zeta / det
            y0 = 0.5 * (x0 / zeta + c0 * q)
            y1 = 0.5 * (x1 / zeta + c1 * q)
            y2 = 0.5 * (x2 / zeta + c2 * q)
            y3 = 0.5 * (x3 / zeta + c3 * q)
            y4 = 0.5 * (x4 / zeta + c4 * q)
            y5 = 0.5 * (x5 / zeta + c5 * q)
            y6 = 0.5 * (x6 / zeta + c6 * q)
            y7 = 0.5 * (x7 / zeta + c7 * q)
            y8 = 0.5 * (x8 / zeta + c8 * q)
            going = False
            nan = False
            for d in (abs(y0 - x0), abs(y1 - x1), abs(y2 - x2), abs(y3 - x3), abs(y4 - x4),
                      abs(y5 - x5), abs(y6 - x6), abs(y7 - x7), abs(y8 - x8)):
                if d != d:
                    nan = True
                elif d > tolerance:
                    going = True
            x0, x1, x2, x3, x4, x5, x6, x7, x8 = y0, y1, y2, y3, y4, y5, y6, y7, y8
            if nan or not going:
                converged = True
                break
        R[i, 0], R[i, 1], R[i, 2] = x0, x1, x2
        R[i, 3], R[i, 4], R[i, 5] = x3, x4, x5
        R[i, 6], R[i, 7], R[i, 8] = x6, x7, x8
        fallback[i] = not converged
    return fallback


@njit(nogil=True, cache=True, error_model="numpy")
def decode_rows(w, s, out):
    """``out[t]`` (9,) = the row-major entries of ``exp(w[t]) S(s[t])``: w (k,3) rotation
    logs, s (k,6) the stretches' upper triangles (S00 S01 S02 S11 S12 S22), float64; the
    operations of :func:`service.geometry.deformation_gradient.decode` in its order."""
    for t in range(w.shape[0]):
        x, y, z = w[t, 0], w[t, 1], w[t, 2]
        th2 = x * x + y * y + z * z
        th = np.sqrt(th2)
        if th < 1e-4:
            a = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
            b = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
        else:
            a = np.sin(th) / th
            b = (1.0 - np.cos(th)) / (th * th)
        c = 1.0 - b * th2
        bx, by, bz = b * x, b * y, b * z
        ax, ay, az = a * x, a * y, a * z
        r00, r01, r02 = c + bx * x, bx * y - az, bx * z + ay
        r10, r11, r12 = bx * y + az, c + by * y, by * z - ax
        r20, r21, r22 = bx * z - ay, by * z + ax, c + bz * z
        e0, e1, e2, e3, e4, e5 = s[t, 0], s[t, 1], s[t, 2], s[t, 3], s[t, 4], s[t, 5]
        out[t, 0] = r00 * e0 + r01 * e1 + r02 * e2
        out[t, 1] = r00 * e1 + r01 * e3 + r02 * e4
        out[t, 2] = r00 * e2 + r01 * e4 + r02 * e5
        out[t, 3] = r10 * e0 + r11 * e1 + r12 * e2
        out[t, 4] = r10 * e1 + r11 * e3 + r12 * e4
        out[t, 5] = r10 * e2 + r11 * e4 + r12 * e5
        out[t, 6] = r20 * e0 + r21 * e1 + r22 * e2
        out[t, 7] = r20 * e1 + r21 * e3 + r22 * e4
        out[t, 8] = r20 * e2 + r21 * e4 + r22 * e5
