"""Per-frame scan weights and blended maps (fyffe, digital_ira_course2014, §5.3 and §7.3).

"The weights w_i^pq additionally enable trivial synthesis of high-resolution reflectance
maps for each dynamic frame of the performance by blending the static pose data" (§5.3);
"We also compute values for w_i^pq for any dynamic-to-static edge pq that was not present
in the performance flow graph, to produce weights for every frame" (§7.3).

:func:`scan_weights` computes, for every scan the tracking registered and every
``stride``-th frame, the flow frame → scan in view 0 at the graph's reduced resolution; a
vertex's correspondence strength for that scan is the flow's confidence at the tracked
vertex's projection times its visibility — v · conf of eq. 4, the scalar of w_i^pq —
linearly interpolated in time between those frames. :func:`blend_maps` interpolates the
per-vertex weights to the texels (bilinearly between vertices, as §7.3) and blends the
scans' maps.

Departure (measured): the correspondence strength alone does not say *which* scan a frame
looks like. The flow warps every scan onto every frame (the scans share the skin's
texture), so the NCC confidence is about equally high for all scans: at frame 0, which *is*
the neutral, the neutral got 0.39 of the weight (0.2 among the vertices any scan matched:
uniform over 6 scans is 0.17), and 24 % of the face vertices matched no scan (view 0 only)
and took the neutral's map. The blended albedo was then no better than the neutral's map
alone (40 frames, 256², 3 views; mean |error| family a 0.0030 vs 0.0030, b 0.0042 vs
0.0037). The weights are therefore multiplied by a local *shape* similarity between the
tracked frame and each registered scan — the "surface stress" by which Digital Ira blends
the scans' maps per vertex at run time (this course, "Real-Time Rendering": "uses surface
stress values to blend diffuse texture, specular, normal, and displacement maps from the
different high-resolution expression scans per-vertex"). :func:`strain_similarity`: per
edge the log strain against the artist mesh, ε = log(ℓ / ℓ_artist); per vertex the mean of
(ε_frame − ε_scan)² over its edges, averaged ``strain_smooth`` times over the one-ring;
kernel exp(−d / 2σ²) with σ = ``strain_sigma``, normalized over the scans. Vertices no scan
matches by flow take the shape kernel alone.

Measured (neutral + 5 scans, 256², 3 views, full graph; mean |albedo error| over the face
texels at the performance's map frames; family a chose σ and the passes at 40 frames —
σ 0.02 / 0.03 / 0.05 at 20 passes: 0.00191 / 0.00194 / 0.00227; σ 0.01 / 0.02 / 0.03 at 5
passes: 0.00192 / 0.00196 / 0.00199 — and b confirms; load 4-8 on 2 cores):

=============================  ========  ========  =========  =========
maps                           a 40 fr   b 40 fr   a 120 fr   b 120 fr
=============================  ========  ========  =========  =========
confidence × strain (this)     0.00191   0.00338   0.00239    0.00378
confidence alone (before)      0.00304   0.00416   0.00317    0.00487
the neutral's map              0.00298   0.00372   0.00333    0.00431
best scan per frame (oracle)   0.00275   0.00295   0.00317    0.00391
best scan per texel (oracle)   0.00140   0.00216   0.00177    0.00264
=============================  ========  ========  =========  =========

The kernel on the ground-truth meshes instead of the tracked ones (40 frames): a 0.00173,
b 0.00270 — on b most of what is left is the tracking's error (tracked frames with true
scans 0.00336, true frames with registered scans 0.00295); b's frame 35 is not spanned by
the scans at all (0.0078 with true geometry, the neutral's map 0.0088).
"""

from __future__ import annotations

import numpy as np

from service.geometry import optical_flow as of
from service.geometry.uv_raster import interpolation_matrix, rasterize_uv
from service.methods.tracking.graph import flow_with_confidence, resize
from service.methods.tracking.params import TrackingParams
from service.methods.tracking.solve import TrackingMesh, visibility


#: σ of the shape kernel, in log edge strain (0.02: a 2 % strain difference); chosen on family a
STRAIN_SIGMA = 0.02
#: one-ring averaging passes of the per-vertex strain difference; chosen on family a
STRAIN_SMOOTH = 20


def strain_similarity(mesh: TrackingMesh, frames: np.ndarray, scans: np.ndarray,
                      sigma: float = STRAIN_SIGMA, smooth: int = STRAIN_SMOOTH) -> np.ndarray:
    """Per-vertex local shape similarity of each frame to each scan (T,n,S) float32, rows sum to 1.

    Digital Ira's "surface stress" blending (this course, "Real-Time Rendering"): a vertex
    takes the maps of the scans whose skin is stretched or compressed there as in the frame.
    Per edge the log strain against the artist mesh, ε = log(ℓ / ℓ_artist) (rotation and
    translation invariant: no head alignment needed); per vertex d = the mean of
    (ε_frame − ε_scan)² over its edges, averaged ``smooth`` times over the one-ring
    (``mesh.smooth``); weight exp(−d / 2σ²), normalized over the scans.

    Parameters
    ----------
    mesh : the artist mesh (:class:`~service.methods.tracking.solve.TrackingMesh`)
    frames : (T,n,3) float   the tracked frames (any rigid pose each, actor's unit)
    scans : (S,n,3) float    the scans registered to the artist topology; NaN rows (a scan
                             not registered) get weight 0
    sigma : kernel width in log strain;  smooth : one-ring averaging passes
    """
    E = mesh.E
    rest = np.linalg.norm(mesh.artist[E[:, 1]] - mesh.artist[E[:, 0]], axis=1)

    def strain(V):
        return np.log(np.maximum(np.linalg.norm(V[:, E[:, 1]] - V[:, E[:, 0]], axis=-1), 1e-12) / rest)

    frames = np.asarray(frames, np.float64)
    scans = np.asarray(scans, np.float64)
    incidence = abs(mesh.D).T.tocsr()                                    # (n,e)
    degree = np.maximum(np.asarray(incidence.sum(axis=1)).ravel(), 1.0)
    et = strain(frames)                                                  # (T,e)
    T, n, S = len(frames), mesh.n, len(scans)
    d = np.full((T, n, S), np.inf)
    for s in range(S):
        if not np.isfinite(scans[s]).all():
            continue
        ds = np.asarray(incidence @ ((et - strain(scans[s][None])[0]) ** 2).T) / degree[:, None]
        for _ in range(smooth):
            ds = mesh.smooth @ ds
        d[:, :, s] = ds.T
    d -= d.min(axis=2, keepdims=True)                                    # stable soft-min
    k = np.exp(-d / (2.0 * sigma ** 2))
    return (k / k.sum(axis=2, keepdims=True)).astype(np.float32)


