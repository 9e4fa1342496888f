"""Confidence of a synthesized frame: how far its deformation lies outside the training data.

One vocabulary for every marker-driven method (issue 17, "never worse than the input"):

* ``confidence`` (F,) float32 in [0, 1], one value per synthesized frame: 1 when the
  frame's deformation lies inside what the model was trained on, decreasing with the
  distance beyond it (the *range confidence*; the reported one also falls with the
  markers' noise and the deformation's size, below); ``confidence_vertices`` (F,n)
  float32 the same per vertex (the per-region confidence, at the finest region the method
  can resolve; the PDM's);
* a method whose detail can go wrong outside its training data fades that detail toward
  its *safe fallback* (the PDM: the thin shell of the detailed neutral and the static neutral map)
  by the confidence: ``fallback + c · (detail − fallback)`` (:func:`fade`), so a frame of
  confidence 0 is exactly the fallback — never worse than the input's large-scale motion.

Two rules of the excess e ≥ 0 (0 inside the training data) are declared here:
:func:`falloff` (compact: exactly 0 from ``e ≥ width`` on, used to fade; the PDM's, with e
the relative distance outside the hull of the point's training parameters,
:mod:`service.methods.pdm.validity`) and :func:`exponential` (``exp(−e/scale)``, pose space's
per-frame confidence, which fades its vertex corrections: ``pose_space.model``, confidence fade).

**The reported confidence** of every marker-driven kind that reports one (``pdm``, ``psd``,
``wpsd``; shape space reports none) is that *range confidence* times the *input factor* of
the frame's markers, declared here once (:class:`MarkerEvidence`):

    confidence = range confidence × n(σ̂) × g(‖u_H‖),

n the fraction of the marker space the frame's markers still determine over their own
noise estimate σ̂ (the residual against the learned marker prior), whatever
``marker_noise_mm`` the model denoises with (0 included), and g the *size factor* of the
frame's large-scale deformation u_H (the handle displacements that drive the thin shell)
against the learned prior's RMS deformation (:meth:`MarkerEvidence.size_factor`); both 1
without a learned prior (a model saved before it). The detail's fade (above) stays on the
range confidence: the reported confidence is the fade's confidence times n g. Fading by n as well was measured
worse on every noisy row of both families (``benchmarks/confidence_factors.py``, every
held-out map frame, PDM biquadratic, mean face vertex error: out of range a 0.523 → 0.636
mm, b 0.586 → 0.692 at ``marker_noise_mm`` = 0; a 0.337 → 0.471, b 0.408 → 0.534 with
``"auto"``; clean rows unchanged or worse by ≤ 0.011 mm): the markers' noise reaches the
surface whether or not the detail is faded, so fading only removes correct detail.

**Filtered takes.** A synthesis job's ``marker_filter_frames`` smooths a take in time
before the model sees it (:mod:`service.geometry.marker_filter`); ``"auto"`` smooths the
prior's floor directions the most, where σ̂ is read, so on the filtered frames a noisy
take's σ̂ fell to 0.05–0.11 mm, near a clean take's, while the noise the filter leaves sits
in the modes carrying the expression: with both ``auto`` settings the confidence ranked the
error out of range at ρ 0.22 (family a) and 0.38 (b). The job therefore passes the frames
as captured (``synthesize(..., captured=)``) and n reads their σ̂
(:meth:`~service.methods.pdm.base_surface.BaseSurface.captured_noise`): 0.74 and 0.77
(``benchmarks/generalization_report.py --pdm-only --marker-filter auto --marker-noise
auto --conditions clean noisy``; in range 0.72 → 0.74 and 0.33 → 0.70, combinations 0.59 →
0.64 and 0.08 → 0.32; WPSD + regression 0.28 → 0.72 and 0.16 → 0.76 out of range), with
every synthesized array unchanged (the denoiser keeps the filtered frames' σ̂). Plain WPSD,
whose error is mostly its own rather than the noise, ranks worse on family b (0.67 →
0.47). :func:`captured_frames` checks that they are the same frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.geometry.marker_prior import MarkerPrior, PriorEigen, dof_fraction, frame_noise
from service.methods.inputs import InvalidInput

#: result keys (API.md: per-frame arrays of the synthesize response)
CONFIDENCE = "confidence"
VERTEX_CONFIDENCE = "confidence_vertices"
#: κ of the size factor ``exp(−‖u_H‖ / (κ s))``, in units of the learned prior's RMS
#: displacement magnitude s (:meth:`MarkerEvidence.size_factor`; chosen on family a)
SIZE_SCALE = 3.5


def falloff(excess: np.ndarray, width: float, dtype=np.float64) -> np.ndarray:
    """Compact C¹ falloff (…) in [0, 1]: 1 for excess ≤ 0, 0 for excess ≥ width,
    ``1 − (3t² − 2t³)`` with ``t = excess / width`` between (a smoothstep), of ``dtype``
    (float64, or float32 for a per-texel pass: within 2 ulp of float32 of the float64 value).

    ``width = inf`` is 1 everywhere (no fade); ``width = 0`` a step at 0.
    """
    e = np.asarray(excess, dtype)
    if width <= 0:
        return (e <= 0).astype(dtype)
    t = np.clip(e / e.dtype.type(width), 0.0, 1.0)
    return 1.0 - t * t * (3.0 - 2.0 * t)


def exponential(excess: np.ndarray, scale: float) -> np.ndarray:
    """``exp(−excess / scale)`` (…): 1 at excess 0, 1/e at one ``scale`` beyond."""
    return np.exp(-np.asarray(excess, np.float64) / scale)


def frame_confidence(point_confidence: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Per-frame confidence (F,) as the ``weights``-weighted (P,) mean of point confidences (F,P)."""
    w = np.asarray(weights, np.float64)
    return np.asarray(point_confidence, np.float64) @ (w / w.sum())


