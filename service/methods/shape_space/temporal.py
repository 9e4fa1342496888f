"""Temporal enhancement: sequence projection and keyframe retiming (bermano2014 §6, eq. 5–6).

Sequences are given as compressed shape-space vectors (rows), compared in a weighted
norm ``‖x‖²_Ω = Σ_c Ω_c x_c²`` (Ω = a region's patch weights repeated per component, so
every region is projected independently, as §6.1 prescribes).

* :func:`segment_projection` — eq. 5: every input frame α_i projected onto every linear
  segment {β_j, β_{j+1}} of a database sequence: the blend weight T_ij of β_j (the convex
  projection of §5.3 restricted to two frames has a closed form, a clamped ratio) and the
  distance E_ij of the projected point.
* :func:`monotonic_assignment` — eq. 6: the non-decreasing segment assignment P minimizing
  Σ_i E_{i,P(i)}, by dynamic programming (``C_i = E_i + cummin(C_{i-1})``, O(m·n)).
* :func:`sequence_projection` — both, giving each input frame a time ``P(i) + (1 − T_i)`` on
  the continuous timeline sampled by β.
* :func:`retime` — §6.2: the keyframe pair projected onto every database sequence, the best
  one's matched subsequence (optionally extended to the full motion), its dynamics
  transferred to the linear interpolation of the keyframes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np


def _weighted(x: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
    return x if weights is None else x * np.sqrt(np.asarray(weights, dtype=np.float64))


def segment_projection(alpha: np.ndarray, beta: np.ndarray, weights: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Projection of every input frame on every segment of a sequence (bermano2014 eq. 5).

    Parameters
    ----------
    alpha : (m,k) float     input sequence (compressed shape vectors)
    beta : (n,k) float      database sequence, n ≥ 2
    weights : (k,) float | None   Ω, non-negative (default 1)

    Returns
    -------
    T : (m,n-1) float64   weight of β_j in the closest point ``T β_j + (1 − T) β_{j+1}``, in [0, 1]
    E : (m,n-1) float64   its distance ``‖α_i − (T β_j + (1 − T) β_{j+1})‖_Ω``

    Notes
    -----
    ``Proj(α_i, {β_j, β_{j+1}})`` is the convex projection of §5.3 on two frames:
    ``T = clamp(⟨α_i − β_{j+1}, β_j − β_{j+1}⟩ / ‖β_j − β_{j+1}‖², 0, 1)`` (T = 1 for a
    segment of length 0). Distances are computed from the differences, row by row, not
    from Gram entries, so they stay accurate near 0.
    """
    A = _weighted(np.asarray(alpha, dtype=np.float64), weights)
    B = _weighted(np.asarray(beta, dtype=np.float64), weights)
    if B.shape[0] < 2:
        raise ValueError(f"a sequence needs at least 2 frames, got {B.shape[0]}")
    e = B[:-1] - B[1:]                                         # (n-1,k)
    ee = np.einsum("jk,jk->j", e, e)
    T = np.empty((len(A), len(e)))
    E = np.empty_like(T)
    for i, a in enumerate(A):
        r = a - B[1:]                                          # (n-1,k)
        t = np.where(ee > 0, np.einsum("jk,jk->j", r, e) / np.where(ee > 0, ee, 1.0), 1.0)
        t = np.clip(t, 0.0, 1.0)
        T[i] = t
        E[i] = np.linalg.norm(r - t[:, None] * e, axis=1)
    return T, E


def monotonic_assignment(E: np.ndarray) -> tuple[np.ndarray, float]:
    """Non-decreasing assignment P minimizing ``Σ_i E[i, P(i)]`` (bermano2014 eq. 6).

    Parameters
    ----------
    E : (m,s) float   cost of assigning input frame i to segment j

    Returns
    -------
    P : (m,) int64    ``P(0) ≤ P(1) ≤ …``; among equal-cost assignments the earliest segments
    cost : float      the minimum
    """
    E = np.asarray(E, dtype=np.float64)
    m, s = E.shape
    C = np.empty_like(E)
    C[0] = E[0]
    for i in range(1, m):
        C[i] = E[i] + np.minimum.accumulate(C[i - 1])
    P = np.empty(m, dtype=np.int64)
    P[-1] = int(np.argmin(C[-1]))
    for i in range(m - 1, 0, -1):
        P[i - 1] = int(np.argmin(C[i - 1][:P[i] + 1]))
    return P, float(C[-1, P[-1]])