def scan_weights(inp, result, params: TrackingParams | None = None,
                 stride: int | None = None, strain_sigma: float | None = STRAIN_SIGMA,
                 strain_smooth: int = STRAIN_SMOOTH) -> np.ndarray:
    """Per-frame per-vertex weights over the static scans (T,n,S) float32, rows summing to 1.

    The correspondence strength v · conf (§5.3, §7.3) times :func:`strain_similarity`
    (the module's departure); where no scan matches by flow, the shape kernel alone.

    Parameters
    ----------
    inp : :class:`~service.methods.tracking.track.TrackingInput`
    result : :class:`~service.methods.tracking.track.TrackingResult` (its tracked vertices and
             registered scans; scans it did not register get weight 0)
    stride : frames between computed correspondence strengths (default ``params.candidate_stride``)
    strain_sigma, strain_smooth : the shape kernel (None: the correspondence strength alone,
             the paper's §7.3, where a vertex no scan matches takes the neutral's maps)
    """
    params = params or TrackingParams()
    stride = stride or params.candidate_stride
    mesh = TrackingMesh.build(inp.artist_vertices, inp.faces)
    T, n, S = inp.frames, mesh.n, len(inp.scan_images)
    used = [s for s in range(S) if np.isfinite(result.scan_vertices[s]).all()]
    scale = params.graph_scale
    cam = inp.cameras[0].scaled(scale)
    scans = {s: resize(inp.scan_images[s, 0], scale) for s in used}
    sampled = sorted(set(range(0, T, stride)) | {T - 1})
    W = np.zeros((len(sampled), n, S))
    for k, t in enumerate(sampled):
        frame = resize(inp.frame_images[t, 0], scale)
        world = result.vertices[t].astype(np.float64)
        vis = visibility(mesh, cam, world, params.visibility_tolerance_mm, params.visibility_size)
        xy = cam.project(world)[:, :2] - 0.5
        for s in used:
            vf = flow_with_confidence(frame, scans[s], params)
            W[k, :, s] = vis * of.sample(vf.confidence, xy, border=0.0)
    shape = None
    if strain_sigma is not None:
        shape = strain_similarity(mesh, result.vertices, result.scan_vertices,
                                  strain_sigma, strain_smooth)
    out = np.empty((T, n, S), np.float32)
    for t in range(T):
        j = min(np.searchsorted(sampled, t, side="right") - 1, len(sampled) - 1)
        j1 = min(j + 1, len(sampled) - 1)
        a = 0.0 if j1 == j else (t - sampled[j]) / (sampled[j1] - sampled[j])
        w = (1 - a) * W[j] + a * W[j1]
        none = w.sum(axis=1) <= 1e-6                   # no scan matched by flow
        if shape is not None:
            w = w * shape[t]
            none |= w.sum(axis=1) <= 1e-12             # matched only scans of another shape
        total = w.sum(axis=1, keepdims=True)
        w = np.where(none[:, None], 0.0, w / np.maximum(total, 1e-30))
        if shape is None:
            w[none, 0] = 1.0
        else:
            w[none] = shape[t][none]
        out[t] = w
    return out


def blend_maps(weights: np.ndarray, faces: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray,
               maps: np.ndarray) -> np.ndarray:
    """Per-frame maps blended from the scans' maps by the per-vertex weights (§7.3).

    Parameters
    ----------
    weights : (T,n,S) float   from :func:`scan_weights`
    faces : (m,3) int; uv : (u,2); uv_faces : (m,3)   the artist mesh and its UV layout
    maps : (S,h,w) or (S,h,w,C) float   one map per scan in the artist mesh's UV space

    Returns
    -------
    blended : (T,h,w) or (T,h,w,C) float32 (0 outside the UV charts)
    """
    maps = np.asarray(maps, np.float32)
    S, h, w = maps.shape[:3]
    flat = maps.reshape(S, h * w, -1)
    raster = rasterize_uv(uv, uv_faces, h, w)
    M = interpolation_matrix(raster, faces, weights.shape[1])
    covered = np.flatnonzero(raster.mask.ravel())
    Mc = M[covered]
    out = np.zeros((len(weights), h * w, flat.shape[2]), np.float32)
    for t, wt in enumerate(weights):
        Wt = np.asarray(Mc @ wt.astype(np.float64))                      # (k,S)
        Wt /= np.maximum(Wt.sum(axis=1, keepdims=True), 1e-12)
        out[t, covered] = np.einsum("ks,skc->kc", Wt, flat[:, covered])
    return out.reshape((len(weights), h, w) + maps.shape[3:])
