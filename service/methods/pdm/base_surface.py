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
* a marker's handle is the vertex of its triangle nearest to it; missing (NaN) markers
  drop their constraints exactly (:func:`~service.geometry.thin_shell.complete_handles`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.errors import InvalidInput
from service.geometry.curvature_flow import LAMBDA_DT, frequency_separation
from service.geometry.rigid import MIN_POINTS, rigid_align, stability_weights_from_rms
from service.geometry.tangent_frames import FrameField
from service.geometry.thin_shell import (
    KB, KS, apply_basis, complete_handles, handle_energy_matrix, thin_shell_basis,
)

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
    """

    smooth: np.ndarray
    faces: np.ndarray
    handles: np.ndarray
    rest_markers: np.ndarray
    basis: np.ndarray
    energy: np.ndarray
    frame_field: FrameField

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
                    energy: np.ndarray | None = None) -> "BaseSurface":
        """As :meth:`build` for an already smooth neutral (e.g. loaded from a model); a stored
        ``basis`` (n,M) float32 and ``energy`` (M,M) of the same inputs skip their solves."""
        smooth = np.asarray(smooth, dtype=np.float64)
        F = np.asarray(F, dtype=np.int64)
        B = (thin_shell_basis(smooth, F, handles, ks=ks, kb=kb, dtype=np.float32)
             if basis is None else np.asfortranarray(basis))
        G = handle_energy_matrix(smooth, F, B, ks=ks, kb=kb) if energy is None else energy
        return cls(smooth, F, np.asarray(handles, np.int64), np.asarray(rest_markers, np.float64),
                   B, G, FrameField.build(smooth, F, uv, uv_faces))

    def handle_displacements(self, aligned: np.ndarray) -> np.ndarray:
        """u_H (F,M,3) of aligned markers (F,M,3); missing rows completed by minimum energy."""
        u = np.asarray(aligned, dtype=np.float64) - self.rest_markers
        missing = ~np.isfinite(u).all(axis=2)
        for f in np.flatnonzero(missing.any(axis=1)):
            u[f] = complete_handles(self.energy, np.where(missing[f, :, None], np.nan, u[f]))
        return u

    def deform(self, u_H: np.ndarray) -> np.ndarray:
        """Base surfaces ``X̄ + B u_H`` (F,n,3) float64 for complete handle displacements (F,M,3)."""
        return self.smooth + apply_basis(self.basis, u_H)

    def frames(self, X: np.ndarray) -> np.ndarray:
        """Tangent frames (…,n,3,3), rows (T, B, N), of base surfaces X (…,n,3)."""
        return self.frame_field.frames(X)

    def to_world(self, X: np.ndarray, C: np.ndarray) -> np.ndarray:
        """Offsets C (…,n,3) in the tangent frames of base surfaces X (…,n,3), as world vectors."""
        return self.frame_field.to_world(X, C)
