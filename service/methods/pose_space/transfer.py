"""Transfer of fine-scale details to another face (bickel2008 §5.4).

The detail is defined in pose space (strain of the feature graph) and stored in per-vertex
tangent frames, so its transfer "reduces to establishing dense correspondence with the target
face model":

1. ~40 corresponding landmarks on both rest poses; a rigid pre-alignment of the source to the
   target on them (weighted Kabsch, no scale: as the paper);
2. the source rest mesh deformed by the large-scale thin shell (§4) with the landmarks as
   handles moved onto the target's, "to approximately fit the target face";
3. projection: every target vertex maps to its closest point on the deformed source (a
   triangle and barycentric weights; any topology);
4. the per-vertex RBF weights w_v,j (and, for WPSD, the edge weights α_v,i the weights were
   fitted with) are interpolated with those barycentric weights; the feature graph's nodes
   are mapped onto the target surface (closest points of the deformed source's nodes), with
   rest lengths measured on the target — strains are dimensionless, so the basis features
   f_j carry over unchanged. The nodes need not coincide with the target's markers: at run
   time they are surface points of the target's own large-scale deformation.

The new model is driven by the **target's** markers (its own thin shell, head pose with
uniform weights unless given).

Departures: the tangent frames of the two faces need not agree (different UV layouts), so
each transferred weight vector is rotated from the deformed source's frame at the
corresponding point into the target's frame (one 3×3 per vertex; identity for the same
layout). The fine map band (texel weights) is transferred by sampling the source's weight
maps at each target texel's corresponding source UV. The polynomial term (:mod:`.polynomial`)
moves like the weights: its constant and linear coefficients are interpolated with the
barycentric correspondence (a sparse product: the union of the supports) and rotated; the
map's by a sparse bilinear lookup. Detail amplitudes stay in the
source's millimetres (no scaling by face size).

The marker regression (:mod:`service.geometry.marker_regression`, ``params.marker_regression``)
is a linear map from the source's marker displacements to the source's head-aligned vertex
offsets, both world vectors of the source's rest pose. It carries over as the corrections do (§5.4: the
pose-space detail only needs a dense correspondence): its input becomes the feature nodes'
displacements on the target — the source markers' corresponding surface points, moved by the
target's own thin shell, exactly the points whose strains drive the RBFs — rotated into the
source's axes by the rigid pre-alignment R; its output rows are interpolated with the
barycentric correspondence and rotated back by R:
``L_t = (I_n ⊗ R) (C ⊗ I_3) L_s (I_M ⊗ Rᵀ)``, ``ū_t = R ū_s``, ``ȳ_t = R (C ȳ_s)``, applied to
L's low-rank factors (``data.regression_input = "nodes"``). World vectors rotate by the rigid R alone, not by the
per-vertex frame rotation of the weights: the source's shell fit to the landmarks bends the
surface locally, a correction stored in tangent frames follows that bend, a regression
stored in world axes does not (its departure on a bent target: the fit's local rotation).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from service.geometry.closest_point import closest_points, surface_points
from service.geometry.deformation_gradient import polar_decomposition
from service.geometry.marker_regression import MarkerRegression
from service.geometry.rigid import rigid_align
from service.geometry.tangent_frames import FrameField
from service.geometry.thin_shell import ThinShellSolver
from service.geometry.uv_raster import dilate, rasterize_uv, sample_map, uv_to_texel
from service.methods.inputs import ActorData, InvalidInput, Progress, no_progress
from service.methods.pose_space.corrections import large_scale_surface
from service.methods.pose_space.model import PoseSpaceData, PoseSpaceEvaluator, PoseSpaceModel, node_operator

#: fewest landmark pairs accepted (a rigid fit and a shell need a few; the paper uses ~40)
MIN_LANDMARKS = 4
#: texels of edge padding of the source weight maps before they are sampled
PAD_TEXELS = 4


def check_landmarks(landmarks, n_source: int, n_target: int) -> np.ndarray:
    """Landmark pairs (L,2) int64 [source vertex, target vertex], or :class:`InvalidInput`
    for a wrong shape, fewer than :data:`MIN_LANDMARKS` pairs, a vertex out of range of its
    neutral or a repeated vertex (each named)."""
    L = np.asarray(landmarks)
    if L.ndim != 2 or L.shape[1] != 2 or not np.issubdtype(L.dtype, np.integer):
        raise InvalidInput(f"landmarks must be (L,2) integer vertex pairs (source, target), got "
                           f"shape {L.shape} dtype {L.dtype}")
    if len(L) < MIN_LANDMARKS:
        raise InvalidInput(f"need at least {MIN_LANDMARKS} landmark pairs, got {len(L)}")
    for col, n, who in ((0, n_source, "source"), (1, n_target, "target")):
        bad = np.flatnonzero((L[:, col] < 0) | (L[:, col] >= n))
        if len(bad):
            raise InvalidInput(f"landmarks[{bad[0]}]: {who} vertex {L[bad[0], col]} is out of "
                               f"range; the {who} neutral has {n} vertices")
        values, counts = np.unique(L[:, col], return_counts=True)
        if (counts > 1).any():
            raise InvalidInput(f"landmarks repeat {who} vertex {values[counts > 1][0]}")
    return L.astype(np.int64)


def _texel_source_uv(raster, index, Ft, Vt, fitted, Fs, uv_s, uvf_s, cp, H) -> np.ndarray:
    """Source UV (Pt,2) of each covered target texel: its corners' corresponding source UVs
    interpolated; where they straddle a source UV seam (their spread exceeds 4 texels plus twice
    the median spread), the closest point of the texel's 3D
    position on the fitted source gives its triangle and UV directly."""
    tri = raster.triangle.ravel()[index]
    bary = raster.barycentric.reshape(-1, 3)[index]
    src_uv = surface_points(uv_s, uvf_s, cp.triangle, cp.barycentric)           # (n_t,2)
    corner_uv = src_uv[Ft[tri]]                                                 # (Pt,3,2)
    out = np.einsum("tk,tkd->td", bary, corner_uv)
    spread = np.ptp(corner_uv, axis=1).max(axis=1)
    pos = np.einsum("tk,tkd->td", bary, Vt[Ft[tri]])
    bad = np.flatnonzero(spread > 4.0 / H + 2.0 * np.median(spread))
    if len(bad):
        near = closest_points(fitted, Fs, pos[bad])
        out[bad] = surface_points(uv_s, uvf_s, near.triangle, near.barycentric)
    return out


def _bilinear_matrix(uv: np.ndarray, H: int, covered: np.ndarray) -> sp.csr_matrix:
    """(K,H·H) sparse bilinear lookup at UV points (``sample_map``'s convention) restricted to
    the ``covered`` (H·H,) texels: uncovered corners are dropped and the rest renormalized (the
    sparse counterpart of dilating the map before ``sample_map``); a point with no covered
    corner gets an empty row."""
    xy = uv_to_texel(uv, H, H)
    x, y = np.clip(xy[:, 0], 0.0, H - 1), np.clip(xy[:, 1], 0.0, H - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(H - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(H - 2, 0))
    fx, fy = x - x0, y - y0
    cols = np.stack([y0 * H + x0, y0 * H + x0 + 1, (y0 + 1) * H + x0, (y0 + 1) * H + x0 + 1], axis=1)
    w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
    w = w * covered[cols]
    tot = w.sum(axis=1, keepdims=True)
    w = np.divide(w, tot, out=np.zeros_like(w), where=tot > 0)
    K = len(uv)
    return sp.csr_matrix((w.ravel(), (np.repeat(np.arange(K), 4), cols.ravel())), shape=(K, H * H))


def _marker_prior(model: PoseSpaceModel, C_handles: sp.csr_matrix, R: np.ndarray) -> dict:
    """The source's marker statistics (``params.marker_prior``) at the target's markers: the
    source marker modes and mean as displacement fields of the source's thin shell (B_s u),
    read at the target markers' corresponding source points (``C_handles`` (M_t,n_s), rows of
    the dense correspondence at the target's handle vertices) and rotated by the rigid
    pre-alignment R (3,3); the per-marker off-mode variance interpolated with the shell's
    normalized |B_s| weights. Empty for a source without them. On the source itself (C the
    identity at its handles, B_s the identity there) the statistics are unchanged."""
    s = model.data
    if s.marker_residual_var is None or s.marker_modes is None or s.marker_mean is None:
        return {}
    T = np.asarray(C_handles @ model.evaluator.base.basis.astype(np.float64))   # (M_t,M_s)
    A = np.abs(T)
    A /= np.maximum(A.sum(axis=1, keepdims=True), 1e-300)
    modes = np.einsum("ts,rsc,dc->rtd", T, s.marker_modes, R)
    return {"marker_mean": np.einsum("ts,sc,dc->td", T, s.marker_mean, R), "marker_modes": modes,
            "marker_residual_var": A @ s.marker_residual_var}


def _regression(s: PoseSpaceData, C: sp.csr_matrix, R: np.ndarray) -> dict:
    """The source's marker regression on the target (module docstring): rows interpolated with
    the dense correspondence C (n_t,n_s) and rotated by the rigid pre-alignment R (3,3), input
    the feature nodes' displacements in the target's axes (the source's markers, in order).
    On the low-rank factors: P ← (I ⊗ R)(C ⊗ I₃) P and Q ← Q (I ⊗ Rᵀ) (rows still orthonormal)."""
    reg = s.regression
    r, n_s = reg.rank, len(reg.mean_y)
    P = np.einsum("dc,tck->tdk", R, (C @ reg.P.astype(np.float64).reshape(n_s, 3 * r)).reshape(-1, 3, r))
    P = P.reshape(-1, r)                                                   # (3n_t, r), row 3t + d
    Q = (reg.Q.astype(np.float64).reshape(r, -1, 3) @ R.T).reshape(r, -1)
    return {"regression": MarkerRegression.from_factors(P, Q, reg.mean_u @ R.T,
                                                        (C @ reg.mean_y.astype(np.float64)) @ R.T),
            "regression_input": "nodes"}


def transfer(model: PoseSpaceModel, target: ActorData, landmarks: np.ndarray,
             pose_weights: np.ndarray | None = None, progress: Progress = no_progress) -> PoseSpaceModel:
    """A pose-space model of the same kind for ``target``, from ``model``'s details (§5.4).

    Parameters
    ----------
    model : PoseSpaceModel    the source model
    target : ActorData        the target face: neutral, UV layout, its own markers
    landmarks : (L,2) int     corresponding (source vertex, target vertex) pairs on the rest
                              poses (~40)
    pose_weights : (M_t,) float, optional   head-alignment weights of the target's markers
                              (default 1)
    progress : Progress       stage reports (the projection dominates: ~1 min at 45k vertices)

    Returns
    -------
    PoseSpaceModel whose ``synthesize`` takes the target's markers (F,M_t,3); its metrics
    hold the source's, and the correspondence's quality under ``"transfer"``.

    Raises :class:`InvalidInput` for bad landmarks or a target whose markers share a handle.
    """
    s = model.data
    Vs, Fs = s.neutral, s.faces
    Vt, Ft = np.asarray(target.vertices, np.float64), np.asarray(target.faces, np.int64)
    L = check_landmarks(landmarks, len(Vs), len(Vt))
    progress(0.0, "rigid pre-alignment and shell fit")
    # 1-2: rigid pre-alignment, then the shell fit of the source to the target landmarks
    rigid = rigid_align(Vs[L[:, 0]], Vt[L[:, 1]])
    Va = rigid.apply(Vs)
    shell = ThinShellSolver(Va, Fs, L[:, 0])
    fitted = Va + shell.deform(Vt[L[:, 1]] - Va[L[:, 0]])
    # 3: dense correspondence
    progress(0.1, "projection")
    cp = closest_points(fitted, Fs, Vt)
    C = node_operator(Fs, cp.triangle, cp.barycentric, len(Vs))                 # (n_t,n_s)
    # frames: source frames at the corresponding points vs the target's own
    src_frames = FrameField.build(Vs, Fs, s.uv, s.uv_faces).frames(fitted)      # (n_s,3,3)
    at = np.einsum("tk,tkij->tij", cp.barycentric, src_frames[Fs[cp.triangle]])
    at, _ = polar_decomposition(at)
    tgt_frames = FrameField.build(Vt, Ft, target.uv, target.uv_faces).frames(Vt)
    rot = np.einsum("tij,tkj->tik", tgt_frames, at)                            # target ← source
    # 4: weights, α, nodes
    progress(0.6, "weights and feature graph")
    n_t, P = len(Vt), s.basis_size
    W = (C @ s.weights.reshape(len(Vs), -1).astype(np.float64)).reshape(n_t, P, 3)
    W = np.einsum("tij,tpj->tpi", rot, W).astype(np.float32)
    alpha = None if s.alpha is None else (C @ s.alpha.astype(np.float64)).tocsr().astype(np.float32)
    poly_const = poly_linear = None
    if s.poly_linear is not None:                # the polynomial term, interpolated and rotated
        poly_const = np.einsum("tij,tj->ti", rot, C @ s.poly_const.astype(np.float64)).astype(np.float32)
        A = s.poly_linear.astype(np.float64).tocsr()
        moved = [C @ A[c::3] for c in range(3)]                                 # (n_t,E) each
        rows = [sum(sp.diags(rot[:, i, j]) @ moved[j] for j in range(3)) for i in range(3)]
        perm = np.arange(3 * n_t).reshape(3, n_t).T.ravel()                   # row 3t + i
        poly_linear = sp.vstack(rows, format="csr")[perm].astype(np.float32)
    src_nodes = surface_points(fitted, Fs, s.node_triangle, s.node_barycentric)
    nodes = closest_points(Vt, Ft, src_nodes)
    node_rest = surface_points(Vt, Ft, nodes.triangle, nodes.barycentric)
    rest_length = np.linalg.norm(node_rest[s.edges[:, 0]] - node_rest[s.edges[:, 1]], axis=1)
    if not (rest_length > 0).all():
        raise InvalidInput("two feature nodes of the source land on the same target point; "
                           "check the landmarks")
    # the fine map band, sampled at each target texel's corresponding source UV
    map_index, map_weights = np.zeros(0, np.int64), np.zeros((0, P), np.float32)
    map_poly_const = map_poly_linear = None
    H = s.map_resolution
    if H:
        img = np.zeros((H * H, P))
        img[s.map_index] = s.map_weights
        mask = np.zeros(H * H, bool)
        mask[s.map_index] = True
        img = dilate(img.reshape(H, H, P), mask.reshape(H, H), PAD_TEXELS)
        raster = rasterize_uv(target.uv, target.uv_faces, H, H)
        map_index = np.flatnonzero(raster.mask.ravel())
        texel_uv = _texel_source_uv(raster, map_index, Ft, Vt, fitted, Fs, s.uv, s.uv_faces, cp, H)
        map_weights = sample_map(img, texel_uv).reshape(len(map_index), P).astype(np.float32)
        if s.map_poly_linear is not None:
            Sm = _bilinear_matrix(texel_uv, H, mask)[:, s.map_index]            # (Pt_t,Pt_s)
            map_poly_const = (Sm @ s.map_poly_const.astype(np.float64)).astype(np.float32)
            map_poly_linear = (Sm @ s.map_poly_linear.astype(np.float64)).tocsr().astype(np.float32)
    progress(0.8, "target thin shell")
    base = large_scale_surface(target)
    M = target.n_markers
    w = np.ones(M) if pose_weights is None else np.asarray(pose_weights, np.float64)
    if w.shape != (M,):
        raise InvalidInput(f"pose_weights must be ({M},), got {w.shape}")
    prior = _marker_prior(model, C[base.handles], rigid.R)
    regression = {} if s.regression is None else _regression(s, C, rigid.R)
    metrics = dict(s.metrics)
    metrics["transfer"] = {
        "landmarks": len(L),
        "landmark_rms_after_rigid_mm": float(np.sqrt(np.mean(np.sum((Va[L[:, 0]] - Vt[L[:, 1]]) ** 2, axis=1)))),
        "projection_mean_mm": float(cp.distance.mean()),
        "projection_p95_mm": float(np.percentile(cp.distance, 95)),
        "projection_max_mm": float(cp.distance.max()),
        "node_projection_max_mm": float(nodes.distance.max()),
    }
    data = PoseSpaceData(
        params=s.params, faces=Ft, uv=np.asarray(target.uv, np.float64),
        uv_faces=np.asarray(target.uv_faces, np.int64), neutral=Vt, handles=base.handles,
        rest_markers=base.rest_markers, pose_weights=w, node_triangle=nodes.triangle,
        node_barycentric=nodes.barycentric, edges=s.edges, rest_length=rest_length,
        basis_features=s.basis_features, weights=W, alpha=alpha, map_resolution=H,
        map_index=map_index, map_weights=map_weights, feature_low=s.feature_low,
        feature_high=s.feature_high, confidence_scale=s.confidence_scale,
        basis_names=s.basis_names, metrics=metrics, poly_const=poly_const, poly_linear=poly_linear,
        map_poly_const=map_poly_const, map_poly_linear=map_poly_linear, **prior, **regression)
    model = PoseSpaceModel(data, PoseSpaceEvaluator(data, base))
    progress(1.0, "done")
    return model
