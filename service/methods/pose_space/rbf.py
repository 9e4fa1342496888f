"""Radial-basis-function fitting of pose-space detail (bickel2008 §5.2, eq. 2 and 5).

The detail of a pose with features f is ``d(f) = Σ_j w_j φ(‖f − f_j‖)`` with the
biharmonic kernel φ(r) = r (eq. 2; [CBC*01]). For WPSD (eq. 5) every vertex has its own
distance ‖·‖_v and weights w_v,j, so all functions here are batched: a leading axis B runs
over independent systems (vertices, texels, or B = 1 for PSD, whose one system is shared by
all vertices).

* :func:`solve_weights` — the weights of P basis poses, either interpolating them exactly
  (the P×P system Φ w = d) or fitting T ≫ P training frames in the least-squares sense.
  Smoothing λ (Tikhonov): ``(ΦᵀΦ + λ̂ I) w = Φᵀ d`` with λ̂ = λ · tr(ΦᵀΦ)/P, relative to
  the mean diagonal so that λ means the same for any kernel scale (scaling every distance
  by s scales w by 1/s and leaves d(f) unchanged — in particular WPSD with all α equal is
  PSD, whose distances are √E larger). Least squares always carries a floor
  ``RIDGE_FLOOR`` (nearly dependent columns stay solvable).
* :func:`greedy_basis` — the greedy selection of §5.2 ([CBC*01]): start from the rest pose,
  repeatedly add the training frame with the largest error and refit, until the relative
  error reaches a threshold or the basis its size.
* :func:`gram_factor` — the residual of any linear fit depends on the targets D (T,C) only
  through their Gram matrix D Dᵀ, so PSD's selection over all 3n coordinates runs on a
  (T,T) factor of it.

Departure: the paper does not regularize; with noisy markers the interpolant of nearby
example poses has large opposite weights that pass feature noise straight into the
detail, so λ is chosen by validation (``model.train``).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from service.methods.pose_space.params import RIDGE_FLOOR


def kernel(r: np.ndarray) -> np.ndarray:
    """The biharmonic RBF kernel φ(r) = r of §5.2."""
    return r


def solve_weights(Phi: np.ndarray, D: np.ndarray, smoothing: float = 0.0,
                  exact: bool = False) -> np.ndarray:
    """RBF weights W of batched systems Φ W ≈ D.

    Parameters
    ----------
    Phi : (B,T,P) float   kernel values φ(‖f_t − f_j‖) of T fitted poses and P basis poses
    D : (B,T,C) float     targets at the T poses (C = 3 per vertex, 1 per texel, 3n for PSD)
    smoothing : float     relative ridge λ (module docstring), ≥ 0
    exact : bool          T ≤ P and the basis poses are interpolated: with λ = 0 the
                          square system is solved as it is (no normal equations), a wide
                          one (T < P: kernel plus polynomial columns, :mod:`.polynomial`)
                          by its minimum-norm solution Φᵀ(ΦΦᵀ)⁻¹D; a singular one (a
                          single pose: φ(0) = 0 makes it [0]) falls back to the ridge floor

    Returns
    -------
    W : (B,P,C) float64
    """
    Phi = np.asarray(Phi, dtype=np.float64)
    D = np.asarray(D, dtype=np.float64)
    T, P = Phi.shape[1:]
    if exact and smoothing == 0:
        try:
            if T == P:
                return np.linalg.solve(Phi, D)
            if T < P:                       # with the polynomial: the minimum-norm interpolant
                Xt = Phi.transpose(0, 2, 1)
                return Xt @ np.linalg.solve(Phi @ Xt, D)
        except np.linalg.LinAlgError:       # one pose (φ(0) = 0) or duplicated poses
            pass
    PhiT = Phi.transpose(0, 2, 1)
    G = PhiT @ Phi                                          # batched GEMM (BLAS per system)
    lam = max(smoothing, RIDGE_FLOOR) * np.trace(G, axis1=1, axis2=2) / P
    G[:, np.arange(P), np.arange(P)] += np.maximum(lam, np.finfo(float).tiny)[:, None]
    return np.linalg.solve(G, PhiT @ D)


def residual_sq(Phi: np.ndarray, D: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Squared residual per fitted pose, summed over batch and channels: (T,)."""
    R = np.asarray(D, np.float64) - Phi @ W
    return np.einsum("btc,btc->t", R, R)


