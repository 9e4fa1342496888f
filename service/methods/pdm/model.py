"""Training and synthesis of deformation-driven PDMs (ma2008 §4–5, §6 albedo PTM).

Training (§4, Figure 2), for every frame of every clip:

1. remove the head pose (weighted Kabsch on the markers, :mod:`.base_surface`);
2. base surface: the smooth neutral deformed to the markers by the linear thin shell;
   medium-band targets ``c = Frame(base) · (captured − base)`` per vertex, in the base's
   tangent frames, interpolated into the ``medium_resolution`` map;
3. 5D deformation vectors S at the markers, per-marker PCA axes, d1, d2 (§4.1, eq. 2–3);
4. the medium PDM: 3 channels per texel, regularized least squares (§4.2);
5. the fine band: the normal component of ``captured − (base + medium PDM)`` (plus the
   clip's own fine displacement map, if it has one), high-pass filtered, fitted as a 1D
   PDM at ``fine_resolution`` (§4: "a high-pass filtered version of the residual");
6. with albedo maps: a 3-channel PTM of the albedo driven by the same d1, d2 (§6).

Synthesis (§5) runs the same chain forwards from markers: head pose, thin shell (missing
markers dropped exactly), S and d1, d2, the medium PDM applied to the vertices, the fine
PDM as a displacement map, the albedo map, a tangent-space normal map, and the head pose
put back.

Departures and choices (the paper is silent or differs):

* the medium PDM is fitted in texture space, as in the paper (the ``medium.exr`` maps,
  for renderers), and a second time *at the mesh's UV points*, where synthesis evaluates
  it: each UV point's polynomial is fitted to its vertex's targets with that point's d1, d2
  (``PdmData.vertex_coeffs``); a seam vertex averages its charts' results. Sampling the
  512² map at the UV points instead (what models stored without ``vertex_coeffs`` still
  do) mixes the texels of neighbouring vertices wherever UV triangles are smaller than a
  texel: on family a's mouth corner (vertex 6639) the sampled polynomial missed its own
  training targets by 4.0 mm RMS, pointing the offset the wrong way (−4.9, 5.9 → 5.6,
  −0.8 mm), against 0.46 mm fitted at the point; that vertex was the worst vertex of the
  combination and out-of-range performances (13 and 15 mm against the thin shell's 4.3
  and 7.4). O(vertices) per frame either way;
* the neutral's own medium detail (detailed neutral − smooth neutral, in the smooth
  neutral's tangent frames) is kept per vertex, and the medium PDM fits what the
  expressions add to it: the paper's constant term a5 would otherwise have to carry sharp
  static features (eyelid creases, lip edges, nostrils) through a 512² map, and the neutral
  would not be reproduced exactly. ``neutral.exr`` holds it as a map for renderers;
* extrapolation limit: per texel (and UV point), (d1, d2) is scaled back towards the
  neutral when its Mahalanobis radius in the training data's second moment exceeds
  ``1 + extrapolation_margin`` times the largest training radius (``None`` disables it;
  :func:`_limits`). Beyond the training data a biquadratic PDM grows quadratically, and
  bermano2014 §7 shows the artefacts of extrapolating detail; the limit holds the detail
  of the most extreme trained expression instead. A per-axis box would not do: its
  corners are (d1, d2) pairs no training frame visited;
* the fine band (issue 17, failure mode 2): its targets are the residual of the mesh synthesis
  makes (with ``medium_regression``, the regression's mesh, not the medium polynomial's it
  replaces: held-out map part of the detail error a 0.52 → 0.51, b 0.58 → 0.57 in range);
  it is learned at the training maps' own resolution unless ``fine_resolution`` says
  otherwise, and by default (``fine_driver`` "strain") driven by the Green strain of the
  synthesized mesh at the texel rather than by d1, d2 (:mod:`.strain_band`, the measurements
  there); ``fine.exr`` holds ma2008's (d1, d2) fine PDM either way, for renderers;
* coefficients are rounded to float32 when training ends (the stored precision), so a
  saved and reloaded model synthesizes bit-identical results;
* ``medium_regression`` (issue 17, s = 4 by default; null: the polynomial): the mesh's medium offsets, head-aligned,
  from a locally weighted ridge regression on the handle displacements u_H
  (:mod:`service.geometry.marker_regression`, anchored at the detailed neutral's offset
  from the smooth base, so rest markers give the neutral exactly) instead of the medium
  polynomial; the polynomial is still trained (the validity regions, the confidence and the
  fine band's residual come from it). The polynomial in each point's own (d1, d2) cannot
  tell combinations the training never showed from the expressions it did show, and its
  max error there exceeds the thin shell's; the regression is linear in every nearby
  marker's displacement vector. Level 0, 6 frames a performance of the sample actors
  ``benchmarks/out/actor-{a,b}-l0``, PDM biquadratic with its defaults otherwise, face
  mean / max mm, the thin shell's max beside; s chosen on family a, confirmed on b. Family a, clean: in range
  0.221 / 3.99 → 0.105 / 1.21 (3.38), combinations 0.300 / 5.86 → 0.097 / 2.57 (5.57), out
  of range 0.280 / 8.24 → 0.023 / 0.65 (7.78) with s = 4, the only s (1, 2, 4) with no
  frame above the thin shell's max on any of a's nine rows (s = 2: 1 of 6 frames in
  range; s = 1: max 4.5–5.5 mm). Family b, s = 4, clean: in range 0.183 / 2.34 → 0.010 /
  0.31 (3.00), combinations 0.436 / 4.97 → 0.193 / 2.43 (4.97), out of range 0.287 / 4.13
  → 0.017 / 0.40 (5.77); no frame of b's 54 above the thin shell's max (the polynomial: 4 of b's, 14 of a's);
  over every held-out map frame a 49 → 6 of 243 and b 27 → 1 of 225 (re-measured on the low-rank
  form with the sample actors built anew: a 9 of 243, b 4 of 225, none on clean markers: README,
  "Generalization report on the current defaults").
  Its cost, kept in low-rank form (:class:`~service.geometry.marker_regression.MarkerRegression`,
  rank 155 of 450 at level 1, P int16): two products per frame, reading P (3n, r) int16
  (42 MB at level 1; the model directory 415 → 495 MB with P in float32), and the mesh
  takes the float64 path, not the compiled :mod:`.shell_mesh` kernels, nor the medium
  polynomial's evaluation and fallback. Paired on the level-1 sample actor (load ~5, 40
  frames alternating, the polynomial model against the regression model): mesh 31.2 →
  28.7 ms, mesh + displacement + normal map (half) 114.8 → 103.5 ms. Training fits it
  from the same frames (per vertex a T×T Cholesky solve).
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np
import scipy.sparse as sp

from service.geometry import marker_regression, ranges
from service.geometry.laplacian import triangle_areas
from service.geometry.marker_filter import MarkerModes
from service.geometry.marker_prior import AdaptiveDenoiser
from service.geometry.normal_map import NormalMapper
from service.geometry.surface_strain import OPERATOR_ARRAYS as STRAIN_FIELD_ARRAYS
from service.geometry.surface_strain import OPERATOR_MATRICES as STRAIN_FIELD_MATRICES, StressField
from service.geometry.thin_shell import thin_shell_basis
from service.geometry.tangent_frames import OPERATORS as FRAME_OPERATORS
from service.geometry.tangent_frames import FrameField, tangent_frames, uv_handedness
from service.geometry.uv_raster import (
    UVRaster, interpolation_matrix, rasterize_uv, sample_map, sampling_matrix, seam_average_matrix,
    texel_uv, uv_sampling_matrix,
)
from service.io.npz import sparse_matrix, sparse_members
from service.methods.inputs import ActorData, Clip, InvalidInput, Progress, check_clips, no_progress
from service.methods.footprint import UNREAD
from service.methods.pdm import polynomial, store
from service.methods.pdm.base_surface import (
    BaseSurface, HeadPose, TooFewMarkers, handle_vertices, head_alignment, training_head_pose,
)
from service.methods.pdm.deformation import (
    DeformationAxes, MarkerMesh, ParameterField, barycentric_operator, deformation_axes,
    deformation_vectors, marker_mesh,
)
from service.methods.pdm.extrapolation import training_limit
from service.methods.pdm.fit_skill import fit_skill, skill_gain
from service.methods.outputs import check_outputs
from service.methods.pdm.data import PdmData, PdmDerived

if TYPE_CHECKING:                          # Numba: imported where an evaluator is built
    from typing import Callable

    from service.methods.pdm.point_validity import PointValidity
    from service.methods.pdm.shell_mesh import ShellMesh
from service.methods.pdm.params import PdmParams
from service.methods.pdm.strain_band import StrainBand, StrainFit, TexelFade, TexelStrain, strain_order
from service.methods.pdm.texel_band import CoefficientMap, CoveredTexels, TexelBand
from service.methods.pdm.validity import (
    BandValidity, Validity, ValidityData, sector_envelope, training_envelope, training_hull,
)
from service.methods.confidence import CONFIDENCE, VERTEX_CONFIDENCE, falloff

#: frames processed at once (bounds the (frames, texels) work arrays)
FRAME_CHUNK = 8
#: the fine band's resolution for clips without maps (ma2008's 1024)
DEFAULT_FINE_RESOLUTION = 1024
#: training frames whose largest handle displacement is at most this fraction of the
#: largest over all frames are rest frames: their targets give the fine and albedo bands'
#: value at zero deformation (``neutral_anchor``)
NEUTRAL_TOL = 0.02
#: threads for per-frame map filtering (NumPy and SciPy release the GIL)
WORKERS = 2
#: gauge ρ below which the medium detail fades in from its fallback (:func:`rest_onset`)
REST_ONSET = 0.3
#: version of the evaluator's stored operators (:meth:`PdmEvaluator.operators`): a stored
#: model whose operators carry another (derived by other code) builds them anew
OPERATORS_VERSION = 1


def element_field(mesh: MarkerMesh, axes: DeformationAxes, index: np.ndarray,
                  H: int) -> tuple[np.ndarray, ParameterField]:
    """The texels (flat indices ``index`` (P,) of an H×H map) grouped by coarse element: the
    permutation (P,) of ``index`` and the parameter field of the texels in that order."""
    W = barycentric_operator(mesh, texel_uv(index, H))
    order = ParameterField.element_order(W)
    return order, ParameterField.build(axes, W[order])


def _parameters(pf: ParameterField, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d1, d2 (T,P) float32 for S (T,M,5), frames in chunks (bounds the (P,T,5) temporary)."""
    T, P = len(S), pf.n_points
    d1, d2 = np.empty((T, P), np.float32), np.empty((T, P), np.float32)
    for t in range(0, T, FRAME_CHUNK):
        d1[t:t + FRAME_CHUNK], d2[t:t + FRAME_CHUNK] = pf(S[t:t + FRAME_CHUNK])
    return d1, d2


