"""The PDM's base surface: rigid head motion removed, a smooth neutral deformed to the markers.

ma2008 §4 (Figure 2): displacements are measured against "a neutral mesh deformed to
match the motion capture markers" by the linear thin shell of Bickel et al., and "rather
than applying the thin shell deformation to a detailed neutral mesh, we instead deform a
smooth neutral mesh". Per frame:

1. head pose: the rigid transform taking the frame's markers onto the neutral markers
   (weighted Kabsch, :func:`head_alignment`), applied to markers and meshes;
2. base surface: ``X_t = X̄ + B u_H(t)``, the thin-shell deformation (bickel2008 §4, basis
   B) of the smooth neutral X̄, driven by the aligned markers' displacements
   ``u_H = R(P_t) − P_ref`` at their handle vertices;
3. tangent frames of ``X_t`` (:class:`~service.geometry.tangent_frames.FrameField`), in
   which displacements are expressed so that the model is invariant to local rotation.

Choices where the paper is silent:

* the smooth neutral is the bermano2014 §4.2 frequency separation (one implicit
  curvature-flow step and one uniform Laplacian step) of the detailed neutral;
* the head pose uses stability weights: after an unweighted fit, each marker is weighted by
  ``1 / (m_i² + m̄²)`` with m_i its RMS offset from the neutral over the training frames
  and m̄ the median of the m_i, so markers on the jaw and lips, which move with the
  expression, do not drag the head estimate (:func:`stability_weights`);
* a marker's handle is the vertex of its triangle nearest to it; missing (NaN) markers are
  completed from the visible ones, by the learned marker prior's conditional mean where the
  model has one (:class:`~service.geometry.marker_prior.PriorCompletion`), else by the
  shell's minimum energy (:func:`~service.geometry.thin_shell.complete_handles`).

Marker noise (issue 17): with ``marker_noise_mm`` σ > 0 the handles are no longer
interpolated exactly but are the MAP estimate under the shell prior
(:func:`~service.geometry.thin_shell.soft_handles`, weight λ = σ²/τ² with the prior scale τ
estimated on the training frames, :meth:`BaseSurface.with_marker_noise`), and the marker
positions every feature is computed from are the denoised ones
(:meth:`BaseSurface.denoised_markers`), in training and synthesis alike. When the base
carries a learned marker prior (fitted on the aligned training markers by
:meth:`BaseSurface.with_marker_noise`, :mod:`service.geometry.marker_prior`), the MAP
estimate is under that prior instead (:class:`~service.geometry.marker_prior.MarkerDenoiser`);
a model saved before the prior existed has none and keeps the shell-prior estimate. The
choice is :func:`~service.geometry.marker_prior.marker_denoiser`'s, shared with shape space's
marker shell. With ``marker_noise_mm = "auto"`` σ is estimated per request from the markers'
residual against the learned prior (:class:`~service.geometry.marker_prior.AdaptiveDenoiser`,
:meth:`BaseSurface.with_noise_estimate`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from service.errors import InvalidInput
from service.geometry.curvature_flow import LAMBDA_DT, frequency_separation
from service.geometry.marker_filter import MarkerModes
from service.geometry.marker_prior import (
    AUTO, AdaptiveDenoiser, MarkerDenoiser, MarkerPrior, ShellDenoiser, marker_denoiser,
)
from service.geometry.rigid import MIN_POINTS, rigid_align, stability_weights_from_rms
from service.geometry.tangent_frames import FrameField
from service.geometry.thin_shell import (
    KB, KS, apply_basis, handle_energy_matrix, marker_noise_ratio, shell_prior_scale, thin_shell_basis,
)
from service.methods.confidence import MarkerEvidence, captured_frames

#: a frame needs at least this many visible markers (rigid fit and thin shell)
MIN_VISIBLE_MARKERS = max(MIN_POINTS, 4)


class TooFewMarkers(InvalidInput):
    """A frame has too few visible markers to be aligned and deformed.

    Attributes: ``frame`` (int), ``visible`` (int), ``required`` (int).
    """

    def __init__(self, frame: int, visible: int, required: int = MIN_VISIBLE_MARKERS):
        super().__init__(f"frame {frame} has {visible} visible markers, at least {required} "
                         f"are needed")
        self.frame, self.visible, self.required = frame, visible, required


@dataclass(frozen=True)
class HeadPose:
    """Per-frame rigid transforms taking world markers onto the neutral: ``x_n = R x + t``.

    R : (F,3,3) float64 rotations;  t : (F,3) float64 translations, mm
    """

    R: np.ndarray
    t: np.ndarray

    def __getitem__(self, frames) -> "HeadPose":
        """The poses of a slice or index array of frames."""
        return HeadPose(self.R[frames], self.t[frames])

    def remove(self, X: np.ndarray) -> np.ndarray:
        """World points X (F,k,3) → neutral-aligned ``R X + t`` (F,k,3)."""
        return np.einsum("fij,fkj->fki", self.R, X) + self.t[:, None, :]

    def restore(self, X: np.ndarray) -> np.ndarray:
        """Neutral-aligned points X (F,k,3) → world ``Rᵀ (X − t)`` (F,k,3)."""
        return np.einsum("fji,fkj->fki", self.R, X - self.t[:, None, :])

    def restore32(self, X: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """:meth:`restore` in float32 (F,k,3), into ``out`` if given: ``X − t`` rounded to
        float32, then one batched float32 product ``(X − t) R`` (row vectors: ``Rᵀ (X − t)``
        per point). What synthesis returns is float32 anyway; this skips the float64
        ``einsum`` and the cast (issue 23: 2.8 → 0.5 ms CPU per level-1 frame under load).

        Bound (tests): per point within ``2⁻²⁰ ‖X − t‖`` of the float64 :meth:`restore`
        (rounding X − t, R and the 3-term sums, each ≤ 2⁻²⁴ relative; 1.9e-4 mm at
        200 mm, measured ≤ 3.1e-5 mm on points of ~80 mm scale)."""
        Y = np.subtract(X, self.t[:, None, :], out=np.empty(np.shape(X), np.float32),
                        casting="same_kind")
        return np.matmul(Y, self.R.astype(np.float32), out=out)



def head_alignment(markers: np.ndarray, rest: np.ndarray,
                   weights: np.ndarray | None = None) -> HeadPose:
    """Rigid head pose of every frame by weighted Kabsch against the neutral markers (ma2008 §4.1).

    Parameters
    ----------
    markers : (F,M,3) float    world marker positions, NaN rows for occluded markers, mm
    rest : (M,3) float         neutral marker positions P_ref, mm
    weights : (M,) float       per-marker weights (default 1), e.g. :func:`stability_weights`

    Raises
    ------
    TooFewMarkers   a frame has fewer than ``MIN_VISIBLE_MARKERS`` visible markers
    """
    markers = np.asarray(markers, dtype=np.float64)
    nf = len(markers)
    visible = np.isfinite(markers).all(axis=2).sum(axis=1)
    R, t = np.empty((nf, 3, 3)), np.empty((nf, 3))
    for f in range(nf):
        if visible[f] < MIN_VISIBLE_MARKERS:
            raise TooFewMarkers(f, int(visible[f]))
        T = rigid_align(markers[f], rest, weights)
        R[f], t[f] = T.R, T.t
    return HeadPose(R, t)


def stability_weights(aligned: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """Marker weights (M,) from the RMS offsets of aligned markers (F,M,3) from ``rest``
    (:func:`~service.geometry.rigid.stability_weights_from_rms`; occluded samples skipped)."""
    d = np.asarray(aligned, dtype=np.float64) - rest
    m = np.sqrt(np.nanmean(np.einsum("fmd,fmd->fm", d, d), axis=0))
    m = np.nan_to_num(m, nan=np.nanmax(m) if np.isfinite(m).any() else 1.0)
    return stability_weights_from_rms(m)


def training_head_pose(markers: np.ndarray, rest: np.ndarray,
                       names: Sequence[str]) -> tuple[HeadPose, np.ndarray]:
    """Head pose of training frames (F,M,3) and the marker stability weights (M,) it used.

    An unweighted alignment first, then :func:`stability_weights` from its residuals, then
    the weighted alignment (ma2008 §4.1), so expressive markers do not drag the head.
    ``names`` (F,) name the frames in the :class:`InvalidInput` of a frame with too few
    visible markers.
    """
    try:
        pose = head_alignment(markers, rest)
        weights = stability_weights(pose.remove(markers), rest)
        return head_alignment(markers, rest, weights), weights
    except TooFewMarkers as e:
        raise InvalidInput(f"{names[e.frame]} has {e.visible} visible markers, at least "
                           f"{e.required} are needed") from None


def handle_vertices(F: np.ndarray, triangle: np.ndarray, barycentric: np.ndarray,
                    names: tuple[str, ...] | None = None) -> np.ndarray:
    """Thin-shell handle of each marker: the corner of its triangle with the largest barycentric.

    Parameters
    ----------
    F : (m,3) int; triangle : (M,) int; barycentric : (M,3) float

    Raises
    ------
    ValueError  two markers share a handle vertex (they are closer than one mesh edge)
    """
    handles = np.asarray(F)[triangle, np.argmax(barycentric, axis=1)]
    uniq, first, count = np.unique(handles, return_index=True, return_counts=True)
    if (count > 1).any():
        v = uniq[count > 1][0]
        who = np.flatnonzero(handles == v)
        label = [names[i] for i in who] if names else who.tolist()
        raise ValueError(f"markers {label} share the thin-shell handle vertex {v}: markers must "
                         f"be at least one mesh edge apart")
    return handles


@dataclass
class BaseSurface:
    """Smooth neutral + precomputed thin shell over the marker handles (ma2008 §4, §5 step 1).

    Attributes
    ----------
    smooth : (n,3) float64     smooth neutral X̄, mm
    faces : (m,3) int64
    handles : (M,) int64       handle vertex of every marker
    rest_markers : (M,3)       neutral marker positions P_ref (on the detailed neutral), mm
    basis : (n,M) float32      thin-shell basis B (Fortran order)
    energy : (M,M) float64     handle energy G = BᵀKB, for exact completion of missing markers
    frame_field : FrameField   per-pose tangent frames (weights from X̄)
    noise_mm : float or "auto" assumed marker noise σ per coordinate, mm (0: interpolation;
                               "auto": estimated per request)
    prior_scale_mm : float     shell prior scale τ, mm (:func:`shell_prior_scale`; NaN unset)
    marker_prior : MarkerPrior learned prior over the aligned marker displacements (None:
                               the shell prior alone)
    denoise : callable         u (F,M,3) → u_H (F,M,3), the marker denoiser of σ, τ and the
                               prior (:func:`~service.geometry.marker_prior.marker_denoiser`;
                               None at construction: exact interpolation)
    evidence : MarkerEvidence  the input factor of the reported confidence under the learned
                               prior (:class:`~service.methods.confidence.MarkerEvidence`;
                               None without a learned prior: factor 1)
    """

    smooth: np.ndarray
    faces: np.ndarray
    handles: np.ndarray
    rest_markers: np.ndarray
    basis: np.ndarray         # read per frame by deform (ShellMesh's compiled path reads its reordered copy)
    energy: np.ndarray
    frame_field: FrameField
    noise_mm: float = 0.0
    prior_scale_mm: float = float("nan")
    marker_prior: MarkerPrior | None = None
    denoise: MarkerDenoiser | ShellDenoiser | None = None
    evidence: MarkerEvidence | None = dataclasses.field(default=None, repr=False)

    def __post_init__(self):
        if self.denoise is None:
            self.denoise = ShellDenoiser(self.energy, 0.0)

    @classmethod
    def build(cls, V: np.ndarray, F: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray,
              handles: np.ndarray, rest_markers: np.ndarray, lam_dt: float = LAMBDA_DT,
              ks: float = KS, kb: float = KB) -> "BaseSurface":
        """From the detailed neutral V (n,3), F (m,3), its layout and the marker handles."""
        smooth = frequency_separation(V, F, lam_dt=lam_dt)
        return cls.from_smooth(smooth, F, uv, uv_faces, handles, rest_markers, ks, kb)

    @classmethod
    def from_smooth(cls, smooth, F, uv, uv_faces, handles, rest_markers,
                    ks: float = KS, kb: float = KB, basis: np.ndarray | None = None,
                    energy: np.ndarray | None = None, frame_field: FrameField | None = None) -> "BaseSurface":
        """As :meth:`build` for an already smooth neutral (e.g. loaded from a model); a stored
        ``basis`` (n,M) float32 and ``energy`` (M,M) of the same inputs skip their solves, a
        stored ``frame_field`` (:meth:`FrameField.from_operators`) its build."""
        smooth = np.asarray(smooth, dtype=np.float64)
        F = np.asarray(F, dtype=np.int64)
        B = (thin_shell_basis(smooth, F, handles, ks=ks, kb=kb, dtype=np.float32)
             if basis is None else np.asfortranarray(basis))
        G = handle_energy_matrix(smooth, F, B, ks=ks, kb=kb) if energy is None else energy
        return cls(smooth, F, np.asarray(handles, np.int64), np.asarray(rest_markers, np.float64),
                   B, G, frame_field or FrameField.build(smooth, F, uv, uv_faces))

    @property
    def noise_ratio(self) -> float:
        """λ = σ²/τ² of the soft marker constraints (0: the paper's exact interpolation; NaN
        for σ estimated per request, ``"auto"``)."""
        if self.noise_mm == AUTO:
            return float("nan")
        return 0.0 if self.noise_mm == 0 else marker_noise_ratio(self.noise_mm, self.prior_scale_mm)

    @property
    def denoiser(self) -> MarkerDenoiser | None:
        """The learned prior's MAP solve (None when σ = 0 or without a learned prior)."""
        return self.denoise if isinstance(self.denoise, MarkerDenoiser) else None

    def with_marker_noise(self, noise_mm: float | str, prior_scale_mm: float | None = None,
                          samples: np.ndarray | None = None,
                          marker_prior: MarkerPrior | None = None) -> "BaseSurface":
        """This base with soft marker constraints for noise σ = ``noise_mm`` (mm; ``"auto"``:
        estimated per request, :class:`~service.geometry.marker_prior.AdaptiveDenoiser`).

        The prior scale τ is ``prior_scale_mm`` (a stored model's) or estimated from
        ``samples``, aligned training markers (F,M,3) (:func:`shell_prior_scale` of their
        exactly interpolated handle displacements). The learned marker prior is
        ``marker_prior`` (a stored model's) or fitted on ``samples``
        (:meth:`MarkerPrior.fit_tapered`); with neither, the shell prior alone is used (a
        model saved before the learned prior existed). σ = 0 gives the exact interpolation.

        Raises
        ------
        ValueError   σ > 0 without a prior scale or samples; σ negative
        """
        noise_mm = noise_mm if noise_mm == AUTO else float(noise_mm)
        if prior_scale_mm is None or not np.isfinite(prior_scale_mm):
            if samples is None:
                if noise_mm and noise_mm != AUTO:
                    raise ValueError("soft marker constraints need the prior scale or samples")
                prior_scale_mm = float("nan")
            else:
                exact = dataclasses.replace(self, noise_mm=0.0, denoise=ShellDenoiser(self.energy, 0.0))
                prior_scale_mm = shell_prior_scale(self.energy, exact.handle_displacements(samples))
        if marker_prior is None and samples is not None:
            marker_prior = MarkerPrior.fit_tapered(np.asarray(samples, np.float64) - self.rest_markers,
                                                   self.rest_markers)
        denoise = marker_denoiser(self.energy, noise_mm, float(prior_scale_mm), marker_prior)
        evidence = None if marker_prior is None else MarkerEvidence.of(
            marker_prior, denoise.eigen if isinstance(denoise, AdaptiveDenoiser) else None)
        return dataclasses.replace(self, noise_mm=noise_mm, prior_scale_mm=float(prior_scale_mm),
                                   marker_prior=marker_prior, denoise=denoise, evidence=evidence)

    def input_confidence(self, aligned: np.ndarray, u_H: np.ndarray,
                         sigma: np.ndarray | None = None) -> np.ndarray:
        """The input factor n g (F,) of the reported confidence of aligned markers (F,M,3), NaN
        rows occluded, whose complete handle displacements are u_H (F,M,3)
        (:meth:`handle_displacements`) (:class:`~service.methods.confidence.MarkerEvidence`;
        ``sigma`` (F,): their σ̂ where already estimated); 1 without a learned prior."""
        aligned = np.asarray(aligned, np.float64)
        if self.evidence is None:
            return np.ones(len(aligned))
        return self.evidence.factor(aligned - self.rest_markers, u_H, sigma)

    def captured_noise(self, captured: np.ndarray, weights: np.ndarray,
                       shape: tuple[int, ...] | None = None) -> np.ndarray | None:
        """σ̂ (F,) mm of markers as captured (F,M,3), NaN rows occluded, before a temporal
        filter smoothed the frames a model is given (a synthesis job's
        ``marker_filter_frames``): aligned with the model's head-alignment ``weights`` (M,)
        and read as :meth:`input_confidence` reads σ̂. The reported confidence's noise factor
        takes this instead of the filtered frames' σ̂ (:mod:`service.methods.confidence`,
        *Filtered takes*). ``shape``: the filtered frames' (F,M,3), which the captured ones
        must have (:func:`~service.methods.confidence.captured_frames`). None without a
        learned prior, or where a frame has too few visible markers to align (the filtered
        frames' own σ̂ then stands)."""
        captured = (np.asarray(captured, np.float64) if shape is None
                    else captured_frames(captured, shape))
        if self.evidence is None:
            return None
        try:
            pose = head_alignment(captured, self.rest_markers, weights)
        except TooFewMarkers:
            return None
        return self.evidence.noise(pose.remove(captured) - self.rest_markers)

    def with_noise_estimate(self, noise_mm: float) -> "BaseSurface":
        """This base (``marker_noise_mm = "auto"``) with the denoiser of one request's
        estimated σ = ``noise_mm`` (:meth:`~service.geometry.marker_prior.AdaptiveDenoiser.fixed`)."""
        return dataclasses.replace(self, denoise=self.denoise.fixed(noise_mm))

    def marker_modes(self, weights: np.ndarray) -> MarkerModes | None:
        """The modes of the learned marker prior, in which a synthesis job's
        ``marker_filter_frames: "auto"`` filters the take
        (:func:`~service.geometry.marker_filter.filter_performance`), aligned with the
        model's head-alignment ``weights`` (M,); None without a prior."""
        return MarkerModes.of(self.rest_markers, self.marker_prior, weights,
                              None if self.evidence is None else self.evidence.eigen)

    def handle_displacements(self, aligned: np.ndarray) -> np.ndarray:
        """u_H (F,M,3) of aligned markers (F,M,3): the markers' displacements, missing rows
        completed by the learned prior's conditional mean given the visible ones
        (:class:`~service.geometry.marker_prior.PriorCompletion`; without a prior, by minimum
        energy); with marker noise σ > 0 the MAP estimate under the
        learned marker prior (:class:`~service.geometry.marker_prior.MarkerDenoiser`) or,
        without one, of the shell's soft constraints
        (:func:`~service.geometry.thin_shell.soft_handles`)."""
        return self.denoise(np.asarray(aligned, dtype=np.float64) - self.rest_markers)

    def denoised_markers(self, aligned: np.ndarray, u_H: np.ndarray) -> np.ndarray:
        """Aligned marker positions (F,M,3) the features are computed from: ``P_ref + u_H``
        where a marker is visible in ``aligned`` (F,M,3), NaN where it is occluded (so it
        drops out of strains as before); ``aligned`` itself when σ = 0."""
        if self.denoise.interpolates:
            return aligned
        visible = np.isfinite(np.asarray(aligned)).all(axis=-1, keepdims=True)
        return np.where(visible, self.rest_markers + u_H, np.nan)

    def deform(self, u_H: np.ndarray) -> np.ndarray:
        """Base surfaces ``X̄ + B u_H`` (F,n,3) float64 for complete handle displacements (F,M,3)."""
        return self.smooth + apply_basis(self.basis, u_H)

    def frames(self, X: np.ndarray) -> np.ndarray:
        """Tangent frames (…,n,3,3), rows (T, B, N), of base surfaces X (…,n,3)."""
        return self.frame_field.frames(X)

    def to_world(self, X: np.ndarray, C: np.ndarray) -> np.ndarray:
        """Offsets C (…,n,3) in the tangent frames of base surfaces X (…,n,3), as world vectors."""
        return self.frame_field.to_world(X, C)