def columns(Phi: np.ndarray, Q: np.ndarray | None) -> np.ndarray:
    """The design matrix (B,T,P+q): kernel columns Phi (B,T,P) and polynomial columns Q
    (B or 1,T,q) (:func:`.polynomial.design`), or Phi alone."""
    if Q is None:
        return Phi
    return np.concatenate([Phi, np.broadcast_to(Q, Phi.shape[:2] + Q.shape[2:])], axis=2)


def fit_basis(Phi: np.ndarray, D: np.ndarray, selected, smoothing: float, exact: bool,
              Q: np.ndarray | None = None) -> np.ndarray:
    """Weights (B,P+q,C) for the basis ``selected`` (P,) — columns of Phi (B,T,P) in that order —
    and the polynomial columns Q (B,T,q) if given, by exact interpolation of the selected
    frames or least squares over all T frames."""
    X = columns(Phi, Q)
    if exact:
        sel = np.asarray(selected)
        return solve_weights(X[:, sel], D[:, sel], smoothing, exact=True)
    return solve_weights(X, D, smoothing)


def greedy_basis(column: Callable[[int], np.ndarray], D: np.ndarray, size: int, first: int,
                 smoothing: float = 0.0, exact: bool = False,
                 threshold: float = 0.0, Q: np.ndarray | None = None) -> tuple[list[int], list[float]]:
    """Greedy basis selection of §5.2 ([CBC*01]).

    Parameters
    ----------
    column : callable      ``column(j)`` → (B,T) kernel values φ(‖f_t − f_j‖) of every
                           training frame t against candidate basis pose j
    D : (B,T,C) float      targets of the T training frames
    size : int             largest basis size P (≤ T)
    first : int            the first basis pose (the rest pose)
    smoothing, exact       as :func:`solve_weights`
    threshold : float      stop once the relative RMS error ``‖R‖/‖D‖`` is ≤ this
    Q : (B,T,q) or None    polynomial columns fitted with every basis (:mod:`.polynomial`)

    Returns
    -------
    selected : list of P int     training frames in the order they were added
    errors : list of P float     relative RMS error over all T frames after each addition
    """
    D = np.asarray(D, dtype=np.float64)
    B, T, _ = D.shape
    size = min(size, T)
    total = max(float(np.einsum("btc,btc->", D, D)), np.finfo(float).tiny)
    Phi = np.empty((B, T, size))
    selected, errors = [], []
    j = int(first)
    for p in range(size):
        Phi[:, :, p] = column(j)
        selected.append(j)
        W = fit_basis(Phi[:, :, :p + 1], D, selected, smoothing, exact, Q)
        err = residual_sq(columns(Phi[:, :, :p + 1], Q), D, W)
        errors.append(float(np.sqrt(err.sum() / total)))
        if errors[-1] <= threshold or p + 1 == size:
            break
        err[selected] = -1.0
        j = int(np.argmax(err))
    return selected, errors


def gram_factor(K: np.ndarray) -> np.ndarray:
    """A (T,T) matrix Y with ``Y Yᵀ = K`` for the Gram matrix K = D Dᵀ (T,T) of targets D
    (T,C): a fit's residual norms per frame are the same for Y as for D, at (T,T) instead
    of (T,C) cost."""
    K = np.asarray(K, dtype=np.float64)
    lam, U = np.linalg.eigh(0.5 * (K + K.T))
    return U * np.sqrt(np.maximum(lam, 0.0))