def _limits(pf: ParameterField, S: np.ndarray) -> np.ndarray:
    """Per-point extrapolation limit (4,P) float32 (:mod:`.extrapolation`) of the training S (T,M,5)."""
    return training_limit(lambda: (pf(S[t:t + FRAME_CHUNK]) for t in range(0, len(S), FRAME_CHUNK)))


@dataclass(frozen=True)
class BandFilter:
    """The Gaussian frequency split of §4 over the covered texels of an H×H map.

    ``lowpass(r) = (G_σ ∗ r) / (G_σ ∗ 1_covered)``: a Gaussian normalized by the blurred
    coverage mask, so texels near chart borders average only covered texels;
    ``highpass(r) = r − lowpass(r)``. σ = 0 passes everything to the low band.
    """

    H: int
    index: np.ndarray                 # (P,) covered texels
    sigma: float                      # texels
    mask_blur: np.ndarray | None      # (P,) G_σ ∗ 1_covered at the covered texels

    @classmethod
    def build(cls, H: int, index: np.ndarray, sigma: float) -> "BandFilter":
        from scipy.ndimage import gaussian_filter  # imported here: training only (issue 23's cold start)

        if sigma <= 0:
            return cls(H, index, 0.0, None)
        mask = np.zeros(H * H)
        mask[index] = 1.0
        return cls(H, index, sigma, gaussian_filter(mask.reshape(H, H), sigma, mode="constant").ravel()[index])

    def lowpass(self, values: np.ndarray) -> np.ndarray:
        """(P,) covered-texel values → their low band (P,)."""
        from scipy.ndimage import gaussian_filter

        if self.sigma <= 0:
            return values
        img = np.zeros(self.H * self.H)
        img[self.index] = values
        return gaussian_filter(img.reshape(self.H, self.H), self.sigma, mode="constant").ravel()[self.index] / self.mask_blur

    def highpass(self, values: np.ndarray) -> np.ndarray:
        """(P,) covered-texel values → their high band (P,); 0 when σ = 0."""
        return values - self.lowpass(values) if self.sigma > 0 else values


def vertex_band(medium: CoefficientMap, uv: np.ndarray, mesh: MarkerMesh, axes: DeformationAxes,
                coeffs: np.ndarray | None = None, field: ParameterField | None = None) -> TexelBand:
    """The medium PDM at the mesh's K UV points (uv (K,2)): the coefficients (K,3,K') fitted
    there (``coeffs``, :attr:`.data.PdmData.vertex_coeffs`) or, for a model stored without
    them, sampled from the map (bilinear, covered texels only), and d1, d2 at the same
    points. A seam vertex has one UV per chart, and d1, d2 jump across seams (they live in
    texture space), so each chart's coefficients are evaluated with that chart's parameters,
    and :func:`medium_offsets` averages the results. ``field``: the parameter field at the UV
    points where already derived (a stored model's operators)."""
    if coeffs is None:
        S = uv_sampling_matrix(uv, medium.mask())[:, medium.index]
        coeffs = (S @ medium.coeffs.reshape(len(medium.index), -1)).reshape(len(uv), 3, -1)
    if field is None:
        field = ParameterField.build(axes, barycentric_operator(mesh, uv))
    return TexelBand.build(0, np.arange(len(uv)), coeffs.astype(np.float32), field)


def rest_onset(values: np.ndarray, rho: np.ndarray, fallback: np.ndarray | None,
               start: float = REST_ONSET, gain: np.ndarray | None = None) -> np.ndarray:
    """The medium band's values (F,K,3) float32 faded in from the ``fallback`` (F,K,3) (None:
    0) near rest, in place: ``fallback + (1 − falloff(ρ, start)) (values − fallback)`` where
    the gauge ρ (F,K) < ``start`` (:func:`service.methods.confidence.falloff`, a smoothstep
    from 0 at ρ = 0 to 1 at ``start``); the values at ρ ≥ ``start`` unchanged (bit for bit).
    With a per-point ``gain`` g (K,) float32 (:mod:`.fit_skill`; None: 1) the weight is
    ``g (1 − falloff)`` near rest and ``g`` elsewhere (points of g = 1 as without).
    The NumPy reference of :func:`.point_onset.onset_points`, which synthesis runs (tests pin
    the two bit for bit).

    Why (issue 17, "the PDM's max vertex error never exceeds the thin shell's"): at rest the
    fallback, the thin shell of the detailed neutral, *is* the neutral, exactly, while the
    polynomial's free constant a5 (ma2008 eq. 1; the intercept of the fit over every
    expression) is not 0: the medium PDM moved vertices at rest by up to 0.73 mm (family a,
    level 0, biquadratic, vertex 9404 at the face region's border; family b 0.50 mm, vertex
    16681), so every frame near the neutral was worse than the thin shell (shell max 0.00–0.02
    mm) and, at small deformations, the intercept sat on vertices the expression leaves
    alone. ρ (:mod:`.validity`) measures d against the largest training radius in its
    direction, so the onset is relative to each point's own range and unit-free. Chosen on
    family a (every map frame of the held-out performances, clean markers, face, float64
    frames): start 0.1 / 0.2 / 0.3 / 0.5 gave frames worse than the thin shell's max, in range
    10 / 10 / 10 / 9 of 31 (11 without), combinations 4 / 3 / 3 / 2 of 25 (6), out of range
    4 / 4 / 3 / 3 of 25 (5), mean face vertex error 0.187 / 0.187 / 0.187 / 0.190 mm (0.194)
    in range, 0.300 (0.308) combinations, 0.233 / 0.232 / 0.232 / 0.232 (0.240) out of
    range; 0.3 taken. Through ``benchmarks/generalization_report.py`` (PDM biquadratic, frames
    above the shell's max by more than 1 µm, clean / noisy / occluded): a in range 11 / 13 / 11
    → 9 / 11 / 9 of 31, combinations 6 / 10 / 7 → 3 / 7 / 4 of 25, out of range 5 / 5 / 7 →
    3 / 5 / 5 of 25; confirmed on family b: 7 / 3 / 9 → 4 / 2 / 6 of 30, 7 / 9 / 8 → 4 / 8 / 5
    of 22, 5 / 4 / 6 → 3 / 3 / 4 of 23, clean mean 0.184 → 0.175, 0.371 → 0.364, 0.325 → 0.316
    mm; the rest frames' 0.50 mm excess is gone. The frames left are lip and mouth-corner
    points whose polynomial is wrong inside its training range (README.md, "Rest onset of
    the medium band"). Neither the fit (``neutral_anchor``, which
    retrains) nor the fine and albedo bands are touched: their fallback at rest is their own
    constant term, which the polynomial already equals there."""
    rho = np.asarray(rho)
    near = rho < start
    damped = near if gain is None else near | (np.asarray(gain, np.float32) < 1)
    if not damped.any():
        return values
    idx = np.flatnonzero(damped)
    r = rho.reshape(-1)[idx]
    w = np.ones(len(idx), np.float32)
    close = r < start
    w[close] = 1 - falloff(r[close], start, np.float32)
    if gain is not None:
        w *= np.broadcast_to(np.asarray(gain, np.float32), rho.shape).reshape(-1)[idx]
    w = w[:, None]
    flat = values.reshape(-1, 3)
    if fallback is None:
        flat[idx] *= w
    else:
        fb = np.asarray(fallback, np.float32).reshape(-1, 3)[idx]
        flat[idx] = fb + w * (flat[idx] - fb)
    return values


def medium_offsets(c: np.ndarray, seam_average: sp.csr_matrix, neutral_offset: np.ndarray) -> np.ndarray:
    """Medium-band offsets (F,n,3) in the base's tangent frames from the medium PDM's values
    c (F,K,3) at the UV points (:func:`vertex_band`'s ``evaluate``, or its valid values,
    :meth:`PdmEvaluator.medium_values`), seam-averaged ((n,K)) onto the vertices plus the
    neutral's static ``neutral_offset`` (n,3)."""
    F, K = c.shape[:2]
    c = (seam_average @ c.transpose(1, 0, 2).reshape(K, 3 * F)).reshape(-1, F, 3)
    return c.transpose(1, 0, 2) + neutral_offset


