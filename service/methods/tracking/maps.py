"""Per-frame scan weights and blended maps (fyffe, digital_ira_course2014, §5.3 and §7.3).

"The weights w_i^pq additionally enable trivial synthesis of high-resolution reflectance
maps for each dynamic frame of the performance by blending the static pose data" (§5.3);
"We also compute values for w_i^pq for any dynamic-to-static edge pq that was not present
in the performance flow graph, to produce weights for every frame" (§7.3).

:func:`correspondence_strength` computes, for every scan the tracking registered and every
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
0.0037). The weights are therefore multiplied by the similarity of the tracked frame's
local *surface stress* to each registered scan's — the measure by which Digital Ira blends
the scans' maps per vertex at run time (this course, "Real-Time Rendering": "uses surface
stress values to blend diffuse texture, specular, normal, and displacement maps from the
different high-resolution expression scans per-vertex"), computed by the same functions as
the game-engine blend (:mod:`service.methods.stress_blend`: the per-vertex Green strain
against the artist mesh, Shepard weights over the scans; :func:`stress_similarity`).
Vertices no scan matches by flow take the stress kernel alone (:func:`combine_weights`).

One surface-stress measure (session 14). Until then this module had its own, per-edge log
strain ε = log(ℓ / ℓ_artist), one-ring averaged 20 times, kernel exp(−d / 2σ²) with
σ = 0.02. Replaced by the stress_blend measure; its kernel's three parameters
(:data:`STRESS_SMOOTHING`, :data:`STRESS_POWER`, :data:`STRESS_GLOBAL_WEIGHT`) chosen on
family a at 40 frames — smoothing / p / β: 4 / 2 / 0.5 (stress_blend's defaults) 0.00191;
20 / 2 / 0.5 0.00190; 4 / 4 / 0.5 0.00175; 4 / 8 / 0.5 0.00183; 20 / 4 / 0.5 0.00170;
4 / 2 / 0.25 0.00178; 2 / 2 / 0 0.00168; 4 / 2 / 0 0.00166; 10 / 2 / 0 0.00164;
4 / 4 / 0 0.00162; **4 / 3 / 0 0.00158** — and confirmed on b (4 / 2 / 0.5 0.00325,
4 / 2 / 0 0.00309, 4 / 4 / 0 0.00302, 4 / 3 / 0 0.00304). β = 0 (purely local) suits the
tracking better than the game blend's 0.5, presumably because a tracked frame is never
exactly a scan and the whole-frame distance pulls skin the expression does not move toward
the globally nearest scan (not measured further).

Measured (neutral + 5 scans, 256², 3 views, full graph; mean |albedo error| over the face
texels at the performance's map frames; load 2.5–8 on 2 cores, one tracking per family and
length for every row; the metric of ``benchmarks/tracking_report.py``):

=================================================  ========  ========  =========  =========
maps                                               a 40 fr   b 40 fr   a 120 fr   b 120 fr
=================================================  ========  ========  =========  =========
confidence × stress, 4 / 3 / 0 (this)              0.00158   0.00304   0.00218    0.00367
confidence × stress, stress_blend's 4 / 2 / 0.5    0.00191   0.00325   0.00233    0.00387
confidence × log edge strain (before)              0.00191   0.00338   0.00239    0.00378
confidence alone (§7.3)                            0.00304   0.00416   0.00317    0.00487
the neutral's map                                  0.00298   0.00372   0.00333    0.00431
=================================================  ========  ========  =========  =========

With stress_blend's own parameters the measure is as good as the log strain on a and
worse on b at 120 frames (0.00387 against 0.00378); with the tracking's parameters it is
better on all four (−3 % on b at 120 frames to −17 % on a at 40).

(The stress kernel alone, without the correspondence strength: a 0.00164, b 0.00300 at
40 frames, a 0.00220, b 0.00372 at 120.)
Earlier measurements of the log-strain kernel, for the record: on the ground-truth meshes
instead of the tracked ones (40 frames) a 0.00173, b 0.00270; b's frame 35 is not spanned
by the scans at all (0.0078 with true geometry, the neutral's map 0.0088).
"""

from __future__ import annotations

import numpy as np

from service.geometry import optical_flow as of
from service.geometry.uv_raster import interpolation_matrix, rasterize_uv
from service.geometry.surface_strain import StressField
from service.methods.stress_blend.weights import shepard_weights
from service.methods.tracking.graph import flow_with_confidence, resize
from service.methods.tracking.params import TrackingParams
from service.methods.tracking.solve import TrackingMesh, visibility


#: Laplacian smoothing steps of the per-vertex stress (stress_blend's default); chosen on family a
STRESS_SMOOTHING = 4
#: exponent p of the Shepard weights over the scans; chosen on family a
STRESS_POWER = 3.0
#: β, the whole frame's share in the stress distance (0: purely local); chosen on family a
STRESS_GLOBAL_WEIGHT = 0.0


