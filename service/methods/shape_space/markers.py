"""Marker input of shape-space enhancement: the linear thin shell and its pose-space correction.

bermano2014 §5.1 carries an input that is "possibly just marker positions" to the database
neutral with "a linear deformation model [Bickel et al. 2008]", and §8 assumes that "the
low-frequency component of the input animation is correct". For markers it is not: the
thin shell of a neutral between ~150 markers misses the captured shape by 0.25–0.45 mm on
the sample actor, mostly in the band the shape space keeps from the input, so enhancement
alone cannot remove that error.

The same bickel2008 pipeline the paper cites has the remedy, its second half: the
weighted pose-space deformation of bickel2008 §5.2–5.3. Per database frame k we store the
correction the linear shell misses,

    c_k = Frame(â_k) · (d_k − â_k),       â_k = shell(markers of d_k)  (aligned, §5.2),

in the per-vertex tangent frames of the shell surface (bickel2008 §5.2: "stored in per-
vertex local frames", so it is invariant to the local rotation of the skin), and for an
input frame we blend the corrections with the shape space's own matched convex weights,
per vertex through the normalized region weights (the WPSD of §5.3 with bermano2014's
region weights in place of the RBF weights):

    a' = â + Frameᵀ(â) · Σ_r ω̂_r Σ_k w_{r,k} c_k.

The corrected surface is then encoded and matched again and enhanced as any other input.
This departs from bermano2014 (which enhances the shell directly) and is switched by
``ShapeSpaceParams.marker_correction``; the database needs the markers of its frames,
which every :class:`~service.methods.inputs.Clip` carries.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.geometry.closest_point import surface_points
from service.geometry.rigid import RigidTransform, rigid_align
from service.geometry.tangent_frames import FrameField
from service.geometry.thin_shell import (
    apply_basis, complete_handles, handle_energy_matrix, thin_shell_basis,
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
    """

    neutral: np.ndarray
    basis: np.ndarray
    energy: np.ndarray
    rest: np.ndarray
    weights: np.ndarray

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

    def __call__(self, markers: np.ndarray) -> np.ndarray:
        """Shell surfaces (F,n,3) float64 in the markers' world pose for markers (F,M,3).

        Per frame: head pose by weighted Kabsch of the visible markers onto the rest
        markers, handle displacements (NaN markers completed, :func:`complete_handles`),
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
        for f, P in enumerate(markers):
            visible = np.isfinite(P).all(axis=1)
            if visible.sum() < MIN_VISIBLE_MARKERS:
                raise InvalidInput(f"frame {f} has {int(visible.sum())} visible markers, at least "
                                   f"{MIN_VISIBLE_MARKERS} are needed")
            T = rigid_align(P, self.rest, self.weights)
            u = complete_handles(self.energy, np.where(visible[:, None], T.apply(P) - self.rest, np.nan))
            out[f] = T.inverse().apply(self.neutral + apply_basis(self.basis, u))
        return out


def pose_space_corrections(shell: MarkerShell, frames: FrameField, markers: np.ndarray,
                           aligned: np.ndarray, transforms: list[RigidTransform]) -> np.ndarray:
    """What the shell misses on every database frame, in its tangent frames (bickel2008 §5.2).

    Parameters
    ----------
    shell : MarkerShell
    frames : FrameField          tangent frames of the neutral's layout
    markers : (N,M,3) float      world markers of the database frames (NaN when occluded)
    aligned : (N,n,3) float      the database frames aligned to the neutral, ``T_k(d_k)``
    transforms : N RigidTransform   the alignments T_k (world → database frame)

    Returns
    -------
    c : (N,n,3) float32   ``Frame(â_k) · (T_k d_k − â_k)`` with ``â_k = T_k(shell(markers_k))``;
                          zero for a frame with too few visible markers (it corrects nothing)
    """
    c = np.zeros(aligned.shape, np.float32)
    for k, (P, T) in enumerate(zip(markers, transforms)):
        if np.isfinite(P).all(axis=1).sum() < MIN_VISIBLE_MARKERS:
            continue
        a = T.apply(shell(P[None])[0])
        c[k] = np.einsum("nij,nj->ni", frames.frames(a), aligned[k] - a)
    return c


def corrected_input(frames: FrameField, aligned_shell: np.ndarray, correction: np.ndarray) -> np.ndarray:
    """``â + Frameᵀ(â) · c``: an aligned shell surface (n,3) plus a blended correction (n,3)."""
    return aligned_shell + frames.to_world(aligned_shell, correction)


__all__ = ["MarkerShell", "corrected_input", "pose_space_corrections"]