@dataclass(frozen=True)
class SequenceProjection:
    """Result of :func:`sequence_projection`.

    segment : (m,) int     P(i), the segment {β_P, β_P+1} of every input frame
    blend : (m,) float     T_i, the weight of β_P(i)
    times : (m,) float     ``P(i) + (1 − T_i)``, on β's timeline (frame units, 0 … n−1)
    error : float          ``Σ_i E_{i,P(i)}`` (eq. 6)
    """

    segment: np.ndarray
    blend: np.ndarray
    times: np.ndarray
    error: float


def sequence_projection(alpha: np.ndarray, beta: np.ndarray, weights: np.ndarray | None = None
                        ) -> SequenceProjection:
    """Project a sequence onto a database sequence, preserving temporal order (bermano2014 §6.1).

    Parameters
    ----------
    alpha : (m,k) float;  beta : (n,k) float, n ≥ 2;  weights : (k,) float | None  (Ω)
    """
    T, E = segment_projection(alpha, beta, weights)
    P, cost = monotonic_assignment(E)
    t = T[np.arange(len(P)), P]
    return SequenceProjection(P, t, P + (1.0 - t), cost)


def sample_sequence(beta: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Points (len(times),k) of the piecewise-linear curve through β (n,k) at continuous times."""
    beta = np.asarray(beta, dtype=np.float64)
    times = np.clip(np.asarray(times, dtype=np.float64), 0.0, len(beta) - 1)
    j = np.minimum(np.floor(times).astype(np.int64), len(beta) - 2)
    f = (times - j)[:, None]
    return (1.0 - f) * beta[j] + f * beta[j + 1]


def extend_to_full_motion(beta: np.ndarray, start: float, end: float,
                          weights: np.ndarray | None = None) -> tuple[float, float]:
    """Extend a matched subsequence [start, end] to the whole monotonic motion it belongs to.

    bermano2014 §6.2 lets the user "extend the matched subsequence to the full corresponding
    database motion" (Figure 7: the match covers the first part of a smile; the extension
    the whole smile). The paper does not define "the motion"; here it is the longest stretch
    around the match over which the progress ``π(t) = ⟨β(t) − β(start), β(end) − β(start)⟩_Ω
    / ‖β(end) − β(start)‖²_Ω`` keeps moving the same way: back from ``start`` while π
    decreases, forward from ``end`` while it increases (to the database's frames, i.e.
    to the neighbouring local extrema of π).

    Parameters
    ----------
    beta : (n,k) float;  start, end : float, times on β's timeline with start < end
    weights : (k,) float | None   Ω

    Returns
    -------
    (start, end) : floats, the extended span (frame units)
    """
    B = _weighted(np.asarray(beta, dtype=np.float64), weights)
    a, b = sample_sequence(B, [start, end])
    d = b - a
    dd = float(d @ d)
    if dd <= 0:
        return start, end
    pi = (B - a) @ d / dd                                      # (n,)
    j0 = int(np.floor(start))
    while j0 > 0 and pi[j0 - 1] < pi[j0]:
        j0 -= 1
    j1 = int(np.ceil(end))
    while j1 < len(B) - 1 and pi[j1 + 1] > pi[j1]:
        j1 += 1
    return float(min(j0, start)), float(max(j1, end))


@dataclass(frozen=True)
class Retiming:
    """Result of :func:`retime`.

    progress : (m,) float     blend fraction of output frame k: ``(1 − s_k) α_0 + s_k α_{m−1}``;
                              ``s_0 = 0``, ``s_{m−1} = 1``, non-decreasing
    timestamps : (m,) float   the time (output frame units, 0 … m−1) at which the uniformly
                              interpolated keyframe blend ``i/(m−1)`` is shown: t(β̂_i) of §6.2
    sequence : int            index of the chosen database sequence
    span : (float, float)     the (possibly extended) subsequence, on that sequence's timeline
    error : float             the keyframe pair's projection error (eq. 6) on it
    """

    progress: np.ndarray
    timestamps: np.ndarray
    sequence: int
    span: tuple[float, float]
    error: float


def retime(key0: np.ndarray, key1: np.ndarray, sequences: Sequence[np.ndarray], length: int,
           weights: np.ndarray | None = None, extend: bool = False) -> Retiming:
    """Data-driven timing of the interpolation between two keyframes (bermano2014 §6.2).

    1. The pair {α_0, α_{m−1}} is projected (:func:`sequence_projection`) onto every database
       sequence; the one with the smallest error gives the matched subsequence
       β = [t(α_0), t(α_{m−1})] on its timeline (optionally extended,
       :func:`extend_to_full_motion`).
    2. β̂_i, i = 0 … m−1, uniformly interpolates β's ends; projecting β̂ onto β places each
       on β's continuous timeline, t(β̂_i) (the dynamics: where β moves fast, consecutive
       β̂_i land close in time).
    3. The linear interpolation α̂_i of the keyframes gets the times t(β̂_i), normalized to
       [0, m−1]; the piecewise-linear curve is resampled at the m uniform output times,
       which gives each output frame its keyframe blend fraction.

    Parameters
    ----------
    key0, key1 : (k,) float         the keyframes' compressed shape vectors
    sequences : list of (n_s,k)     database sequences, each n_s ≥ 2
    length : int                    m ≥ 2, frames of the result (keyframes included)
    weights : (k,) float | None     Ω (a region's weights, or None for all components)
    extend : bool                   extend the matched subsequence to the full motion

    Returns
    -------
    Retiming

    Notes
    -----
    Departures: a matched subsequence of (near) zero length — both keyframes projecting to
    the same point — carries no dynamics, and the timing stays linear. The times t(β̂_i) are
    made non-decreasing (running maximum) before resampling; the monotonic projection
    guarantees it for the segments, but two frames on one segment can swap.
    """
    if length < 2:
        raise ValueError(f"length must be >= 2, got {length}")
    if not sequences:
        raise ValueError("need at least one database sequence")
    pair = np.stack([np.asarray(key0, dtype=np.float64), np.asarray(key1, dtype=np.float64)])
    projections = [sequence_projection(pair, seq, weights) for seq in sequences]
    best = int(np.argmin([p.error for p in projections]))
    beta = np.asarray(sequences[best], dtype=np.float64)
    s0, s1 = (float(x) for x in projections[best].times)
    linear = np.linspace(0.0, 1.0, length)
    if s1 - s0 <= 1e-9:
        return Retiming(linear, linear * (length - 1), best, (s0, s1), projections[best].error)
    if extend:
        s0, s1 = extend_to_full_motion(beta, s0, s1, weights)
    # the subsequence as a sampled curve on its own timeline
    inner = np.arange(np.ceil(s0), np.floor(s1) + 1.0)
    times = np.unique(np.r_[s0, inner, s1])
    curve = sample_sequence(beta, times)
    ends = sample_sequence(beta, [s0, s1])
    beta_hat = (1.0 - linear)[:, None] * ends[0] + linear[:, None] * ends[1]
    proj = sequence_projection(beta_hat, curve, weights)
    j = proj.segment
    tau = times[j] + (1.0 - proj.blend) * (times[j + 1] - times[j])
    u = np.clip((tau - s0) / (s1 - s0), 0.0, 1.0)
    u = np.maximum.accumulate(u)
    u[0], u[-1] = 0.0, 1.0
    # resample the curve (u_i, i/(m-1)) at the uniform output times; ties made strictly increasing
    u_strict = u + np.arange(length) * 1e-12
    u_strict[-1] = max(u_strict[-1], 1.0)
    progress = np.interp(linear, u_strict, linear)
    progress[0], progress[-1] = 0.0, 1.0
    return Retiming(progress, u * (length - 1), best, (s0, s1), projections[best].error)


# ---------------------------------------------------------------------------- keyframe sequences
def keyframe_indices(keyframes: int, length: int) -> np.ndarray:
    """Output frame (K,) int64 of each of K keyframes in m = ``length`` frames:
    ``⌊k (m−1)/(K−1) + ½⌋`` (see :func:`retime_keyframes`)."""
    k = np.arange(keyframes)
    return np.floor(k * (length - 1) / (keyframes - 1) + 0.5).astype(np.int64)


def retime_keyframes(model, keyframes: np.ndarray, length: int,
                     extend: bool = False) -> dict[str, np.ndarray]:
    """Retime K ≥ 2 keyframes into ``length`` frames, segment by segment (bermano2014 §6.2
    extended from a pair to a sequence of keyframes).

    Keyframe k is placed at output frame ``i_k = ⌊k (m − 1) / (K − 1) + ½⌋`` (i_0 = 0,
    i_{K−1} = m − 1, strictly increasing for m ≥ K), and each consecutive pair is retimed by
    the model over its segment of ``i_{k+1} − i_k + 1`` frames; neighbouring segments share
    their end frame, which is taken from the later segment (its first frame, exactly the
    keyframe). Two keyframes are one segment: the result is the model's own.

    Parameters
    ----------
    model : a model with ``retime(keyframes (2,n,3), length, extend) -> dict`` and ``faces``
    keyframes : (K,n,3) float   on the model's topology, world pose, actor's unit
    length : int                m ≥ K, output frames
    extend : bool               extend each matched subsequence to the full database motion

    Returns
    -------
    dict with ``vertices`` (m,n,3) float32 (keyframe k exactly at ``keyframe_indices[k]``);
    ``timestamps`` (m,) float64, output frame units (segment times offset by the segment's
    first frame); ``progress`` (m,) float64, keyframe units (k + the segment's blend
    fraction: 0 … K−1); ``region_progress`` (R,m) likewise per region;
    ``keyframe_indices`` (K,) int64; per segment ``segment_sequences`` (K−1,R) int64 (the
    database sequence each region matched) and ``segment_spans`` (K−1,R,2) (the matched
    span on it); ``region_names`` (R,); ``faces`` (T,3) int32
    """
    K = len(keyframes)
    index = keyframe_indices(K, length)
    parts: dict[str, list[np.ndarray]] = {"vertices": [], "timestamps": [], "progress": [],
                                          "region_progress": []}
    sequences, spans = [], []
    result: dict[str, np.ndarray] = {}
    for k in range(K - 1):
        result = model.retime(keyframes[k:k + 2], int(index[k + 1] - index[k] + 1), extend)
        # a shared end frame appears once: as the first frame of the next segment
        keep = slice(None) if k == K - 2 else slice(None, -1)
        parts["vertices"].append(result["vertices"][keep])
        parts["timestamps"].append(index[k] + np.asarray(result["timestamps"])[keep])
        parts["progress"].append(k + np.asarray(result["progress"])[keep])
        parts["region_progress"].append(k + np.asarray(result["region_progress"])[:, keep])
        sequences.append(result["region_sequences"])
        spans.append(result["region_spans"])
    return {
        "vertices": np.concatenate(parts["vertices"]).astype(np.float32, copy=False),
        "timestamps": np.concatenate(parts["timestamps"]),
        "progress": np.concatenate(parts["progress"]),
        "region_progress": np.concatenate(parts["region_progress"], axis=1),
        "keyframe_indices": index,
        "segment_sequences": np.stack(sequences).astype(np.int64),
        "segment_spans": np.stack(spans),
        "region_names": result["region_names"],
        "faces": np.asarray(model.faces, dtype=np.int32),
    }