def stress_similarity(artist: np.ndarray, faces: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray,
                      frames: np.ndarray, scans: np.ndarray, smoothing: int = STRESS_SMOOTHING,
                      power: float = STRESS_POWER, global_weight: float = STRESS_GLOBAL_WEIGHT
                      ) -> np.ndarray:
    """Per-vertex surface-stress similarity of each frame to each scan (T,n,S) float32.

    Digital Ira's stress blend, as the real-time renderer computes it
    (:mod:`service.methods.stress_blend`): the local Green strain of every frame and scan
    against the artist mesh (:class:`~service.geometry.surface_strain.StressField`,
    ``smoothing`` Laplacian steps) and Shepard weights over the registered scans
    (:func:`~service.methods.stress_blend.weights.shepard_weights`, exponent ``power``,
    whole-frame share ``global_weight``). Rows sum to 1; NaN rows of ``scans`` (a scan
    the tracking did not register) get weight 0.

    Parameters
    ----------
    artist : (n,3) float; faces : (m,3) int; uv : (u,2); uv_faces : (m,3)   the artist mesh
    frames : (T,n,3) float   the tracked frames (any rigid pose each; Green strain is
                             rotation and translation invariant)
    scans : (S,n,3) float    the scans registered to the artist topology
    """
    scans = np.asarray(scans, np.float64)
    used = [s for s in range(len(scans)) if np.isfinite(scans[s]).all()]
    field = StressField.build(artist, faces, uv, uv_faces, smoothing)
    out = np.zeros((len(frames), len(artist), len(scans)), np.float32)
    if used:
        out[:, :, used] = shepard_weights(field.stress(np.asarray(frames, np.float64)),
                                          field.stress(scans[used]), power, global_weight)
    return out


def correspondence_strength(inp, result, params: TrackingParams | None = None,
                            stride: int | None = None) -> np.ndarray:
    """The correspondence strength v · conf of every frame's vertices for every registered
    scan (T,n,S) float64 (§5.3's scalar of w_i^pq, §7.3 for edges not in the graph).

    Every ``stride``-th frame (default ``params.candidate_stride``) and the last: the flow
    frame → scan in view 0 at the graph's reduced resolution, its NCC confidence at the
    tracked vertex's projection times the vertex's visibility; linearly interpolated in
    time in between. Scans the tracking did not register get 0.
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
    out = np.empty((T, n, S))
    for t in range(T):
        j = min(np.searchsorted(sampled, t, side="right") - 1, len(sampled) - 1)
        j1 = min(j + 1, len(sampled) - 1)
        a = 0.0 if j1 == j else (t - sampled[j]) / (sampled[j1] - sampled[j])
        out[t] = (1 - a) * W[j] + a * W[j1]
    return out


def combine_weights(strength: np.ndarray, shape: np.ndarray | None) -> np.ndarray:
    """Scan weights (T,n,S) float32, rows summing to 1, from the correspondence strength
    (T,n,S) times the shape kernel (T,n,S) (None: the strength alone, §7.3, where a vertex
    no scan matches takes the neutral's maps). Where no scan matches by flow, or only
    scans of another shape, the shape kernel alone."""
    out = np.empty(strength.shape, np.float32)
    for t in range(len(strength)):
        w = strength[t]
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


def scan_weights(inp, result, uv: np.ndarray, uv_faces: np.ndarray,
                 params: TrackingParams | None = None, stride: int | None = None,
                 stress: bool = True) -> np.ndarray:
    """Per-frame per-vertex weights over the static scans (T,n,S) float32, rows summing to 1.

    The correspondence strength v · conf (§5.3, §7.3; :func:`correspondence_strength`)
    times :func:`stress_similarity` (the module's departure); where no scan matches by
    flow, the stress kernel alone.

    Parameters
    ----------
    inp : :class:`~service.methods.tracking.track.TrackingInput`
    result : :class:`~service.methods.tracking.track.TrackingResult` (its tracked vertices and
             registered scans; scans it did not register get weight 0)
    uv : (u,2), uv_faces : (m,3)   the artist mesh's UV layout (the stress's tangent frames)
    stride : frames between computed correspondence strengths (default ``params.candidate_stride``)
    stress : False: the correspondence strength alone, the paper's §7.3, where a vertex no
             scan matches takes the neutral's maps
    """
    strength = correspondence_strength(inp, result, params, stride)
    shape = None
    if stress:
        shape = stress_similarity(inp.artist_vertices, inp.faces, uv, uv_faces, result.vertices,
                                  result.scan_vertices)
    return combine_weights(strength, shape)


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
