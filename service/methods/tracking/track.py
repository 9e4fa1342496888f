"""Performance-flow tracking end to end: graph, keyframes, then spans (fyffe, digital_ira_course2014, §4–5.7).

:func:`track` runs the stages in order; each is a plain function so a job can run, resume or
fan them out:

1. :func:`build_graph` — candidate flows at reduced resolution, region confidences, voting
   (§4.1);
2. :func:`solve_keyframes` — the static poses and the keyframes (the frames with a static
   edge, plus the first and last), with concatenated temporal flows between consecutive
   keyframes (§5.7 "we first minimize the energy at only the keyframes and static poses");
3. :func:`solve_span` — one span of in-between frames with its two keyframes and the static
   poses held fixed, without the shrink-wrap and ground terms (§5.7 "each span of in-between
   frames may be solved independently"). A span needs only the images of its frames, the
   cameras, the artist mesh and its two keyframe states: it is one function call, with no
   state shared with any other span, which is what a job queue fans out.

Baselines (same solver, other graphs): ``method="neutral"`` — static candidates from the
neutral scan only (anchor frames); ``method="sequential"`` — frame-to-frame propagation
from the first frame (registered to the neutral by one edge), each frame solved alone
from its predecessor.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from service.errors import InvalidInput
from service.geometry.rigid import rigid_align, stability_weights_from_rms
from service.methods.tracking.graph import (EdgeFlows, FlowGraph, candidate_table, concatenate,
                                            edge_flows, vote)
from service.methods.tracking.params import TrackingParams
from service.methods.tracking.regions import face_regions
from service.methods.tracking.solve import (PoseState, RawScan, TrackingMesh, size_band, size_region,
                                            solve_poses)

METHODS = ("graph", "neutral", "sequential")


@dataclass
class TrackingInput:
    """What tracking needs (world coordinates, mm; the artist mesh in the neutral's pose).

    Attributes
    ----------
    artist_vertices : (n,3) float;  faces : (m,3) int
    cameras : list of C :class:`~service.geometry.camera.Camera`
    scan_images : (S,C,H,W) uint8   scan 0 is the neutral (the artist mesh's scan)
    scan_points : list of (k_s,3) float, scan_faces : list of (l_s,3) int   raw scan geometry
    frame_images : (T,C,H,W) uint8
    scan_names : tuple of S names;  face : (n,) bool   vertices the regions are drawn on
    """

    artist_vertices: np.ndarray
    faces: np.ndarray
    cameras: list
    scan_images: np.ndarray
    scan_points: list
    scan_faces: list
    frame_images: np.ndarray
    scan_names: tuple = ()
    face: np.ndarray | None = None

    def __post_init__(self):
        S, C = self.scan_images.shape[:2]
        if self.scan_images.ndim != 4 or self.frame_images.ndim != 4:
            raise InvalidInput("scan and frame images must be (S,C,H,W) and (T,C,H,W) uint8")
        if self.frame_images.shape[1:] != self.scan_images.shape[1:] or C != len(self.cameras):
            raise InvalidInput(f"images per view must match the {len(self.cameras)} cameras and each "
                               f"other: scans {self.scan_images.shape}, frames {self.frame_images.shape}")
        if len(self.scan_points) != S or len(self.scan_faces) != S:
            raise InvalidInput(f"{S} scans have images but {len(self.scan_points)} have geometry")
        if len(self.frame_images) < 2:
            raise InvalidInput("a performance needs at least 2 frames")

    @classmethod
    def from_sample(cls, sample, views: int | None = None, frames: int | None = None,
                    scans: int | None = None) -> "TrackingInput":
        """From a :class:`service.samples.tracking.TrackingSample` (duck-typed), optionally the
        first ``views`` cameras, ``frames`` frames and ``scans`` scans."""
        C = len(sample.cameras) if views is None else views
        T = len(sample.frame_images) if frames is None else frames
        S = len(sample.scan_images) if scans is None else scans
        return cls(sample.artist_vertices, sample.faces, list(sample.cameras[:C]),
                   sample.scan_images[:S, :C], list(sample.scan_vertices[:S]),
                   list(sample.scan_faces[:S]), sample.frame_images[:T, :C],
                   tuple(str(x) for x in sample.scan_names[:S]), sample.region == 0)

    @property
    def frames(self) -> int:
        return len(self.frame_images)


@dataclass
class TrackingResult:
    """The tracked performance on the artist mesh (world, mm).

    Attributes
    ----------
    vertices : (T,n,3) float32           every frame
    rotations : (T,3,3), translations : (T,3)   head → world per frame
    scan_vertices : (S,n,3) float32      the static scans registered to the artist topology
                                         (NaN rows for scans the graph did not use)
    graph : FlowGraph;  keyframes : list[int];  timings : stage → seconds (wall)
    states : pose key → PoseState (the solver's states, for the maps and re-use)
    cpu_timings : stage → CPU seconds of this process (all its threads)
    """

    vertices: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    scan_vertices: np.ndarray
    graph: FlowGraph | None
    keyframes: list
    timings: dict
    states: dict = field(repr=False, default_factory=dict)
    cpu_timings: dict = field(default_factory=dict)


def ground_state(mesh: TrackingMesh) -> PoseState:
    """The neutral pose: the artist mesh, identity transform, certainty 1 (eq. 12)."""
    return PoseState(mesh.artist.copy(), np.eye(3), np.zeros(3), np.ones(mesh.n))


def unknown_state(mesh: TrackingMesh) -> PoseState:
    """A pose not yet reached: the artist mesh at the neutral's transform, certainty 0 (§5.6)."""
    return PoseState(mesh.artist.copy(), np.eye(3), np.zeros(3), np.zeros(mesh.n))


def build_graph(inp: TrackingInput, params: TrackingParams, scans: list[int] | None = None,
                progress=None) -> FlowGraph:
    """The performance flow graph (§4.1) from view 0 at ``params.graph_scale``.

    ``scans`` restricts the candidates to those scans (``[0]``: neutral anchors only).
    """
    R = params.region_rows * params.region_cols
    labels = face_regions(inp.cameras[0], inp.artist_vertices, inp.faces, inp.face,
                          params.region_rows, params.region_cols, params.graph_scale)
    use = list(range(len(inp.scan_images))) if scans is None else list(scans)
    dense = np.array([inp.scan_names[s] in params.dense_scans if inp.scan_names else False for s in use])
    table, scan_labels, count = candidate_table(inp.scan_images[use, 0], inp.frame_images[:, 0],
                                                labels, R, params, dense, progress)
    full = np.full((len(inp.scan_images),) + table.shape[1:], np.nan)
    full[use] = table
    chosen = vote(full, params.hat_slope, params.stop_fraction, ground=0,
                  suppression=params.vote_suppression)
    finite = full[np.isfinite(full)]
    return FlowGraph(inp.frames, sorted(chosen, key=lambda e: (e[1], e[0])), full,
                     float(finite.max()) if len(finite) else 0.0, count, scan_labels)


class TemporalFlows:
    """The temporal edges' flows (t → t+1, every view), computed once and kept for reuse.

    The keyframe stage flows every temporal edge (to concatenate them between keyframes,
    §5.7) and each span solve needs the same flows again: in one process the second
    computation is a third of all flows (58 of 197 on 30 frames). Edges are kept until
    ``budget_mb`` of arrays is held (a 512² view's edge is 6 MB); beyond that they are
    computed again, as a span job in another process always does.
    """

    def __init__(self, inp: "TrackingInput", params: TrackingParams, budget_mb: float = 1024.0):
        self.inp, self.params, self.budget = inp, params, budget_mb * 2 ** 20
        self.kept: dict[int, EdgeFlows] = {}
        self.bytes = 0
        self.computed = 0

    def __call__(self, t: int) -> EdgeFlows:
        if t in self.kept:
            return self.kept[t]
        inp = self.inp
        e = edge_flows(inp.frame_images[t], inp.frame_images[t + 1], ("frame", t), ("frame", t + 1),
                       self.params)
        self.computed += 1
        size = _edge_bytes(e)
        if self.bytes + size <= self.budget:
            self.kept[t] = e
            self.bytes += size
        return e

    def release(self, frames) -> None:
        """Drop the kept flows of the edges t → t+1 for t in ``frames``."""
        for t in frames:
            e = self.kept.pop(t, None)
            if e is not None:
                self.bytes -= _edge_bytes(e)


def _edge_bytes(e: EdgeFlows) -> int:
    """Bytes of an edge's flows and confidences, both directions, every view."""
    return sum(v.flow.nbytes + v.confidence.nbytes for v in e.forward + e.backward)


def _temporal(inp: TrackingInput, t: int, params: TrackingParams) -> EdgeFlows:
    return edge_flows(inp.frame_images[t], inp.frame_images[t + 1], ("frame", t), ("frame", t + 1), params)


def rigidity_weights(mesh: TrackingMesh, poses: list[np.ndarray], face: np.ndarray | None) -> np.ndarray:
    """§5.6 rigidity weights (n,): high where the static poses barely deform.

    Each pose's head-frame positions are rigidly aligned to the artist mesh; the RMS residual
    over the poses gives :func:`~service.geometry.rigid.stability_weights_from_rms` (eye
    sockets, temples and the nose bridge come out stiff, the jaw and lips soft). Restricted
    to the face vertices when given.
    """
    if not poses:
        return mesh.rigidity
    res = []
    for X in poses:
        T = rigid_align(X, mesh.artist)
        res.append(np.sum((T.apply(X) - mesh.artist) ** 2, axis=1))
    w = stability_weights_from_rms(np.sqrt(np.mean(res, axis=0)))
    return w * (1.0 if face is None else np.asarray(face, float))


@dataclass
class KeyframeSolution:
    """States of the static poses and keyframes after §5.7's first stage."""

    states: dict
    keyframes: list
    rigidity: np.ndarray
    timings: dict
    cpu_timings: dict = field(default_factory=dict)
    size_weights: np.ndarray | None = None
    size_band: float = 0.0


def solve_keyframes(inp: TrackingInput, graph: FlowGraph, params: TrackingParams,
                    mesh: TrackingMesh | None = None, progress=None,
                    temporal: TemporalFlows | None = None) -> KeyframeSolution:
    """Stage 2 of §5.7: the static poses and keyframes, coupled (eq. 1 over those poses).

    Edges: the graph's static-to-dynamic edges (full-resolution flows in every view, both
    directions) and concatenated temporal flows between consecutive keyframes. The neutral
    is held at the artist mesh (ground); shrink-wrap on the other static poses.
    ``temporal``: where the temporal flows come from (and are kept for the spans).
    """
    mesh = mesh or TrackingMesh.build(inp.artist_vertices, inp.faces)
    temporal = temporal or TemporalFlows(inp, params, 0.0)
    timings, cpu = {}, {}
    t0, c0 = time.perf_counter(), time.process_time()
    keyframes = graph.keyframes()
    used = sorted({0} | {s for s, _ in graph.static_edges})
    edges = [edge_flows(inp.scan_images[s], inp.frame_images[t], ("scan", s), ("frame", t), params)
             for s, t in graph.static_edges]
    for a, b in zip(keyframes[:-1], keyframes[1:]):
        chain = [temporal(t) for t in range(a, b)]
        edges.append(chain[0] if len(chain) == 1 else
                     concatenate(chain, inp.frame_images[a], inp.frame_images[b], params))
        if progress is not None:
            progress(0.5 * b / max(inp.frames - 1, 1), "full flows")
    timings["full_flows"], cpu["full_flows"] = time.perf_counter() - t0, time.process_time() - c0
    t0, c0 = time.perf_counter(), time.process_time()
    states = {("scan", 0): ground_state(mesh)}
    states.update({("scan", s): unknown_state(mesh) for s in used if s != 0})
    states.update({("frame", t): unknown_state(mesh) for t in keyframes})
    free = [("scan", s) for s in used if s != 0] + [("frame", t) for t in keyframes]
    raw = {("scan", s): RawScan.build(inp.scan_points[s], inp.scan_faces[s]) for s in used if s != 0}
    first = max(1, params.keyframe_iterations // 2)
    states = solve_poses(mesh, inp.cameras, states, free, edges, raw, params, first)
    # rigidity from the static poses as far as they are known, then the remaining iterations
    known = [states[("scan", s)].X for s in used if s != 0
             and np.mean(states[("scan", s)].certainty) > 0.2]
    mesh.rigidity = rigidity_weights(mesh, known, inp.face)
    mesh.size_weights = size_region(mesh, known, params.monocular_size_fraction, inp.face)
    mesh.size_band = size_band(mesh, known, mesh.size_weights)
    if params.keyframe_iterations > first:
        states = solve_poses(mesh, inp.cameras, states, free, edges, raw, params,
                             params.keyframe_iterations - first)
    timings["keyframe_solve"], cpu["keyframe_solve"] = time.perf_counter() - t0, time.process_time() - c0
    return KeyframeSolution(states, keyframes, mesh.rigidity, timings, cpu, mesh.size_weights,
                            mesh.size_band)


def spans(keyframes: list[int]) -> list[tuple[int, int]]:
    """The in-between spans (a, b): consecutive keyframes with frames between them."""
    return [(a, b) for a, b in zip(keyframes[:-1], keyframes[1:]) if b - a > 1]


def interpolate_state(left: PoseState, right: PoseState, alpha: float) -> PoseState:
    """Linear blend of head-frame positions and translations, slerp of rotations."""
    rot = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([left.R, right.R])))([alpha]).as_matrix()[0]
    return PoseState((1 - alpha) * left.X + alpha * right.X, rot,
                     (1 - alpha) * left.t + alpha * right.t,
                     np.minimum(left.certainty, right.certainty))


def solve_span(inp: TrackingInput, params: TrackingParams, mesh: TrackingMesh, left: PoseState,
               right: PoseState, a: int, b: int, temporal: TemporalFlows | None = None
               ) -> dict[int, PoseState]:
    """Stage 3 of §5.7: the frames strictly between keyframes a and b, with a and b fixed.

    Independent of every other span: its inputs are the frames a..b's images, the cameras, the
    artist mesh (with the keyframe stage's rigidity weights) and the two keyframe states
    (``temporal``: flows kept from the keyframe stage, in one process).

    Returns
    -------
    frame → PoseState for the frames a+1 … b−1
    """
    temporal = temporal or TemporalFlows(inp, params, 0.0)
    edges = [temporal(t) for t in range(a, b)]
    states = {("frame", a): left, ("frame", b): right}
    for t in range(a + 1, b):
        states[("frame", t)] = interpolate_state(left, right, (t - a) / (b - a))
    free = [("frame", t) for t in range(a + 1, b)]
    states = solve_poses(mesh, inp.cameras, states, free, edges, {}, params, params.span_iterations)
    return {t: states[("frame", t)] for t in range(a + 1, b)}


def solve_sequential(inp: TrackingInput, params: TrackingParams, mesh: TrackingMesh) -> dict:
    """Frame-to-frame propagation: frame 0 from the neutral, then each frame from the last."""
    ground = ground_state(mesh)
    e0 = edge_flows(inp.scan_images[0], inp.frame_images[0], ("scan", 0), ("frame", 0), params)
    states = solve_poses(mesh, inp.cameras, {("scan", 0): ground, ("frame", 0): unknown_state(mesh)},
                         [("frame", 0)], [e0], {}, params, params.span_iterations)
    out = {("scan", 0): ground, ("frame", 0): states[("frame", 0)]}
    for t in range(1, inp.frames):
        prev = out[("frame", t - 1)]
        s = solve_poses(mesh, inp.cameras, {("frame", t - 1): prev, ("frame", t): replace(prev)},
                        [("frame", t)], [_temporal(inp, t - 1, params)], {}, params,
                        params.span_iterations)
        out[("frame", t)] = s[("frame", t)]
    return out


def track(inp: TrackingInput, params: TrackingParams | None = None, method: str = "graph",
          graph: FlowGraph | None = None, progress=None, flow_cache_mb: float = 1024.0
          ) -> TrackingResult:
    """Track a performance (fyffe §4–5): graph, keyframes, spans; or a baseline.

    Parameters
    ----------
    method : "graph" (the full flow graph), "neutral" (neutral-scan anchors only) or
             "sequential" (frame-to-frame propagation)
    graph : a graph already built for this input (skips stage 1)
    progress : callable(fraction, stage) or None
    flow_cache_mb : memory for the temporal flows kept from the keyframe stage for the spans
                    (:class:`TemporalFlows`; 0: compute them again)
    """
    if method not in METHODS:
        raise InvalidInput(f"method must be one of {METHODS}, got {method!r}")
    params = params or TrackingParams()
    report = progress or (lambda f, s: None)
    mesh = TrackingMesh.build(inp.artist_vertices, inp.faces)
    timings: dict[str, float] = {}
    cpu: dict[str, float] = {}
    T = inp.frames
    if method == "sequential":
        t0, c0 = time.perf_counter(), time.process_time()
        states = solve_sequential(inp, params, mesh)
        timings["sequential_solve"], cpu["sequential_solve"] = time.perf_counter() - t0, time.process_time() - c0
        keyframes: list[int] = [0]
    else:
        t0, c0 = time.perf_counter(), time.process_time()
        if graph is None:
            report(0.0, "graph flows")
            graph = build_graph(inp, params, [0] if method == "neutral" else None,
                                lambda f: report(0.2 * f, "graph flows"))
        timings["graph"], cpu["graph"] = time.perf_counter() - t0, time.process_time() - c0
        report(0.2, "keyframe solve")
        temporal = TemporalFlows(inp, params, flow_cache_mb)
        key = solve_keyframes(inp, graph, params, mesh,
                              lambda f, s: report(0.2 + 0.2 * f, s), temporal)
        timings.update(key.timings)
        cpu.update(key.cpu_timings)
        states = dict(key.states)
        keyframes = key.keyframes
        t0, c0 = time.perf_counter(), time.process_time()
        todo = spans(keyframes)
        for k, (a, b) in enumerate(todo):
            report(0.5 + 0.5 * k / max(len(todo), 1), "tween solve")
            for t, s in solve_span(inp, params, mesh, states[("frame", a)], states[("frame", b)], a, b,
                                   temporal).items():
                states[("frame", t)] = s
            temporal.release(range(a, b))     # a span's flows are not needed again
        timings["tween_solve"], cpu["tween_solve"] = time.perf_counter() - t0, time.process_time() - c0
    report(1.0, "done")
    frames = [states[("frame", t)] for t in range(T)]
    S = len(inp.scan_images)
    scans = np.full((S, mesh.n, 3), np.nan, np.float32)
    for s in range(S):
        if ("scan", s) in states:
            scans[s] = states[("scan", s)].world()
    return TrackingResult(np.stack([f.world() for f in frames]).astype(np.float32),
                          np.stack([f.R for f in frames]), np.stack([f.t for f in frames]),
                          scans, graph if method != "sequential" else None, keyframes, timings, states,
                          cpu)
