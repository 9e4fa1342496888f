"""The ``correspond`` job: warp a source scan into a target scan's UV space (Vuvuzela).

digital_ira_course2014, "Vuvuzela: A Facial Scan Correspondence Tool": the three steps of
:func:`service.methods.correspondence.correspond` (Delaunay pre-warp from the landmarks,
dense flow on over-sharpened diffuse textures, the composed warp applied to every map), and
with ``artist_uv`` its by-product, the blendshape of the actor's neutral ("looking up vertex
positions in the warped point clouds", :func:`~service.methods.correspondence.
blendshape_vertices`).

Payload (as :func:`service.app.scans.submit_correspondence` writes it)::

    {"source_scan_id": "scn_…", "target_scan_id": "scn_…",
     "landmarks": [[[u_s, v_s], [u_t, v_t]], ...],   # (L,2,2) unit-tile UV
     "pinned": [0, 3],                                  # landmark indices
     "params": {...},                                   # CorrespondenceParams
     "artist_uv": false}                                # the neutral's UVs are the target's

Artifacts, in the target's UV space (H,W):

- ``<map>.exr`` per warped map (``albedo``, ``position``, ``specular``, ``normal``): one
  multi-channel float32 EXR, channels ``R``, ``G``, ``B``, 0 outside the warp's mask;
- ``warp.npz``: ``coords`` (H,W,2) float32 (source texel column, row of every target texel),
  ``confidence`` (H,W) float32 in [0,1] (NCC, fyffe §4.1), ``mask`` (H,W) bool,
  ``prewarp`` (H,W,2) and ``flow`` (H,W,2) float32;
- ``blendshape.npz`` (with ``artist_uv``): ``vertices`` (n,3) float32 in the actor's unit,
  NaN for vertices without a UV or outside the warped scan, and ``valid`` (n,) bool.

Result ``{"artifact_ids": [...], "artifacts": {filename: id}, "source_scan_id",
"target_scan_id", "metrics": {"mean_confidence", "coverage", "width", "height",
"seconds": {stage: s}}}``; ``coverage`` is the fraction of the target's covered texels that
the warped source covers. The result is a function of the stored scans and the payload, so a
retry (after a worker died mid-way) reuses the artifacts an earlier attempt stored, by file
name, instead of storing them twice.
"""

from __future__ import annotations

import io
import time
from typing import Any, Mapping

import numpy as np
from pydantic import ValidationError

from models_store import registry
from models_store.errors import NotFound
from service.io.exr import write_exr
from service.io.npz import npz_bytes
from service.jobs.running import RunningJob
from service.methods.correspondence import (CorrespondenceParams, blendshape_vertices,
                                            correspond)
from service.methods.inputs import InvalidInput
from service.store.actors import load_neutral_arrays, open_npz

# the job's progress: loading, the correspondence, then storing the artifacts
LOADED, CORRESPONDED = 0.05, 0.85
EXR = "image/x-exr"
NPZ = "application/x-npz"
#: channel names of a map's EXR by its channel count (API.md)
CHANNELS = {1: ("Y",), 3: ("R", "G", "B")}


