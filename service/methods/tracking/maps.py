"""Per-frame scan weights and blended maps (fyffe, digital_ira_course2014, §5.3 and §7.3).

"The weights w_i^pq additionally enable trivial synthesis of high-resolution reflectance
maps for each dynamic frame of the performance by blending the static pose data" (§5.3);
"We also compute values for w_i^pq for any dynamic-to-static edge pq that was not present
in the performance flow graph, to produce weights for every frame" (§7.3).

:func:`scan_weights` computes, for every scan the tracking registered and every
``stride``-th frame, the flow frame → scan in view 0 at the graph's reduced resolution; a
vertex's weight for that scan is the flow's confidence at the tracked vertex's projection
times its visibility — the correspondence strength v · conf of eq. 4, the scalar of w_i^pq
— linearly interpolated in time between those frames and normalized over the scans (a
vertex no scan matches takes the neutral's maps). :func:`blend_maps` interpolates the
per-vertex weights to the texels (bilinearly between vertices, as §7.3) and blends the
scans' maps.
"""

from __future__ import annotations

import numpy as np

from service.geometry import optical_flow as of
from service.geometry.uv_raster import interpolation_matrix, rasterize_uv
from service.methods.tracking.graph import flow_with_confidence, resize
from service.methods.tracking.params import TrackingParams
from service.methods.tracking.solve import TrackingMesh, visibility


def scan_weights(inp, result, params: TrackingParams | None = None,
                 stride: int | None = None) -> np.ndarray:
    """Per-frame per-vertex weights over the static scans (T,n,S) float32, rows summing to 1.

    Parameters
    ----------
    inp : :class:`~service.methods.tracking.track.TrackingInput`
    result : :class:`~service.methods.tracking.track.TrackingResult` (its tracked vertices and
             registered scans; scans it did not register get weight 0)
    stride : frames between computed weights (default ``params.candidate_stride``)
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
    out = np.empty((T, n, S), np.float32)
    for t in range(T):
        j = min(np.searchsorted(sampled, t, side="right") - 1, len(sampled) - 1)
        j1 = min(j + 1, len(sampled) - 1)
        a = 0.0 if j1 == j else (t - sampled[j]) / (sampled[j1] - sampled[j])
        w = (1 - a) * W[j] + a * W[j1]
        total = w.sum(axis=1, keepdims=True)
        w = np.where(total > 1e-6, w / np.maximum(total, 1e-12), 0.0)
        w[total[:, 0] <= 1e-6, 0] = 1.0
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
