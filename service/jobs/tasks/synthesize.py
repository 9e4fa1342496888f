"""The ``synthesize`` job: meshes and maps for a whole performance, stored as an artifact.

Payload::

    {"model_id": "mdl_…",
     "markers_artifact_id": "art_…"               # the input .npz with "markers" (F,M,3) …
       | "markers_blob": "<key>", "markers_sha256": "<hex>",   # … or a blob of the store
     "outputs": ["mesh", "displacement"],          # optional (API.md's outputs)
     "clamp": true,                                # optional: the extrapolation limit
     "marker_filter_frames": 3.0,                  # optional: temporal marker filter σ, frames, or "auto"
     "format": "npz"}                              # optional: "npz", "obj-exr-zip", "usd"

A mesh-driven model (``shape_space``) takes ``vertices`` instead of ``markers``
(``vertices_artifact_id`` | ``vertices_blob`` + ``vertices_sha256``: (F,n,3) on the actor's
topology), or vertices (F,v,3) on a registered input rig with ``"rig_id"``, ``"rig"``,
``"registration_blob"``, ``"registration_sha256"``: the frames are propagated to the actor's
topology with exactly that registration (:meth:`RigRegistration.propagate`, verified
against its sha256) before they are enhanced.

Result ``{"model_id", "artifact_ids": [one artifact]}``: for ``npz`` the arrays of API.md's
synthesize response (``vertices`` (F,n,3), ``faces``, the asked maps, ``clamped`` (F,)); for
``obj-exr-zip`` one OBJ per frame and mesh output and one EXR per frame and map
(:mod:`service.jobs.frame_zip`); for ``usd`` one USD point cache at the input's frame rate
(its ``fps``, else 30), or a zip of the cache and the EXR maps it references when maps are
asked (:mod:`service.jobs.frame_usd`). All are written chunk by chunk, so memory stays
bounded for any length (a USD stage holds the points once; they are not kept twice).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np
from sqlalchemy.orm import Session

from models_store import registry
from models_store.blobs import BlobStore
from models_store.errors import NotFound
from service.geometry.marker_filter import filter_performance
from service.io.npz import npz_arrays
from service.jobs.frame_npz import STATIC_KEYS, FrameNpzWriter
from service.jobs.formats import artifact_type, check_result_format, usd_is_zip
from service.jobs.frame_usd import DEFAULT_FPS, FrameUsdWriter
from service.jobs.frame_zip import FrameZipWriter
from service.jobs.running import RunningJob
from service.methods.inputs import InvalidInput
from service.methods.kinds import get_kind, takes
from service.methods.outputs import DEFAULT_OUTPUTS
from service.methods.shape_space.registration import RigRegistration

#: frames synthesized (and progress points passed) per step
CHUNK_FRAMES = 16
# the job's progress: loading, then the frames, then storing the artifact
LOADED, SYNTHESIZED = 0.05, 0.95
#: per-model (not per-frame) arrays of the outputs, stored once in an NPZ result
STATIC_OUTPUTS = STATIC_KEYS | {"region_names"}


def synthesize(job: RunningJob) -> dict[str, Any]:
    """Synthesize the payload's markers (or vertices) with the payload's model into one
    artifact."""
    payload = job.payload
    model_id = payload["model_id"]
    fmt = payload.get("format", "npz")
    outputs = tuple(payload.get("outputs") or DEFAULT_OUTPUTS)
    check_result_format(fmt, outputs)
    clamp = bool(payload.get("clamp", True))
    store = job.store
    job.progress(0.0, "loading the model")
    with store.sessions() as session:
        model = registry.get_model(session, model_id)
        kind = get_kind(model.kind)
        key = "markers" if kind.input == "markers" else "vertices"
        if model.status != "ready":
            raise InvalidInput(f"model {model_id!r} is {model.status}, not ready")
        path = registry.model_dir(session, store.blobs, model_id)
        inputs, fps = read_frames(session, store.blobs, payload, key)
    registration = read_registration(store.blobs, payload) if payload.get("rig_id") else None
    if registration is not None and key != "vertices":
        raise InvalidInput(f"a {kind.name} model is driven by markers; an input rig does not apply")
    trained = kind.load(path)
    captured = None                   # the markers before the filter, where the model reads them
    if payload.get("marker_filter_frames") and key == "markers":
        # the whole performance at once: the filter looks ahead and behind; "auto" chooses its
        # windows in the modes of the model's marker prior (geometry/marker_filter.py)
        captured = inputs if takes(trained, "captured") else None
        inputs = filter_performance(inputs, payload["marker_filter_frames"],
                                    modes=getattr(trained, "marker_modes", None))
    frames = len(inputs)
    media_type, suffix = artifact_type(fmt, outputs)
    uv, uv_faces = getattr(trained, "uv", None), getattr(trained, "uv_faces", None)
    with store.blobs.scratch_dir("synthesize") as tmp:  # locked: never swept while in use
        if fmt == "npz":
            writer = FrameNpzWriter(Path(tmp), frames, STATIC_OUTPUTS)
        elif fmt == "usd":
            writer = FrameUsdWriter(Path(tmp), frames, uv, uv_faces,
                                    fps=DEFAULT_FPS if fps is None else fps,
                                    as_zip=usd_is_zip(outputs))
        else:
            writer = FrameZipWriter(Path(tmp) / "result.zip", frames, uv, uv_faces)
        for start in range(0, frames, CHUNK_FRAMES):
            job.progress(LOADED + (SYNTHESIZED - LOADED) * start / frames, "synthesizing")
            stop = min(start + CHUNK_FRAMES, frames)
            try:
                chunk = inputs[start:stop]
                if registration is not None:
                    chunk = registration.propagate(chunk)
                extra = {} if captured is None else {"captured": captured[start:stop]}
                writer.write(start, trained.synthesize(chunk, outputs, clamp, **extra))
            except InvalidInput as error:
                raise InvalidInput(f"frames {start}-{stop - 1}: {error}") from None
        job.progress(SYNTHESIZED, "storing the result")
        result = writer.finish()
        with store.sessions() as session:
            artifact = registry.add_artifact(session, store.blobs, job.id, result,
                                             media_type=media_type,
                                             filename=f"{job.id}.{suffix}")
    return {"model_id": model_id, "artifact_ids": [artifact.id]}


def read_frames(session: Session, blobs: BlobStore, payload: Mapping[str, Any],
                key: str = "markers") -> tuple[np.ndarray, float | None]:
    """The payload's input frames under ``key``, markers (F,M,3) or vertices (F,V,3)
    float64 (InvalidInput if absent or malformed), and the input's ``fps`` (None if it
    states none)."""
    if payload.get(f"{key}_artifact_id"):
        artifact, stream = registry.open_artifact(session, blobs, payload[f"{key}_artifact_id"])
        with stream:
            data = stream.read()
    elif payload.get(f"{key}_blob"):
        data = blobs.read_bytes(payload[f"{key}_blob"], payload[f"{key}_sha256"])
    else:
        raise InvalidInput(f"the job names no input: give {key}_artifact_id or {key}_blob")
    try:
        arrays = npz_arrays(data)
        frames = np.asarray(arrays[key], np.float64)
        fps = float(arrays["fps"]) if "fps" in arrays else None
    except KeyError:
        raise InvalidInput(f"the input .npz has no '{key}' array") from None
    except (ValueError, OSError, EOFError) as error:
        raise InvalidInput(f"the input is not a readable .npz: {error}") from None
    if frames.ndim != 3 or frames.shape[-1] != 3 or len(frames) == 0:
        raise InvalidInput(f"{key} must be (F,N,3) with F >= 1, got {frames.shape}")
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise InvalidInput(f"the input's fps must be a positive number, got {fps}")
    return frames, fps


def read_registration(blobs: BlobStore, payload: Mapping[str, Any]) -> RigRegistration:
    """The input-rig registration the job was submitted with (its blob verified against
    ``registration_sha256``); InvalidInput if it is gone (the rig was uploaded again)."""
    try:
        data = blobs.read_bytes(payload["registration_blob"], payload["registration_sha256"])
    except KeyError as error:
        raise InvalidInput(f"the job names input rig {payload.get('rig')!r} but not its "
                           f"registration ({error.args[0]})") from None
    except NotFound:
        raise InvalidInput(f"the registration of input rig {payload.get('rig')!r} this job was "
                           "submitted with is gone (the rig was uploaded again); submit the "
                           "job again") from None
    return RigRegistration.load(data)
