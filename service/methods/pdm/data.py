"""What a trained PDM stores (ma2008 §4): :class:`PdmData`, round-tripped bit for bit by
:mod:`.store`; what synthesis precomputes from it is the
:class:`~service.methods.pdm.model.PdmEvaluator`. :class:`PdmDerived` is what a load would
otherwise recompute from the data (the store's optional ``cache.npz`` and ``validity.npz``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.geometry.marker_prior import MarkerPrior
from service.geometry.marker_regression import MarkerRegression
from service.methods.footprint import UNREAD
from service.methods.pdm.deformation import DeformationAxes, MarkerMesh
from service.methods.pdm.params import PdmParams
from service.methods.pdm.strain_band import StrainBand
from service.methods.pdm.texel_band import CoefficientMap
from service.methods.pdm.validity import ValidityData


@dataclass(frozen=True)
class PdmData:
    """Everything a trained PDM stores (the store round-trips it bit for bit).

    Attributes (n vertices, m triangles, K UV points, M markers, T training frames)
    ----------
    params : PdmParams
    faces : (m,3) int64;  uv : (K,2) float64;  uv_faces : (m,3) int64   mesh and UV layout
    smooth : (n,3) float64           the smooth neutral X̄ the thin shell deforms, mm
    handles : (M,) int64             thin-shell handle vertex of every marker
    rest_markers : (M,3) float64     neutral marker positions, mm
    prior_scale_mm : float           the shell prior's scale τ (NaN: unset; marker noise)
    mesh : MarkerMesh                the coarse marker mesh in texture space (§4.1)
    axes : DeformationAxes           per-marker PCA axes q̂, r̂ and strain scales (§4.1)
    pose_weights : (M,) float64      head-pose weights
    S_train : (T,M,5) float64        the training frames' deformation vectors (eq. 2)
    neutral_offset : (n,3) float32   the neutral's medium detail in the smooth neutral's
                                     tangent frames (static part, per vertex)
    medium : CoefficientMap          C = 3 (tangent, bitangent, normal), mm (a loaded model with
                                     ``vertex_coeffs``: a :class:`~.store.StoredCoefficientMap`,
                                     read from its directory when saved)
    fine : CoefficientMap            C = 1 (normal), mm
    albedo : CoefficientMap | None   C = 3 (linear RGB)
    metrics : dict
    validity : ValidityData | None   the training data's validity regions (None: trained with
                                     ``validity_width`` None, or stored before they were kept)
    vertex_coeffs : (K,3,K') float32 | None   the medium PDM fitted at the K UV points (what
                                     synthesis evaluates; None: stored before, sampled from
                                     ``medium``)
    marker_prior : MarkerPrior | None   learned prior over the aligned marker displacements
                                     (:mod:`service.geometry.marker_prior`; None: stored before
                                     it existed, marker noise then uses the shell prior alone)
    medium_skill : (K,) float32 | None   the medium band's cross-validated fit skill at the UV
                                     points (:mod:`.fit_skill`; None: stored before it existed,
                                     no gain then)
    medium_regression : MarkerRegression | None   the mesh's medium offsets as a marker
                                     regression (``params.medium_regression``; None: the
                                     medium polynomial)
    fine_strain : StrainBand | None  the fine band as a polynomial of the mesh's strain
                                     (``params.fine_driver`` "strain"; :mod:`.strain_band`;
                                     None: ``fine`` drives it, as ma2008)

    The maps' texels are in row-major order (as the EXR files hold them).
    """

    params: PdmParams
    faces: np.ndarray
    uv: np.ndarray
    uv_faces: np.ndarray
    smooth: np.ndarray
    handles: np.ndarray
    rest_markers: np.ndarray
    prior_scale_mm: float
    mesh: MarkerMesh
    axes: DeformationAxes
    pose_weights: np.ndarray
    S_train: np.ndarray
    neutral_offset: np.ndarray
    medium: CoefficientMap
    fine: CoefficientMap
    albedo: CoefficientMap | None
    metrics: dict = field(default_factory=dict)
    validity: ValidityData | None = None
    vertex_coeffs: np.ndarray | None = None
    marker_prior: MarkerPrior | None = None
    medium_skill: np.ndarray | None = None
    medium_regression: MarkerRegression | None = None
    # synthesis reads the evaluator's copy in its texel order (mapped from the model's cache)
    fine_strain: StrainBand | None = field(default=None, metadata=UNREAD)

    @property
    def n_vertices(self) -> int:
        return len(self.smooth)

    @property
    def n_markers(self) -> int:
        return len(self.handles)


@dataclass(frozen=True)
class PdmDerived:
    """What loading would otherwise recompute from a :class:`PdmData` (all optional).

    basis : (n,M) float32 | None;  energy : (M,M) float64 | None   the thin shell's basis and
                                     handle energy (:class:`~.base_surface.BaseSurface`)
    limits : dict name → (4,P) float32   extrapolation limits of the evaluated bands
                                     (``vertex``, ``fine``, ``albedo``), in the evaluator's
                                     point order (``PdmEvaluator.orders``: the fine and albedo
                                     texels grouped by coarse element, a function of the data)
    operators : dict name → array    the evaluator's operators (issue 23, cold start:
                                     rasterizations, barycentric parameter fields, sparse
                                     sampling matrices; ``PdmEvaluator.operators``), empty
                                     for a model stored before they were kept
    """

    basis: np.ndarray | None = None
    energy: np.ndarray | None = None
    limits: dict = field(default_factory=dict)
    operators: dict = field(default_factory=dict)


__all__ = ["PdmData", "PdmDerived"]
