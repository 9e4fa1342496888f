"""Pose-space detail models: training, the stored data and the per-frame evaluator
(bickel2008 §3-5: PSD eq. 2, WPSD eq. 3-5).

Training (:func:`train`), from clips of high-resolution frames with their markers:

1. head pose removed from every frame (weighted Kabsch with stability weights, as the PDM);
2. large scale: the detailed neutral deformed by the precomputed thin shell (§4), driven by
   the markers' posterior mean under the training marker prior (below: marker prior);
3. features: relative stretch of the feature-graph edges (§5.1), measured on the shell at
   the feature nodes (the markers' surface points), ``node_rest + (N B) u_H``;
4. corrections: each frame minus its shell, in the shell's tangent frames (§5.2);
   the clips' fine displacement maps (detail below the mesh resolution, relative to the
   mesh) are learned by the same RBFs at the texels (below);
5. WPSD only: the sparse edge weights α of eq. 4;
6. smoothing λ (if not given) by validation on held-out training frames (below);
7. basis: greedy selection (§5.2) from the frame of smallest strain (the rest pose);
8. weights: exact interpolation of the basis or least squares over all frames (§5.2),
   per vertex with the vertex's metric for WPSD (eq. 5), shared for PSD (eq. 2), with the
   linear polynomial term of the biharmonic spline where ``params.polynomial`` is
   ``"linear"`` (WPSD's default: local, over the vertex's α support; :mod:`.polynomial`
   has the form, the reason and the measured effect).

Synthesis (:meth:`PoseSpaceModel.synthesize`, §5.3 "at run-time"): markers → head pose →
handle displacements (denoised and completed by the marker prior, below) → shell ``X = 𝓕 + B u_H`` → features → per-vertex
distances to the basis poses (one sparse product for WPSD) → ``c_v = Σ_j w_v,j φ_v,j``
rotated into X's tangent frames → head pose put back.

Choices and departures (the paper is silent or differs):

* **fine map band** — the paper's details live at the vertices of a 1M-triangle mesh. The
  sample actor's (and a scanner's) detail below the mesh resolution arrives as a
  displacement map relative to the mesh; it is learned per covered texel with the same
  RBF: a texel's squared distance is the barycentric interpolation of its triangle's
  vertex distances (for WPSD this is eq. 3 with α interpolated to the texel, eq. 3 being
  linear in α), its weights are fitted like a vertex's (scalar target). Output
  ``displacement``; ``vertices_detailed`` adds it along the normals;
* **rest pose** — the greedy selection starts from the training frame of smallest feature
  norm (the captured rest pose; the clips start neutral);
* **selection on a vertex sample** — WPSD's greedy selection and the validation measure the
  fit error on ``selection_vertices`` vertices (an even stride); the final weights are fitted
  at every vertex. PSD's selection uses every vertex (through the (T,T) Gram factor of the
  corrections, :func:`~.rbf.gram_factor`). The maps do not take part in the selection;
* **smoothing** — ``params.smoothing = None`` picks λ from ``smoothing_grid``: every
  ``validation_stride``-th training frame is held out, the basis is selected on the others
  (once, at λ = 0) and fitted for each λ, and the held-out frames' features, computed from
  their markers plus Gaussian noise of ``validation_noise_mm`` (seeded), predict their
  corrections; the λ of smallest RMS error wins. The table is in ``metrics["validation"]``;
* **noisy copies** — with ``params.noise_copies`` = K > 0 the least-squares fits (weights,
  polynomial, map texels, and the smoothing validation's fits) see every training frame
  K + 1 times: once with its features, K times with features from its markers plus Gaussian
  noise of ``validation_noise_mm`` (seed ``NOISE_COPIES_SEED``), always with the frame's own
  targets. Training with input noise is Tikhonov regularization of the response to the
  features [Bishop 1995] — for the linear term exactly a ridge with the features' noise
  covariance — so the fitted detail does not follow marker noise. The basis selection uses
  the clean frames. Measured on family b (K = 2): in range clean / noisy / occluded 0.373 /
  1.033 / 1.155 → 0.325 / 0.993 / 1.125, combinations clean 0.812 → 0.935 (worse), so the
  default is K = 0;
* **marker prior** (default ``params.marker_prior = "posterior"``) — before the shell, in
  training and synthesis alike, the aligned markers are replaced by their posterior mean
  under a Gaussian of the training markers (:func:`marker_posterior`): mean + principal modes
  (:func:`marker_statistics`) plus an independent off-mode part whose per-marker variance τ²_m
  is estimated by leaving one training clip out (:func:`residual_variance`: what an
  expression the other clips never showed adds at that marker), observation noise
  σ = ``validation_noise_mm``. A Wiener filter: the part the modes explain is kept, the rest
  shrunk by τ²/(τ² + σ²), so marker noise reaches neither the shell nor the features
  unfiltered while a combination keeps its off-mode part where the training says such parts
  occur. Occluded markers get the modes' prediction plus the shell's minimum-energy
  completion of the visible residual (:func:`posterior_displacements`). Chosen on family b,
  level 0 (WPSD fine rel. err, nearest frame in brackets; evaluation-only switch on a model
  trained without it): in range clean / noisy / occluded 0.373 / 1.033 / 1.155 → 0.378 /
  0.819 / 0.427 (0.391 / 0.959 / 1.020), combinations 0.812 / 1.183 / 0.936 → 0.836 / 1.061 /
  1.066 (1.254 / 1.496 / 1.360), max error below the shell's on every row; confirmed on
  family a (6 frames per row: noisy in range 0.936 → 0.823, combinations 0.940 → 0.767).
  ``"none"`` uses the markers as given (then ``marker_completion`` applies). A transferred
  model carries the statistics to the target's markers through the source's shell
  (:mod:`.transfer`);
* **posterior noise per frame** (``params.posterior_noise = "frame"``, opt-in;
  :func:`posterior_noise`) — the posterior's σ is each frame's own estimate σ̂ (the
  confidence's, :func:`~service.geometry.marker_prior.frame_noise` against the base's learned
  marker prior) clipped to [:data:`POSTERIOR_NOISE_FLOOR_MM`, ``validation_noise_mm``], in
  training and synthesis. Why (``benchmarks/local_blend_study.py``, level 0, 6 frames a row,
  WPSD + regression s = 3, λ = 0.1, detail rel. err): the fixed σ = 0.3 mm also shrinks the
  off-mode part of *clean* markers — an expression the training did not show — and the shell
  then misses it; the markers as given (``"none"``, evaluation-only) give a in range 0.365 →
  0.317, combinations 0.398 → 0.376, b combinations 0.770 → 0.701, but noisy a in range 0.593
  → 0.761. σ̂ cannot tell such a frame from noise everywhere (clean sneer markers of a model
  trained on brow raise, smile and pucker: σ̂ 0.7–1.1 mm), hence the cap: no frame is filtered
  more than with the fixed σ. Measured (``generalization_report.py --pose-space-params``,
  trained with it): clean and occluded rows a in range 0.365 / 0.376 → 0.344 / 0.356,
  combinations 0.398 / 0.410 → 0.380 / 0.389; b combinations 0.770 / 1.049 → 0.708 / 1.003;
  noisy rows within +0.006 (b out of range 0.665 → 0.671), b out of range occluded 0.377 →
  0.401 (mean error 0.085 → 0.072 mm); README "Pose-space detail". Not the default: it does
  not win on every row. Cost: one posterior per frame (+0.3 ms CPU a frame single, +0.5 ms in
  8-frame calls, 150 markers; independent of the mesh);
* **occlusion** — with ``marker_prior = "none"`` occluded markers (NaN) are completed before the shell: by default by the
  shell's minimum energy; with ``marker_completion = "training"`` by the training frames'
  marker statistics (the MAP of the missing markers under the Gaussian of the aligned
  training marker displacements, observation noise ``validation_noise_mm``:
  :func:`complete_markers`). Measured on family b (level 0, WPSD defaults, fine rel. err):
  in range occluded 1.155 → 0.382, but combinations occluded 0.936 → 1.221 with a max error
  above the thin shell's (7.35 vs 6.80 mm): the training's 12 marker modes mispredict
  combinations, so it is not the default. ``occlusion = "reweight"`` also weights every edge's
  term of eq. 3 by its visibility ν (the share of its nodes' shell displacement that visible
  markers carry, :meth:`PoseSpaceEvaluator.edge_visibility`) and renormalizes α per vertex;
* **clamp** — with ``clamp`` each feature is limited to its training range widened by
  ``extrapolation_margin`` (the linear kernel extrapolates without bound); ``clamped`` (F,)
  is the fraction of limited features;
* **confidence** (F,) — how far the frame's features lie outside the training features:
  δ = ‖max(0, f − f_max, f_min − f)‖ (per-edge excess beyond the training range, strain
  units, before the clamp), relative to the median feature norm of the training frames δ₀
  (a typical expression's strength): ``confidence = exp(−δ / δ₀)``; 1 inside the training
  box, 1/e a typical expression's distance beyond it; the *reported* confidence is that
  times the input factor of the frame's markers (:class:`service.methods.confidence.MarkerEvidence`:
  the Wiener fraction at the frame's own noise estimate times the size factor of its
  large-scale deformation u_H, 1 for a model without a learned marker prior; no separate
  occlusion term), the rule every marker-driven kind shares;
* **marker regression** (``params.marker_regression`` = s; WPSD's default s = 3, λ = 0.1, PSD's none;
  :mod:`service.geometry.marker_regression`) — before the corrections, a per-vertex ridge regression of the
  aligned offsets ``V − X`` on the markers' displacement vectors (weights exp(−d²/s²) of the
  rest distance, s in median marker spacings) is fitted and subtracted; the RBFs learn the
  rest, synthesis adds it back (``X + L(u_H) + Frame(X)ᵀ c``, unfaded). Why: the detail
  metric's high-pass (2 mm) passes the thin shell's medium-scale error (its RMS there is
  0.9–1.8× the truth's detail RMS, level 0, both families), which the corrections must cancel;
  measured (``benchmarks/blend_study.py``) the medium band the nearest frame carries to a
  held-out pose costs rel. err 0.45–0.93 against 0.11–0.53 for its detail, and WPSD's
  mesh 0.30–1.14 against 0.11–0.31 for its maps. Strain features cannot say which way the
  skin bulges; the markers' displacement vectors can;
* **confidence fade** (``params.confidence_fade``, default on) — the frame's vertex
  corrections are multiplied by its range confidence κ (not the input factor), ``X + Frame(X)ᵀ (κ c)`` (the fade rule of
  :mod:`service.methods.confidence` with the shell as the safe fallback): the biharmonic
  kernel and the linear polynomial extrapolate linearly without bound (§5.2), and a
  combination outside the training box can put a wrong correction where the examples all
  agree. Measured (level 0, WPSD defaults, 6 frames a row): family b, combinations with
  noisy markers, frame 3 (κ = 0.63), vertex 18483: truth (0.32, 0.24, −3.93) mm in the
  frame, WPSD (0.06, 1.36, 1.08) (its polynomial part (1.7, −1.0, 0.0): the two trained
  expressions' linear responses added), error 5.16 mm against the thin shell's row maximum
  4.91. No per-vertex quantity flags it: its feature-box excess in its own α metric is 0.04 of
  its training span and its distance to the nearest basis pose 0.54 of it, as at the
  neighbour 16815 that WPSD corrects from 4.9 to 0.8 mm, and the prediction lies inside the
  vertex's training envelope of corrections (1.97 vs 3.72 mm; clipping it to the training
  box changes nothing). With the fade every row of both families keeps its max error below
  the thin shell's (b combinations noisy 5.16 → 4.57; family a passed before and still does,
  its out-of-range max 2.33 → 5.53 against the shell's 7.57) at the cost of
  the out-of-range rows: mean error b 0.117 → 0.210 mm, a 0.154 → 0.249 (thin shell 0.303 /
  0.435), and their detail, whose metric includes the corrections' wrinkles (fine rel. err
  clean b 0.660 → 1.156 (nearest frame 0.482), a 0.521 → 0.751 (nearest 0.906)); in range
  clean unchanged (κ = 1), combinations b 0.775 → 0.763 / a 0.515 → 0.531. The fine map is not
  faded (sub-mesh detail, 0.02–0.03 mm RMS, no part of the vertex error; fading it too gave
  b 1.209, a 0.841);
* weights are rounded to float32 when training ends (the stored precision), so a saved and
  reloaded model synthesizes bit-identical results;
* **per-frame mesh path in float32, compiled** (:meth:`PoseSpaceEvaluator.shell_detail`,
  :meth:`PoseSpaceModel._corrections`): Numba kernels over contiguous vertex ranges in a
  cache-friendly vertex order (:mod:`service.geometry.ranges`): :mod:`.correction_sum`
  (WPSD: eq. 3's distances, eq. 5's sum, the polynomial and the fade, per vertex in float32,
  α and the polynomial on one CSR pattern) and :mod:`service.geometry.shell_frames` (the
  displacement ``B u_H`` from the basis rows in that order, the shell's tangent frames from
  the rest edges plus the
  displacement's edges, the corrections rotated into them, the head pose). Training and the
  float64 operators are unchanged. Within 1e-4 mm of the float64 path (tests). The speed
  rows are in issue 18's report (``benchmarks/pose_space_report.py --speed-only``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.sparse as sp

from service.geometry import ranges
from service.geometry.marker_filter import MarkerModes
from service.geometry.normal_map import NormalMapper
from service.geometry.uv_raster import (
    interpolation_matrix, rasterize_uv, sample_map, sampling_matrix, texel_centers_uv,
)
from service.methods.confidence import exponential
from service.methods.inputs import ActorData, Clip, InvalidInput, Progress, check_clips, no_progress
from service.methods.outputs import check_outputs
from service.methods.pdm.base_surface import (
    BaseSurface, HeadPose, TooFewMarkers, head_alignment, training_head_pose,
)
from service.geometry import marker_regression
from service.methods.pose_space import polynomial, rbf, store
from service.methods.pose_space.data import PoseSpaceData
from service.methods.pose_space.corrections import corrections, large_scale_surface
from service.methods.pose_space.feature_graph import automatic_graph, graph_from_pairs
from service.methods.pose_space.outputs import OUTPUTS
from service.methods.pose_space.params import (
    NOISE_COPIES_SEED, VALIDATION_SEED, Params, PsdParams, WpsdParams,
)
from service.methods.pose_space.weighting import edge_weights, weighted_sq_distances

#: frames evaluated at once
FRAME_CHUNK = 8
#: vertices / texels per chunk of the per-vertex fits
FIT_CHUNK = 2048
TEXEL_CHUNK = 4096
#: principal modes of the training markers kept for the completion of occluded markers
MARKER_MODES = 64
#: occlusion: a vertex whose visible α mass is below this keeps its unweighted distance
OCCLUSION_FLOOR = 0.05
#: ``posterior_noise = "frame"``: the posterior's σ is at least this, mm (a clean frame's σ̂
#: can be ~0: the Wiener gain then keeps its off-mode part whole)
POSTERIOR_NOISE_FLOOR_MM = 0.01


# ---------------------------------------------------------------------------------------
# the stored data

def node_operator(faces: np.ndarray, triangle: np.ndarray, barycentric: np.ndarray, n: int) -> sp.csr_matrix:
    """(N,n) sparse: vertices → surface points at (triangle (N,), barycentric (N,3))."""
    N = len(triangle)
    return sp.csr_matrix((np.asarray(barycentric, np.float64).ravel(),
                          (np.repeat(np.arange(N), 3), np.asarray(faces)[triangle].ravel())), shape=(N, n))


# ---------------------------------------------------------------------------------------
# the evaluator: precomputed once, evaluated per frame

class PoseSpaceEvaluator:
    """What synthesis evaluates per frame, derived once from :class:`PoseSpaceData`.

    Attributes: ``base`` the thin shell (basis B, handle energy, tangent-frame field);
    ``node_rest`` (N,3) and ``node_basis`` (N,M) so that node positions are
    ``node_rest + node_basis @ u_H``; ``alpha`` (n,E) float64 CSR (WPSD; the float64 distances
    of :meth:`sq_distances`); ``shell_frames`` with ``smooth_internal`` (3,n) and
    ``basis_internal`` (n,M), the rest pose and a float32 copy of the basis in its vertex
    order (the compiled per-frame shell); ``correction_sum`` (WPSD: α, the polynomial and the
    RBF weights as the compiled per-frame sum reads them) or ``weights`` (PSD: (P,3n), one
    BLAS product per frame); the map band's vertex → texel interpolation (Pt,n) and texel →
    vertex sampler (n,Pt).
    """

    def __init__(self, data: PoseSpaceData, base: BaseSurface | None = None):
        self.data = data
        self.base = base or BaseSurface.from_smooth(data.neutral, data.faces, data.uv, data.uv_faces,
                                                    data.handles, data.rest_markers)
        n = data.n_vertices
        nodes = node_operator(data.faces, data.node_triangle, data.node_barycentric, n)
        self.node_rest = nodes @ data.neutral
        self.node_basis = np.asarray(nodes @ self.base.basis.astype(np.float64))
        self.graph = data.graph
        # how much of each node's shell displacement its visible markers carry (occlusion)
        influence = np.abs(self.node_basis)
        self.node_influence = influence / np.maximum(influence.sum(axis=1, keepdims=True), 1e-300)
        self.alpha = None if data.alpha is None else data.alpha.astype(np.float64).tocsr()
        # compiled kernels: Numba is imported where a model is built, not with the kinds
        from service.methods.pose_space.correction_sum import CorrectionSum
        from service.geometry.shell_frames import ShellFrames

        # the per-frame mesh path: float32 frames from the displacement (:mod:`service.geometry.shell_frames`)
        self.shell_frames = ShellFrames.build(self.base.smooth, self.base.faces, data.uv, data.uv_faces)
        self.smooth_internal = self.shell_frames.to_internal(self.base.smooth)
        self.basis_internal = self.shell_frames.internal_basis(self.base.basis)
        if self.alpha is None:        # PSD: one (P,3n) system, a BLAS product per frame
            self.weights = np.ascontiguousarray(data.weights.transpose(1, 0, 2).reshape(data.basis_size, -1))
            self.correction_sum = None
        else:                         # WPSD: the compiled per-vertex sum, in the frames' vertex order
            self.weights = None
            self.correction_sum = CorrectionSum.build(data.alpha, data.weights, data.basis_features,
                                                      data.poly_const, data.poly_linear,
                                                      order=self.shell_frames.order)
        self.regression = data.regression
        self.poly_linear = None if data.poly_linear is None else data.poly_linear.tocsr()
        self.map_poly_linear = None if data.map_poly_linear is None else data.map_poly_linear.tocsr()
        self.map_interp = self.map_sampler = None
        self.normal_mapper: NormalMapper | None = None      # built here, never on first use
        if data.map_resolution:
            H = data.map_resolution
            raster = rasterize_uv(data.uv, data.uv_faces, H, H)
            self.map_interp = interpolation_matrix(raster, data.faces, n)[data.map_index].tocsr()
            self.map_interp32 = self.map_interp.astype(np.float32)
            mask = np.zeros(H * H, bool)
            mask[data.map_index] = True
            self.map_sampler = sampling_matrix(data.uv, data.uv_faces, data.faces, n,
                                               mask.reshape(H, H))[:, data.map_index].tocsr()
            self.normal_mapper = NormalMapper(raster, data.faces, data.uv, data.uv_faces, n)

    # -- large scale and features
    def deformation(self, markers: np.ndarray) -> tuple[HeadPose, np.ndarray]:
        """Head pose and complete handle displacements u_H (F,M,3) of world markers (F,M,3)."""
        try:
            pose = head_alignment(markers, self.data.rest_markers, self.data.pose_weights)
        except TooFewMarkers as e:
            raise InvalidInput(f"frame {e.frame} has {e.visible} visible markers, at least "
                               f"{e.required} are needed") from None
        aligned = pose.remove(markers)
        d = self.data
        if d.params.marker_prior == "posterior" and d.marker_residual_var is not None:
            return pose, posterior_displacements(self.base, aligned, d.marker_mean, d.marker_modes,
                                                 d.marker_residual_var, posterior_noise(self.base, aligned, d.params))
        if d.params.marker_completion == "training" and d.marker_modes is not None:
            aligned = complete_markers(aligned, d.rest_markers + d.marker_mean, d.marker_modes,
                                       d.params.validation_noise_mm)
        return pose, self.base.handle_displacements(aligned)

    def features(self, u_H: np.ndarray) -> np.ndarray:
        """Features f (F,E) of complete handle displacements (F,M,3) (§5.1)."""
        nodes = self.node_rest + np.einsum("nm,fmd->fnd", self.node_basis, u_H)
        return self.graph.features(nodes)

    def regression_offsets(self, u_H: np.ndarray) -> np.ndarray | None:
        """The marker regression's head-aligned vertex offsets (F,n,3) float32 for handle
        displacements u_H (F,M,3), None without one. It reads u_H itself, or for a transferred
        model (``data.regression_input == "nodes"``) the feature nodes' shell displacements
        ``node_basis @ u_H`` (the source markers' corresponding points on the target)."""
        if self.regression is None:
            return None
        if self.data.regression_input == "nodes":
            u_H = np.einsum("nm,fmd->fnd", self.node_basis, u_H)
        return self.regression(u_H)

    def limit(self, f: np.ndarray, margin: float | None) -> tuple[np.ndarray, np.ndarray]:
        """Features limited to the widened training range, and the fraction limited (F,)."""
        if margin is None:
            return f, np.zeros(len(f))
        d = self.data
        span = d.feature_high - d.feature_low
        g = np.clip(f, d.feature_low - margin * span, d.feature_high + margin * span)
        return g, np.mean(g != f, axis=-1)

    def confidence(self, f: np.ndarray) -> np.ndarray:
        """exp(−δ/δ₀) (F,) of features f (F,E) (module docstring)."""
        d = self.data
        excess = np.maximum(0.0, np.maximum(f - d.feature_high, d.feature_low - f))
        return exponential(np.linalg.norm(excess, axis=-1), d.confidence_scale)

    def edge_visibility(self, markers: np.ndarray) -> np.ndarray | None:
        """Visibility ν (F,E) in [0, 1] of the feature edges for markers (F,M,3) with NaN rows
        occluded (module docstring: occlusion), or None when every marker is visible."""
        seen = np.isfinite(markers).all(axis=-1)                                   # (F,M)
        if seen.all():
            return None
        node = seen.astype(np.float64) @ self.node_influence.T                     # (F,N)
        e = self.graph.edges
        return node[:, e[:, 0]] * node[:, e[:, 1]]

    def shell_detail(self, u_H: np.ndarray, C: np.ndarray, R: np.ndarray | None = None,
                     t: np.ndarray | None = None, aligned: bool = False,
                     world: np.ndarray | None = None) -> np.ndarray | None:
        """One frame's shell plus its corrections ``X + Frame(X)ᵀ c``, float32: handle
        displacements u_H (M,3), corrections C (3,n) in the tangent frames in the internal
        vertex order of :attr:`shell_frames`. ``aligned`` returns X (3,n) internal order
        (neutral-aligned); ``world`` (n,3) float32 is filled with ``Rᵀ (X − t)`` in vertex
        order (:class:`~service.methods.pdm.base_surface.HeadPose` of the frame, R (3,3),
        t (3,)).

        The displacement ``B u_H`` by :meth:`ShellFrames.displacement` from the basis rows in
        the internal order (:attr:`basis_internal`, a float32 copy of the base's basis), the
        rest by :meth:`ShellFrames.shell`. Within 1e-4 mm of the float64
        ``apply_corrections(base, base.deform(u_H), c)`` (tests; one float32 ulp of a
        position at the sample actor's ~190 mm is 1.5e-5 mm)."""
        sf = self.shell_frames
        U = sf.displacement(self.basis_internal, u_H, out=ranges.scratch("pose_space.U", (3, sf.n_vertices)))
        return sf.shell(U, self.smooth_internal, C, R, t, aligned=aligned, world=world)

    # -- fine scale
    def sq_distances(self, f: np.ndarray, visibility: np.ndarray | None = None) -> np.ndarray:
        """Squared feature distances to the basis poses: WPSD (n,F,P) per vertex (eq. 3),
        PSD (1,F,P) (eq. 2). With ``visibility`` ν (F,E) (:meth:`edge_visibility`) every edge's
        term is weighted by ν and the weights renormalized (module docstring: occlusion).

        term is weighted by ν and the weights renormalized (module docstring: occlusion).
        Float64; the synthesis path sums them in float32 inside :attr:`correction_sum`."""
        fb = self.data.basis_features
        if self.alpha is None:
            g = f[:, None, :] - fb[None]
            if visibility is None:
                return np.einsum("fpe,fpe->fp", g, g)[None]
            tot = visibility.sum(axis=1)                                          # (F,)
            scale = np.where(tot > OCCLUSION_FLOOR * g.shape[-1], g.shape[-1] / np.maximum(tot, 1e-300), 0.0)
            full = np.einsum("fpe,fpe->fp", g, g)
            part = np.einsum("fpe,fe,fpe->fp", g, visibility, g) * scale[:, None]
            return np.where(scale[:, None] > 0, part, full)[None]
        D2 = weighted_sq_distances(self.alpha, f, fb)
        if visibility is None:
            return D2
        F, P = len(f), len(fb)
        G = (f[:, None, :] - fb[None]) ** 2 * visibility[:, None, :]                  # (F,P,E)
        part = np.asarray(self.alpha @ G.reshape(F * P, -1).T).reshape(-1, F, P)
        mass = np.asarray(self.alpha @ visibility.T)                                # (n,F)
        ok = mass > OCCLUSION_FLOOR
        part /= np.where(ok, mass, 1.0)[:, :, None]
        return np.where(ok[:, :, None], part, D2)

    def corrections(self, D2: np.ndarray, f: np.ndarray) -> np.ndarray:
        """Corrections c (F,n,3) float32 in the tangent frames, vertex order, from
        :meth:`sq_distances` of features f (F,E) (eq. 2, 5, plus the polynomial term of
        :mod:`.polynomial` if stored). WPSD: :attr:`correction_sum` per frame with the
        distances given; the synthesis path sums the distances there too.

        The sums run in float32, the stored precision of the weights (kernel values rounded
        to float32; within 1e-5 mm of the float64 sums on the sample actor, tested)."""
        if self.alpha is None:      # per frame W.T @ φ: a GEMV (a (1,P)@(P,3n) GEMM is ~100x
            phi = rbf.kernel(np.sqrt(D2)).astype(np.float32)
            Wt = self.weights.T       # slower in OpenBLAS when the cores are busy)
            c = np.stack([Wt @ p for p in phi[0]]).reshape(len(phi[0]), -1, 3)
            if self.poly_linear is not None:
                c = c + polynomial.evaluate(self.data.poly_const, self.poly_linear, f)
            return c
        sf, cs = self.shell_frames, self.correction_sum
        return np.stack([sf.to_vertices(cs(fk, D2=D2[sf.order, k])) for k, fk in enumerate(f)])

    def fine_map(self, D2: np.ndarray, f: np.ndarray) -> np.ndarray:
        """Fine displacement (F,Pt) float32 at the map texels of features f (F,E) (module
        docstring: the map band)."""
        W = self.data.map_weights
        if self.alpha is None:
            out = (rbf.kernel(np.sqrt(D2[0])) @ W.T).astype(np.float32)
        else:
            n, F, P = D2.shape
            t2 = self.map_interp32 @ D2.reshape(n, F * P).astype(np.float32)      # (Pt,F·P)
            np.maximum(t2, 0.0, out=t2)
            phi = rbf.kernel(np.sqrt(t2, out=t2)).reshape(-1, F, P)
            out = np.matmul(phi, W[:, :, None])[..., 0].T                         # (F,Pt)
        if self.map_poly_linear is not None:
            out = out + polynomial.evaluate(self.data.map_poly_const[:, None], self.map_poly_linear,
                                            f)[..., 0].astype(np.float32)
        return out


# ---------------------------------------------------------------------------------------
# the model

class PoseSpaceModel:
    """A trained PSD or WPSD model (bickel2008 §5); :meth:`synthesize` turns markers into
    meshes and maps. Build with :func:`train`, :meth:`load` or
    :func:`~service.methods.pose_space.transfer.transfer`."""

    def __init__(self, data: PoseSpaceData, evaluator: PoseSpaceEvaluator | None = None):
        self.data = data
        self.evaluator = evaluator or PoseSpaceEvaluator(data)

    @property
    def metrics(self) -> dict:
        return self.data.metrics

    @property
    def params(self) -> Params:
        return self.data.params

    @property
    def kind(self) -> str:
        return self.data.kind

    @property
    def n_markers(self) -> int:
        return self.data.n_markers

    @property
    def marker_modes(self) -> MarkerModes | None:
        """:meth:`BaseSurface.marker_modes` of the model's base surface."""
        return self.evaluator.base.marker_modes(self.data.pose_weights)

    def synthesize(self, markers: np.ndarray, outputs: Sequence[str] = ("mesh", "displacement"),
                   clamp: bool = True, captured: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Meshes and maps for world-space markers (F,M,3), NaN for occluded (§5.3 run time).

        Returns a dict with (as asked in ``outputs``, API.md; the PDM's keys):
        ``vertices`` (F,n,3) float32 shell plus pose-space corrections, in the markers'
        world pose; ``vertices_detailed`` (F,n,3) with the fine map baked along the normals;
        ``displacement`` (F,H,H) float32 the fine map (detail below the mesh, relative to
        ``vertices``, along the normal); ``normal_map`` (F,H,H,3) tangent space; always
        ``faces``, ``clamped`` (F,) the fraction of features limited (``clamp``) and
        ``confidence`` (F,) (module docstring). ``captured`` (F,M,3): the same frames as
        captured, where ``markers`` were smoothed in time (a synthesis job's
        ``marker_filter_frames``): the confidence's noise factor reads their σ̂ (as the PDM's).

        Raises :class:`InvalidInput` for a wrong marker shape, too few visible markers, an
        unknown output, or a map output of a model trained without maps.
        """
        ev, d = self.evaluator, self.data
        markers = np.asarray(markers, dtype=np.float64)
        if markers.ndim == 2:
            markers = markers[None]
        M = d.n_markers
        if markers.ndim != 3 or markers.shape[1:] != (M, 3):
            raise InvalidInput(f"model expects markers (F,{M},3), got {markers.shape}")
        want = set(outputs)
        check_outputs(outputs, OUTPUTS)
        if want & {"mesh_detailed", "displacement", "normal_map"} and not d.map_resolution:
            raise InvalidInput("this model was trained without displacement maps; only 'mesh' "
                               "is available")
        nf, n = len(markers), d.n_vertices
        out: dict[str, np.ndarray] = {"faces": d.faces.astype(np.int32),
                                      "clamped": np.zeros(nf, np.float32),
                                      "confidence": np.zeros(nf, np.float32)}
        if want & {"mesh", "mesh_detailed"}:
            out["vertices"] = np.empty((nf, n, 3), np.float32)
        if "mesh_detailed" in want:
            out["vertices_detailed"] = np.empty((nf, n, 3), np.float32)
        H = d.map_resolution
        if want & {"displacement", "normal_map"}:
            out["displacement"] = np.zeros((nf, H, H), np.float32)
        if "normal_map" in want:
            out["normal_map"] = np.empty((nf, H, H, 3), np.float32)
        margin = d.params.extrapolation_margin if clamp else None
        noise = (None if captured is None else
                 ev.base.captured_noise(captured, d.pose_weights, markers.shape))
        for s in range(0, nf, FRAME_CHUNK):
            sl = slice(s, min(s + FRAME_CHUNK, nf))
            pose, u_H = ev.deformation(markers[sl])
            f = ev.features(u_H)
            conf = ev.confidence(f)                                 # the range's: it fades
            out["confidence"][sl] = conf * ev.base.input_confidence(
                pose.remove(markers[sl]), u_H, None if noise is None else noise[sl])
            fade = conf.astype(np.float32) if d.params.confidence_fade else None     # (f,)
            f, out["clamped"][sl] = ev.limit(f, margin)
            vis = ev.edge_visibility(markers[sl]) if d.params.occlusion == "reweight" else None
            maps = want & {"mesh_detailed", "displacement", "normal_map"}
            need_medium = want & {"mesh_detailed", "normal_map"}
            C, D2 = self._corrections(f, vis, fade, keep_distances=bool(maps))
            if "vertices" in out or need_medium:
                medium = np.empty((len(f), n, 3), np.float64) if need_medium else None
                lin = ev.regression_offsets(u_H)                                         # (f,n,3) aligned
                for k in range(len(f)):
                    world = out["vertices"][s + k] if "vertices" in out else None
                    Xa = ev.shell_detail(u_H[k], C[k], pose.R[k], pose.t[k], aligned=bool(need_medium),
                                         world=world)
                    if need_medium:
                        medium[k] = ev.shell_frames.to_vertices(Xa)
                    if lin is not None:            # aligned offsets: world = Rᵀ(· − t) adds Rᵀ y
                        if world is not None:
                            world += lin[k] @ pose.R[k].astype(np.float32)
                        if need_medium:
                            medium[k] += lin[k]
            if not maps:
                continue
            disp = ev.fine_map(D2, f)                                            # (f,Pt)
            if "displacement" in out:
                out["displacement"][sl].reshape(len(disp), -1)[:, d.map_index] = disp
            if want & {"mesh_detailed", "normal_map"}:
                mframes = ev.base.frames(medium)
            if "mesh_detailed" in want:
                h = (ev.map_sampler @ disp.T).T
                out["vertices_detailed"][sl] = pose.restore(medium + h[..., None] * mframes[..., 2, :])
            if "normal_map" in want:
                for k in range(sl.stop - sl.start):
                    out["normal_map"][s + k] = ev.normal_mapper.normal_map(
                        out["displacement"][s + k], medium[k], mframes[k])
        if "displacement" not in want:
            out.pop("displacement", None)
        return out

    def _corrections(self, f: np.ndarray, vis: np.ndarray | None, fade: np.ndarray | None,
                     keep_distances: bool) -> tuple[list[np.ndarray], np.ndarray | None]:
        """Per frame the corrections (3,n) float32 in the frames' internal vertex order, faded
        by ``fade`` (f,), and, with ``keep_distances``, the distances (n,f,P) in vertex order
        (the fine map's input) — for features f (f,E) and edge visibility ``vis`` (f,E)."""
        ev = self.evaluator
        sf, cs = ev.shell_frames, ev.correction_sum
        kappa = np.ones(len(f), np.float32) if fade is None else fade
        if cs is None:                                         # PSD: one system, NumPy
            D2 = ev.sq_distances(f, vis)
            c = ev.corrections(D2, f)
            return [sf.to_internal(ck * kk) for ck, kk in zip(c, kappa)], D2 if keep_distances else None
        C, D = [], []
        for k, fk in enumerate(f):
            if vis is None:
                res = cs(fk, kappa[k], keep_distances=keep_distances)
                Ck, Dk = res if keep_distances else (res, None)
                Dk = None if Dk is None else Dk[sf.rank]
            else:
                Dk = ev.sq_distances(fk[None], vis[k:k + 1])[:, 0]                  # (n,P) vertex order
                Ck = cs(fk, kappa[k], D2=Dk[sf.order])
            C.append(Ck)
            D.append(Dk)
        return C, np.stack(D, axis=1) if keep_distances else None

    def save(self, path) -> dict:
        """Write the model directory (manifest.json, model.npz, cache.npz); see :mod:`.store`."""
        return store.write_model(self.data, self.evaluator.base, path)

    @classmethod
    def load(cls, path) -> "PoseSpaceModel":
        """Read a model directory written by :meth:`save`, verifying checksums."""
        data, base = store.read_model(path)
        return cls(data, PoseSpaceEvaluator(data, base))


# ---------------------------------------------------------------------------------------
# training

def _phi(rows: np.ndarray, basis: np.ndarray, alpha: sp.csr_matrix | None) -> np.ndarray:
    """Kernel values (B,T,P) of features ``rows`` (T,E) against ``basis`` (P,E): PSD B = 1,
    WPSD one row per vertex of ``alpha`` (B,E)."""
    if alpha is None:
        g = rows[:, None, :] - basis[None]
        return rbf.kernel(np.sqrt(np.einsum("tpe,tpe->tp", g, g)))[None]
    return rbf.kernel(np.sqrt(weighted_sq_distances(alpha, rows, basis)))


def _row_argmax(M: sp.csr_matrix) -> np.ndarray:
    """Column of the largest entry of every row (B,) of a CSR matrix without empty rows."""
    M = M.tocsr()
    r = np.repeat(np.arange(M.shape[0]), np.diff(M.indptr))
    order = np.lexsort((-M.data, r))
    return M.indices[order[M.indptr[:-1]]]


def marker_statistics(u: np.ndarray, max_modes: int = MARKER_MODES) -> tuple[np.ndarray, np.ndarray]:
    """Mean (M,3) and principal modes (r,M,3) of aligned marker displacements u (T,M,3), each
    mode scaled by its standard deviation (modes below 1e-6 of the largest variance dropped),
    so that u ≈ mean + Σ_k z_k mode_k with z ~ N(0, I)."""
    u = u[np.isfinite(u).all(axis=(1, 2))]                                     # complete frames
    T, M, _ = u.shape
    mean = u.mean(axis=0)
    _, s, Vt = np.linalg.svd((u - mean).reshape(T, -1), full_matrices=False)
    keep = s ** 2 >= 1e-6 * max(s[0] ** 2, 1e-300) if len(s) else np.zeros(0, bool)
    r = min(int(keep.sum()), max_modes)
    return mean, (Vt[:r] * (s[:r, None] / np.sqrt(max(T - 1, 1)))).reshape(r, M, 3)


def complete_markers(aligned: np.ndarray, mean: np.ndarray, modes: np.ndarray,
                     noise_mm: float) -> np.ndarray:
    """Occluded (NaN) rows of aligned markers (F,M,3) replaced by their MAP estimate under the
    training Gaussian ``mean`` (M,3) + modes (r,M,3)·z, z ~ N(0, I), from the visible rows with
    observation noise σ = ``noise_mm``: z = (LᵥᵀLᵥ + σ²I)⁻¹ Lᵥᵀ(xᵥ − meanᵥ), x_o = mean_o + L_o z.
    Visible rows are returned as given; a frame with every marker visible is untouched."""
    out = np.array(aligned, dtype=np.float64)
    seen = np.isfinite(out).all(axis=-1)                                       # (F,M)
    r = len(modes)
    if r == 0:
        return out
    L = modes.reshape(r, -1).T                                                 # (3M,r)
    s2 = max(float(noise_mm), 1e-6) ** 2
    for f in np.flatnonzero(~seen.all(axis=1)):
        v = np.repeat(seen[f], 3)
        Lv = L[v]
        z = np.linalg.solve(Lv.T @ Lv + s2 * np.eye(r), Lv.T @ (out[f].ravel()[v] - mean.ravel()[v]))
        fill = (mean.ravel() + L @ z).reshape(-1, 3)
        out[f, ~seen[f]] = fill[~seen[f]]
    return out


def residual_variance(u: np.ndarray, clip_frames: Sequence[int], max_modes: int = MARKER_MODES,
                      floor_mm: float = 1e-3) -> np.ndarray:
    """Per-marker variance τ²_m (M,) (actor unit² per coordinate) of aligned marker
    displacements u (T,M,3) *outside* the training modes, by leaving one clip out: for every
    clip (``clip_frames`` its frame counts, in order) the mean and modes of the other clips
    (:func:`marker_statistics`) leave a residual on its frames (their orthogonal projection
    onto those modes removed); τ²_m is the mean of |r_m|²/3 over all frames, at least
    ``floor_mm``². It is what an expression no training clip showed adds at each marker: the
    off-mode prior of :func:`marker_posterior`. With one clip only, the residual of the
    leave-every-4th-frame-out split is used instead."""
    u = np.asarray(u, np.float64)
    T, M, _ = u.shape
    bounds = np.cumsum([0, *clip_frames])
    if bounds[-1] != T:
        raise ValueError(f"clip frames sum to {bounds[-1]}, u has {T}")
    groups = [np.arange(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    if len(groups) < 2:
        groups = [np.arange(k, T, 4) for k in range(4)]
    sq = np.zeros(M)
    count = 0
    for g in groups:
        rest = np.setdiff1d(np.arange(T), g)
        mean, modes = marker_statistics(u[rest], max_modes)
        x = (u[g] - mean).reshape(len(g), -1)
        x = x[np.isfinite(x).all(axis=1)]
        if len(modes):
            Q, _ = np.linalg.qr(modes.reshape(len(modes), -1).T)                # (3M,r) orthonormal
            x = x - (x @ Q) @ Q.T
        sq += (x.reshape(len(x), M, 3) ** 2).sum(axis=(0, 2)) / 3.0
        count += len(x)
    return np.maximum(sq / max(count, 1), floor_mm ** 2)


def marker_posterior(u: np.ndarray, mean: np.ndarray, modes: np.ndarray, resid_var: np.ndarray,
                     noise_mm: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Posterior mean of aligned marker displacements from noisy, partly occluded ones.

    Prior (a Gaussian of the training markers): u = mean + Σ_k z_k mode_k + r with
    z ~ N(0, I) (``modes`` (r,M,3) scaled by their std, :func:`marker_statistics`) and an
    independent off-mode part r_m ~ N(0, τ²_m I₃) (``resid_var`` (M,), leave one clip out,
    :func:`residual_variance`); observation x_v = u_v + ε, ε ~ N(0, σ² I) at the visible
    markers, σ = ``noise_mm``. With N = diag(τ² + σ²) over the visible coordinates:

        ẑ = (L_vᵀ N⁻¹ L_v + I)⁻¹ L_vᵀ N⁻¹ (x_v − mean_v),     r̂_v = τ²/(τ² + σ²) · (x_v − mean_v − L_v ẑ)

    (the exact posterior mean E[u_v | x] = mean_v + L_v ẑ + r̂_v: a Wiener filter that keeps
    what the training modes explain and shrinks the rest by its signal-to-noise ratio).
    Occluded markers get the in-mode part mean_o + L_o ẑ; their off-mode part is left to the
    caller (the thin shell completes it from the visible r̂ at minimum energy — a smooth prior
    for the residual field where the independent Gaussian would give 0).

    u (F,M,3) with NaN rows for occluded markers, mean (M,3). Returns ``inmode`` (F,M,3)
    complete and ``resid`` (F,M,3), r̂ at visible markers and NaN at occluded ones; the
    estimate at visible markers is their sum.
    """
    u = np.asarray(u, np.float64)
    if np.ndim(noise_mm):                       # σ per frame: each frame its own filter
        parts = [marker_posterior(u[k:k + 1], mean, modes, resid_var, float(s)) for k, s in enumerate(noise_mm)]
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    F, M, _ = u.shape
    r = len(modes)
    seen = np.isfinite(u).all(axis=-1)                                          # (F,M)
    L = np.asarray(modes, np.float64).reshape(r, 3 * M).T                       # (3M,r)
    tau2 = np.repeat(np.asarray(resid_var, np.float64), 3)                      # (3M,)
    s2 = float(noise_mm) ** 2
    ninv = 1.0 / (tau2 + s2)
    keep = tau2 * ninv                                                          # Wiener gain
    d = (u - mean).reshape(F, -1)
    Z = np.zeros((F, r))
    patterns, which = np.unique(seen, axis=0, return_inverse=True)
    for k, pat in enumerate(patterns):
        fr = np.flatnonzero(which.ravel() == k)
        v = np.repeat(pat, 3)
        if r and v.any():
            Lv = L[v] * ninv[v, None]
            Z[fr] = np.linalg.solve(L[v].T @ Lv + np.eye(r), Lv.T @ d[fr][:, v].T).T
    inmode = mean.ravel() + Z @ L.T                                             # (F,3M)
    resid = np.where(np.repeat(seen, 3, axis=1), keep * (np.nan_to_num(d) + mean.ravel() - inmode), np.nan)
    return inmode.reshape(F, M, 3), resid.reshape(F, M, 3)


def posterior_noise(base: BaseSurface, aligned: np.ndarray, params: Params) -> float | np.ndarray:
    """The observation noise σ (mm) of the marker posterior for aligned markers (F,M,3):
    ``validation_noise_mm``, or with ``posterior_noise = "frame"`` each frame's own estimate σ̂
    (F,) (:func:`~service.geometry.marker_prior.frame_noise` against the base's learned marker
    prior, the confidence's estimate) clipped to [:data:`POSTERIOR_NOISE_FLOOR_MM`,
    ``validation_noise_mm``]: a clean frame is filtered less, never more than the capture
    system's stated noise (an expression far from the training reads as noise to σ̂: 0.7–1.1 mm
    on clean sneer markers of a model trained on brow raise, smile and pucker) (module
    docstring: marker prior). A base without a learned marker prior (a transferred model's)
    takes ``validation_noise_mm``."""
    if params.posterior_noise == "validation" or base.evidence is None:
        return params.validation_noise_mm
    return np.clip(base.evidence.noise(np.asarray(aligned, np.float64) - base.rest_markers),
                   POSTERIOR_NOISE_FLOOR_MM, params.validation_noise_mm)


def posterior_displacements(base: BaseSurface, aligned: np.ndarray, mean: np.ndarray, modes: np.ndarray,
                            resid_var: np.ndarray, noise_mm: float) -> np.ndarray:
    """Complete handle displacements u_H (F,M,3) of aligned markers (F,M,3) (NaN rows
    occluded) with ``params.marker_prior = "posterior"``: the in-mode part of
    :func:`marker_posterior` at every marker plus its shrunk residual, completed at the
    occluded markers by the thin shell's minimum energy (the shell is linear, so the two
    parts are completed separately and added). With marker noise σ > 0 the base's
    denoiser is affine, D(x) = P x + o (the learned prior's mean gives o): each part's call
    adds o, so D(0) of the residual's occlusion pattern is taken off once —
    D(a) + D(b) − D(0) = P (a + b) + o."""
    rest = base.rest_markers
    inmode, resid = marker_posterior(aligned - rest, mean, modes, resid_var, noise_mm)
    u = base.handle_displacements(rest + inmode) + base.handle_displacements(rest + resid)
    if not base.denoise.interpolates:
        u -= base.handle_displacements(rest + np.where(np.isnan(resid), np.nan, 0.0))
    return u


def _even_sample(n: int, k: int) -> np.ndarray:
    return np.unique(np.linspace(0, n - 1, min(k, n)).round().astype(np.int64))


def _targets(C: np.ndarray, verts: np.ndarray, wpsd: bool) -> np.ndarray:
    """Correction targets (B,T,C) of vertices ``verts``: WPSD (|v|,T,3), PSD (1,T,3|v|)."""
    c = C[:, verts].astype(np.float64)
    return c.transpose(1, 0, 2) if wpsd else c.reshape(len(C), 1, -1).transpose(1, 0, 2)


def support(alpha: sp.csr_matrix | None, n_edges: int, params: Params):
    """The polynomial's support (idx, mask) (B,w) (:func:`.polynomial.support_index`): WPSD the
    rows of ``alpha``, PSD one row of all ``n_edges`` features; None without a polynomial."""
    if params.polynomial == "none":
        return None
    if alpha is None:
        return np.arange(n_edges)[None], np.ones((1, n_edges), bool)
    return polynomial.support_index(alpha)


def _poly(F: np.ndarray, sup, rows=slice(None)) -> np.ndarray | None:
    """Polynomial columns (B,T,1+w) of features F (T,E) for the support rows ``rows``."""
    if sup is None:
        return None
    idx, mask = sup
    return polynomial.design(F, idx[rows], mask[rows])


def select_basis(F: np.ndarray, D: np.ndarray, alpha: sp.csr_matrix | None, params: Params,
                 smoothing: float, first: int, Q: np.ndarray | None = None) -> tuple[list[int], list[float]]:
    """Greedy basis (§5.2) over training features F (T,E) and targets D (B,T,C)
    (WPSD: alpha (B,E) of the B vertices; PSD: alpha None, B = 1), fitted with the
    polynomial columns Q (B,T,q) if given."""
    return rbf.greedy_basis(lambda j: _phi(F, F[j:j + 1], alpha)[:, :, 0], D, params.basis_size,
                            first, smoothing, params.fit == "exact", params.error_threshold, Q)


def fit_rows(F: np.ndarray, F_copies: np.ndarray | None) -> tuple[np.ndarray, int]:
    """The rows the least-squares fit sees (T(1+K),E): the clean features F (T,E) and the K
    noisy copies F_copies (K,T,E) of ``params.noise_copies`` (module docstring), and 1+K."""
    if F_copies is None or not len(F_copies):
        return F, 1
    return np.concatenate([F[None], F_copies]).reshape(-1, F.shape[1]), 1 + len(F_copies)


def _tile(D: np.ndarray, k: int) -> np.ndarray:
    """Targets D (B,T,C) repeated for the k row blocks of :func:`fit_rows` (B,kT,C)."""
    return D if k == 1 else np.concatenate([D] * k, axis=1)


def validate_smoothing(F: np.ndarray, F_noisy: np.ndarray, D: np.ndarray, alpha, params: Params,
                       first: int, sup=None, F_copies: np.ndarray | None = None) -> tuple[float, list[dict]]:
    """λ from ``params.smoothing_grid`` by held-out training frames (module docstring).

    F (T,E) clean features, F_noisy (T,E) features from noisy markers, D (B,T,C) targets,
    sup the polynomial's support of the B rows (:func:`support`) or None, F_copies (K,T,E)
    the noisy copies the fit also sees (:func:`fit_rows`; the held-out frames' copies are
    left out with them).
    Returns the chosen λ and the table [{smoothing, rms}] (rms in the targets' unit).
    """
    T = len(F)
    held = np.zeros(T, bool)
    held[::params.validation_stride] = True
    held[first] = False
    fit, val = np.flatnonzero(~held), np.flatnonzero(held)
    rows, k = fit_rows(F[fit], None if F_copies is None else F_copies[:, fit])
    # one greedy selection (at the ridge floor); every λ refits that basis
    Q, Q_val = _poly(rows, sup), _poly(F_noisy[val], sup)
    sel, _ = select_basis(F[fit], D[:, fit], alpha, params, 0.0, int(np.searchsorted(fit, first)),
                          _poly(F[fit], sup))
    basis = F[fit][sel]
    Phi, Phi_val = _phi(rows, basis, alpha), _phi(F_noisy[val], basis, alpha)
    table = []
    for lam in params.smoothing_grid:
        W = rbf.fit_basis(Phi, _tile(D[:, fit], k), sel, lam, params.fit == "exact", Q)
        err = rbf.residual_sq(rbf.columns(Phi_val, Q_val), D[:, val], W)
        table.append({"smoothing": float(lam), "rms": float(np.sqrt(err.sum() / (D[:, val].size)))})
    best = min(table, key=lambda r: r["rms"])
    return best["smoothing"], table


def _clip_maps(clips: Sequence[Clip], H: int, index: np.ndarray) -> np.ndarray:
    """The clips' fine maps (T,Pt) float32 at the covered texels of an H×H map."""
    out = []
    uv = texel_centers_uv(H, H).reshape(-1, 2)[index]
    for c in clips:
        m = c.displacement
        if m.shape[1] == H:
            out.append(m.reshape(len(m), -1)[:, index].astype(np.float32))
        else:
            out.append(np.stack([sample_map(x, uv) for x in m]).astype(np.float32))
    return np.concatenate(out)


def train(actor: ActorData, clips: Sequence[Clip], params: Params | None = None,
          progress: Progress = no_progress) -> PoseSpaceModel:
    """Fit a PSD or WPSD model to training clips (bickel2008 §5; steps in the module docstring).

    Parameters
    ----------
    actor : ActorData          neutral, UV layout, markers
    clips : sequence of Clip   high-resolution frames with their markers (maps optional: with
                               maps the model also learns the fine displacement map)
    params : PsdParams | WpsdParams   (default WpsdParams())
    progress : Progress

    Raises :class:`InvalidInput` for clips that do not match the actor, frames with too few
    markers, markers sharing a handle, or a bad feature graph.
    """
    params = params if params is not None else WpsdParams()
    if not isinstance(params, (PsdParams, WpsdParams)):
        raise InvalidInput(f"params must be PsdParams or WpsdParams, got {type(params).__name__}")
    wpsd = params.method == "wpsd"
    clips = list(clips)
    check_clips(actor, clips)
    progress(0.0, "alignment")
    markers = np.concatenate([c.markers for c in clips]).astype(np.float64)
    names = [f"{c.name}:{f}" for c in clips for f in range(c.frames)]
    T, n = len(markers), actor.n_vertices
    if T < 2:
        raise InvalidInput(f"training needs at least 2 frames, got {T}")
    rest = actor.marker_positions()
    pose, pose_weights = training_head_pose(markers, rest, names)

    progress(0.05, "large-scale shell")
    base = large_scale_surface(actor).with_marker_noise(params.marker_noise_mm, samples=pose.remove(markers))
    aligned = pose.remove(markers)
    marker_mean, marker_modes = marker_statistics(aligned - rest)
    marker_residual_var = residual_variance(aligned - rest, [c.frames for c in clips])

    def shell_input(a):
        """u_H of aligned markers a (T,M,3) as synthesis computes them (the marker prior)."""
        if params.marker_prior == "posterior":
            return posterior_displacements(base, a, marker_mean, marker_modes, marker_residual_var,
                                           posterior_noise(base, a, params))
        return base.handle_displacements(a)

    u_H = shell_input(aligned)
    graph = (graph_from_pairs(params.feature_edges, actor.marker_names, rest) if params.feature_edges
             else automatic_graph(actor.marker_uv(), rest, params.max_edge_ratio, params.min_angle_deg))

    def shell_features(u):
        nodes_now = node_rest + np.einsum("nm,fmd->fnd", node_basis, u)
        return graph.features(nodes_now)

    nodes = node_operator(actor.faces, actor.marker_triangle, actor.marker_barycentric, n)
    node_rest, node_basis = nodes @ actor.vertices, np.asarray(nodes @ base.basis.astype(np.float64))
    F = shell_features(u_H)                                                   # (T,E)

    progress(0.15, "corrections")
    regression = None
    if params.marker_regression is not None:      # the part linear in the markers first
        Y = np.empty((T, n, 3), np.float32)
        t0 = 0
        for c in clips:
            sl = slice(t0, t0 + c.frames)
            Y[sl] = pose[sl].remove(c.vertices) - base.deform(u_H[sl])
            t0 += c.frames
        regression = marker_regression.fit(u_H, Y, actor.vertices, rest,
                                           params.marker_regression * marker_regression.marker_spacing(rest),
                                           params.marker_regression_ridge)
        del Y
    C = np.empty((T, n, 3), np.float32)
    t0 = 0
    for c in clips:
        sl = slice(t0, t0 + c.frames)
        aligned_c = pose[sl].remove(c.vertices)
        if regression is not None:
            aligned_c = aligned_c - regression(u_H[sl])
        C[sl] = corrections(base, u_H[sl], aligned_c)
        t0 += c.frames
    maps = None
    if clips[0].displacement is not None:
        H = params.map_resolution or clips[0].displacement.shape[1]
        raster = rasterize_uv(actor.uv, actor.uv_faces, H, H)
        map_index = np.flatnonzero(raster.mask.ravel())
        maps = _clip_maps(clips, H, map_index)                                # (T,Pt)
    else:
        H, map_index = 0, np.zeros(0, np.int64)

    alpha = None
    if wpsd:
        progress(0.25, "edge weights")
        alpha = edge_weights(actor.vertices, node_rest, graph, params.alpha_threshold,
                             params.max_edges_per_vertex, params.beta)

    first = int(np.argmin(np.linalg.norm(F, axis=1)))
    sample = _even_sample(n, params.selection_vertices)
    alpha_s = None if alpha is None else alpha[sample]
    E = graph.n_edges
    sup = support(alpha, E, params)                                           # polynomial
    sup_s = sup if sup is None or not wpsd else (sup[0][sample], sup[1][sample])
    D_s = _targets(C, sample, wpsd)
    table = None
    F_copies = None
    if params.noise_copies and params.fit == "least_squares":
        progress(0.28, "noisy copies")
        rng = np.random.default_rng(NOISE_COPIES_SEED)
        F_copies = np.empty((params.noise_copies, T, E))
        for k in range(params.noise_copies):
            noisy = markers + rng.normal(0.0, params.validation_noise_mm, markers.shape)
            pn = head_alignment(noisy, rest, pose_weights)
            F_copies[k] = shell_features(shell_input(pn.remove(noisy)))
    F_fit, reps = fit_rows(F, F_copies)                                          # (T·reps,E)
    smoothing = params.smoothing
    if smoothing is None:
        progress(0.3, "smoothing validation")
        rng = np.random.default_rng(VALIDATION_SEED)
        noisy = markers + rng.normal(0.0, params.validation_noise_mm, markers.shape)
        pn = head_alignment(noisy, rest, pose_weights)
        F_noisy = shell_features(shell_input(pn.remove(noisy)))
        smoothing, table = validate_smoothing(F, F_noisy, D_s, alpha_s, params, first, sup_s, F_copies)

    progress(0.45, "basis selection")
    if wpsd:
        sel, sel_errors = select_basis(F, D_s, alpha_s, params, smoothing, first, _poly(F, sup_s))
    else:
        K = np.zeros((T, T))
        for v0 in range(0, n, FIT_CHUNK):
            Cv = C[:, v0:v0 + FIT_CHUNK].reshape(T, -1).astype(np.float64)
            K += Cv @ Cv.T
        sel, sel_errors = select_basis(F, rbf.gram_factor(K)[None], None, params, smoothing, first,
                                       _poly(F, sup))
    basis = F[sel]
    P = len(sel)
    exact = params.fit == "exact"

    progress(0.55, "weights")
    weights = np.empty((n, P, 3), np.float32)
    fit_sq = np.zeros(n)
    poly_parts = []                                   # (const (c,3), linear CSR (3c,E)) per chunk
    if wpsd:
        for v0 in range(0, n, FIT_CHUNK):
            vs = np.arange(v0, min(v0 + FIT_CHUNK, n))
            Phi = _phi(F_fit, basis, alpha[vs])
            Q = _poly(F_fit, sup, vs)
            Dv = _targets(C, vs, True)
            W = rbf.fit_basis(Phi, _tile(Dv, reps), sel, smoothing, exact, Q)
            weights[vs] = W[:, :P]
            if Q is not None:
                poly_parts.append(polynomial.to_sparse(W[:, P:], sup[0][vs], sup[1][vs], E))
            R = Dv - rbf.columns(Phi[:, :T], None if Q is None else Q[:, :T]) @ W
            fit_sq[vs] = np.einsum("btc,btc->b", R, R)
    else:
        Phi = _phi(F_fit, basis, None)
        Q = _poly(F_fit, sup)
        S = rbf.fit_basis(Phi, _tile(np.eye(T)[None], reps), sel, smoothing, exact, Q)[0]   # (P+q,T): W = S D
        X = rbf.columns(Phi, Q)[0][:T]                                          # clean rows
        for v0 in range(0, n, FIT_CHUNK):
            Cv = C[:, v0:v0 + FIT_CHUNK].astype(np.float64)                     # (T,c,3)
            W = np.einsum("pt,tvc->vpc", S, Cv)
            weights[v0:v0 + FIT_CHUNK] = W[:, :P]
            if Q is not None:
                c = len(W)
                poly_parts.append(polynomial.to_sparse(W[:, P:], np.tile(sup[0], (c, 1)),
                                                       np.tile(sup[1], (c, 1)), E))
            R = Cv - np.einsum("tp,vpc->tvc", X, W)
            fit_sq[v0:v0 + FIT_CHUNK] = np.einsum("tvc,tvc->v", R, R)
    poly_const = poly_linear = None
    if poly_parts:
        poly_const = np.concatenate([c for c, _ in poly_parts]).astype(np.float32)
        poly_linear = sp.vstack([a for _, a in poly_parts], format="csr").astype(np.float32)

    map_weights = np.zeros((len(map_index), P), np.float32)
    map_poly_const = map_poly_linear = None
    map_rms = None
    if maps is not None:
        progress(0.75, "map weights")
        if wpsd:
            interp = interpolation_matrix(raster, actor.faces, n)[map_index].tocsr()
            Tf = len(F_fit)
            G = ((F_fit[:, None, :] - basis[None]) ** 2).reshape(Tf * P, -1).T  # (E,Tf·P)
            sq = 0.0
            # the polynomial of a texel: its nearest vertex's support (polynomial.py)
            nearest = _row_argmax(interp) if sup is not None else None
            parts = []
            for t0 in range(0, len(map_index), TEXEL_CHUNK):
                rows = interp[t0:t0 + TEXEL_CHUNK]
                verts = np.unique(rows.indices)
                D2 = np.asarray(alpha[verts] @ G)                                 # (|v|,T·P)
                Phi = rbf.kernel(np.sqrt(np.maximum(rows[:, verts] @ D2, 0.0))).reshape(-1, Tf, P)
                Dt = maps[:, t0:t0 + TEXEL_CHUNK].T[..., None].astype(np.float64)
                Q = None if sup is None else _poly(F_fit, sup, nearest[t0:t0 + TEXEL_CHUNK])
                W = rbf.fit_basis(Phi, _tile(Dt, reps), sel, smoothing, exact, Q)
                map_weights[t0:t0 + TEXEL_CHUNK] = W[:, :P, 0]
                if Q is not None:
                    nv = nearest[t0:t0 + TEXEL_CHUNK]
                    parts.append(polynomial.to_sparse(W[:, P:], sup[0][nv], sup[1][nv], E))
                sq += rbf.residual_sq(rbf.columns(Phi[:, :T], None if Q is None else Q[:, :T]), Dt, W).sum()
            if parts:
                map_poly_const = np.concatenate([c[:, 0] for c, _ in parts]).astype(np.float32)
                map_poly_linear = sp.vstack([a for _, a in parts], format="csr").astype(np.float32)
        else:
            Wm = (S @ maps.astype(np.float64)).T                                  # (Pt,P+q)
            map_weights[:] = Wm[:, :P]
            R = maps - X @ Wm.T
            sq = float(np.einsum("tp,tp->", R, R))
            if Q is not None:
                Pt = len(map_index)
                map_poly_const, map_poly_linear = polynomial.to_sparse(
                    Wm[:, P:, None], np.tile(sup[0], (Pt, 1)), np.tile(sup[1], (Pt, 1)), E)
                map_poly_const = map_poly_const[:, 0].astype(np.float32)
                map_poly_linear = map_poly_linear.astype(np.float32)
        map_rms = float(np.sqrt(sq / maps.size))

    progress(0.95, "metrics")
    regions = {k: np.asarray(v, bool) for k, v in actor.regions.items()}
    signal = np.einsum("tvc,tvc->v", C, C, dtype=np.float64)
    rms = {"all": float(np.sqrt(fit_sq.sum() / (T * n)))}
    sig = {"all": float(np.sqrt(signal.sum() / (T * n)))}
    for k, m in regions.items():
        if m.any():
            rms[k] = float(np.sqrt(fit_sq[m].sum() / (T * m.sum())))
            sig[k] = float(np.sqrt(signal[m].sum() / (T * m.sum())))
    norms = np.linalg.norm(F, axis=1)
    metrics = {
        "kind": params.method,
        "training_frames": T,
        "clips": [c.name for c in clips],
        "feature_edges": graph.n_edges,
        "basis_size": P,
        "basis": [names[j] for j in sel],
        "selection_relative_error": sel_errors,
        "smoothing": float(smoothing),
        "validation": table,
        "correction_fit_rms_mm": rms,
        "correction_signal_rms_mm": sig,
        "map_fit_rms_mm": map_rms,
        "map_signal_rms_mm": None if maps is None else float(np.sqrt(np.mean(maps.astype(np.float64) ** 2))),
        "alpha_nonzero_per_vertex": None if alpha is None else float(alpha.nnz / n),
        "polynomial": params.polynomial,
    }
    data = PoseSpaceData(
        params=params, faces=np.asarray(actor.faces, np.int64), uv=np.asarray(actor.uv, np.float64),
        uv_faces=np.asarray(actor.uv_faces, np.int64), neutral=np.asarray(actor.vertices, np.float64),
        handles=base.handles, rest_markers=rest, pose_weights=pose_weights,
        node_triangle=np.asarray(actor.marker_triangle, np.int64),
        node_barycentric=np.asarray(actor.marker_barycentric, np.float64),
        edges=graph.edges, rest_length=graph.rest_length, basis_features=basis, weights=weights,
        alpha=None if alpha is None else alpha.astype(np.float32),
        map_resolution=int(H), map_index=map_index, map_weights=map_weights,
        feature_low=F.min(axis=0), feature_high=F.max(axis=0),
        confidence_scale=float(max(np.median(norms), 1e-9)),
        basis_names=tuple(names[j] for j in sel), metrics=metrics,
        poly_const=poly_const, poly_linear=poly_linear,
        map_poly_const=map_poly_const, map_poly_linear=map_poly_linear,
        marker_mean=marker_mean, marker_modes=marker_modes, marker_residual_var=marker_residual_var,
        regression=regression)
    progress(1.0, "done")
    return PoseSpaceModel(data, PoseSpaceEvaluator(data, base))


__all__ = ["OUTPUTS", "PoseSpaceData", "PoseSpaceEvaluator", "PoseSpaceModel", "node_operator",
           "train"]