def correspond_scans(job: RunningJob) -> dict[str, Any]:
    """Correspond the payload's source scan to its target scan and store the artifacts."""
    t0 = time.perf_counter()
    payload = job.payload
    store = job.store
    try:
        params = CorrespondenceParams(**(payload.get("params") or {}))
    except ValidationError as error:
        raise InvalidInput(f"invalid correspondence parameters: {error}") from None
    job.progress(0.0, "loading the scans")
    with store.sessions() as session:
        source = _read_scan(session, store.blobs, payload["source_scan_id"], job.actor_id)
        target = _read_scan(session, store.blobs, payload["target_scan_id"], job.actor_id)
        neutral = None
        if payload.get("artist_uv"):
            neutral = load_neutral_arrays(session, store.blobs, job.actor_id, "artist_uv")
    scan_uv = vertex_uv(neutral) if neutral is not None else None
    seconds = {"load": time.perf_counter() - t0}
    result = correspond(source, target, np.asarray(payload["landmarks"], np.float64), params,
                        job.sub_progress(LOADED, CORRESPONDED),
                        pinned=np.asarray(payload.get("pinned") or [], np.int64))
    seconds.update(result.seconds)

    t1 = time.perf_counter()
    files: list[tuple[str, bytes, str]] = []
    for name in sorted(result.maps):
        files.append((f"{name}.exr", map_exr(result.maps[name]), EXR))
    files.append(("warp.npz", npz_bytes(coords=result.coords, confidence=result.confidence,
                                        mask=result.mask, prewarp=result.prewarp,
                                        flow=result.flow), NPZ))
    if scan_uv is not None:
        if "position" not in result.maps:
            raise InvalidInput("artist_uv needs the scans' 'position' maps")
        vertices = blendshape_vertices(result.maps["position"], result.mask, scan_uv)
        valid = np.isfinite(vertices).all(axis=1)
        files.append(("blendshape.npz", npz_bytes(vertices=vertices.astype(np.float32),
                                                  valid=valid), NPZ))
    with store.sessions() as session:       # a retry keeps what an earlier attempt stored
        ids = {a.filename: a.id for a in registry.list_artifacts(session, job.id)
               if a.filename in {f for f, _, _ in files}}
    for k, (filename, data, media_type) in enumerate(files):
        job.progress(CORRESPONDED + (1.0 - CORRESPONDED) * k / len(files), "storing the results")
        if filename in ids:
            continue
        with store.sessions() as session:
            ids[filename] = registry.add_artifact(session, store.blobs, job.id, data,
                                                  media_type=media_type,
                                                  filename=filename).id
    ids = {f: ids[f] for f, _, _ in files}
    seconds["store"] = time.perf_counter() - t1
    seconds["total"] = time.perf_counter() - t0
    covered = target.get("mask")
    covered = (np.asarray(covered, bool) if covered is not None else
               (np.asarray(target["albedo"]) != 0).any(axis=-1))
    metrics = {
        "mean_confidence": float(result.confidence[result.mask].mean()) if result.mask.any() else 0.0,
        "coverage": float(result.mask.sum() / max(int(covered.sum()), 1)),
        "width": int(result.mask.shape[1]), "height": int(result.mask.shape[0]),
        "seconds": {stage: round(float(s), 4) for stage, s in seconds.items()},
    }
    if scan_uv is not None:
        metrics["blendshape_vertices"] = int(valid.sum())
    return {"artifact_ids": list(ids.values()), "artifacts": ids,
            "source_scan_id": payload["source_scan_id"],
            "target_scan_id": payload["target_scan_id"], "metrics": metrics}


def _read_scan(session, blobs, scan_id: str, actor_id: str) -> dict[str, np.ndarray]:
    """A stored scan's maps; InvalidInput if it was deleted after the job was queued."""
    try:
        data = registry.read_scan(session, blobs, registry.get_scan(session, scan_id, actor_id).id)
    except NotFound:
        raise InvalidInput(f"scan {scan_id!r} of actor {actor_id!r} no longer exists (deleted "
                           "after the job was queued)") from None
    return dict(open_npz(data, f"scan {scan_id!r}"))


def map_exr(values: np.ndarray) -> bytes:
    """One warped map (H,W) or (H,W,C) as a float32 EXR (``Y``, or ``R``, ``G``, ``B``;
    other channel counts ``c0``, ``c1``, ...)."""
    m = np.asarray(values, np.float32)
    m = m[..., None] if m.ndim == 2 else m
    names = CHANNELS.get(m.shape[2], tuple(f"c{k}" for k in range(m.shape[2])))
    buffer = io.BytesIO()
    write_exr(buffer, {name: m[..., k] for k, name in enumerate(names)})
    return buffer.getvalue()


def vertex_uv(neutral: Mapping[str, np.ndarray]) -> np.ndarray:
    """(n,2) float64: one UV per vertex of a canonical neutral (``uv`` (K,2) indexed by
    ``uv_faces`` per corner); a vertex on a UV seam takes one of its UVs, a vertex in no
    triangle NaN."""
    V = np.asarray(neutral["vertices"])
    if "uv" not in neutral:
        raise InvalidInput("artist_uv needs a neutral with UVs (the target scan's layout)")
    F = np.asarray(neutral["faces"], np.int64)
    uv = np.asarray(neutral["uv"], np.float64)
    uv_faces = np.asarray(neutral.get("uv_faces", F), np.int64)
    out = np.full((len(V), 2), np.nan)
    out[F.ravel()] = uv[uv_faces.ravel()]
    return out
