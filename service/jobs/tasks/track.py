"""The ``track`` job (performance-flow tracking, fyffe, digital_ira_course2014 §4–7) and its
``track_span`` child jobs.

The parent runs the stages of :mod:`service.methods.tracking.track` in order, reporting
:data:`service.jobs.track_stages.STAGES`:

1. **graph flows**, **graph selection** — :func:`~service.methods.tracking.track.build_graph`
   (candidate flows at reduced resolution, region confidences, the voting of §4.1);
2. **full flows**, **keyframe solve** — :func:`~service.methods.tracking.track.solve_keyframes`
   (§5.7's first stage: the static poses and keyframes coupled);
3. **tween solve** — one ``track_span`` job per in-between span
   (:func:`~service.methods.tracking.track.spans`) through the queue, so the spans run on
   every worker at once (§5.7: "each span of in-between frames may be solved
   independently"). The parent does not wait in a worker slot: it checks its spans and,
   while some are unfinished, raises :class:`~service.jobs.running.Requeue` — it is queued
   again (not counted as a retry) and checks again :data:`JOIN_DELAY` seconds later. A span
   job whose worker dies is requeued by the reaper like any job: a killed worker costs that
   span, not the performance;
4. **maps** — :func:`~service.methods.tracking.maps.scan_weights` (per-frame per-vertex
   weights over the scans) and :func:`~service.methods.tracking.maps.blend_maps` of the scans'
   reflectance maps (:func:`service.methods.scan_textures.scan_reflectance`) and of the
   uploaded maps;
5. **storing results** — the artifacts.

Resumable per stage: the graph (``graph.npz``), the keyframe states (``keyframes.npz``) and
each span's states (``spans/<a>-<b>.npz``) are kept beside the input under the job's blob
prefix (``actors/<actor>/tracking/<token>/``, deleted with the actor), so a retried parent
(its worker died) continues after the last stage it stored, finds the span jobs it created
(by their payload's ``parent_job_id``) and reuses artifacts stored by an earlier attempt.
The states travel as float64, so the result equals a single-process
:func:`~service.methods.tracking.track.track` on the same input.

Artifacts: ``tracked.npz`` (``vertices`` (T,n,3) float32 world, ``faces``, ``rotations``
(T,3,3), ``translations`` (T,3) head → world, ``keyframes``, ``static_edges`` (E,2) (scan,
frame), ``scan_names``), ``weights.npz`` (``weights`` (T,n,S) float32, rows sum to 1),
``maps.npz`` (``reflectance`` (T,h,w) float32 and each uploaded map, (T,h,w[,C])),
``scans.npz`` (``vertices`` (S,n,3) float32 the static scans registered to the artist
topology, NaN for scans the graph did not use, ``registered`` (S,), ``reflectance``
(S,h,w)); with ``format`` ``obj-exr-zip`` also ``tracked.zip`` (one OBJ per frame), with
``usd`` ``tracked.usd`` (a point cache).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from models_store import registry
from service.geometry.camera import Camera
from service.io.npz import npz_bytes
from service.jobs.frame_usd import DEFAULT_FPS, FrameUsdWriter
from service.jobs.frame_zip import FrameZipWriter
from service.jobs.running import JobCancelled, Requeue, RunningJob, worker_name
from service.jobs.track_jobs import SPAN_JOB, span_jobs
from service.jobs.track_stages import overall
from service.methods.inputs import InvalidInput
from service.methods.scan_textures import scan_reflectance
from service.methods.tracking.graph import FlowGraph
from service.methods.tracking.maps import blend_maps, scan_weights
from service.methods.tracking.params import TrackingParams
from service.methods.tracking.solve import PoseState, TrackingMesh
from service.methods.tracking.track import (KeyframeSolution, TrackingInput, TrackingResult,
                                            build_graph, solve_keyframes, solve_span, spans)

#: seconds between a waiting parent's checks of its span jobs
JOIN_DELAY = 0.5
NPZ = "application/x-npz"
#: pose kinds in the stored states
_KINDS = ("scan", "frame")


# ---------------------------------------------------------------------------- the input
def load_input(store, payload: dict, frames: tuple[int, int] | None = None) -> tuple[TrackingInput, dict]:
    """The job's :class:`TrackingInput` (only frames a … b with ``frames=(a, b)``, renumbered
    from 0) and the rest of the input NPZ (``uv``, ``uv_faces``, ``map_<name>``, names)."""
    with store.blobs.open(payload["input_blob"], payload["input_sha256"]) as stream:
        with np.load(stream, allow_pickle=False) as d:
            a = {k: d[k] for k in d.files}
    images = np.load(store.blobs.path(payload["frames_blob"]), mmap_mode="r")
    images = np.array(images if frames is None else images[frames[0]:frames[1] + 1])
    vsplit = np.cumsum(a.pop("scan_vertex_counts"))[:-1]
    fsplit = np.cumsum(a.pop("scan_face_counts"))[:-1]
    cameras = [Camera.from_json(c) for c in json.loads(str(a.pop("cameras")))]
    inp = TrackingInput(a.pop("artist_vertices"), a.pop("faces"), cameras, a.pop("scan_images"),
                        np.split(a.pop("scan_vertices"), vsplit), np.split(a.pop("scan_faces"), fsplit),
                        images, tuple(str(s) for s in a["scan_names"]), a.pop("face"))
    return inp, a


# ---------------------------------------------------------------------------- stage files
def _states_arrays(states: dict) -> dict[str, np.ndarray]:
    """Pose states as arrays (float64, exact): ``kind`` (P,) 0 scan / 1 frame, ``index``
    (P,), ``X`` (P,n,3), ``R`` (P,3,3), ``t`` (P,3), ``certainty`` (P,n)."""
    keys = sorted(states, key=lambda k: (_KINDS.index(k[0]), k[1]))
    return dict(kind=np.array([_KINDS.index(k[0]) for k in keys], np.int64),
                index=np.array([k[1] for k in keys], np.int64),
                X=np.stack([states[k].X for k in keys]), R=np.stack([states[k].R for k in keys]),
                t=np.stack([states[k].t for k in keys]),
                certainty=np.stack([states[k].certainty for k in keys]))


def _read_states(d) -> dict:
    return {(_KINDS[int(k)], int(i)): PoseState(d["X"][j], d["R"][j], d["t"][j], d["certainty"][j])
            for j, (k, i) in enumerate(zip(d["kind"], d["index"]))}


def _read(store, key: str) -> dict | None:
    if not store.blobs.exists(key):
        return None
    with np.load(store.blobs.path(key), allow_pickle=False) as d:
        return {k: d[k] for k in d.files}


def _keep(store, key: str, data: bytes) -> None:
    """Store a stage's output (write-once: an earlier attempt's copy is kept)."""
    if not store.blobs.exists(key):
        store.blobs.put_bytes(key, data)


def _graph_npz(graph: FlowGraph, seconds: float) -> bytes:
    return npz_bytes(seconds=np.float64(seconds), frames=np.int64(graph.frames),
                     static_edges=np.array(graph.static_edges, np.int64).reshape(-1, 2),
                     table=graph.table, initial_max=np.float64(graph.initial_max),
                     candidates=np.int64(graph.candidates), scan_labels=graph.scan_labels)


def _graph_of(d: dict) -> FlowGraph:
    return FlowGraph(int(d["frames"]), [(int(s), int(t)) for s, t in d["static_edges"]],
                     d["table"], float(d["initial_max"]), int(d["candidates"]), d["scan_labels"])


def _keyframes_of(d: dict) -> KeyframeSolution:
    return KeyframeSolution(_read_states(d), [int(t) for t in d["keyframes"]], d["rigidity"], {},
                            size_weights=d["size_weights"] if d.get("size_weights") is not None
                            and d["size_weights"].any() else None,
                            size_band=float(d["size_band"]) if "size_band" in d else 0.0)


def span_key(prefix: str, a: int, b: int) -> str:
    return f"{prefix}/spans/{a:06d}-{b:06d}.npz"


# ---------------------------------------------------------------------------- the parent
def track(job: RunningJob) -> dict[str, Any]:
    """Run (or continue) a tracking job: see the module docstring."""
    payload, store = job.payload, job.store
    params = TrackingParams(**payload["params"])
    prefix = payload["prefix"]
    seconds: dict[str, float] = {}
    with store.sessions() as session:
        children = {(j.payload["a"], j.payload["b"]): j for j in span_jobs(session, job)}
    inp = extra = None
    keyframes = _read(store, f"{prefix}/keyframes.npz")
    if keyframes is None:
        job.progress(0.0, "graph flows")
        inp, extra = load_input(store, payload)
        t0 = time.perf_counter()
        stored = _read(store, f"{prefix}/graph.npz")
        if stored is None:
            def graph_progress(f: float) -> None:
                job.progress(overall("graph flows", f), "graph flows")
                if f >= 1.0:
                    job.progress(overall("graph selection", 0.0), "graph selection")
            graph = build_graph(inp, params, None, graph_progress)
            _keep(store, f"{prefix}/graph.npz", _graph_npz(graph, time.perf_counter() - t0))
        else:
            graph = _graph_of(stored)
        graph_seconds = float(_read(store, f"{prefix}/graph.npz")["seconds"])
        job.progress(overall("full flows", 0.0), "full flows")

        def key_progress(f: float, stage: str) -> None:      # f ∈ [0, 0.5]: the full flows
            job.progress(overall("full flows", 2 * f), "full flows")
            if f >= 0.5:
                job.progress(overall("keyframe solve", 0.0), "keyframe solve")
        t0 = time.perf_counter()
        solution = solve_keyframes(inp, graph, params, None, key_progress)
        _keep(store, f"{prefix}/keyframes.npz", npz_bytes(
            **_states_arrays(solution.states), keyframes=np.array(solution.keyframes, np.int64),
            rigidity=solution.rigidity, size_band=np.float64(solution.size_band),
            size_weights=np.zeros(len(solution.rigidity)) if solution.size_weights is None
            else solution.size_weights,
            static_edges=np.array(graph.static_edges, np.int64).reshape(-1, 2),
            candidates=np.int64(graph.candidates), graph_seconds=np.float64(graph_seconds),
            seconds=np.float64(time.perf_counter() - t0)))
        keyframes = _read(store, f"{prefix}/keyframes.npz")
    seconds["graph"] = float(keyframes["graph_seconds"])
    seconds["keyframes"] = float(keyframes["seconds"])
    solution = _keyframes_of(keyframes)
    todo = spans(solution.keyframes)
    job.progress(overall("tween solve", 0.0), "tween solve")
    missing = [(a, b) for a, b in todo if (a, b) not in children]
    if missing:
        with store.sessions() as session:
            created = [registry.create_job(session, SPAN_JOB, job.actor_id, payload={
                "parent_job_id": job.id, "prefix": prefix, "a": a, "b": b,
                "input_blob": payload["input_blob"], "input_sha256": payload["input_sha256"],
                "frames_blob": payload["frames_blob"], "params": payload["params"]})
                for a, b in missing]
            ids = [c.id for c in created]
        for child_id in ids:
            if job.enqueue is None:
                raise RuntimeError("this runner has no queue to send the span jobs to")
            job.enqueue(child_id)
        with store.sessions() as session:
            children = {(j.payload["a"], j.payload["b"]): j for j in span_jobs(session, job)}
    _join(job, children, todo)

    # every span is done: the whole sequence, the weights and maps, the artifacts
    if inp is None:
        inp, extra = load_input(store, payload)
    states = dict(solution.states)
    for a, b in todo:
        states.update(_read_states(_read(store, span_key(prefix, a, b))))
    result = _result(inp, states, solution)
    seconds["spans_total"] = sum(float((children[sp].result or {}).get("seconds", 0.0)) for sp in todo)
    return _outputs(job, inp, extra, result, params, seconds,
                    span_ids=[children[s].id for s in todo],
                    static_edges=keyframes["static_edges"].tolist(),
                    candidates=int(keyframes["candidates"]))


def _join(job: RunningJob, children: dict, todo: list) -> None:
    """Return when every span job succeeded; fail with the first failed one's error; else
    report the spans' progress and requeue (:class:`Requeue`)."""
    done = 0
    for a, b in todo:
        child = children[(a, b)]
        if child.status == "succeeded":
            done += 1
        elif child.status in ("failed", "cancelled"):
            with job.store.sessions() as session:    # cancelled with its parent (DELETE)?
                if registry.get_job(session, job.id).cancel_requested:
                    raise JobCancelled(job.id)
            error = child.error or {}
            message = (f"span {a}–{b} (job {child.id}) {child.status}: "
                       f"{error.get('message', '')}")
            if error.get("code") == "invalid_input":
                raise InvalidInput(message)
            raise RuntimeError(message)
    job.progress(overall("tween solve", done / max(len(todo), 1)), "tween solve")
    if done < len(todo):
        raise Requeue(JOIN_DELAY, f"{len(todo) - done} of {len(todo)} spans running")