def fade(detail: np.ndarray, fallback: np.ndarray, confidence: np.ndarray) -> np.ndarray:
    """``fallback + confidence · (detail − fallback)`` (broadcast): the detail at confidence 1,
    the fallback at 0."""
    return fallback + confidence * (detail - fallback)


def captured_frames(captured: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Markers as captured (F,M,3) (or one (M,3) frame), float64, for a request of marker
    frames of ``shape`` (F,M,3) that were smoothed from them; :class:`InvalidInput` naming
    both shapes unless they match."""
    frames = np.asarray(captured, np.float64)
    if frames.ndim == 2:
        frames = frames[None]
    if frames.shape != tuple(shape):
        raise InvalidInput(f"the captured markers have shape {frames.shape}, the filtered "
                           f"ones {tuple(shape)}: give the same frames before the filter")
    return frames


@dataclass(frozen=True)
class MarkerEvidence:
    """The input factor n g of a frame's reported confidence (module docstring), under the
    model's learned marker prior N(μ, C) (3M×3M): the *noise factor* n, the fraction of the
    marker space the frame's markers still determine over their own noise, times the *size
    factor* g of its large-scale deformation (below).

    ``noise_factor(u) = n(σ̂) = tr(C (C + σ̂² I)⁻¹) / 3M`` per frame of head-aligned marker
    displacements u (F,M,3), mm, NaN rows occluded: the Wiener filter's effective degrees of
    freedom over its dimension (Hastie, Tibshirani & Friedman, ESL eq. 3.50;
    :func:`~service.geometry.marker_prior.noise_confidence`) at the frame's own σ̂
    (:func:`~service.geometry.marker_prior.frame_noise`, which also sees what occlusion does
    to the visible residual). On the sample families' held-out frames: 0.18–0.37 at σ = 0.3
    mm; on clean markers a median of 0.86–1.0 per performance, down to 0.28 on frames far
    from the training span (family a's one-sided in-range expressions, σ̂ up to 0.34 mm:
    their off-span deformation reads as noise).

    Measured (``benchmarks/confidence_factors.py``, PDM biquadratic, Spearman ρ of 1 −
    confidence against the frame's mean face vertex error, clean / noisy / occluded frames
    pooled; every held-out map frame, 69–93 per range; issue 17's 8 frames a performance in
    the README): the noise factor lifts ρ at ``marker_noise_mm`` = 0 on both families (out of
    range a 0.70 → 0.89, b 0.66 → 0.71; in range a 0.71 → 0.87, b 0.64 → 0.71). An
    occlusion term — 1 minus the occluded markers' share of the frame's displacement energy
    Σ‖u_m‖² (completed by the prior), the visible fraction, or the prior's conditional
    variance share — was chosen against on family a (paired bootstrap 5–95 % of Δρ out of
    range −0.20…+0.02, −0.06…+0.01, 0.00) and did not help on b either (−0.23…+0.02,
    −0.04…+0.02, 0.00): σ̂ already rises on frames whose occlusion the prior completes
    badly. So there is none.

    **The size factor** ``g(u_H) = exp(−‖u_H‖ / (κ s))`` (:meth:`size_factor`), u_H (F,M,3)
    the frame's complete large-scale handle displacements (denoised where the model denoises,
    occluded markers completed), ‖·‖ the Euclidean norm over all 3M coordinates, s =
    ``sqrt(‖μ‖² + tr C)`` the prior's RMS displacement magnitude (the training frames' RMS
    ‖u‖ within the prior's floor: 34.0 against 33.9 mm on family a, 21.4 against 21.3 on b),
    κ = :data:`SIZE_SCALE`: 1 at the neutral, e^(−1/κ) = 0.75 at the training's RMS size.
    Why (issue 17): under ``marker_noise_mm = "auto"`` the denoiser brings the noisy frames
    near the clean ones, so the ranking *within* the clean frames decides, and what
    separates them is the size of the deformation — the thin shell's large-scale error, which
    the PDM corrects only in part, grows with it — not its distance beyond the training
    frames: the held-out out-of-range performances lie inside the training frames' marker
    envelope (‖u_H‖ a median 0.31–0.38 of the largest training frame's; per-marker
    magnitude, per-coordinate box and leading-direction Mahalanobis excesses beyond the
    training frames are 0 on most of them), and every such *excess* term left ρ out of range
    at 0.32–0.50 on family b (``auto``; 0.45 without), while ρ(‖u_H‖, error) on the clean
    frames is 0.60–0.89 (a) and 0.77–0.92 (b). So the term is not 1 on the training frames:
    a strong training expression reports its size too. κ chosen on family a (grid κ ∈ {2, 2.5, 3,
    3.5, 4, 5, 7.5, 10}: the highest mean ρ over the six cells of both ``marker_noise_mm``
    settings × three ranges with no cell lowered by more than 0.05) and confirmed on b:
    ρ out of range (every held-out map frame, ``benchmarks/confidence_factors.py``, range ×
    n before → range × n × g) at ``marker_noise_mm`` 0 a 0.90 → 0.85, b 0.71 → 0.77; with
    ``"auto"`` a 0.68 → 0.69, b 0.45 → 0.60; in range and combinations rise on both
    families, e.g. b ``auto`` 0.56 → 0.70 and 0.51 → 0.65 (README, "The confidence rule").

    Attributes
    ----------
    prior : MarkerPrior         the learned prior over head-aligned marker displacements
    eigen : PriorEigen          its eigendecomposition (n, and σ̂'s fill of occluded markers)
    basis : (3M,k) float64      its floor directions (σ̂)
    scale_mm : float            s, the prior's RMS displacement magnitude, mm (g)
    """

    prior: MarkerPrior
    eigen: PriorEigen
    basis: np.ndarray
    scale_mm: float

    @classmethod
    def of(cls, prior: MarkerPrior, eigen: PriorEigen | None = None) -> "MarkerEvidence":
        """Of a prior (``eigen``: its eigendecomposition, where already computed)."""
        eigen = PriorEigen.of(prior) if eigen is None else eigen
        scale = float(np.sqrt(np.sum(prior.mean ** 2) + np.trace(prior.covariance)))
        return cls(prior, eigen, eigen.floor_directions(), scale)

    def noise(self, u: np.ndarray) -> np.ndarray:
        """σ̂ (F,) mm of displacements u (F,M,3) (:func:`~service.geometry.marker_prior.frame_noise`)."""
        return frame_noise(self.prior, u, self.basis, self.eigen)

    def noise_factor(self, u: np.ndarray, sigma: np.ndarray | None = None) -> np.ndarray:
        """n(σ̂) (F,) float64 of displacements u (F,M,3) (or (M,3): a float), mm; ``sigma``
        (F,): the frames' σ̂ where already estimated."""
        s = self.noise(u) if sigma is None else np.asarray(sigma, np.float64)
        return dof_fraction(self.eigen.values, s)

    def size_factor(self, u_H: np.ndarray) -> np.ndarray:
        """g (F,) float64 of complete handle displacements u_H (F,M,3) (or (M,3): a float),
        mm: ``exp(−‖u_H‖ / (κ s))`` (class docstring)."""
        u_H = np.asarray(u_H, np.float64)
        size = np.sqrt(np.einsum("...mk,...mk->...", u_H, u_H))
        return exponential(size, SIZE_SCALE * self.scale_mm)

    def factor(self, u: np.ndarray, u_H: np.ndarray, sigma: np.ndarray | None = None) -> np.ndarray:
        """The input factor n g (F,) float64 of a frame's head-aligned marker displacements u
        (F,M,3), NaN rows occluded, and its complete handle displacements u_H (F,M,3), mm;
        ``sigma`` (F,): the frames' σ̂ where already estimated."""
        return self.noise_factor(u, sigma) * self.size_factor(u_H)
