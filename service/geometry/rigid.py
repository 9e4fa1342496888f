"""Weighted rigid (optionally similarity) alignment of corresponding point sets.

Finds the rotation R (det R = +1), translation t and, optionally, uniform scale s that
minimize ``Σ_i w_i ‖s R p_i + t − q_i‖²`` in closed form: the weighted cross-covariance's
SVD (Kabsch 1976; Horn 1987 solves the same problem with quaternions) with the
reflection fix and the scale of Umeyama 1991 ("Least-squares estimation of transformation
parameters between two point patterns", IEEE PAMI 13(4), eqs. 40-42). Used to remove rigid
head motion before anything measures deformation (DESIGN.md) and to put it back after.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: fewest valid correspondences accepted (3 non-collinear points fix a rotation)
MIN_POINTS = 3


@dataclass(frozen=True)
class RigidTransform:
    """``x ↦ s R x + t`` (a rigid motion when s = 1).

    Attributes
    ----------
    R : (3,3) float64   rotation, det = +1
    t : (3,) float64    translation, units of the points (mm)
    s : float           uniform scale (1.0 unless estimated)
    """

    R: np.ndarray
    t: np.ndarray
    s: float = 1.0

    def apply(self, X: np.ndarray) -> np.ndarray:
        """Transform points X (...,3) — one point set (n,3) or frames (F,n,3) — to (...,3) float64."""
        X = np.asarray(X, dtype=np.float64)
        if X.shape[-1] != 3:
            raise ValueError(f"points must be (...,3), got {X.shape}")
        return self.s * (X @ self.R.T) + self.t

    __call__ = apply

    def inverse(self) -> "RigidTransform":
        """The transform undoing this one: ``x ↦ (1/s) Rᵀ (x − t)``."""
        Rt = self.R.T
        return RigidTransform(R=Rt, t=-(Rt @ self.t) / self.s, s=1.0 / self.s)

    def matrix(self) -> np.ndarray:
        """Homogeneous (4,4) matrix ``[[s R, t], [0, 1]]``."""
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.t
        return M


def rigid_align(
    P: np.ndarray, Q: np.ndarray, weights: np.ndarray | None = None, scale: bool = False
) -> RigidTransform:
    """Least-squares rigid (or similarity) transform taking P onto Q (Kabsch / Umeyama 1991).

    Minimizes ``Σ_i w_i ‖s R p_i + t − q_i‖²`` over rotations R (det R = +1, never a
    reflection), translations t and, if ``scale``, s > 0.

    Parameters
    ----------
    P : (n,3) float         source points, e.g. markers of a frame, mm
    Q : (n,3) float         corresponding target points, e.g. the same markers at rest, mm
    weights : (n,) float    non-negative per-point weights (default all 1)
    scale : bool            also estimate a uniform scale (Umeyama 1991, eq. 42)

    Returns
    -------
    RigidTransform
        ``T.apply(P) ≈ Q``.

    Raises
    ------
    ValueError
        mismatched shapes, negative or non-finite weights, fewer than ``MIN_POINTS`` valid
        rows, or all valid source points coincide.

    Notes
    -----
    Rows where P or Q has a NaN (occluded markers) or whose weight is 0 are ignored.
    With R = U S Vᵀ from the SVD of the weighted cross-covariance Σ = Σ w (q−q̄)(p−p̄)ᵀ,
    S = diag(1, 1, sign det(U Vᵀ)) (Umeyama eq. 39-40), and ``s = tr(D S) / σ_p²``
    (eq. 42) with σ_p² the weighted variance of P. For collinear points the rotation
    about their line is not determined; the SVD returns one of the minimizers.
    """
    P = np.asarray(P, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or P.shape != Q.shape:
        raise ValueError(f"P and Q must both be (n,3), got {P.shape} and {Q.shape}")
    if weights is None:
        w = np.ones(len(P))
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (len(P),):
            raise ValueError(f"weights must be ({len(P)},), got {w.shape}")
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise ValueError("weights must be finite and non-negative")
    valid = np.isfinite(P).all(axis=1) & np.isfinite(Q).all(axis=1) & (w > 0)
    if valid.sum() < MIN_POINTS:
        raise ValueError(f"need at least {MIN_POINTS} valid correspondences (finite, weight > 0), "
                         f"got {int(valid.sum())} of {len(P)}")
    P, Q, w = P[valid], Q[valid], w[valid] / w[valid].sum()
    p_mean = w @ P
    q_mean = w @ Q
    Pc = P - p_mean
    Qc = Q - q_mean
    sigma = (Qc * w[:, None]).T @ Pc                    # (3,3) cross-covariance
    U, D, Vt = np.linalg.svd(sigma)
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2] = -1.0
    R = (U * S) @ Vt
    s = 1.0
    if scale:
        var_p = float(w @ np.einsum("nd,nd->n", Pc, Pc))
        if var_p <= 0:
            raise ValueError("all valid source points coincide; scale is undefined")
        s = float(D @ S) / var_p
    t = q_mean - s * (R @ p_mean)
    return RigidTransform(R=R, t=t, s=s)


def rigid_align_frames(P: np.ndarray, Q: np.ndarray, weights: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rigid_align` of many frames onto one target at once (no NaN rows, no scale).

    The weighted means and cross-covariances of all frames come from two contractions
    over the frames, so nothing of size (F,n,3) is allocated besides the input.

    Parameters
    ----------
    P : (F,n,3) float     source frames (all finite), mm
    Q : (n,3) float       the common target, mm
    weights : (n,) float  non-negative per-point weights (default all 1), not all 0

    Returns
    -------
    R : (F,3,3) float64   rotations, det +1
    t : (F,3) float64     translations: ``P[f] @ R[f].T + t[f] ≈ Q``
    """
    P = np.asarray(P, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != Q.shape or Q.shape[1:] != (3,):
        raise ValueError(f"P must be (F,n,3) and Q (n,3), got {P.shape} and {Q.shape}")
    w = np.ones(len(Q)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(Q),) or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError(f"weights must be ({len(Q)},), finite, non-negative, not all 0")
    w = w / w.sum()
    p_mean = np.matmul(w, P)                                           # (F,3)
    q_mean = w @ Q
    # Σ_f = Σ_i w_i (q_i − q̄)(p_fi − p̄_f)ᵀ = Σ_i w_i (q_i − q̄) p_fiᵀ  (batched GEMM)
    sigma = np.matmul(((Q - q_mean) * w[:, None]).T, P)               # (F,3,3)
    U, _, Vt = np.linalg.svd(sigma)
    S = np.ones((len(P), 3))
    S[np.linalg.det(U) * np.linalg.det(Vt) < 0, 2] = -1.0
    R = (U * S[:, None, :]) @ Vt
    t = q_mean - np.einsum("fde,fe->fd", R, p_mean)
    return R, t


def stability_weights_from_rms(m: np.ndarray) -> np.ndarray:
    """Weights ``1 / (m_i² + m̄²)`` (n,) float64, normalized to mean 1, from the RMS offsets
    m (n,) of points from their rest positions after alignment; m̄ is the median of m.

    A point that never moves gets about 2× the weight of a typical one, one moving 3× the
    median about a fifth, so the moving parts of a face do not drag its head pose
    (ma2008 §4.1's stable markers; bermano2014 §5.2's stable vertices).
    """
    med = max(float(np.median(m)), 1e-9)
    w = 1.0 / (m ** 2 + med ** 2)
    return w / w.mean()
