"""Marker input of shape-space enhancement: the linear thin shell, matched and corrected.

bermano2014 §5.1 carries an input that is "possibly just marker positions" to the database
neutral with "a linear deformation model [Bickel et al. 2008]", and §8 assumes that "the
low-frequency component of the input animation is correct". For markers it is not: the
thin shell of a neutral between ~150 markers misses the captured shape by 0.25–0.45 mm on
the sample actor, mostly in the band the shape space keeps from the input, and its shape
differs systematically from the captured frames it is matched against.

Two departures, both switched by ``ShapeSpaceParams.marker_correction``, make marker input
a first-class input; the database needs the markers of its frames, which every
:class:`~service.methods.inputs.Clip` carries:

1. **like with like** — the input shell is matched (§5.3) against the database frames' own
   shells, ``shell(markers of d_k)``, encoded and compressed exactly as an input is, rather
   than against the captured frames: both sides then carry the same interpolation error;
2. **pose-space correction** — the second half of the bickel2008 pipeline the paper cites,
   its weighted pose-space deformation (§5.2–5.3). Per database frame k we store what the
   linear shell misses,

       c_k = Frame(â_k) · (T_k d_k − â_k),       â_k = T_k shell(markers of d_k),

   in the per-vertex tangent frames of the aligned shell (bickel2008 §5.2: corrections
   "stored in per-vertex local frames", invariant to the local rotation of the skin), T_k
   the shell's own alignment (as an input's). For an input frame the corrections are
   blended with the matched convex weights, per vertex through the normalized region
   weights (the WPSD of §5.3 with bermano2014's region weights in place of its RBF weights):

       ā' = ā + Frameᵀ(ā) · Σ_r ω̂_r Σ_k w_{r,k} c_k,

   and ā' is what is enhanced (see ``ShapeSpaceModel._pose_space_correction``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from service.geometry.closest_point import surface_points
from service.geometry.marker_prior import (
    AUTO, AdaptiveDenoiser, MarkerDenoiser, MarkerPrior, ShellDenoiser, marker_denoiser,
)
from service.geometry.rigid import rigid_align
from service.geometry.tangent_frames import FrameField
from service.geometry.thin_shell import (
    apply_basis, handle_energy_matrix, marker_noise_ratio, shell_prior_scale, thin_shell_basis,
)
from service.methods.inputs import InvalidInput
from service.methods.pdm.base_surface import MIN_VISIBLE_MARKERS, handle_vertices


@dataclass(frozen=True)
class MarkerShell:
    """The neutral deformed to markers by the linear thin shell (bickel2008 §4).

    Attributes (n vertices, M markers)
    ----------
    neutral : (n,3) float64   the rest surface the shell deforms, mm
    basis : (n,M) float64     ``B = −A⁻¹A_H`` on the markers' handle vertices
    energy : (M,M) float64    ``Bᵀ K B`` (missing markers are completed at minimum energy)
    rest : (M,3) float64      the markers on the neutral, mm
    weights : (M,) float64    head-alignment weights of the markers
    noise_mm : float          assumed marker noise σ, mm: soft marker constraints when > 0
    prior_scale_mm : float    the shell prior's scale τ, mm (:meth:`prior_scale`)
    denoise : callable        u (M,3) → u_H (M,3), the marker denoiser of σ, τ and the learned
                              prior (:meth:`learned_prior`), the same as the PDM's base
                              surface (:func:`~service.geometry.marker_prior.marker_denoiser`;
                              None at construction: exact interpolation)
    """

    neutral: np.ndarray
    basis: np.ndarray
    energy: np.ndarray
    rest: np.ndarray
    weights: np.ndarray
    noise_mm: float = 0.0
    prior_scale_mm: float = float("nan")
    denoise: MarkerDenoiser | ShellDenoiser | None = None

    def __post_init__(self):
        if self.denoise is None:
            object.__setattr__(self, "denoise", ShellDenoiser(self.energy, 0.0))

    @classmethod
    def build(cls, neutral: np.ndarray, faces: np.ndarray, marker_triangle: np.ndarray,
              marker_barycentric: np.ndarray, weights: np.ndarray) -> "MarkerShell":
        """The shell of ``neutral`` (n,3) with markers at (triangle (M,), barycentric (M,3))."""
        neutral = np.asarray(neutral, dtype=np.float64)
        B = thin_shell_basis(neutral, faces, handle_vertices(faces, marker_triangle, marker_barycentric))
        return cls(neutral, B, handle_energy_matrix(neutral, faces, B),
                   surface_points(neutral, faces, marker_triangle, marker_barycentric),
                   np.asarray(weights, dtype=np.float64))

    @property
    def n_markers(self) -> int:
        return len(self.rest)

    @property
    def noise_ratio(self) -> float:
        """λ = σ²/τ² (0: exact interpolation)."""
        if self.noise_mm == AUTO:
            return float("nan")
        return 0.0 if self.noise_mm == 0 else marker_noise_ratio(self.noise_mm, self.prior_scale_mm)

    @property
    def denoiser(self) -> MarkerDenoiser | None:
        """The learned prior's MAP solve (None when σ = 0 or without a learned prior)."""
        return self.denoise if isinstance(self.denoise, MarkerDenoiser) else None

    def with_marker_noise(self, noise_mm: float | str, prior_scale_mm: float | None,
                          marker_prior: MarkerPrior | None = None) -> "MarkerShell":
        """This shell with soft marker constraints for noise σ = ``noise_mm`` and prior scale
        τ = ``prior_scale_mm`` (mm); σ = 0 interpolates exactly (τ may then be None). With a
        learned ``marker_prior`` (:meth:`learned_prior`) the handles are its MAP estimate
        (:class:`~service.geometry.marker_prior.MarkerDenoiser`), else the shell prior's."""
        tau = float("nan") if prior_scale_mm is None else float(prior_scale_mm)
        noise_mm = noise_mm if noise_mm == AUTO else float(noise_mm)
        if noise_mm and noise_mm != AUTO and not np.isfinite(tau):
            raise ValueError("soft marker constraints need the shell prior's scale")
        return dataclasses.replace(self, noise_mm=noise_mm, prior_scale_mm=tau,
                                   denoise=marker_denoiser(self.energy, noise_mm, tau, marker_prior))

    def _handles(self, P: np.ndarray, T) -> np.ndarray:
        """Handle displacements (M,3) of world markers P (M,3) under head pose T."""
        visible = np.isfinite(P).all(axis=1)
        return self.denoise(np.where(visible[:, None], T.apply(P) - self.rest, np.nan))

    def _aligned_displacements(self, markers: np.ndarray) -> np.ndarray:
        """Head-aligned displacements (F',M,3) of the sample world markers (F,M,3) with
        every marker visible."""
        markers = np.asarray(markers, dtype=np.float64)
        full = markers[np.isfinite(markers).all(axis=(1, 2))]
        if not len(full):
            raise InvalidInput("no frame has every marker visible; cannot estimate the shell prior")
        return np.stack([rigid_align(P, self.rest, self.weights).apply(P) - self.rest for P in full])

    def prior_scale(self, markers: np.ndarray) -> float:
        """The shell prior's scale τ (mm) from sample world markers (F,M,3), e.g. the
        database's (:func:`~service.geometry.thin_shell.shell_prior_scale` of their exactly
        interpolated, head-aligned handle displacements; frames with a missing marker skipped)."""
        return shell_prior_scale(self.energy, self._aligned_displacements(markers))

    def learned_prior(self, markers: np.ndarray) -> MarkerPrior:
        """The learned marker prior (:meth:`MarkerPrior.fit_tapered`) of sample world markers
        (F,M,3), e.g. the database's, head-aligned (frames with a missing marker skipped)."""
        return MarkerPrior.fit_tapered(self._aligned_displacements(markers), self.rest)

    def __call__(self, markers: np.ndarray) -> np.ndarray:
        """Shell surfaces (F,n,3) float64 in the markers' world pose for markers (F,M,3).

        Per frame: head pose by weighted Kabsch of the visible markers onto the rest
        markers, handle displacements (NaN markers completed at minimum energy; soft
        constraints when ``noise_mm`` > 0, :attr:`denoise`),
        ``neutral + B u_H``, and the pose put back.

        Raises
        ------
        InvalidInput   wrong shape, or a frame with fewer than MIN_VISIBLE_MARKERS markers
        """
        markers = np.asarray(markers, dtype=np.float64)
        M = self.n_markers
        if markers.ndim != 3 or markers.shape[1:] != (M, 3):
            raise InvalidInput(f"markers must be (F,{M},3), got {markers.shape}")
        out = np.empty((len(markers),) + self.neutral.shape)
        poses = []
        for f, P in enumerate(markers):
            visible = np.isfinite(P).all(axis=1)
            if visible.sum() < MIN_VISIBLE_MARKERS:
                raise InvalidInput(f"frame {f} has {int(visible.sum())} visible markers, at least "
                                   f"{MIN_VISIBLE_MARKERS} are needed")
            poses.append(rigid_align(P, self.rest, self.weights))
        shell = self
        if isinstance(self.denoise, AdaptiveDenoiser):     # σ estimated once over the request
            u = np.stack([np.where(np.isfinite(P).all(axis=1)[:, None], T.apply(P) - self.rest, np.nan)
                          for P, T in zip(markers, poses)])
            shell = dataclasses.replace(self, denoise=self.denoise.fixed(self.denoise.request_noise(u)))
        for f, (P, T) in enumerate(zip(markers, poses)):
            out[f] = T.inverse().apply(self.neutral + apply_basis(self.basis, shell._handles(P, T)))
        return out


@dataclass(frozen=True)
class MarkerDatabase:
    """What marker input is matched against and corrected by (N database frames, P patches).

    Attributes
    ----------
    shapes : (N,9P) float64        compressed low-frequency shapes of the frames' shells (§5.2)
    gram : (R,N,N) float64         their Gram matrices per region (§5.3)
    corrections : (N,n,3) float32  c_k, in the aligned shells' tangent frames, mm
    """

    shapes: np.ndarray
    gram: np.ndarray
    corrections: np.ndarray


def corrected_input(frames: FrameField, aligned_shell: np.ndarray, correction: np.ndarray) -> np.ndarray:
    """``â + Frameᵀ(â) · c``: an aligned shell surface (n,3) plus a blended correction (n,3)."""
    return aligned_shell + frames.to_world(aligned_shell, correction)


__all__ = ["MIN_VISIBLE_MARKERS", "MarkerDatabase", "MarkerShell", "corrected_input"]
