"""The medium band's cross-validated fit skill per UV point, and the gain it gives (issue 17).

ma2008 §4.2 fits one polynomial in (d1, d2) per point by regularized least squares and
evaluates it wherever (d1, d2) lands; nothing says how well the polynomial predicts a frame
it was not fitted to. Where the point's detail is not a function of (d1, d2) of that order
(lip and mouth-corner points of family a: training R² ≈ 0.45 against 0.86 at the median
point), held-out frames inside the training range got medium detail of the right size but
110–120° off in direction, and the PDM's max vertex error exceeded the thin shell's.

The skill of a point is measured at training by leaving one frame out — the PRESS residuals
of the point's least squares (:func:`.polynomial.loo_residuals`) — against the detail the
safe fallback leaves, the thin shell of the detailed neutral (:func:`.model.shell_fallback`,
what the PDM must never be worse than):

    skill_p = 1 − Σ_t,c e₍₋ₜ₎² / Σ_t,c (f_t − b_t)²        (f the targets, b the fallback)

1 where the polynomial predicts every left-out frame exactly; ≤ 0 where it predicts them no
better than the fallback does.

Which frames to leave out, measured on family a (level 0, biquadratic, 11.4k UV points):

* one frame (chosen): median skill 0.85, 5th percentile 0.60; vertex 6417 (lip) 0.39. The
  training clips ramp up and down through the same poses, so each frame has a near-twin in
  its clip and this is close to the training R²; it finds points whose detail is not a
  polynomial of (d1, d2) at all, not points whose polynomial fails on other expressions;
* one clip, scored only where the frame lies inside the other clips' validity hull
  (:func:`.validity.training_hull`, ρ ≤ 1; without that restriction it measures
  extrapolation, 3–100 mm): median −0.21, 62 % of the points below 0 — the polynomial of
  the other expressions predicts a clip's poses worse than the thin shell at most points —
  so any gain from it took most of the medium detail: held-out in-range mean face error
  0.187 → 0.253 mm (gain = skill), 0.230 (gain = clip((skill + 1) / 2, 0, 1)), against the
  thin shell's 0.265.

The worst vertices of the held-out frames above the thin shell's max (every map frame, three
ranges × three marker conditions) have leave-one-frame-out skills of 0.39–0.96, median ≈ 0.8
(a), and 0.08–0.96, median ≈ 0.6 (b): most are points that fit their training well and fail
on expressions the training never combined, which no per-point statistic of the training
fit sees; the gain removes the failures at the poorly fitted points (6417).

At synthesis the point's medium detail is blended towards its fallback by the gain

    g_p = clip((skill_p − s₀) / (1 − s₀), 0, 1),   value = b + g_p (D − b)

with s₀ the ``fit_skill_floor`` (:class:`.params.PdmParams`): points that predict well keep
their detail (g = 1 only where the skill is 1), points whose skill is at or below s₀ get
the fallback's.
"""

from __future__ import annotations

import numpy as np


def fit_skill(loo: np.ndarray, targets: np.ndarray, baseline: np.ndarray) -> np.ndarray:
    """Cross-validated skill (module docstring) per point.

    Parameters
    ----------
    loo : (T,P,C)            held-out residuals (:func:`.polynomial.loo_residuals`; NaN:
                             not scored, left out of both sums)
    targets : (T,P,C)        the fitted targets f
    baseline : (T,P,C)       the fallback's prediction b of the same frames

    Returns
    -------
    skill : (P,) float64     ``1 − Σ e² / Σ (f − b)²`` over frames and channels (NaN rows left
                             out); 1 where both sums are 0 (a point the fallback and the fit
                             both reproduce), −inf where only the fallback's is 0
    """
    e = np.asarray(loo, np.float64)
    scored = np.isfinite(e)
    e = np.where(scored, e, 0.0)
    r = np.where(scored, np.asarray(targets, np.float64) - np.asarray(baseline, np.float64), 0.0)
    press = np.einsum("tpc,tpc->p", e, e)
    base = np.einsum("tpc,tpc->p", r, r)
    with np.errstate(divide="ignore", invalid="ignore"):
        skill = 1.0 - press / base
    return np.where(press == 0, 1.0, skill)


def skill_gain(skill: np.ndarray, floor: float) -> np.ndarray:
    """The gain (P,) float32 ``clip((skill − floor) / (1 − floor), 0, 1)`` (module docstring)
    of ``skill`` (P,) for a ``floor`` s₀ < 1."""
    if not floor < 1:
        raise ValueError(f"the skill floor must be < 1, got {floor}")
    return np.clip((np.asarray(skill, np.float64) - floor) / (1.0 - floor), 0.0, 1.0).astype(np.float32)
