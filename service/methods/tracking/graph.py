"""The performance flow graph (fyffe, digital_ira_course2014, §4–4.1, Fig. 3–5).

Nodes are the static poses (scans) and the dynamic poses (frames). Edges: every pair of
temporally neighbouring frames, plus a sparse set of static-to-dynamic edges selected by
:func:`vote` from candidate flows at reduced resolution in one view (:func:`candidate_table`:
each scan to every n-th frame, every frame for the ``dense_scans``), their NCC confidence
averaged over facial regions (:mod:`.regions`). The retained edges then get full-resolution
flows in every view, both directions (:func:`edge_flows`). Flows are OpenCV DIS
(:mod:`service.geometry.optical_flow`; the paper's is FlowLib's GPU flow).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from service.geometry import optical_flow as of
from service.methods.tracking.params import TrackingParams
from service.methods.tracking.regions import carry_regions, region_means


@dataclass
class ViewFlow:
    """One direction of an edge in one view: the backward flow on the source image's grid
    (``target(x + flow(x)) ≈ source(x)``: source pixel x is found at x + flow(x) in the
    target) and its smoothed NCC confidence (H,W) in [0, 1]."""

    flow: np.ndarray
    confidence: np.ndarray


@dataclass
class EdgeFlows:
    """Flows of one graph edge in every view: ``forward[c]`` source → target, ``backward[c]``
    target → source. Pose keys are ``("scan", s)`` or ``("frame", t)``."""

    source: tuple
    target: tuple
    forward: list
    backward: list


@dataclass
class FlowGraph:
    """The selected graph: static-to-dynamic edges ``(scan, frame)`` plus (implicitly) all
    temporal edges ``(t, t+1)``; ``table`` (S,R,T) the candidates' region confidences (NaN
    where no candidate flow was computed); ``initial_max`` its maximum."""

    frames: int
    static_edges: list
    table: np.ndarray
    initial_max: float
    candidates: int
    scan_labels: np.ndarray = field(repr=False)

    def keyframes(self) -> list[int]:
        """Frames with a static edge, plus the first and last frame (§5.7)."""
        return sorted({t for _, t in self.static_edges} | {0, self.frames - 1})

    def edges_per_scan(self) -> dict[int, list[int]]:
        out: dict[int, list[int]] = {}
        for s, t in self.static_edges:
            out.setdefault(s, []).append(t)
        return out


def flow_with_confidence(reference: np.ndarray, moving: np.ndarray, params: TrackingParams
                         ) -> ViewFlow:
    """DIS flow reference → moving (uint8 (H,W) images) and its NCC confidence (§4.1, Fig. 4).

    The confidence is the smoothed NCC between the reference and the moving image warped by
    the flow, over the reference's foreground (non-zero pixels).
    """
    flow = of.refined_flow(reference, moving, passes=params.dis_passes, preset=params.dis_preset,
                           patch_stride=params.dis_patch_stride)
    warped = of.warp(moving.astype(np.float32), flow)
    mask = reference > 0
    conf = of.ncc_confidence(reference.astype(np.float32), warped, params.ncc_window,
                             params.ncc_smooth, mask=mask, eps=1.0)
    return ViewFlow(flow, stretch(conf, params.confidence_floor))


def consistency(flow: np.ndarray, back: np.ndarray, sigma: float, smooth: float) -> np.ndarray:
    """Forward-backward consistency weight (H,W) float32 in [0, 1] of a flow on its source grid.

    A source pixel x goes to x + f(x) in the target and back by the reverse flow b; the
    round trip's miss ``r(x) = ‖f(x) + b(x + f(x))‖`` (:func:`~service.geometry.optical_flow.
    compose_flows` (b, f)) is ~0 where both flows found the same match and large where one
    of them failed (occlusion, a mismatched expression's mouth or eyelids). Weight
    ``exp(−(r/σ)²)``, smoothed by ``smooth`` pixels like the NCC (§4.1's "smoothed,
    per-pixel confidence"). Departure: the paper's confidence is the NCC alone; on the
    rendered performances the static-to-dynamic flows between unlike expressions miss by
    2–9 px on 15–30 % of the face with an NCC confidence of 0.05–0.2, which the quadratic
    correspondence term (eq. 2) cannot ignore. ``sigma`` 0 returns ones.

    Parameters
    ----------
    flow : (H,W,2) backward flow source → target;  back : (H,W,2) target → source
    sigma : σ of the weight, pixels;  smooth : σ of the Gaussian smoothing, pixels
    """
    if sigma <= 0:
        return np.ones(flow.shape[:2], np.float32)
    miss = np.linalg.norm(of.compose_flows(back, flow), axis=2)
    w = np.exp(-(miss / sigma) ** 2).astype(np.float32)
    return (of.gaussian_blur(w, smooth) if smooth > 0 else w).astype(np.float32)


def stretch(ncc: np.ndarray, floor: float) -> np.ndarray:
    """Confidence from NCC: ``clip((ncc − floor) / (1 − floor), 0, 1)`` float32."""
    return np.clip((ncc - floor) / (1.0 - floor), 0.0, 1.0).astype(np.float32)


def resize(image: np.ndarray, scale: float) -> np.ndarray:
    """An 8-bit image resized by ``scale`` (area filter when shrinking)."""
    if scale == 1.0:
        return image
    H, W = image.shape[:2]
    return cv2.resize(image, (max(8, round(W * scale)), max(8, round(H * scale))),
                      interpolation=cv2.INTER_AREA)


def candidate_table(scan_images: np.ndarray, frame_images: np.ndarray, neutral_labels: np.ndarray,
                    n_regions: int, params: TrackingParams, dense: np.ndarray | None = None,
                    progress=None) -> tuple[np.ndarray, np.ndarray, int]:
    """Per-region confidences of the candidate static-to-dynamic flows (§4.1, Fig. 4–5).

    Parameters
    ----------
    scan_images : (S,H,W) uint8   one view of every static scan, scan 0 the neutral
    frame_images : (T,H,W) uint8  the same view of every frame
    neutral_labels : (h,w) int    region labels on the neutral image at the graph scale
                                  (:func:`~.regions.face_regions` with ``scale``)
    n_regions : R;  dense : (S,) bool   scans flowed to every frame
    progress : callable(fraction) or None

    Returns
    -------
    table : (S,R,T) float   mean NCC confidence per region (NaN: no candidate flow)
    scan_labels : (S,h,w) int   the regions carried to each scan by static-to-static flow
    candidates : int        number of candidate flows computed
    """
    S, T = len(scan_images), len(frame_images)
    scale = params.graph_scale
    scans = [resize(im, scale) for im in scan_images]
    frames = [resize(im, scale) for im in frame_images]
    labels = np.empty((S,) + neutral_labels.shape, np.int64)
    labels[0] = neutral_labels
    for s in range(1, S):       # "warped to all other static poses using rough static-to-static flow"
        labels[s] = carry_regions(neutral_labels, of.dis_flow(scans[s], scans[0], params.dis_preset),
                                  scans[s] > 0)
    dense = np.zeros(S, bool) if dense is None else np.asarray(dense, bool)
    table = np.full((S, n_regions, T), np.nan)
    todo = [(s, t) for s in range(S) for t in range(T)
            if dense[s] or t % params.candidate_stride == 0 or t == T - 1]
    for k, (s, t) in enumerate(todo):
        # "normalized cross correlation fields between the warped dynamic frames and each
        # original static scan": reference = the scan, moving = the frame
        vf = flow_with_confidence(scans[s], frames[t], params)
        table[s, :, t] = region_means(vf.confidence, labels[s], n_regions)
        if progress is not None:
            progress((k + 1) / len(todo))
    return table, labels, len(todo)


def vote(table: np.ndarray, hat_slope: float = 0.04, stop_fraction: float = 0.2,
         ground: int | None = None, suppression: str = "all") -> list[tuple[int, int]]:
    """Iterative greedy voting with hat-function suppression (§4.1, Fig. 5).

    Each iteration takes the maximum confidence over all scans s, regions r and frames t,
    adds the edge (s, t), and subtracts from every scan's curve of every region r′ a hat
    centred on t, ``c[s, r′, t] · max(0, 1 − hat_slope · |t′ − t|)`` — the chosen flow's own
    confidence in that region, fading by ``hat_slope`` per temporal flow it would be
    concatenated with: the regions the flow satisfies are accounted for, near t and
    partly farther away. It stops when every value is below ``stop_fraction`` of the
    initial maximum.

    Parameters
    ----------
    table : (S,R,T) float   region confidences (NaN: no candidate)
    suppression : whose curves the hat is subtracted from. ``"all"``: every scan's (a region
        satisfied at t by one scan needs no other scan's edge near t); ``"scan"``: only the
        chosen scan's (the paper's "the recorded confidence of the identified region" read
        as that scan's curve, Fig. 5: an edge to one scan does not satisfy another scan's
        regions, so every scan keeps edges wherever it matches well and the graph has loops
        through several scans).

    ground : if given, the scan that must have an edge: when the voting chose none for it,
        its best candidate (highest mean over regions) is added last. Departure: the
        tracking propagates from the ground (the neutral, eq. 12), and a graph without a
        path to it leaves every pose undetermined; the paper's graphs always had one.

    Returns
    -------
    edges : list of (scan, frame), in the order chosen
    """
    if suppression not in ("all", "scan"):
        raise ValueError(f"suppression must be 'all' or 'scan', got {suppression!r}")
    C = np.where(np.isfinite(table), table, -np.inf).astype(np.float64)
    S, R, T = C.shape
    if not np.isfinite(C).any():
        return []
    initial = float(C.max())
    stop = stop_fraction * initial
    tt = np.arange(T)
    chosen: list[tuple[int, int]] = []
    while True:
        s, r, t = np.unravel_index(int(np.argmax(C)), C.shape)
        if not C[s, r, t] >= stop or C[s, r, t] <= 0:
            break
        chosen.append((int(s), int(t)))
        height = np.where(np.isfinite(table[s, :, t]), table[s, :, t], 0.0)     # (R,)
        hat = np.maximum(0.0, 1.0 - hat_slope * np.abs(tt - t))               # (T,)
        if suppression == "scan":
            C[s] -= height[:, None] * hat[None, :]
        else:
            C -= height[None, :, None] * hat[None, None, :]
        C[s, :, t] = -np.inf                        # an edge is added once
    if ground is not None and all(s != ground for s, _ in chosen):
        g = np.where(np.isfinite(table[ground]), table[ground], 0.0)
        count = np.isfinite(table[ground]).sum(axis=0)
        mean = np.where(count > 0, g.sum(axis=0) / np.maximum(count, 1), np.nan)
        if np.isfinite(mean).any():
            chosen.append((int(ground), int(np.nanargmax(mean))))
    return chosen


def edge_flows(source_images: np.ndarray, target_images: np.ndarray, source: tuple,
               target: tuple, params: TrackingParams) -> EdgeFlows:
    """Full-resolution flows of one edge in every view, both directions (§4.1, last step).

    Parameters
    ----------
    source_images, target_images : (C,H,W) uint8   the two poses' images per view
    """
    fwd = [flow_with_confidence(a, b, params) for a, b in zip(source_images, target_images)]
    bwd = [flow_with_confidence(b, a, params) for a, b in zip(source_images, target_images)]
    return EdgeFlows(source, target, *_consistent(fwd, bwd, params))


def _consistent(fwd: list, bwd: list, params: TrackingParams) -> tuple[list, list]:
    """Both directions' confidences times their :func:`consistency` weight."""
    out_f = [ViewFlow(f.flow, f.confidence * consistency(f.flow, b.flow, params.consistency_sigma,
                                                          params.ncc_smooth)) for f, b in zip(fwd, bwd)]
    out_b = [ViewFlow(b.flow, b.confidence * consistency(b.flow, f.flow, params.consistency_sigma,
                                                          params.ncc_smooth)) for f, b in zip(fwd, bwd)]
    return out_f, out_b


def concatenate(chain: list[EdgeFlows], source_images: np.ndarray, target_images: np.ndarray,
                params: TrackingParams) -> EdgeFlows:
    """Temporal flows concatenated along a chain of edges (§5.7's keyframe-to-keyframe edges).

    ``chain[k]`` goes from pose k to pose k+1 (forward) and back; the composed forward flow
    maps a point x of the first pose through every link: ``x ↦ x + f₀(x) ↦ … ``
    (:func:`~service.geometry.optical_flow.compose_flows`), and its confidence is the NCC of
    the first image against the last warped by the composed flow.
    """
    views = len(chain[0].forward)
    fwd, bwd = [], []
    for c in range(views):
        f = chain[0].forward[c].flow
        for e in chain[1:]:
            f = of.compose_flows(e.forward[c].flow, f)
        b = chain[-1].backward[c].flow
        for e in reversed(chain[:-1]):
            b = of.compose_flows(e.backward[c].flow, b)
        for flow, ref, mov, out in ((f, source_images[c], target_images[c], fwd),
                                    (b, target_images[c], source_images[c], bwd)):
            warped = of.warp(mov.astype(np.float32), flow)
            conf = of.ncc_confidence(ref.astype(np.float32), warped, params.ncc_window,
                                     params.ncc_smooth, mask=ref > 0, eps=1.0)
            out.append(ViewFlow(flow, stretch(conf, params.confidence_floor)))
    return EdgeFlows(chain[0].source, chain[-1].target, *_consistent(fwd, bwd, params))