def _result(inp: TrackingInput, states: dict, solution: KeyframeSolution) -> TrackingResult:
    """The :class:`TrackingResult` of the joined states (as
    :func:`~service.methods.tracking.track.track` assembles it)."""
    frames = [states[("frame", t)] for t in range(inp.frames)]
    S, n = len(inp.scan_images), len(inp.artist_vertices)
    scans = np.full((S, n, 3), np.nan, np.float32)
    for s in range(S):
        if ("scan", s) in states:
            scans[s] = states[("scan", s)].world()
    return TrackingResult(np.stack([f.world() for f in frames]).astype(np.float32),
                          np.stack([f.R for f in frames]), np.stack([f.t for f in frames]),
                          scans, None, solution.keyframes, {}, states)


def _outputs(job: RunningJob, inp: TrackingInput, extra: dict, result: TrackingResult,
             params: TrackingParams, seconds: dict, *, span_ids: list, static_edges: list,
             candidates: int) -> dict[str, Any]:
    payload, store = job.payload, job.store
    t0 = time.perf_counter()
    job.progress(overall("maps", 0.0), "maps")
    mesh = TrackingMesh.build(inp.artist_vertices, inp.faces)
    uv, uv_faces = extra["uv"], extra["uv_faces"]
    size = int(payload.get("map_resolution", 256))
    weights = scan_weights(inp, result, uv, uv_faces, params)
    job.progress(overall("maps", 0.4), "maps")
    S = len(inp.scan_images)
    registered = np.isfinite(result.scan_vertices).all(axis=(1, 2))
    reflectance = np.zeros((S, size, size), np.float32)
    for s in np.flatnonzero(registered):
        reflectance[s] = scan_reflectance(mesh, inp.cameras, inp.scan_images[s],
                                          result.scan_vertices[s].astype(np.float64), uv, uv_faces,
                                          size, params.visibility_tolerance_mm)
    maps = {"reflectance": blend_maps(weights, inp.faces, uv, uv_faces, reflectance)}
    for name in payload.get("maps") or []:
        maps[name] = blend_maps(weights, inp.faces, uv, uv_faces, extra[f"map_{name}"])
    seconds["maps"] = time.perf_counter() - t0
    job.progress(overall("storing results", 0.0), "storing results")
    names = np.array(inp.scan_names)
    faces = inp.faces.astype(np.int32)
    files: list[tuple[str, Any, str]] = [
        ("tracked.npz", npz_bytes(vertices=result.vertices, faces=faces,
                                  rotations=result.rotations, translations=result.translations,
                                  keyframes=np.array(result.keyframes, np.int64),
                                  static_edges=np.array(static_edges, np.int64).reshape(-1, 2),
                                  scan_names=names), NPZ),
        ("weights.npz", npz_bytes(weights=weights, scan_names=names), NPZ),
        ("maps.npz", npz_bytes(**maps), NPZ),
        ("scans.npz", npz_bytes(vertices=result.scan_vertices, registered=registered,
                                reflectance=reflectance, faces=faces, scan_names=names), NPZ),
    ]
    with store.blobs.scratch_dir("track") as tmp:
        fmt = payload.get("format", "npz")
        if fmt == "obj-exr-zip":
            writer = FrameZipWriter(Path(tmp) / "tracked.zip", inp.frames, uv, uv_faces)
            writer.write(0, {"vertices": result.vertices, "faces": faces})
            files.append(("tracked.zip", writer.finish(), "application/zip"))
        elif fmt == "usd":
            writer = FrameUsdWriter(Path(tmp), inp.frames, uv, uv_faces, fps=DEFAULT_FPS)
            writer.write(0, {"vertices": result.vertices, "faces": faces})
            files.append(("tracked.usd", writer.finish(), "application/octet-stream"))
        with store.sessions() as session:          # a retry keeps what an earlier attempt stored
            ids = {a.filename: a.id for a in registry.list_artifacts(session, job.id)}
        for filename, data, media_type in files:
            if filename in ids:
                continue
            with store.sessions() as session:
                ids[filename] = registry.add_artifact(session, store.blobs, job.id, data,
                                                      media_type=media_type, filename=filename).id
    ids = {f: ids[f] for f, _, _ in files}
    seconds["store"] = time.perf_counter() - t0 - seconds["maps"]
    metrics = {"frames": inp.frames, "views": len(inp.cameras), "scans": S,
               "registered_scans": int(registered.sum()), "keyframes": len(result.keyframes),
               "spans": len(span_ids), "static_edges": len(static_edges), "candidates": candidates,
               "seconds": {k: round(float(v), 4) for k, v in seconds.items()}}
    return {"artifact_ids": list(ids.values()), "artifacts": ids, "span_job_ids": span_ids,
            "metrics": metrics}


