"""What a trained shape-space model stores (bermano2014 §4): :class:`ShapeSpaceData`, round-tripped
bit for bit by :mod:`.store`; what enhancement precomputes from it is the
:class:`~service.methods.shape_space.model.ShapeSpaceEvaluator`."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.geometry.marker_prior import MarkerPrior
from service.methods.shape_space.maps import DatabaseMaps
from service.methods.shape_space.markers import MarkerDatabase
from service.methods.shape_space.params import ShapeSpaceParams


@dataclass(frozen=True)
class ShapeSpaceData:
    """Everything a trained shape-space model stores (the store round-trips it bit for bit).

    Attributes
    ----------
    (n vertices, m triangles, N database frames, P patches, R regions, M markers)

    params : ShapeSpaceParams
    faces : (m,3) int64
    neutral : (n,3) float64           d0, mm
    smooth_neutral : (n,3) float64    f(d0), the rest mesh of the encoding and reconstruction
    align_weights : (n,) float64      per-vertex weights of the rigid alignment
    patches : (n,) int64              vertex patch labels; ``tri_patch`` (m,) the triangles'
    tri_patch : (m,) int64
    shapes : (N,9P) float64           compressed low-frequency shape vectors (D̃ᵀ), patch-major
    detail : (N,m,9) float32          high-frequency detail d_h per frame and triangle
    region_names : tuple of R str
    region_vertices : (R,n) bool      the regions' vertex sets
    region_weights : (R,m) float64    ω_r per triangle (1 inside, Gaussian fall-off outside)
    patch_weights : (R,P) float64     ω_r averaged over the patches (the diagonal of Ω_r)
    gram : (R,N,N) float64            ``D̃ᵀ Ω_r D̃``
    frame_clip, frame_index : (N,) int64   source clip and frame of every database frame
    clip_names : tuple of str;  clip_fps : tuple of float   the clips' frame rates
    colors : (N,n,C) float32 | None   per-vertex colours of the database frames
    marker_triangle, marker_barycentric : (M,), (M,3)   the actor's markers (M may be 0)
    marker_weights : (M,) float64     head-alignment weights of the markers
    uv : (K,2) float64;  uv_faces : (m,3) int64   the neutral's UV layout (displacement maps)
    metrics : dict
    marker_database : MarkerDatabase | None   the database frames' marker shells, compressed,
                                      and what they miss (:mod:`.markers`; None: marker input
                                      is matched against the frames and not corrected)
    fine_maps, albedo_maps : DatabaseMaps | None   the database frames' fine displacement and
                                      albedo maps (None: the database had none; :mod:`.maps`)
    marker_prior : MarkerPrior | None   learned prior over the database's head-aligned marker
                                      displacements (:mod:`service.geometry.marker_prior`; None:
                                      no markers, or stored before it existed: marker noise
                                      then uses the shell prior alone)
    """

    params: ShapeSpaceParams
    faces: np.ndarray
    neutral: np.ndarray
    smooth_neutral: np.ndarray
    align_weights: np.ndarray
    patches: np.ndarray
    tri_patch: np.ndarray
    shapes: np.ndarray
    detail: np.ndarray
    region_names: tuple[str, ...]
    region_vertices: np.ndarray
    region_weights: np.ndarray
    patch_weights: np.ndarray
    gram: np.ndarray
    frame_clip: np.ndarray
    frame_index: np.ndarray
    clip_names: tuple[str, ...]
    clip_fps: tuple[float, ...]
    colors: np.ndarray | None
    marker_triangle: np.ndarray
    marker_barycentric: np.ndarray
    marker_weights: np.ndarray
    uv: np.ndarray
    uv_faces: np.ndarray
    metrics: dict = field(default_factory=dict)
    marker_database: MarkerDatabase | None = None
    fine_maps: DatabaseMaps | None = None
    albedo_maps: DatabaseMaps | None = None
    marker_prior: MarkerPrior | None = None

    @property
    def n_vertices(self) -> int:
        return len(self.neutral)

    @property
    def n_frames(self) -> int:
        return len(self.shapes)

    @property
    def n_patches(self) -> int:
        return len(self.patch_weights[0])

    @property
    def n_markers(self) -> int:
        return len(self.marker_triangle)


__all__ = ["ShapeSpaceData"]
