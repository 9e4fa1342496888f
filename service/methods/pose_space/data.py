"""What a trained pose-space model stores (bickel2008 §5): :class:`PoseSpaceData`, round-tripped
bit for bit by :mod:`.store`; the per-frame evaluator is built from it
(:class:`~service.methods.pose_space.model.PoseSpaceEvaluator`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from service.geometry.marker_regression import MarkerRegression
from service.methods.pose_space.feature_graph import FeatureGraph
from service.methods.pose_space.params import Params


@dataclass(frozen=True)
class PoseSpaceData:
    """Everything a trained pose-space model stores (the store round-trips it bit for bit).

    Mesh (n vertices), markers (M), feature nodes (N), edges (E), basis poses (P), map
    texels (Pt):

    params : PsdParams | WpsdParams
    faces (m,3) int64, uv (K,2) float64, uv_faces (m,3) int64
    neutral (n,3) float64           the detailed rest mesh 𝓕 the shell deforms, mm
    handles (M,) int64              thin-shell handle vertex of each marker
    rest_markers (M,3) float64      the markers on the neutral, mm
    pose_weights (M,) float64       head-alignment weights
    node_triangle (N,) int64, node_barycentric (N,3) float64   feature nodes as surface points
    edges (E,2) int64, rest_length (E,) float64                 the feature graph (§5.1)
    basis_features (P,E) float64    f_j of the basis poses
    weights (n,P,3) float32         w_v,j in the tangent frames (PSD: the same system at every
                                    vertex, stored per vertex all the same)
    alpha (n,E) CSR float32 | None  WPSD edge weights (eq. 4)
    map_resolution int              0: no map band
    map_index (Pt,) int64           covered texels (row-major) of the map
    map_weights (Pt,P) float32      per-texel weights of the fine displacement
    poly_const (n,3) float32 | None     constant of the polynomial term (:mod:`.polynomial`)
    poly_linear (3n,E) CSR float32 | None   its linear coefficients, row 3v + c
    map_poly_const (Pt,) float32 | None, map_poly_linear (Pt,E) CSR float32 | None   the same
                                    for the fine map's texels
    marker_mean (M,3) float64 | None, marker_modes (r,M,3) float64 | None   the training
                                    frames' aligned marker displacements: mean and principal
                                    modes scaled by their standard deviation (occluded markers,
                                    ``params.marker_completion``); None for a transferred model
    marker_residual_var (M,) float64 | None   their variance outside the modes, per marker and
                                    coordinate, by leaving one clip out (``params.marker_prior``)
    regression MarkerRegression | None   the marker regression (:mod:`service.geometry.marker_regression`,
                                    ``params.marker_regression``), head-pose-aligned offsets
                                    added to the shell before the corrections
    regression_input str            what the regression reads: ``"handles"`` the handle
                                    displacements u_H (a trained model), ``"nodes"`` the
                                    feature nodes' shell displacements ``node_basis @ u_H`` (a
                                    transferred model: the source markers' corresponding points)
    feature_low, feature_high (E,) float64   training range of every feature
    confidence_scale float          δ₀ of the confidence (module docstring)
    basis_names tuple of str        the basis poses as "clip:frame"
    metrics dict
    """

    params: Params
    faces: np.ndarray
    uv: np.ndarray
    uv_faces: np.ndarray
    neutral: np.ndarray
    handles: np.ndarray
    rest_markers: np.ndarray
    pose_weights: np.ndarray
    node_triangle: np.ndarray
    node_barycentric: np.ndarray
    edges: np.ndarray
    rest_length: np.ndarray
    basis_features: np.ndarray
    weights: np.ndarray
    alpha: sp.csr_matrix | None
    map_resolution: int
    map_index: np.ndarray
    map_weights: np.ndarray
    feature_low: np.ndarray
    feature_high: np.ndarray
    confidence_scale: float
    basis_names: tuple[str, ...] = ()
    metrics: dict = field(default_factory=dict)
    poly_const: np.ndarray | None = None
    poly_linear: sp.csr_matrix | None = None
    map_poly_const: np.ndarray | None = None
    map_poly_linear: sp.csr_matrix | None = None
    marker_mean: np.ndarray | None = None
    marker_modes: np.ndarray | None = None
    marker_residual_var: np.ndarray | None = None
    regression: MarkerRegression | None = None
    regression_input: str = "handles"

    @property
    def kind(self) -> str:
        return self.params.method

    @property
    def n_vertices(self) -> int:
        return len(self.neutral)

    @property
    def n_markers(self) -> int:
        return len(self.rest_markers)

    @property
    def basis_size(self) -> int:
        return len(self.basis_features)

    @property
    def graph(self) -> FeatureGraph:
        return FeatureGraph(self.edges, self.rest_length)