# ---------------------------------------------------------------------------- a span
def track_span(job: RunningJob) -> dict[str, Any]:
    """Solve one in-between span a … b (§5.7) with its keyframes held fixed and store its
    states; cancelled when its parent is cancelled or ended."""
    payload, store = job.payload, job.store
    with store.sessions() as session:
        parent = registry.get_job(session, payload["parent_job_id"])
        if parent.cancel_requested or parent.status in ("failed", "cancelled", "succeeded"):
            raise JobCancelled(job.id)
    a, b = int(payload["a"]), int(payload["b"])
    key = span_key(payload["prefix"], a, b)
    job.progress(0.0, "tween solve")
    t0 = time.perf_counter()
    if not store.blobs.exists(key):
        params = TrackingParams(**payload["params"])
        inp, _ = load_input(store, payload, (a, b))
        solution = _keyframes_of(_read(store, f"{payload['prefix']}/keyframes.npz"))
        mesh = TrackingMesh.build(inp.artist_vertices, inp.faces)
        mesh.rigidity = solution.rigidity
        mesh.size_weights, mesh.size_band = solution.size_weights, solution.size_band
        solved = solve_span(inp, params, mesh, solution.states[("frame", a)],
                            solution.states[("frame", b)], 0, b - a)
        states = {("frame", a + t): s for t, s in solved.items()}
        job.progress(0.95, "tween solve")
        _keep(store, key, npz_bytes(**_states_arrays(states)))
    return {"parent_job_id": payload["parent_job_id"], "span": [a, b], "frames": b - a - 1,
            "states_blob": key, "seconds": round(time.perf_counter() - t0, 4),
            "worker": worker_name()}