@dataclass(frozen=True)
class PdmEvaluator:
    """What synthesis evaluates per frame, derived once from :class:`~.data.PdmData` by
    :meth:`build` (ma2008 §5) and unchanged afterwards.

    Attributes (n vertices, K UV points, Pf fine texels)
    ----------
    base : BaseSurface              head pose weights' rest markers, thin-shell basis, frames
    vertex_band : TexelBand         the medium PDM at the K UV points (:func:`vertex_band`)
    fine : TexelBand | CoveredTexels   the fine PDM, texels grouped by coarse element; with
                                    ``fine_strain`` their layout only (resolution, index): the
                                    (d1, d2) band is stored for renderers, never evaluated
    albedo : TexelBand | None       the albedo PTM, grouped the same way (None: no albedo)
    orders : dict name → (P,) int   each band's points as indices into the data's band
                                    (row-major texels; the UV points for ``vertex``)
    seam_average : (n,K) CSR        UV points → vertices (seam mean)
    fine_sampler : (n,Pf) CSR       fine texels → vertices (``mesh_detailed``)
    normal_mapper : NormalMapper    tangent-space normal maps at the fine resolution
    fine_inverse : (Hf·Hf,) uint32  each texel's position in the fine band (``fine.index``),
                                    :data:`~service.geometry.texel_image.NOT_COVERED` where
                                    uncovered (:func:`~service.geometry.texel_image.band_image`)
    validity : Validity | None      where the polynomial holds (:mod:`.validity`; None when
                                    ``validity_width`` is None)
    shell_correction : (n,M) float32   thin-shell basis of the detailed neutral minus the
                                    smooth neutral's (:meth:`shell_fallback`)
    shell_offset : (n,3) float64    detailed minus smooth neutral, world, mm
    uv_vertex : (K,) int64          the vertex of each UV point
    shell_mesh : ShellMesh | None   the per-frame medium mesh on the compiled shell kernels
                                    (:mod:`.shell_mesh`: base surface, fallback, composition;
                                    None with ``medium_regression``, whose mesh is
                                    ``base.deform`` plus the regression's offsets)
    point_validity : PointValidity | None   the medium band's validity at the UV points on
                                    compiled kernels (:mod:`.point_validity`; None without validity;
                                    with ``medium_regression`` its gauge only, no sector box)
    onset : callable | None         the medium band's rest onset (:func:`rest_onset`) on its
                                    compiled kernel (:func:`.point_onset.point_onset`; None
                                    without validity)
    fine_strain : StrainBand | None  the strain-driven fine band in ``fine``'s texel order
                                    (:mod:`.strain_band`; None: ``fine`` drives the fine band)
    strain_field : StressField | None   the detailed neutral's strain operators
    strain_texels : TexelStrain | None   vertices → fine texels (barycentric, padded rows),
                                    ``fine``'s order
    strain_rho : TexelStrain | None   the UV points' ρ → fine texels (padded ``corner``,
                                    float64 ``weight``) for the strain band's fade
    """

    data: PdmData = dataclasses.field(repr=False)
    base: BaseSurface
    vertex_band: TexelBand
    fine: "TexelBand | CoveredTexels"
    albedo: TexelBand | None
    orders: dict
    seam_average: sp.csr_matrix
    fine_sampler: sp.csr_matrix
    normal_mapper: NormalMapper
    fine_inverse: np.ndarray
    validity: Validity | None
    shell_correction: np.ndarray = dataclasses.field(metadata=UNREAD)   # synthesis reads shell_mesh's copy
    shell_offset: np.ndarray
    uv_vertex: np.ndarray
    shell_mesh: "ShellMesh | None" = dataclasses.field(default=None, repr=False)
    point_validity: "PointValidity | None" = dataclasses.field(default=None, repr=False)
    onset: "Callable | None" = dataclasses.field(default=None, repr=False, compare=False)
    medium_gain: np.ndarray | None = None
    fine_strain: StrainBand | None = None
    strain_field: StressField | None = dataclasses.field(default=None, repr=False)
    strain_texels: TexelStrain | None = dataclasses.field(default=None, repr=False)
    strain_rho: TexelStrain | None = dataclasses.field(default=None, repr=False)

    @classmethod
    def build(cls, d: PdmData, base: BaseSurface | None = None,
              derived: PdmDerived = PdmDerived()) -> "PdmEvaluator":
        """Precompute everything of the class docstring from ``d``; ``base`` (the training's)
        and the arrays of ``derived`` (a stored model's cache) are used instead of their
        computation where given (the rest is derived from ``d.S_train``).

        ``derived.operators`` (:meth:`operators` of the evaluator that was saved, issue 23)
        replaces what the layout alone determines: the rasterization at the fine resolution,
        the barycentric parameter fields with the fine and albedo texels' element order, and
        the sparse seam, sampling and validity operators, the detailed neutral's shell
        correction (:meth:`shell_fallback`; a cache of this version without it derives it) (at level 1 most of a build: under
        cProfile, of 17.4 s wall, :func:`barycentric_operator` of the 700k texels took 11.9 s
        and ``rasterize_uv`` 2.4 s; the whole load measured 4.8 → 0.45 s of CPU, wall
        7.1 → 0.67 s at load average 4.4). They
        are the saved evaluator's own arrays (memory-mapped as the store reads them), so
        synthesis is bit for bit the same; without them (a model stored before they were
        kept, or of another :data:`OPERATORS_VERSION`) they are derived as before."""
        ops = derived.operators
        if not ops or int(ops.get("version", -1)) != OPERATORS_VERSION:
            ops = {}
        if base is None:
            frame_field = FrameField.from_operators(d.faces, {k: m for k in FRAME_OPERATORS if (
                m := sparse_matrix(ops, f"frame_field_{k}")) is not None})
            base = BaseSurface.from_smooth(d.smooth, d.faces, d.uv, d.uv_faces, d.handles, d.rest_markers,
                                           basis=derived.basis, energy=derived.energy, frame_field=frame_field)
            base = base.with_marker_noise(d.params.marker_noise_mm, d.prior_scale_mm, marker_prior=d.marker_prior)
        n, K = d.n_vertices, len(d.uv)
        fields = {k: ParameterField.from_arrays(d.axes, a) for k in ("vertex", "fine", "albedo")
                  if (a := _members(ops, f"{k}_field"))}
        bands = {"vertex": vertex_band(d.medium, d.uv, d.mesh, d.axes, d.vertex_coeffs, fields.get("vertex"))}
        orders = {"vertex": np.arange(K)}
        layouts = {}            # texels whose band is not evaluated: the strain band drives them
        stored_only = {}        # ... whose validity envelope is still stored
        for name in ("fine", "albedo"):
            m = getattr(d, name)
            if m is not None:
                layout_only = name == "fine" and d.fine_strain is not None
                if (name in fields or layout_only) and f"{name}_order" in ops:
                    order, fld = np.array(ops[f"{name}_order"]), fields.get(name)
                else:
                    order, fld = element_field(d.mesh, d.axes, m.index, m.resolution)
                if len(order) != len(m.index) or (fld is not None and fld.n_points != len(order)):
                    raise ValueError(f"the stored {name} operators do not fit its {len(m.index)} texels")
                orders[name] = order
                if layout_only:         # the strain band drives it: ma2008's (d1, d2) band is never evaluated
                    layouts[name] = CoveredTexels(m.resolution, m.index[order])
                    if d.validity is None and d.params.validity_width is not None:
                        # ... but its envelope is stored, for a server of an earlier version
                        fld = fld if fld is not None else element_field(d.mesh, d.axes, m.index, m.resolution)[1]
                        stored_only[name] = TexelBand.build(m.resolution, m.index[order], m.coeffs[order], fld)
                    continue
                terms = ops.get(f"{name}_terms")          # term-major, as the band reads them
                ok = (terms is not None and terms.shape == m.coeffs.shape[::-1] and terms.dtype == np.float32
                      and terms.flags.c_contiguous)
                bands[name] = TexelBand.build(m.resolution, m.index[order], None if ok else m.coeffs[order], fld,
                                              terms=terms if ok else None)
        for name, band in bands.items():
            limit = derived.limits.get(name)
            bands[name] = dataclasses.replace(band, limit=_limits(band.field, d.S_train) if limit is None else limit)
        seam = sparse_matrix(ops, "seam_average")
        if seam is None:
            seam = seam_average_matrix(d.uv_faces, d.faces, n, K)
        fine = bands.get("fine") or layouts["fine"]
        Hf = fine.resolution
        fine_sampler = sparse_matrix(ops, "fine_sampler")
        if fine_sampler is None:
            fine_sampler = sampling_matrix(d.uv, d.uv_faces, d.faces, n, fine.mask())[:, fine.index].tocsr()
        normal_mapper = NormalMapper.from_arrays(_members(ops, "normal_mapper"), n, len(d.faces))
        if normal_mapper is None or normal_mapper.shape != (Hf, Hf):
            if "raster_triangle" in ops:    # the rasterization of an older cache (float32: all it reads)
                triangle = ops["raster_triangle"]
                raster = UVRaster(triangle, ops["raster_barycentric"], triangle >= 0)
            else:
                raster = rasterize_uv(d.uv, d.uv_faces, Hf, Hf)
            normal_mapper = NormalMapper(raster, d.faces, d.uv, d.uv_faces, n)
        texel_rho = {k: m for k in ("fine", "albedo") if k in bands
                     and (m := sparse_matrix(ops, f"{k}_texel_rho")) is not None}
        detailed = detailed_neutral(base, d.neutral_offset)
        correction = ops.get("shell_correction")
        if correction is None:           # the detailed neutral's thin shell (seconds at level 0)
            correction = np.asfortranarray(thin_shell_basis(detailed, d.faces, d.handles, dtype=np.float32)
                                           - base.basis)
        uv_vertex = np.zeros(K, np.int64)
        uv_vertex[np.asarray(d.uv_faces).ravel()] = np.asarray(d.faces).ravel()
        shell = (correction, detailed - base.smooth, uv_vertex)
        from service.geometry.texel_image import inverse_index
        from service.methods.pdm.shell_mesh import ShellMesh     # Numba: only where a model is built

        from service.methods.pdm.point_onset import point_onset
        from service.methods.pdm.point_validity import PointValidity

        shell_mesh = None if d.medium_regression is not None else \
            ShellMesh.build(base.smooth, d.faces, d.uv, d.uv_faces, base.basis, correction, shell[1],
                            d.neutral_offset, uv_vertex, seam, _members(ops, "shell_mesh"))
        validity = _validity(d, base, bands, orders, seam, shell, texel_rho, stored_only)
        if validity is not None and "fine" in bands:
            validity.prepare("fine", fine.coeffs)        # the fine band's compiled validity
        strain = {}
        if d.fine_strain is not None:
            texels = TexelStrain.from_arrays(ops, "strain_texels")
            raster = None
            if texels is None or texels.corner.shape != (3, len(fine.index)):
                raster = rasterize_uv(d.uv, d.uv_faces, Hf, Hf)
                texels = TexelStrain.from_csr(interpolation_matrix(raster, d.faces, n)[fine.index])
            # the fade's ρ operator, UV points → fine texels, padded (float64 weights, SciPy's sums)
            rho_op = None if validity is None else TexelStrain.from_arrays(ops, "strain_rho")
            if validity is not None and (rho_op is None or rho_op.corner.shape != (3, len(fine.index))):
                raster = rasterize_uv(d.uv, d.uv_faces, Hf, Hf) if raster is None else raster
                rho_op = TexelStrain.from_csr(interpolation_matrix(raster, d.uv_faces, K)[fine.index], np.float64)
            band = StrainBand.from_arrays(ops, "strain_band")       # as the evaluator holds it, mapped
            if band is None or band.coeffs.shape != d.fine_strain.coeffs.shape:
                band = d.fine_strain.permuted(orders["fine"])
            stored = {k: v for k in STRAIN_FIELD_ARRAYS if (v := ops.get(f"strain_field_{k}")) is not None}
            stored.update({k: m for k in STRAIN_FIELD_MATRICES if (m := sparse_matrix(ops, f"strain_field_{k}")) is not None})
            field = StressField.from_operators(detailed, d.faces, stored) or \
                StressField.build(detailed, d.faces, d.uv, d.uv_faces, 0)
            strain = {"fine_strain": band, "strain_texels": texels, "strain_rho": rho_op, "strain_field": field}
        return cls(
            data=d, base=base, vertex_band=bands["vertex"], fine=fine, albedo=bands.get("albedo"),
            orders=orders, seam_average=seam, fine_sampler=fine_sampler,
            normal_mapper=normal_mapper,
            fine_inverse=inverse_index(fine.index, Hf * Hf), validity=validity, shell_correction=shell[0],
            shell_offset=shell[1], uv_vertex=uv_vertex, shell_mesh=shell_mesh,
            point_validity=None if validity is None else PointValidity.build(
                validity, bands["vertex"].terms, ops.get("point_box"), values=d.medium_regression is None),
            onset=None if validity is None else point_onset, medium_gain=medium_gain(d), **strain)

    @property
    def bands(self) -> dict[str, TexelBand]:
        """The bands synthesis evaluates per frame: the medium PDM at the UV points
        (``vertex``), the fine and (if trained) the albedo texels. The medium texel maps
        themselves are only read to build ``vertex`` and written for renderers."""
        return {k: b for k, b in (("vertex", self.vertex_band), ("fine", self.fine),
                                  ("albedo", self.albedo)) if isinstance(b, TexelBand)}

    def derived(self) -> PdmDerived:
        """What a load of the data would recompute (the store's optional files)."""
        return PdmDerived(basis=self.base.basis, energy=self.base.energy,
                          limits={k: b.limit for k, b in self.bands.items()}, operators=self.operators())

    def operators(self) -> dict[str, np.ndarray]:
        """What :meth:`build` derives from the data's layout and neutral alone (no training
        statistics), as named arrays for the
        store (``derived.operators`` of a later build): ``version``
        (:data:`OPERATORS_VERSION`); ``<band>_field_*`` the bands' parameter fields
        (:meth:`.deformation.ParameterField.arrays`) and ``<band>_order`` the fine and albedo
        texels' element order; ``shell_correction`` (n,M) float32 the detailed neutral's
        thin-shell basis less the base's (:meth:`shell_fallback`); ``shell_mesh_*`` the
        compiled mesh's vertex order, both bases in it and its ShellFrames
        (:meth:`.shell_mesh.ShellMesh.stored`: a load maps them instead of permuting 2 × (n,M)
        and building the frames' order and incidence; a cache without them does that);
        ``<band>_terms`` (K,C,P) float32 the fine and albedo bands' coefficients term-major in
        that order (:attr:`.texel_band.TexelBand.terms`; a cache without them copies them from
        the maps', ~85 ms at level 1); ``frame_field_*`` the base surface's :class:`~service.geometry.tangent_frames.FrameField`
        operators (CSR; a cache without them builds it, ~70 ms at level 1); the CSR matrices ``seam_average``, ``fine_sampler`` and
        ``<band>_texel_rho`` (:func:`service.io.npz.sparse_members`); ``strain_texels_*`` the
        strain band's padded vertices → texels operator (:meth:`.strain_band.TexelStrain.arrays`),
        ``strain_rho_*`` its fade's, ``strain_band_*`` the band in the fine texels' order with
        its coefficients term-major (:meth:`.strain_band.StrainBand.arrays`: mapped, not
        permuted at load, 0.17 s at level 1) and ``strain_field_*`` its
        :class:`~service.geometry.surface_strain.StressField` operators (not built at load, 0.2 s);
        ``normal_mapper_*``
        the normal mapper's arrays (:meth:`~service.geometry.normal_map.NormalMapper.arrays`,
        27 MB at 1024²: a load maps them instead of reading the rasterization, 16 MB, and
        building the mapper, ~40 ms at level 1; a cache of this version with ``raster_triangle``
        (H,H) int32 and ``raster_barycentric`` (H,H,3) float32 instead, as stored before,
        builds it from them); ``point_box`` (D,P,2,3) float32 the medium band's sector box in
        the layout its kernel reads (:meth:`.point_validity.PointValidity.point_box`, 35 MB at
        level 1: mapped instead of transposed at load; a cache without it transposes)."""
        d, Hf = self.data, self.fine.resolution
        out = {"version": np.int64(OPERATORS_VERSION), **sparse_members("seam_average", self.seam_average),
               **sparse_members("fine_sampler", self.fine_sampler), "shell_correction": self.shell_correction,
               **({} if self.strain_texels is None else self.strain_texels.arrays("strain_texels")),
               **({} if self.strain_rho is None else self.strain_rho.arrays("strain_rho")),
               **({} if self.fine_strain is None else self.fine_strain.arrays("strain_band")),
               **({} if self.shell_mesh is None else
                  {f"shell_mesh_{k}": v for k, v in self.shell_mesh.stored().items()})}
        for k, m in self.base.frame_field.operators().items():
            out.update(sparse_members(f"frame_field_{k}", m))
        for k, v in ({} if self.strain_field is None else self.strain_field.operators()).items():
            out.update(sparse_members(f"strain_field_{k}", v) if k in STRAIN_FIELD_MATRICES else {f"strain_field_{k}": v})
        for name, band in self.bands.items():
            out.update({f"{name}_field_{k}": v for k, v in band.field.arrays().items()})
            if name != "vertex":
                out[f"{name}_terms"] = band.terms
        out.update({f"{name}_order": order for name, order in self.orders.items() if name != "vertex"})
        for name, m in ({} if self.validity is None else self.validity.texel_rho).items():
            out.update(sparse_members(f"{name}_texel_rho", m))
        out.update({f"normal_mapper_{k}": v for k, v in self.normal_mapper.arrays().items()})
        if self.point_validity is not None and len(self.point_validity.box):
            out["point_box"] = self.point_validity.box
        return out

    def validity_data(self) -> ValidityData | None:
        """The validity regions as stored (:class:`~.validity.ValidityData`: the envelopes in
        the data's point order), None without validity."""
        v = self.validity
        if v is None:
            return None
        return ValidityData(v.hull, {k: _unpermute(e, self.orders[k]) for k, e in v.envelope.items()}, v.sectors,
                            v.sector_box)

    def deformation(self, markers: np.ndarray, base: BaseSurface | None = None
                    ) -> tuple[HeadPose, np.ndarray, np.ndarray]:
        """Head pose, complete handle displacements u_H (F,M,3) and S (F,M,5) of world markers
        (F,M,3), denoised by ``base`` (default this evaluator's; a request's
        :meth:`request_base` when σ is estimated per request)."""
        base = self.base if base is None else base
        pose = head_alignment(markers, base.rest_markers, self.data.pose_weights)
        aligned = pose.remove(markers)
        u_H = base.handle_displacements(aligned)
        return pose, u_H, deformation_vectors(self.data.mesh, base.denoised_markers(aligned, u_H), offsets=u_H)

    def request_base(self, markers: np.ndarray) -> tuple[BaseSurface, np.ndarray | None]:
        """The base surface a request of world markers (F,M,3) is denoised with, and the
        per-frame noise estimates σ̂ (F,) mm: this evaluator's base and None unless
        ``marker_noise_mm = "auto"``, where σ is estimated once over the whole request
        (:class:`~service.geometry.marker_prior.AdaptiveDenoiser`: the median of the frames'
        σ̂, so frame chunks share one σ).

        Raises :class:`TooFewMarkers` for a frame with too few visible markers."""
        if not isinstance(self.base.denoise, AdaptiveDenoiser):
            return self.base, None
        pose = head_alignment(markers, self.base.rest_markers, self.data.pose_weights)
        u = pose.remove(markers) - self.base.rest_markers
        sigma = self.base.denoise.frame_noise(u)
        return self.base.with_noise_estimate(float(np.median(sigma))), sigma

    def gauge(self, d1: np.ndarray, d2: np.ndarray) -> tuple[np.ndarray, tuple]:
        """ρ (F,K) float32 at the UV points for their parameters d1, d2 (F,K), and the
        sectors of their directions for :meth:`medium_values`
        (:meth:`.point_validity.PointValidity.gauge`; a model with validity)."""
        return self.point_validity.gauge(d1, d2)

    def medium_values(self, d1: np.ndarray, d2: np.ndarray, rho: np.ndarray | None = None,
                      sectors: tuple | None = None, fallback: np.ndarray | None = None) -> np.ndarray:
        """The medium PDM (F,K,3) float32 at the UV points for d1, d2 (F,K); with ρ (F,K) and
        the ``sectors`` of :meth:`gauge`, continued, limited and faded outside the hull
        towards ``fallback`` (F,K,3) (:meth:`shell_fallback`; None: 0) (:mod:`.validity`, on
        the kernels of :mod:`.point_validity`), and faded in from it near rest
        (:func:`rest_onset`, on the kernel of :mod:`.point_onset`)."""
        if rho is None:
            return self.vertex_band.evaluate(d1, d2)
        return self.onset(self.point_validity.values(d1, d2, rho, sectors, fallback), fallback, rho, REST_ONSET,
                          self.medium_gain)

    def medium_offsets(self, d1: np.ndarray, d2: np.ndarray, rho: np.ndarray | None = None,
                       sectors: tuple | None = None, fallback: np.ndarray | None = None) -> np.ndarray:
        """:func:`medium_offsets` (F,n,3) of this model's :meth:`medium_values`."""
        return medium_offsets(self.medium_values(d1, d2, rho, sectors, fallback), self.seam_average,
                              self.data.neutral_offset)

    def shell_fallback(self, u_H: np.ndarray, X: np.ndarray, rows: list | None = None) -> np.ndarray:
        """:func:`shell_fallback` (F,K,3) of this model for u_H (F,M,3) and the base surfaces X
        (``rows``: their float32 frames, ``FrameField.rows32``, where already computed)."""
        return shell_fallback(self.base, self.data.neutral_offset, self.shell_correction, self.shell_offset,
                              self.uv_vertex, u_H, X, rows)

    def fine_band(self, S: np.ndarray, margin: float | None, rho: np.ndarray | None = None,
                  medium: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Fine displacement (F,Pf) at the fine texels and the clamped fraction (F,); with ρ
        (F,K) at the UV points, continued and faded outside the hull (:mod:`.validity`).

        With a strain-driven band (``fine_strain``) the values come from the strain of the
        head-aligned medium meshes ``medium`` (F,n,3) instead, clamped to the training
        (``params.extrapolation_margin``, whatever ``margin`` says: the band's own guards)
        and faded by the texels' w(ρ) (:mod:`.strain_band`); the fraction is of the vertices
        whose strain was clamped."""
        if self.fine_strain is None:
            values, frac = self.fine.synthesize(S, margin, self._band_validity(self.fine, "fine", rho))
            return values[..., 0], frac
        guard = self.data.params.extrapolation_margin if margin is not None or rho is not None else None
        out, frac = np.empty((len(medium), len(self.fine.index)), np.float32), np.empty(len(medium))
        for k, V in enumerate(medium):
            fade = None
            if rho is not None and np.max(rho[k]) > 1:   # else every texel's ρ ≤ 1: w = 1
                op = self.strain_rho
                fade = TexelFade(op.corner, op.weight, rho[k], self.validity.width)
            frac[k] = self.fine_strain.compiled(self.strain_field.stress32(V), self.strain_texels, guard, fade, out[k])
        return out, frac

    def albedo_band(self, S: np.ndarray, margin: float | None, rho: np.ndarray | None = None) -> np.ndarray:
        """Albedo (F,Pa,3) at the albedo texels; with ρ (F,K) valid as :meth:`fine_band`."""
        return self.albedo.synthesize(S, margin, self._band_validity(self.albedo, "albedo", rho))[0]

    def _band_validity(self, band: TexelBand, name: str, rho: np.ndarray | None) -> BandValidity | None:
        return None if rho is None else self.validity.band(name, band.coeffs, rho)


def medium_gain(d: PdmData) -> np.ndarray | None:
    """The medium band's gain (K,) float32 at the UV points (:func:`.fit_skill.skill_gain` of the
    stored skill and ``params.fit_skill_floor``); None (no gain) without either."""
    floor = d.params.fit_skill_floor
    return None if floor is None or d.medium_skill is None else skill_gain(d.medium_skill, floor)


def _members(arrays: dict, prefix: str) -> dict:
    """The members ``<prefix>_<name>`` of ``arrays`` by ``name``."""
    n = len(prefix) + 1
    return {k[n:]: v for k, v in arrays.items() if k.startswith(prefix + "_")}


def detailed_neutral(base: BaseSurface, neutral_offset: np.ndarray) -> np.ndarray:
    """The detailed neutral (n,3): the smooth neutral plus its per-vertex offset (n,3)."""
    return base.smooth + np.einsum("nji,nj->ni", base.frames(base.smooth), neutral_offset)


def shell_fallback(base: BaseSurface, neutral_offset: np.ndarray, correction: np.ndarray, offset: np.ndarray,
                   uv_vertex: np.ndarray, u_H: np.ndarray, X: np.ndarray | None = None,
                   rows: list | None = None) -> np.ndarray:
    """The medium band's fallback (F,K,3) float32 at the UV points (:mod:`.validity`, module
    docstring 4.): the thin shell of the detailed neutral, ``V + B_det u_H`` (the *no
    detail* result), for handle displacements u_H (F,M,3), as a medium offset from the base
    surfaces ``X = X̄ + B u_H`` (F,n,3; computed when None) in their tangent frames, less the
    static ``neutral_offset`` (n,3): ``Frame(X) (offset + (B_det − B) u_H) − neutral_offset``
    with ``correction`` = B_det − B (n,M), ``offset`` = V − X̄ (n,3), taken at the UV points'
    vertices ``uv_vertex`` (K,). 0 at the neutral. The frames are FrameField's float32 ones
    (``rows``: X's ``FrameField.rows32`` where already computed). Batched NumPy (BLAS)
    arithmetic: what training's validity regions (the sector envelope and box) measure the
    training frames with; synthesis computes the same fallback per frame on the compiled
    kernels (:meth:`.shell_mesh.ShellMesh.fallback`; the two within ~1e-4 of the largest
    |fallback|, both against float64, tests/methods/pdm/test_shell_mesh.py).

    Computed at every UV point (issue 23 asked for it only where it can change the result):
    a point's fallback is unused exactly when ρ ≤ 1, the box does not clip and the norm is
    within the envelope, which needs ``|fallback_c|`` bounded without the product. Measured on
    the level-1 sample actor (``heldout_in_range`` frames 7–49, every 7th), bounding with
    ``Frame(X)·offset − neutral_offset`` computed and ``‖(B_det − B)_v u_H‖`` by
    Cauchy–Schwarz per row (or a rank-32 SVD part plus its residual's, or 30 marker groups)
    leaves 92–99.8 % of the points unproven; even the exact ``‖(B_det − B)_v u_H‖`` leaves
    33–54 %, because 9–37 % of the points genuinely fade or clip there and the box is tight
    per channel. A skip would save little of the product (3.8–4.2 ms), so it is not done."""
    from service.geometry.thin_shell import apply_basis

    X = base.deform(u_H) if X is None else X
    world = (offset + apply_basis(correction, u_H)).astype(np.float32)                 # (F,n,3)
    local = base.frame_field.to_frame(X, world, rows)                  # (F,n,3), component-major memory
    out = np.empty((len(local), len(uv_vertex), 3), np.float32)
    point = np.dtype((np.void, 3 * out.itemsize))
    for f, frame in enumerate(local):   # less the neutral's offset into C order, then one 12-byte
        a = np.subtract(frame, neutral_offset, out=np.empty(frame.shape, np.float32))     # item per
        np.take(a.view(point).reshape(-1), uv_vertex, out=out[f].view(point).reshape(-1))  # UV point
    return out                          # (the same values as the strided gather: 0.85 → 0.46 ms)


def _validity(d: PdmData, base: BaseSurface, bands: dict[str, TexelBand], orders: dict[str, np.ndarray],
              seam: sp.csr_matrix, shell: tuple, texel_rho: dict | None = None,
              stored_only: dict | None = None) -> Validity | None:
    """The validity regions (:mod:`.validity`) of the training S at the UV points, or None
    when ``params.validity_width`` is None (the extrapolation limit applies instead): the
    stored ``d.validity`` (its envelopes put in the bands' order ``orders``), or, for a model
    stored without it, derived from ``d.S_train`` (seconds). ``shell``: the evaluator's
    (shell_correction, shell_offset, uv_vertex) (:meth:`PdmEvaluator.shell_fallback`), the
    fallback the medium band's sector envelope and box are measured from; ``texel_rho`` as
    :meth:`.validity.Validity.build`'s. Only the evaluated ``bands`` take ρ; a stored envelope
    of another band (the (d1, d2) fine band of a strain-driven model) is kept, and derived
    for ``stored_only`` ones, so the model stays loadable by a server of an earlier version."""
    if d.params.validity_width is None:
        return None
    S = d.S_train

    def over_training(field):          # the field's (d1, d2) of the training S, a chunk at a time
        return lambda: (field(S[t:t + FRAME_CHUNK]) for t in range(0, len(S), FRAME_CHUNK))

    def with_shell(field):             # ... and each frame's shell fallback (u_H: S's offsets)
        def chunks():
            for t in range(0, len(S), FRAME_CHUNK):
                u_H = S[t:t + FRAME_CHUNK, :, :3]
                yield (*field(S[t:t + FRAME_CHUNK]), shell_fallback(base, d.neutral_offset, *shell, u_H))
        return chunks

    vb = bands["vertex"]
    stored = d.validity is not None and d.validity.sector_box is not None
    sectors, box = (d.validity.sectors, d.validity.sector_box) if stored else \
        sector_envelope(vb.coeffs, with_shell(vb.field), None, box=True)    # a few seconds at level 0
    if d.validity is not None:
        hull = d.validity.hull
        envelope = {k: d.validity.envelope[k][orders[k]] for k in orders if k in d.validity.envelope}
    else:
        hull = training_hull(over_training(bands["vertex"].field))
        envelope = {k: training_envelope(b.coeffs, over_training(b.field), Validity.fallback(k, b.coeffs))
                    for k, b in {**bands, **(stored_only or {})}.items()}
    texels = {k: (b.resolution, b.index) for k, b in bands.items() if k != "vertex"}
    return Validity.build(hull, envelope, d.params.validity_width, d.params.validity_slope, d.uv,
                          d.uv_faces, seam, base.smooth, d.faces, texels, sectors, box, texel_rho)


class PdmModel:
    """A trained PDM model (ma2008): the stored :class:`~.data.PdmData` and its
    :class:`PdmEvaluator`; :meth:`synthesize` turns markers into meshes and maps. Build with
    :func:`train` or :meth:`load`; neither part changes after construction."""

    def __init__(self, data: PdmData, evaluator: PdmEvaluator | None = None):
        self.data = data
        self.evaluator = evaluator or PdmEvaluator.build(data)

    @property
    def metrics(self) -> dict:
        return self.data.metrics

    @property
    def params(self) -> PdmParams:
        return self.data.params

    @property
    def faces(self) -> np.ndarray:
        """(m,3) the mesh's triangles (with ``uv`` (K,2), ``uv_faces`` (m,3): the layout the
        service writes meshes and maps with)."""
        return self.data.faces

    @property
    def uv(self) -> np.ndarray:
        return self.data.uv

    @property
    def uv_faces(self) -> np.ndarray:
        return self.data.uv_faces

    @property
    def n_vertices(self) -> int:
        return self.data.n_vertices

    @property
    def n_markers(self) -> int:
        return self.data.n_markers

    @property
    def marker_modes(self) -> MarkerModes | None:
        """:meth:`BaseSurface.marker_modes` of the model's base surface."""
        return self.evaluator.base.marker_modes(self.data.pose_weights)

    def neutral(self) -> np.ndarray:
        """The detailed neutral (n,3): the smooth neutral plus its per-vertex offset."""
        return detailed_neutral(self.evaluator.base, self.data.neutral_offset)

    # ------------------------------------------------------------------ synthesis
    def synthesize(self, markers: np.ndarray, outputs: Sequence[str] = ("mesh", "displacement"),
                   clamp: bool = True, half: bool = False, confidence: bool = True,
                   captured: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Meshes and maps for world-space markers (F,M,3), NaN for occluded (ma2008 §5).

        Returns a dict with (as asked in ``outputs``, API.md): ``vertices`` (F,n,3) medium
        scale in the input's world pose, ``vertices_detailed`` (F,n,3) with the fine map
        baked along the normals, ``displacement`` (F,H,H) fine-scale normal displacement,
        ``albedo`` (F,Ha,Ha,3), ``normal_map`` (F,H,H,3) tangent space; always ``faces``,
        ``clamped`` (F,) the fraction of points outside their validity hull (or, with
        ``validity_width`` None, whose d1/d2 hit the extrapolation limit): of the fine map's
        texels when a fine-scale output (``displacement``, ``normal_map``, ``mesh_detailed``)
        is asked (a strain-driven fine band: of the vertices whose strain was clamped), else
        of the mesh's UV points (the fine band is not computed for such a call); ``confidence`` (F,) and ``confidence_vertices`` (F,n)
        (:mod:`service.methods.confidence`, :meth:`.validity.Validity.confidence`). With
        ``clamp`` the detail outside the hull is continued and faded to the neutral's
        (:mod:`.validity`); without, the raw polynomial. With ``marker_noise_mm = "auto"``
        the request's markers are denoised with σ estimated over the request
        (:meth:`PdmEvaluator.request_base`). Whatever the σ setting, each frame's confidence
        (per frame and per vertex) is the validity's times the input factor of its markers
        (:meth:`.base_surface.BaseSurface.input_confidence`, the rule of
        :mod:`service.methods.confidence`: the Wiener fraction at its own noise estimate,
        which occlusion enters through, times the size factor of its handle displacements
        u_H); the fade stays the validity's. ``captured`` (F,M,3): the same frames as
        captured, where ``markers`` were smoothed in time (a synthesis job's
        ``marker_filter_frames``): the noise factor then reads their σ̂
        (:meth:`.base_surface.BaseSurface.captured_noise`); the synthesis is unchanged.

        With ``half`` the maps (``displacement``, ``normal_map``, ``albedo``) are float16:
        NumPy's ``astype(np.float16)`` of the float32 maps bit for bit, written as such by the
        map kernels (:func:`~service.geometry.texel_image.band_image`, the normal mapper's
        texel pass; :func:`~service.geometry.half_kernel.binary16`), not converted after: a
        half-precision stream frame (issue 23) neither writes the 16 MB of float32 maps nor
        reads them back. With ``confidence`` False the result has no ``confidence`` and
        ``confidence_vertices``, and neither is computed (for a caller that does not send them,
        as the gRPC stream's MeshFrame: ~1 ms of a level-1 mesh frame's 16); everything else
        is the same, bit for bit.

        Raises :class:`InvalidInput` for a wrong marker count or too few visible markers.
        """
        ev, d = self.evaluator, self.data
        markers = np.asarray(markers, dtype=np.float64)
        if markers.ndim == 2:
            markers = markers[None]
        M = self.n_markers
        if markers.ndim != 3 or markers.shape[1:] != (M, 3):
            raise InvalidInput(f"model expects markers (F,{M},3), got {markers.shape}")
        check_outputs(outputs)
        if "albedo" in outputs and ev.albedo is None:
            raise InvalidInput("this model was trained without albedo maps; 'albedo' is not available")
        nf, n = len(markers), self.n_vertices
        out: dict[str, np.ndarray] = {"faces": d.faces.astype(np.int32), "clamped": np.zeros(nf, np.float32)}
        if confidence:
            out[CONFIDENCE], out[VERTEX_CONFIDENCE] = np.ones(nf, np.float32), np.ones((nf, n), np.float32)
        want = set(outputs)
        if want & {"mesh", "mesh_detailed"}:
            out["vertices"] = np.empty((nf, n, 3), np.float32)
        if "mesh_detailed" in want:
            out["vertices_detailed"] = np.empty((nf, n, 3), np.float32)
        Hf = ev.fine.resolution
        maps = np.float16 if half else np.float32
        if "displacement" in want:
            out["displacement"] = np.empty((nf, Hf, Hf), maps)
        if "normal_map" in want:
            out["normal_map"] = np.empty((nf, Hf, Hf, 3), maps)
        if "albedo" in want:
            Ha = ev.albedo.resolution
            out["albedo"] = np.zeros((nf, Ha, Ha, 3), np.float32)
        valid = ev.validity
        margin = d.params.extrapolation_margin if clamp and valid is None else None
        fine = bool(want & {"displacement", "normal_map", "mesh_detailed"})
        try:
            base, sigma = ev.request_base(markers)
        except TooFewMarkers as e:
            raise InvalidInput(f"frame {e.frame} has {e.visible} visible markers, at "
                               f"least {e.required} are needed") from None
        if confidence and captured is not None:   # σ̂ of the noise factor only: the denoiser keeps its σ
            noise = base.captured_noise(captured, d.pose_weights, markers.shape)
            sigma = sigma if noise is None else noise
        for s in range(0, nf, FRAME_CHUNK):
            sl = slice(s, min(s + FRAME_CHUNK, nf))
            try:
                pose, u_H, S = ev.deformation(markers[sl], base)
            except TooFewMarkers as e:
                raise InvalidInput(f"frame {s + e.frame} has {e.visible} visible markers, at "
                                   f"least {e.required} are needed") from None
            d1, d2, clamped = ev.vertex_band.parameters(S, margin)
            rho, sectors = (None, None) if valid is None else ev.gauge(d1, d2)
            if rho is not None:
                if confidence:
                    out[CONFIDENCE][sl], out[VERTEX_CONFIDENCE][sl] = valid.confidence(rho)
                clamped = np.mean(rho > 1, axis=-1)
            if confidence:
                factor = base.input_confidence(pose.remove(markers[sl]), u_H, None if sigma is None else sigma[sl])
                out[CONFIDENCE][sl] *= factor.astype(np.float32)           # the fade's × the input's
                out[VERTEX_CONFIDENCE][sl] *= factor[:, None].astype(np.float32)
            rho = rho if clamp else None
            out["clamped"][sl] = clamped
            need_medium = bool(want & {"mesh_detailed", "normal_map"}) or (fine and ev.fine_strain is not None)
            medium = None
            if "vertices" in out or need_medium:   # the medium mesh on the compiled kernels (.shell_mesh)
                medium = self._medium_mesh(u_H, d1, d2, rho, sectors, pose,
                                           out["vertices"][sl] if "vertices" in out else None, need_medium)
            if fine:                            # mesh only: the fine band is not evaluated
                disp, out["clamped"][sl] = ev.fine_band(S, margin, rho, medium)
            if want & {"displacement", "normal_map"}:
                fine_maps = self._fine_images(disp, out.get("displacement"), s, "normal_map" in want)
            if want & {"mesh_detailed", "normal_map"}:  # T, N of the medium mesh (float32 frames)
                rows = [ev.base.frame_field.normal_rows(m) for m in medium]
            if "mesh_detailed" in want:
                h = (ev.fine_sampler @ disp.T).T                           # (f,n)
                normal = np.stack([tn[3:].T for tn, _ in rows])            # (f,n,3)
                pose.restore32(medium + h[..., None] * normal, out=out["vertices_detailed"][sl])
            if "normal_map" in want:
                for k in range(sl.stop - sl.start):          # written in place (no copy)
                    ev.normal_mapper.normal_map(fine_maps[k], medium[k], None, out=out["normal_map"][s + k],
                                                rows=rows[k])
            if "albedo" in want:
                a = ev.albedo_band(S, margin, rho)
                out["albedo"][sl] = ev.albedo.image(np.maximum(a, 0.0), channels=True)
        if half and "albedo" in out:
            from service.io.half import to_float16
            out["albedo"] = to_float16(out["albedo"])
        return out

    def _fine_images(self, disp: np.ndarray, images: np.ndarray | None, s: int, float32: bool) -> np.ndarray | None:
        """The fine displacement maps of a chunk of frames from the band's values disp (f,Pf),
        texel by texel (:func:`~service.geometry.texel_image.band_image`, ``band_image_half``):
        into ``images`` (F,H,H) from frame ``s`` on, the output (float32, or float16 written
        as such; None: not asked), and with ``float32`` their float32 form returned (f,H,H)
        for the normal map: the float32 output itself, or else a work array of the calling
        thread (:func:`~service.geometry.ranges.scratch`, written in the same pass)."""
        from service.geometry.texel_image import band_image, band_image_half     # Numba: loaded by build

        ev = self.evaluator
        Hf = ev.fine.resolution
        direct = images is not None and images.dtype == np.float32          # the output itself
        work = images[s:s + len(disp)] if direct else \
            ranges.scratch("pdm.fine_images", (len(disp), Hf, Hf)) if float32 else None
        for k in range(len(disp)):
            flat32 = None if work is None else work[k].reshape(-1)
            half = images[s + k].reshape(-1).view(np.uint16) if images is not None and not direct else None
            if half is None:
                ranges.run(band_image, Hf * Hf, ev.fine_inverse, disp[k], flat32)
            else:
                ranges.run(band_image_half, Hf * Hf, ev.fine_inverse, disp[k], flat32, half)
        return work if float32 else None

    def _medium_mesh(self, u_H, d1, d2, rho, sectors, pose, world, aligned):
        """The medium meshes of a chunk of frames (:mod:`.shell_mesh`): base surfaces and
        their float32 frames, the fallback at the UV points where ρ is given, the medium
        offsets, then ``world`` (f,n,3) float32 filled with the head pose put back (if given)
        and, with ``aligned``, the neutral-aligned meshes (f,n,3) float64 returned."""
        ev = self.evaluator
        if self.data.medium_regression is not None:      # the thin shell plus the regression's offsets
            A = ev.base.deform(u_H) + self.data.medium_regression(u_H)            # (f,n,3) aligned
            if world is not None:
                world[:] = pose.restore(A)
            return A if aligned else None
        sm = ev.shell_mesh
        surfaces = [sm.surface(u, correction=rho is not None) for u in u_H]
        fallback = None
        if rho is not None:
            fallback = np.empty((len(u_H), len(ev.uv_vertex), 3), np.float32)
            for k, (_, frames, Uc) in enumerate(surfaces):
                sm.fallback(Uc, frames, out=fallback[k])
        C = medium_offsets(ev.medium_values(d1, d2, rho, sectors, fallback), sm.seam_average,
                           sm.neutral_offset)                           # (f,n,3), internal order
        medium = np.empty((len(u_H), self.n_vertices, 3)) if aligned else None
        for k, (U, frames, _) in enumerate(surfaces):
            sm.place(U, frames, C[k], pose.R[k], pose.t[k], False if medium is None else medium[k],
                     None if world is None else world[k])
        return medium

    # ------------------------------------------------------------------ storage
    def save(self, path) -> dict:
        """Write the model directory (manifest.json, model.npz, *.exr, the derived cache); see
        :mod:`.store`. The validity regions written are the evaluator's (as training stores
        them), so a model loaded from a directory stored without some of them (the sector
        box) writes what its load derived and the next load reads it (about 10 s CPU at level 1)."""
        data = dataclasses.replace(self.data, validity=self.evaluator.validity_data())
        return store.write_model(data, self.evaluator.derived(), path)

    @classmethod
    def load(cls, path) -> "PdmModel":
        """Read a model directory written by :meth:`save`, verifying checksums."""
        data, derived = store.read_model(path)
        return cls(data, PdmEvaluator.build(data, derived=derived))


# ---------------------------------------------------------------------- training
def marker_axes(actor: ActorData) -> np.ndarray:
    """Unit texture axes (û, v̂) (M,2,3) of the neutral at the markers (ma2008 eq. 2)."""
    V, F = actor.vertices, actor.faces
    fr = tangent_frames(V, F, actor.uv, actor.uv_faces)
    sign = uv_handedness(F, actor.uv, actor.uv_faces, len(V))
    corners = F[actor.marker_triangle]                                        # (M,3)
    w = actor.marker_barycentric[..., None]
    u = np.sum(w * fr[corners, 0], axis=1)
    v = np.sum(w * (sign[corners, None] * fr[corners, 1]), axis=1)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v -= np.sum(v * u, axis=1, keepdims=True) * u
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return np.stack([u, v], axis=1)


def mean_texel_size(actor: ActorData, H: int) -> float:
    """Mean surface length (actor's unit) of one texel side of an H×H map."""
    A3 = triangle_areas(actor.vertices, actor.faces).sum()
    U = actor.uv[actor.uv_faces]
    e1, e2 = U[:, 1] - U[:, 0], U[:, 2] - U[:, 0]
    Auv = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
    return float(np.sqrt(A3 / Auv) / H)


def fine_resolution(params: PdmParams, clips: Sequence[Clip]) -> int:
    """The fine band's resolution: ``params.fine_resolution``, or (None) the clips' map
    resolution, or :data:`DEFAULT_FINE_RESOLUTION` for clips without maps."""
    if params.fine_resolution is not None:
        return params.fine_resolution
    maps = [c.displacement for c in clips if c.displacement is not None]
    return int(maps[0].shape[1]) if maps else DEFAULT_FINE_RESOLUTION


def _band_raster(actor: ActorData, H: int):
    raster = rasterize_uv(actor.uv, actor.uv_faces, H, H)
    index = np.flatnonzero(raster.mask.ravel())
    interp = interpolation_matrix(raster, actor.faces, actor.n_vertices)[index].tocsr()
    return raster, index, interp


def _region_rms(sq: np.ndarray, count: float, regions: dict) -> dict:
    out = {"all": float(np.sqrt(sq.sum() / (count * len(sq))))}
    for name, sel in regions.items():
        if np.any(sel):
            out[name] = float(np.sqrt(sq[sel].sum() / (count * np.count_nonzero(sel))))
    return out


def train(actor: ActorData, clips: Sequence[Clip], params: PdmParams = PdmParams(),
          progress: Progress = no_progress) -> PdmModel:
    """Fit a PDM model to training clips (ma2008 §4; steps in the module docstring).

    Raises :class:`InvalidInput` for clips that do not match the actor, frames with too few
    markers, or marker layouts whose markers share a thin-shell handle.
    """
    clips = list(clips)
    check_clips(actor, clips)
    n, F = actor.n_vertices, np.asarray(actor.faces, np.int64)
    progress(0.0, "alignment")
    markers = np.concatenate([c.markers for c in clips]).astype(np.float64)
    names = [f"clip '{c.name}' frame {f}" for c in clips for f in range(c.frames)]
    rest = actor.marker_positions()
    pose, weights = training_head_pose(markers, rest, names)
    aligned = pose.remove(markers)
    try:
        handles = handle_vertices(F, actor.marker_triangle, actor.marker_barycentric, actor.marker_names)
    except ValueError as e:
        raise InvalidInput(str(e)) from None

    progress(0.05, "base surface")
    base = BaseSurface.build(actor.vertices, F, actor.uv, actor.uv_faces, handles, rest,
                             lam_dt=params.smoothing_lam_dt).with_marker_noise(params.marker_noise_mm, samples=aligned)
    u_H = base.handle_displacements(aligned)

    progress(0.15, "deformation space")
    mesh = marker_mesh(actor.marker_uv(), rest, marker_axes(actor))
    S = deformation_vectors(mesh, base.denoised_markers(aligned, u_H), offsets=u_H)
    axes = deformation_axes(mesh, S, params.axis_threshold_deg)

    T = len(markers)
    rest_frames = neutral_frames(u_H)
    anchored = params.neutral_anchor

    def world_vertices(t0, t1):
        return np.concatenate([clips[i].vertices[a:b] for i, a, b in _clip_slices(clips, t0, t1)])

    # ---- medium band (3D, in the base's tangent frames)
    progress(0.2, "medium band")
    Hm = params.medium_resolution
    # the neutral's own medium detail is static: kept per vertex (exact at any map size); the
    # map holds what the expressions add to it
    neutral_offset = np.einsum("nij,nj->ni", base.frames(base.smooth), actor.vertices - base.smooth).astype(np.float32)
    _, idx_m, interp_m = _band_raster(actor, Hm)
    # row-major texel order, as load reads the maps back (the vertex band sums in that order)
    field_m = ParameterField.build(axes, barycentric_operator(mesh, texel_uv(idx_m, Hm)))
    # all of the residual, as §4 fits the medium PDM to the scans (fitting it to the low
    # band of the split instead lowered held-out fine-detail r from 0.747 to 0.710)
    f_med = np.empty((T, len(idx_m), 3), np.float32)
    uv_vertex = np.zeros(len(actor.uv), np.int64)                  # the vertex of each UV point
    uv_vertex[np.asarray(actor.uv_faces).ravel()] = F.ravel()
    f_uv = np.empty((T, len(uv_vertex), 3), np.float32)             # the targets at the UV points
    # the mesh's medium offsets from the thin shell, head-aligned (medium_regression's targets)
    Y = np.empty((T, n, 3), np.float32) if params.medium_regression is not None else None
    for t0 in range(0, T, FRAME_CHUNK):
        t1 = min(t0 + FRAME_CHUNK, T)
        X = base.deform(u_H[t0:t1])
        offset = pose[t0:t1].remove(world_vertices(t0, t1)) - X
        if Y is not None:
            Y[t0:t1] = offset
        c = np.einsum("fnij,fnj->fni", base.frames(X), offset)
        c -= neutral_offset
        f_uv[t0:t1] = c[:, uv_vertex]
        f_med[t0:t1] = (interp_m @ c.transpose(1, 0, 2).reshape(n, -1)).reshape(-1, t1 - t0, 3).transpose(1, 0, 2)
    d1, d2 = _parameters(field_m, S)
    regression = None
    if Y is not None:   # through the neutral: its offset from the smooth base at u = 0
        regression = marker_regression.fit(
            u_H, Y, actor.vertices, rest, params.medium_regression * marker_regression.marker_spacing(rest),
            params.medium_regression_ridge, anchor=actor.vertices - base.smooth)
        del Y
    progress(0.3, "medium band fit")
    ridge = {"ridge": params.ridge, "gamma": params.gamma}         # the fit's regularization
    # the medium target of the neutral is 0 by construction (its offset is kept per vertex)
    anchor_m = np.zeros(f_med.shape[1:]) if anchored else None
    medium = CoefficientMap(Hm, idx_m, polynomial.fit(d1, d2, f_med, params.order, anchor=anchor_m,
                                                      **ridge).astype(np.float32))
    med_rms = polynomial.fit_residual_rms(medium.coeffs, d1, d2, f_med)
    del f_med, d1, d2

    uv, uvf = np.asarray(actor.uv, np.float64), np.asarray(actor.uv_faces, np.int64)
    # the medium result at the vertices, as synthesis computes it (without the clamp)
    seam = seam_average_matrix(uvf, F, n, len(uv))
    # the medium PDM where synthesis evaluates it: fitted at the UV points to their vertex's
    # targets with that point's d1, d2 (module docstring)
    field_v = ParameterField.build(axes, barycentric_operator(mesh, uv))
    dv1, dv2 = _parameters(field_v, S)
    anchor_v = np.zeros(f_uv.shape[1:]) if anchored else None
    vertex_coeffs = polynomial.fit(dv1, dv2, f_uv, params.order, anchor=anchor_v, **ridge).astype(np.float32)
    # that fit's leave-one-frame-out residuals, for its cross-validated skill (fit_skill)
    loo_v = polynomial.loo_residuals(dv1, dv2, f_uv, params.order, anchor=anchor_v, **ridge).astype(np.float32)
    vertex = vertex_band(medium, uv, mesh, axes, vertex_coeffs)

    # ---- fine band (1D along the normal, high-pass residual)
    progress(0.45, "fine band")
    Hf = fine_resolution(params, clips)
    raster_f, idx_f, interp_f = _band_raster(actor, Hf)
    order_f, field_f = element_field(mesh, axes, idx_f, Hf)
    idx_f_stored, idx_f, interp_f = idx_f, idx_f[order_f], interp_f[order_f]
    sigma = params.fine_highpass_mm / mean_texel_size(actor, Hf)
    split_f = BandFilter.build(Hf, idx_f, sigma)
    uv_f = texel_uv(idx_f, Hf)
    f_fine = np.empty((T, len(idx_f)), np.float32)
    vert_sq = np.zeros(n)
    strain = None
    if params.fine_driver == "strain":       # the strain of the mesh synthesis makes (strain_band)
        strain_field = StressField.build(detailed_neutral(base, neutral_offset), F, uv, uvf, 0)
        strain = StrainFit(len(idx_f), n, strain_order(params.order))
    for t0 in range(0, T, FRAME_CHUNK):
        t1 = min(t0 + FRAME_CHUNK, T)
        X = base.deform(u_H[t0:t1])
        fr = base.frames(X)
        if regression is None:
            c = medium_offsets(vertex.evaluate(dv1[t0:t1], dv2[t0:t1]), seam, neutral_offset)
            result = X + np.einsum("fnji,fnj->fni", fr, c)
        else:       # the mesh synthesis makes: the shell plus the regression's offsets
            result = X + regression(u_H[t0:t1])
        err = pose[t0:t1].remove(world_vertices(t0, t1)) - result
        vert_sq += np.einsum("fnd,fnd->n", err, err)
        r = interp_f @ np.einsum("fnd,fnd->nf", err, fr[..., 2, :])           # (Pf,f)
        disp = [clips[i].displacement[a:b] for i, a, b in _clip_slices(clips, t0, t1)
                if clips[i].displacement is not None]
        if disp:
            disp = np.concatenate(disp)
            r = r + (disp.reshape(len(disp), -1)[:, idx_f].T if disp.shape[1] == Hf
                     else np.stack([sample_map(d, uv_f) for d in disp], axis=1))
        with ThreadPoolExecutor(WORKERS) as pool:
            cols = list(pool.map(lambda k: split_f.highpass(r[:, k]), range(t1 - t0)))
        f_fine[t0:t1] = np.stack(cols)
        if strain is not None:
            strain.add(strain_field.stress(result), interp_f, f_fine[t0:t1])
    d1, d2 = _parameters(field_f, S)
    progress(0.6, "fine band fit")
    anchor_f = _neutral_target(f_fine, rest_frames) if anchored else None
    coeffs_f = polynomial.fit(d1, d2, f_fine, params.order, anchor=anchor_f, **ridge).astype(np.float32)
    fine = CoefficientMap(Hf, idx_f_stored, _unpermute(coeffs_f, order_f))
    fine_rms = polynomial.fit_residual_rms(coeffs_f, d1, d2, f_fine)[:, 0]
    fine_strain = None
    if strain is not None:
        fine_strain = strain.solve(anchor=anchor_f)
        fine_rms = np.sqrt(strain.residual_sq(fine_strain) / T)
        fine_strain = fine_strain.permuted(np.argsort(order_f))      # stored in row-major texel order
        del strain
    fine_signal = np.sqrt(np.mean(f_fine.astype(np.float64) ** 2, axis=0))
    del f_fine, d1, d2

    # ---- albedo PTM (§6)
    alb_rms, albedo = None, None
    if clips[0].albedo is not None:
        progress(0.8, "albedo")
        Ha = clips[0].albedo.shape[1]
        _, idx_a, _ = _band_raster(actor, Ha)
        order_a, field_a = element_field(mesh, axes, idx_a, Ha)
        f_alb = np.concatenate([c.albedo.reshape(c.frames, -1, 3)[:, idx_a[order_a]] for c in clips]).astype(np.float32)
        d1, d2 = _parameters(field_a, S)
        anchor_a = _neutral_target(f_alb, rest_frames) if anchored else None
        coeffs_a = polynomial.fit(d1, d2, f_alb, params.order, anchor=anchor_a, **ridge).astype(np.float32)
        albedo = CoefficientMap(Ha, idx_a, _unpermute(coeffs_a, order_a))
        alb_rms = polynomial.fit_residual_rms(coeffs_a, d1, d2, f_alb)
        del f_alb, d1, d2

    progress(0.9, "metrics")
    regions = {k: np.asarray(v, bool) for k, v in actor.regions.items()}
    tex_region = {k: v[F[raster_f.triangle.ravel()[idx_f], 0]] for k, v in regions.items()}
    metrics = {
        "training_frames": T,
        "clips": [c.name for c in clips],
        "medium_fit_rms_mm": float(np.sqrt(np.nanmean(med_rms ** 2))),
        "medium_vertex_rms_mm": _region_rms(vert_sq, T, regions),
        "fine_fit_rms_mm": _region_rms(np.nan_to_num(fine_rms) ** 2, 1, tex_region),
        "fine_signal_rms_mm": _region_rms(fine_signal ** 2, 1, tex_region),
        "albedo_fit_rms": None if alb_rms is None else float(np.sqrt(np.nanmean(alb_rms ** 2))),
        "pca_energy": [float(x) for x in axes.energy.mean(axis=0)],
        "axis_smoothing": {"replaced": int(axes.replaced), "worst_angle_deg": float(axes.worst_angle_deg),
                           "threshold_deg": params.axis_threshold_deg},
        "highpass_sigma_texels": float(sigma),
        "neutral_frames": int(len(rest_frames)),
        "neutral_anchor": {"medium": anchored, "fine": anchored and len(rest_frames) > 0},
        "params": params.model_dump(mode="json"),
    }
    data = PdmData(params, F, uv, uvf, base.smooth, base.handles, base.rest_markers, base.prior_scale_mm,
                   mesh, axes, weights, S, neutral_offset, medium, fine, albedo, metrics,
                   vertex_coeffs=vertex_coeffs, marker_prior=base.marker_prior,
                   medium_regression=regression, fine_strain=fine_strain)
    progress(0.95, "prepare")
    evaluator = PdmEvaluator.build(data, base)
    # the medium band's skill against its fallback on the training frames (fit_skill)
    fallback = np.concatenate([evaluator.shell_fallback(u_H[t:t + FRAME_CHUNK], base.deform(u_H[t:t + FRAME_CHUNK]))
                               for t in range(0, T, FRAME_CHUNK)])
    skill = fit_skill(loo_v, f_uv, fallback).astype(np.float32)
    del loo_v, f_uv, fallback
    metrics["medium_skill"] = {"median": float(np.median(skill)), "p05": float(np.percentile(skill, 5)),
                               "below_0": float(np.mean(skill < 0))}
    # the validity regions of the training data are stored with the model (a load reads them)
    data = dataclasses.replace(data, validity=evaluator.validity_data(), medium_skill=skill)
    model = PdmModel(data, dataclasses.replace(evaluator, data=data, medium_gain=medium_gain(data)))
    progress(1.0, "done")
    return model


def neutral_frames(u_H: np.ndarray, tol: float = NEUTRAL_TOL) -> np.ndarray:
    """Indices of the training frames at rest: whose largest aligned handle displacement
    ``max_m ‖u_H[t,m]‖`` (u_H (T,M,3)) is at most ``tol`` × its largest over the frames."""
    amp = np.linalg.norm(np.nan_to_num(u_H), axis=-1).max(axis=-1)           # (T,)
    return np.flatnonzero(amp <= tol * max(float(amp.max()), 1e-30))


def _neutral_target(f: np.ndarray, frames: np.ndarray) -> np.ndarray | None:
    """The band's target at zero deformation (P,C): the mean of ``f`` (T,P,C) or (T,P) over
    the rest ``frames`` (NaN-free: 0 where no rest frame measured the point); None without
    rest frames (the constant is then fitted)."""
    if len(frames) == 0:
        return None
    f0 = np.nanmean(np.asarray(f[frames], np.float64), axis=0) if np.isnan(f[frames]).any() \
        else np.asarray(f[frames], np.float64).mean(axis=0)
    return np.nan_to_num(f0)


def _unpermute(values: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Rows of ``values`` (P,…) given in ``order`` (P,) back in the original order."""
    out = np.empty_like(values)
    out[order] = values
    return out


def _clip_slices(clips: Sequence[Clip], t0: int, t1: int):
    """(clip index, start, stop) pieces of the global frame range [t0, t1)."""
    start = 0
    for i, c in enumerate(clips):
        a, b = max(t0 - start, 0), min(t1 - start, c.frames)
        if a < b:
            yield i, a, b
        start += c.frames
