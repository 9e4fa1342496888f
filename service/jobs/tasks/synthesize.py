"""The ``synthesize`` job: meshes and maps for a whole performance, stored as an artifact.

Payload::

    {"model_id": "mdl_…",
     "markers_artifact_id": "art_…"               # the input .npz with "markers" (F,M,3) …
       | "markers_blob": "<key>", "markers_sha256": "<hex>",   # … or a blob of the store
     "outputs": ["mesh", "displacement"],          # optional (API.md's outputs)
     "clamp": true,                                # optional: the extrapolation limit
     "format": "npz"}                              # optional: "npz" or "obj-exr-zip"

Result ``{"model_id", "artifact_ids": [one artifact]}``: for ``npz`` the arrays of API.md's
synthesize response (``vertices`` (F,n,3), ``faces``, the asked maps, ``clamped`` (F,)); for
``obj-exr-zip`` one OBJ per frame and mesh output and one EXR per frame and map
(:mod:`service.jobs.frame_zip`). Both are written chunk by chunk, so memory stays bounded
for any length.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from sqlalchemy.orm import Session

from models_store import registry
from models_store.blobs import BlobStore
from service.io.npz import npz_arrays
from service.jobs.frame_npz import FrameNpzWriter
from service.jobs.frame_zip import FrameZipWriter
from service.jobs.runner import RunningJob
from service.methods.inputs import InvalidInput
from service.methods.kinds import get_kind

#: frames synthesized (and progress points passed) per step
CHUNK_FRAMES = 16
DEFAULT_OUTPUTS = ("mesh", "displacement")
#: result format → (media type, file suffix)
FORMATS = {"npz": ("application/x-npz", "npz"), "obj-exr-zip": ("application/zip", "zip")}
# the job's progress: loading, then the frames, then storing the artifact
LOADED, SYNTHESIZED = 0.05, 0.95


def synthesize(job: RunningJob) -> dict[str, Any]:
    """Synthesize the payload's markers with the payload's model into one artifact."""
    payload = job.payload
    model_id = payload["model_id"]
    fmt = payload.get("format", "npz")
    if fmt not in FORMATS:
        raise InvalidInput(f"result format {fmt!r} is not supported; choose from {list(FORMATS)}")
    outputs = tuple(payload.get("outputs") or DEFAULT_OUTPUTS)
    clamp = bool(payload.get("clamp", True))
    store = job.store
    job.progress(0.0, "loading the model")
    with store.sessions() as session:
        model = registry.get_model(session, model_id)
        kind = get_kind(model.kind)
        if kind.input != "markers":
            raise InvalidInput(f"a {kind.name} model is driven by {kind.input}, not markers")
        if model.status != "ready":
            raise InvalidInput(f"model {model_id!r} is {model.status}, not ready")
        path = registry.model_dir(session, store.blobs, model_id)
        markers = read_markers(session, store.blobs, payload)
    trained = kind.load(path)
    frames = len(markers)
    media_type, suffix = FORMATS[fmt]
    with tempfile.TemporaryDirectory(dir=store.blobs.root, prefix=".synthesize-") as tmp:
        writer = (FrameNpzWriter(Path(tmp), frames) if fmt == "npz" else
                  FrameZipWriter(Path(tmp) / "result.zip", frames,
                                 getattr(trained, "uv", None), getattr(trained, "uv_faces", None)))
        for start in range(0, frames, CHUNK_FRAMES):
            job.progress(LOADED + (SYNTHESIZED - LOADED) * start / frames, "synthesizing")
            stop = min(start + CHUNK_FRAMES, frames)
            try:
                writer.write(start, trained.synthesize(markers[start:stop], outputs, clamp))
            except InvalidInput as error:
                raise InvalidInput(f"frames {start}-{stop - 1}: {error}") from None
        job.progress(SYNTHESIZED, "storing the result")
        result = writer.finish()
        with store.sessions() as session:
            artifact = registry.add_artifact(session, store.blobs, job.id, result,
                                             media_type=media_type,
                                             filename=f"{job.id}.{suffix}")
    return {"model_id": model_id, "artifact_ids": [artifact.id]}


def read_markers(session: Session, blobs: BlobStore, payload: Mapping[str, Any]) -> np.ndarray:
    """The payload's input markers (F,M,3) float64 (InvalidInput if absent or malformed)."""
    if payload.get("markers_artifact_id"):
        artifact, stream = registry.open_artifact(session, blobs, payload["markers_artifact_id"])
        with stream:
            data = stream.read()
    elif payload.get("markers_blob"):
        data = blobs.read_bytes(payload["markers_blob"], payload["markers_sha256"])
    else:
        raise InvalidInput("the job names no input: give markers_artifact_id or markers_blob")
    try:
        markers = np.asarray(npz_arrays(data)["markers"], np.float64)
    except KeyError:
        raise InvalidInput("the input .npz has no 'markers' array") from None
    except (ValueError, OSError, EOFError) as error:
        raise InvalidInput(f"the input is not a readable .npz: {error}") from None
    if markers.ndim != 3 or markers.shape[-1] != 3 or len(markers) == 0:
        raise InvalidInput(f"markers must be (F,M,3) with F >= 1, got {markers.shape}")
    return markers
