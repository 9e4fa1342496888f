"""Rigid alignment of frames to the neutral before anything is encoded (bermano2014 §5.2, §5.5).

The paper aligns every smoothed input frame "to the database using the method of Horn
[1987]" and undoes the transform after reconstruction. The database frames carry head
motion too (a captured performance does), so they are aligned the same way: otherwise the
rotation logs of the shape space would encode head pose instead of expression.

What "aligned" means has to be chosen: expressions move the jaw and lips by centimetres,
so an unweighted fit over all vertices tilts the head when the mouth opens. Here every
vertex gets a stability weight ``1 / (m_i² + m̄²)`` from its RMS offset m_i from the
neutral over the database (m̄ the median), after an unweighted first fit, refined until
the weights settle — the per-vertex form of the marker weights of
:mod:`service.methods.pdm.base_surface`. The skull and ears then dominate the fit. On the
level-0 sample actor's database (63 frames, ground-truth head poses known) the mean
alignment error is 0.37 mm unweighted, 0.25 mm after one refinement and 0.23 mm
converged (3 refinements); what remains is the rig's own non-rigid motion of the head.
"""

from __future__ import annotations

import numpy as np

from service.geometry.rigid import RigidTransform, rigid_align_frames, stability_weights_from_rms


def align_frames(frames: np.ndarray, neutral: np.ndarray, weights: np.ndarray | None = None,
                 inplace: bool = False) -> tuple[np.ndarray, list[RigidTransform]]:
    """Weighted Horn/Kabsch alignment of every frame onto the neutral (bermano2014 §5.2).

    Parameters
    ----------
    frames : (F,n,3) float     vertices in correspondence with the neutral, mm
    neutral : (n,3) float      d0, mm
    weights : (n,) float | None   per-vertex weights (default uniform), e.g.
                               :func:`stability_weights`
    inplace : bool             overwrite ``frames`` (a float64 array) with the result, one
                               frame at a time (a 630-frame level-2 database is 2.7 GB)

    Returns
    -------
    aligned : (F,n,3) float64  ``T_f(frames[f])``
    transforms : list of F :class:`~service.geometry.rigid.RigidTransform`  frame → neutral;
                               ``T.inverse()`` restores the frame's pose
    """
    frames = np.asarray(frames, dtype=np.float64)
    if not len(frames):
        return frames.copy(), []
    R, t = rigid_align_frames(frames, neutral, weights)
    if inplace:
        if frames.dtype != np.float64:
            raise ValueError("inplace alignment needs float64 frames")
        for f in range(len(frames)):
            frames[f] = frames[f] @ R[f].T + t[f]
        aligned = frames
    else:
        aligned = frames @ np.swapaxes(R, 1, 2) + t[:, None, :]
    return aligned, [RigidTransform(R=r, t=x) for r, x in zip(R, t)]


def stability_weights(frames: np.ndarray, neutral: np.ndarray, refinements: int = 10,
                      rtol: float = 1e-3) -> np.ndarray:
    """Per-vertex alignment weights ``1 / (m_i² + m̄²)`` from the motion of the database.

    Parameters
    ----------
    frames : (F,n,3) float    database frames (world pose), mm
    neutral : (n,3) float     d0, mm
    refinements : int         at most this many re-fits with the weights of the previous
                              fit (the first fit is unweighted) — iteratively reweighted
                              least squares, which converges geometrically as the still
                              vertices' residuals (and so m̄) shrink
    rtol : float              stop when no weight changes by more than this (relative)

    Returns
    -------
    w : (n,) float64   mean 1; a vertex that never moves gets about 2× the weight of a
                       typical one, one moving 3× the median about a fifth
    """
    frames = np.asarray(frames, dtype=np.float64)
    neutral = np.asarray(neutral, dtype=np.float64)
    F = max(len(frames), 1)
    p2 = np.einsum("fnd,fnd->n", frames, frames)            # Σ_f |p_fi|², fixed
    w = None
    for _ in range(refinements + 1):
        R, t = rigid_align_frames(frames, neutral, w)
        # m_i² = (1/F) Σ_f |R_f p_fi + t_f − q_i|², expanded so that no aligned copy of
        # the frames is made: |Rp|² = |p|², and the cross terms contract over f (the
        # cancellation costs ~|p|²·1e-16 mm², far below the motions that set the weights)
        Rp, tp = np.zeros_like(neutral), np.zeros(len(neutral))
        for X, Rf, tf in zip(frames, R, t):
            Y = X @ Rf.T                                      # R_f p_fi
            Rp += Y                                           # Σ_f R_f p_fi
            tp += Y @ tf                                      # Σ_f t_f · R_f p_fi
        m2 = (p2 + 2 * tp - 2 * np.einsum("nd,nd->n", neutral, Rp)
              + F * np.einsum("nd,nd->n", neutral, neutral)
              - 2 * neutral @ t.sum(axis=0) + np.einsum("fd,fd->", t, t)) / F
        new = stability_weights_from_rms(np.sqrt(np.maximum(m2, 0.0)))
        if w is not None and np.max(np.abs(new - w) / w) < rtol:
            return new
        w = new
    return w
