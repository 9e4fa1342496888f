"""Wrinkle-map regions: a few masks and, per frame, one weight per region and expression.

Real-time engines do not evaluate per-vertex stress similarity; they blend each expression
map with ``mask_r(uv) · ω_rk(t)`` for a handful of static masks (Jimenez et al. 2011,
"Practical and realistic facial wrinkles animation"; MetaHuman's animated maps). This
module turns the per-vertex blend weights of :mod:`.weights` into that form:

* **masks** (training): k-means (k-means++, seeded) on the feature
  ``(p_i, α · tanh(s_k,i / s₀) for every expression k)``, rest position and the scans'
  saturated local stresses (α = ``region_stress_scale_mm``, s₀ = :data:`STRESS_SATURATION`;
  without the saturation the few vertices of extreme strain, at the mouth corners, take
  the clusters), run on the *active* vertices (where some expression changes the maps:
  importance above :data:`ACTIVE_IMPORTANCE`) so the regions are spent where the wrinkles
  are; every vertex then joins its nearest cluster centre. A region is compact and moves
  one way in every scan;
  the one-hot labels are softened by ``mask_smoothing`` uniform Laplacian steps (each step
  averages rows of a partition of unity, so the masks stay one);
* **region weights** (per frame): for each expression k the weights ω_·k minimize the
  weighted squared error ``Σ_i a_i δ_ik (w_ik − Σ_r m_ir ω_rk)²`` with a_i the vertex area
  and δ_ik how much expression k changes the maps at vertex i (its squared map difference
  from the neutral, normalized), so the fit is spent where an expression has detail. The
  normal equations depend on the masks only: the per-frame fit is one (R,n) product per
  expression (:class:`RegionFit`). Weights are clipped to [0, 1] and, where a region's
  expression weights sum above 1, scaled to sum to 1 (the engine's neutral weight
  ``1 − Σ_k`` stays non-negative).

An engine reproduces the blend as ``M = M_0 + Σ_k (Σ_r mask_r ω_rk) (M_k − M_0)``
(:func:`engine_weights`); the report measures what this costs against the per-vertex blend.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.geometry.curvature_flow import uniform_smoothing_operator

#: relative ridge of the region normal equations (regions an expression never reaches)
RIDGE = 1e-9
#: strain at which the clustering feature saturates (tanh(s / s₀)); wrinkles buckle at ~0.05
STRESS_SATURATION = 0.05
#: a vertex takes part in the clustering when some expression's normalized importance exceeds this
ACTIVE_IMPORTANCE = 0.1


def region_masks(neutral: np.ndarray, faces: np.ndarray, scan_stress: np.ndarray, regions: int,
                 stress_scale_mm: float, smoothing: int, seed: int,
                 importance: np.ndarray | None = None) -> np.ndarray:
    """Soft region masks (n,R) float64, rows summing to 1 (module docstring).

    scan_stress : (K,n,3) the expressions' local stresses (neutral excluded)
    importance : (K,n) normalized map change per expression (None: every vertex is active)
    """
    n = len(neutral)
    feats = np.concatenate([neutral, stress_scale_mm * np.tanh(
        scan_stress.transpose(1, 0, 2).reshape(n, -1) / STRESS_SATURATION)], axis=1)
    active = (np.ones(n, bool) if importance is None
              else np.asarray(importance).max(axis=0) > ACTIVE_IMPORTANCE)
    if active.sum() < regions:
        active = np.ones(n, bool)
    R = min(regions, int(active.sum()))
    if R == 1:
        labels = np.zeros(n, np.int64)
    else:
        from scipy.cluster.vq import kmeans2  # imported here: serve's start never needs it (issue 23's cold start)

        centres, _ = kmeans2(feats[active], R, minit="++", rng=np.random.default_rng(seed), missing="warn")
        d2 = (np.sum(feats ** 2, axis=1)[:, None] - 2 * feats @ centres.T
              + np.sum(centres ** 2, axis=1)[None])
        labels = np.argmin(d2, axis=1)
    used = np.unique(labels)
    labels = np.searchsorted(used, labels)
    m = np.zeros((n, len(used)))
    m[np.arange(n), labels] = 1.0
    step = uniform_smoothing_operator(faces, n)
    for _ in range(smoothing):
        m = step @ m
    return m / m.sum(axis=1, keepdims=True)


@dataclass(frozen=True)
class RegionFit:
    """The per-frame least-squares fit of region weights (module docstring).

    projector : (K,R,n) float64   ω_·k = projector[k] @ w_·k
    """

    projector: np.ndarray

    @classmethod
    def build(cls, masks: np.ndarray, importance: np.ndarray, area: np.ndarray) -> "RegionFit":
        """masks (n,R); importance (K,n) δ_ik ≥ 0; area (n,) vertex areas."""
        K = len(importance)
        R = masks.shape[1]
        P = np.empty((K, R, len(masks)))
        for k in range(K):
            a = area * importance[k]
            N = masks.T @ (a[:, None] * masks)
            N += RIDGE * max(np.trace(N) / R, 1e-300) * np.eye(R)
            P[k] = np.linalg.solve(N, masks.T * a[None])
        return cls(P)

    def fit(self, weights: np.ndarray) -> np.ndarray:
        """Region weights (F,R,K) of per-vertex blend weights (F,n,S) (neutral first, S = K+1)."""
        w = np.asarray(weights)[..., 1:]                                  # (F,n,K)
        om = np.einsum("krn,fnk->frk", self.projector, w)
        om = np.clip(om, 0.0, 1.0)
        tot = om.sum(axis=-1, keepdims=True)
        return om / np.maximum(tot, 1.0)


def engine_weights(masks: np.ndarray, region_weights: np.ndarray) -> np.ndarray:
    """Per-point weights (F,P,S) an engine evaluates from masks (P,R) and region weights
    (F,R,K): expression k gets Σ_r mask_r ω_rk, the neutral 1 − Σ_k of those."""
    wk = np.einsum("pr,frk->fpk", masks, region_weights)
    return np.concatenate([1.0 - wk.sum(axis=-1, keepdims=True), wk], axis=-1)
