"""What each write route does, one function per operation, over the process's
:class:`~service.app.services.Services`: check the state, parse and validate the upload
(:mod:`service.app.uploads`), store it through :mod:`models_store.registry`, queue jobs.

These are plain (blocking) functions; the routers run them in the thread pool. Each opens
its own database sessions and raises errors by meaning (``NotFound``, ``Conflict``,
``InvalidInput``, ...), which each transport maps once (``service/api/errors.py``, ``service/grpc/server.py``).
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Sequence

import OpenEXR
import numpy as np
from pydantic import BaseModel
from sqlalchemy.orm import Session

from models_store import registry
from models_store.blobs import ScratchFile
from models_store.ids import new_token
from models_store.schema import Actor, Job
from service.app import schemas
from service.app import uploads
from service.app.input_rigs import REGISTER_JOB, LoadedRig, load_rig
from service.app.retiming import check_retime_kind, parse_retime_request, resolve_keyframes
from service.app.limits import RETRY_AFTER_SECONDS
from service.app.validation import check_text
from service.app.services import Services, Submit
from service.app.synthesis import (NPZ, Expected, SynthesisInput, Synthesizer,
                                   check_response_request, encode, negotiate, parse_job_input,
                                   parse_synthesis_request)
from service.io.atomic import sha256_file
from service.io.exr import read_exr, write_exr
from service.io.npz import NpzParts, npz_bytes
from service.jobs.formats import check_result_format
from service.errors import BlobCorrupt, Conflict, InvalidInput, NotFound, Unavailable
from service.methods.confidence import CONFIDENCE
from service.methods.kinds import get_kind
from service.methods.shape_space.temporal import retime_keyframes

log = logging.getLogger("facesynth.api")

#: job kinds the API creates (the training job kind is the registry's default, "train")
TRAIN_JOB = "train"
SYNTHESIS_JOB = "synthesize"
ACTIVE = ("queued", "running")


# ---------------------------------------------------------------------------- jobs
def submit(session: Session, submit_job: Submit, job: Job) -> Job:
    """Hand a queued job to the task queue; if the queue cannot take it, cancel the job
    (and fail its training model) and answer 503 so the client retries."""
    try:
        submit_job(job.id)
    except Exception as error:  # noqa: BLE001 - any queue failure
        log.exception("could not submit job %s", job.id)
        registry.request_cancel(session, job.id)
        raise Unavailable(f"the job queue did not accept job {job.id} ({type(error).__name__}: "
                         f"{error}); it was cancelled, retry later",
                         retry_after=RETRY_AFTER_SECONDS) from error
    return job


# ---------------------------------------------------------------------------- actors
def _actor_with(session: Session, actor_id: str, *, neutral: bool = False,
                markers: bool = False, doing: str = "") -> Actor:
    """The actor, or Conflict if it lacks the neutral or marker layout ``doing`` needs."""
    actor = registry.get_actor(session, actor_id)
    if neutral and actor.neutral_blob is None:
        raise Conflict(f"actor {actor_id!r} has no neutral mesh yet; PUT "
                       f"/v1/actors/{actor_id}/neutral before {doing}")
    if markers and actor.markers_blob is None:
        raise Conflict(f"actor {actor_id!r} has no marker layout yet; PUT "
                       f"/v1/actors/{actor_id}/markers before {doing}")
    return actor


def delete_actor(services: Services, actor_id: str, cascade: bool) -> None:
    """Delete an actor (and with ``cascade`` its models, dropped from the cache too)."""
    with services.session() as session:
        models = [m.id for m in registry.list_models(session, actor_id)]
        registry.delete_actor(session, services.blobs, actor_id, cascade=cascade)
    for model_id in models:
        services.forget_model(model_id)


def put_neutral(services: Services, actor_id: str, kind: str,
                data: bytes | os.PathLike) -> schemas.NeutralInfo:
    """Validate and store an actor's neutral.

    Replacing a neutral that clips or a marker layout already refer to must keep its vertex
    and triangle counts (only positions may change); models forbid any replacement.
    """
    with services.session() as session:
        registry.get_actor(session, actor_id)
    upload, blob = uploads.parse_neutral(kind, data, services.settings)
    V, T = len(upload.mesh.vertices), len(upload.mesh.faces)
    with services.session() as session:
        actor = registry.get_actor(session, actor_id)
        has_clips = bool(registry.list_clips(session, actor_id))
        if (has_clips or actor.markers_blob) and (V, T) != (actor.vertex_count, actor.triangle_count):
            users = " and ".join(what for what, used in (("clips", has_clips),
                                                          ("a marker layout", actor.markers_blob))
                                 if used)
            raise Conflict(f"actor {actor_id!r} has {users} made for a neutral of "
                           f"{actor.vertex_count} vertices and {actor.triangle_count} triangles; "
                           f"the new one has {V} and {T}. Only the positions of a neutral with "
                           "clips or markers can change (create a new actor for a new topology)")
        registry.set_neutral(session, services.blobs, actor_id, blob, vertex_count=V,
                             triangle_count=T)
    return schemas.NeutralInfo(vertex_count=V, triangle_count=T,
                               uv_seams=upload.uv_seam_vertices,
                               polygons_split=upload.polygons_split,
                               regions=sorted(upload.regions))


def put_markers(services: Services, actor_id: str, data: bytes) -> schemas.MarkersInfo:
    """Resolve a marker layout onto the actor's neutral and store it (clips recorded with
    the current layout require the same marker count)."""
    with services.session() as session:
        actor = _actor_with(session, actor_id, neutral=True, doing="its marker layout")
        neutral = registry.read_neutral(session, services.blobs, actor_id)
    layout = uploads.parse_layout(data, neutral)
    with services.session() as session:
        actor = registry.get_actor(session, actor_id)
        if registry.list_clips(session, actor_id) and layout.marker_count != actor.marker_count:
            raise Conflict(f"actor {actor_id!r} has clips recorded with {actor.marker_count} "
                           f"markers; the new layout has {layout.marker_count}. Delete the clips "
                           "first, or keep the marker count")
        registry.set_markers(session, services.blobs, actor_id, layout.blob,
                             marker_count=layout.marker_count)
    return schemas.MarkersInfo(marker_count=layout.marker_count, snapped=layout.snapped,
                               max_snap_distance=layout.max_snap_distance,
                               renormalized=layout.renormalized)


# ---------------------------------------------------------------------------- clips
def add_clip(services: Services, actor_id: str, kind: str,
             data: bytes | os.PathLike | uploads.ClipForm, name: str | None) -> schemas.ClipAdded:
    """Validate a clip (NPZ bytes, the spool file of a large NPZ body, or a multipart
    :class:`~service.app.uploads.ClipForm`) against the actor's neutral and layout, and store
    it; the stored clip and the marker reader's notes.

    The canonical blob is written, a block of frames at a time as it is validated, into a
    scratch directory of the blob store and moved into place
    (:class:`~models_store.blobs.ScratchFile`): no array of the body is held whole in memory,
    and a failure at any point (a full disk: 507) leaves no blob (issue 16, defect 11).
    """
    if name is not None:
        check_text(name, "the clip name")
    with services.session() as session:
        actor = _actor_with(session, actor_id, neutral=True, markers=True, doing="adding clips")
        names = (uploads.layout_names(registry.read_markers(session, services.blobs, actor_id))
                 if isinstance(data, uploads.ClipForm) else None)
    with services.blobs.scratch_dir("clip") as scratch:
        target = scratch / "clip.npz"
        if isinstance(data, uploads.ClipForm):
            clip = uploads.parse_clip_form(data, services.settings, actor.vertex_count, names,
                                           target)
        else:
            clip = uploads.parse_clip_npz(data, services.settings, actor.vertex_count,
                                          actor.marker_count, target)
        with services.session() as session:
            row = registry.add_clip(session, services.blobs, actor_id, ScratchFile(target),
                                    frames=clip.frames, name=name)
            added = schemas.ClipAdded.model_validate(row)
    return added.model_copy(update={"notes": list(clip.notes)})


# ---------------------------------------------------------------------------- input rigs
def put_input_rig(services: Services, submit_job: Submit, actor_id: str, name: str, kind: str,
                  data: bytes | os.PathLike, landmarks: str | None) -> schemas.RigAccepted:
    """Store an input rig's mesh and queue its registration to the actor's neutral (a
    registration of the same rig still queued or running is cancelled first).

    The ``register`` job's payload is ``{"rig_id", "rig", "landmarks": [[rig_vertex,
    neutral_vertex], ...]}``.
    """
    with services.session() as session:
        actor = _actor_with(session, actor_id, neutral=True, doing="registering input rigs")
    upload, blob = uploads.parse_rig_mesh(kind, data, services.settings)
    pairs = uploads.parse_landmarks(landmarks, len(upload.mesh.vertices), actor.vertex_count)
    with services.session() as session:
        rig = registry.put_input_rig(session, services.blobs, actor_id, name, blob)
        for job in registry.list_jobs(session, actor_id=actor_id, kind=REGISTER_JOB):
            if job.status in ACTIVE and job.payload.get("rig_id") == rig.id:
                registry.request_cancel(session, job.id)
        job = registry.create_job(session, REGISTER_JOB, actor_id,
                                  payload={"rig_id": rig.id, "rig": name, "landmarks": pairs})
        submit(session, submit_job, job)
    return schemas.RigAccepted(rig_id=rig.id, name=name, job_id=job.id,
                               vertex_count=len(upload.mesh.vertices),
                               triangle_count=len(upload.mesh.faces), landmarks=len(pairs))


# ---------------------------------------------------------------------------- models
def create_model(services: Services, submit_job: Submit, actor_id: str, kind_name: str,
                 clip_ids: Sequence[str], params: BaseModel | dict[str, Any] | None
                 ) -> schemas.ModelAccepted:
    """Create a model of ``kind_name`` (validated parameters) and queue its training."""
    kind = get_kind(kind_name)
    parsed = kind.parse_params(params)
    with services.session() as session:
        _actor_with(session, actor_id, neutral=True, markers=True, doing="training models")
        model, job = registry.create_model(session, actor_id, kind.name,
                                           parsed.model_dump(mode="json"), clip_ids=clip_ids,
                                           job_kind=TRAIN_JOB)
        submit(session, submit_job, job)
    return schemas.ModelAccepted(model_id=model.id, job_id=job.id)


def delete_model(services: Services, model_id: str) -> None:
    """Delete a model (its running jobs are cancelled) and drop it from the cache."""
    with services.session() as session:
        registry.delete_model(session, services.blobs, model_id)
    services.forget_model(model_id)


def _ready_dir(services: Services, model_id: str) -> tuple[Path, dict]:
    """A ready model's directory and manifest (Conflict if not ready)."""
    with services.session() as session:
        row = registry.get_model(session, model_id)
    if row.status != "ready":
        raise Conflict(f"model {model_id!r} is {row.status}, not ready; its maps exist once "
                       "training succeeds")
    path = services.blobs.path(row.blob)
    try:
        manifest = json.loads((path / "manifest.json").read_bytes())
    except (OSError, ValueError):
        manifest = {}
    return path, manifest


def list_maps(services: Services, model_id: str) -> list[schemas.MapInfo]:
    """The UV-space maps (EXR files) of a ready model, read from their headers."""
    path, _ = _ready_dir(services, model_id)
    maps = []
    for file in sorted(path.glob("*.exr")):
        header = OpenEXR.File(str(file), header_only=True).header()
        (x0, y0), (x1, y1) = (tuple(map(int, corner)) for corner in header["dataWindow"])
        channels = sorted(channel.name for channel in header["channels"])
        maps.append(schemas.MapInfo(name=file.stem, channels=channels,
                                    width=x1 - x0 + 1, height=y1 - y0 + 1,
                                    size_bytes=file.stat().st_size,
                                    url=f"/v1/models/{model_id}/maps/{file.stem}.exr"))
    return maps


def map_file(services: Services, model_id: str, name: str) -> tuple[Path, str | None]:
    """The verified EXR file of map ``name`` of a ready model and its sha256 (checked
    against the model's manifest; None if the manifest does not list it)."""
    path, manifest = _ready_dir(services, model_id)
    file = path / f"{name}.exr" if uploads.is_safe_name(name) else None
    if file is None or not file.is_file():
        available = ", ".join(sorted(p.stem for p in path.glob("*.exr")))
        raise NotFound("map", name, f"model {model_id!r} has the maps {available}")
    digest = manifest.get("files", {}).get(file.name)
    if digest is not None and str(file) not in services.verified_blobs:
        actual = sha256_file(file)
        if actual != digest:
            raise BlobCorrupt(f"{model_id}/{file.name}", digest, actual)
        services.verified_blobs.add(str(file))
    return file, digest


def half_exr(file: Path) -> bytes:
    """An EXR file rewritten with 16-bit (half) float channels."""
    buffer = io.BytesIO()
    write_exr(buffer, read_exr(file), half=True)
    return buffer.getvalue()


# ---------------------------------------------------------------------------- synthesis
@dataclass(frozen=True)
class Synthesized:
    """A synthesis response: media type, body, frame count, and the per-frame confidence
    (:mod:`service.methods.confidence`) as the ``X-Facesynth-Confidence`` header's value
    (None: the model reports none)."""

    media_type: str
    body: bytes | memoryview | NpzParts      # NpzParts: an NPZ sent as its pieces
    frames: int
    confidence: str | None = None


#: response header of the per-frame confidence of a synchronous synthesis (API.md)
CONFIDENCE_HEADER = "X-Facesynth-Confidence"


def confidence_header(result: dict) -> str | None:
    """The per-frame ``confidence`` (F,) of a synthesis result as comma-separated values
    (4 decimals, frame order), or None when the result has none."""
    values = result.get(CONFIDENCE)
    if values is None:
        return None
    return ",".join(f"{float(v):.4f}" for v in np.asarray(values).ravel())


@dataclass(frozen=True)
class Topology:
    """A model's topology resource (``GET /v1/models/{id}/topology``): an NPZ of its
    ``faces`` (T,3) int32 and, where the model has them, ``uv`` (K,2) float64 and
    ``uv_faces`` (T,3) int32; its strong ETag is the sha256 of the arrays' names, dtypes,
    shapes and bytes (not of the zip, whose member timestamps vary), so it is the same for
    every request and server process while the model exists."""

    body: bytes
    etag: str

    @classmethod
    def of(cls, model: Any) -> "Topology":
        arrays = {"faces": np.asarray(model.faces, dtype=np.int32)}
        uv, uv_faces = getattr(model, "uv", None), getattr(model, "uv_faces", None)
        if uv is not None:
            arrays["uv"] = np.ascontiguousarray(uv)
            if uv_faces is not None:
                arrays["uv_faces"] = np.asarray(uv_faces, dtype=np.int32)
        digest = hashlib.sha256()
        for name, values in arrays.items():
            digest.update(f"{name}:{values.dtype.str}:{values.shape};".encode())
            digest.update(np.ascontiguousarray(values).tobytes())
        return cls(npz_bytes(**arrays), f'"{digest.hexdigest()}"')


def model_topology(services: Services, model_id: str) -> Topology:
    """The topology resource of a ready model, built once per loaded model (404 unknown,
    409 not ready)."""
    loaded = services.loaded_model(model_id)
    if loaded.topology is None:
        loaded.topology = Topology.of(loaded.model)
    return loaded.topology


def synthesize(services: Services, synthesizer: Synthesizer, model_id: str, kind: str,
               data: bytes, *, accept: str | None, outputs: tuple[str, ...] | None,
               clamp: bool, half: bool, route_input: str, rig: str | None = None,
               topology: bool = True) -> Synthesized:
    """Run a synchronous synthesis (``/synthesize`` for marker-driven, ``/enhance`` for
    mesh-driven kinds: ``route_input``) and encode the response ``accept`` asks for
    (``half``: maps in 16-bit floats, EXR and NPZ; ``topology=False``: an NPZ without
    ``faces``, which :func:`model_topology` serves once).

    With ``rig`` (``/enhance``), the frames are vertices (F,v,3) on that ready input rig of
    the model's actor, carried to the actor's topology by its registration first.
    """
    media = negotiate(accept)
    loaded = services.loaded_model(model_id)
    if loaded.kind.input != route_input:
        other = "synthesize" if loaded.kind.input == "markers" else "enhance"
        raise InvalidInput(f"a {loaded.kind.name} model takes {loaded.kind.input}: use "
                           f"POST /v1/models/{model_id}/{other}")
    # the actor's layout as of the load: it cannot change while the model exists
    expected = replace(Expected.of(loaded), reference=loaded.reference)
    loaded_rig = None
    if rig is not None:
        loaded_rig = load_rig(services, loaded.actor_id, rig, expected.count)
        expected = loaded_rig.expected(expected)
    request: SynthesisInput = parse_synthesis_request(kind, data, expected, services.settings,
                                                      outputs, clamp)
    if loaded_rig is not None:
        request = replace(request, frames=loaded_rig.propagate(request.frames))
    check_response_request(media, request)
    result = synthesizer.run(loaded, request, half=half and media == NPZ)
    return Synthesized(media, encode(media, result, loaded, request, half, topology),
                       len(request.frames), confidence_header(result))


def submit_synthesis_job(services: Services, submit_job: Submit, model_id: str, kind: str,
                         data: bytes, filename: str | None, *, outputs: tuple[str, ...],
                         result_format: str, clamp: bool, rig: str | None = None,
                         marker_filter_frames: float | str = 0.0) -> Job:
    """Store a performance and queue a ``synthesize`` job for it.

    The job's payload is ``{"model_id", "markers_blob", "markers_sha256", "frames",
    "outputs", "format", "clamp"}`` (``vertices_blob``, ``vertices_sha256`` for mesh-driven
    kinds; :mod:`service.jobs.tasks.synthesize`); the input blob is a canonical NPZ
    (``markers`` (F,M,3) float32 or ``vertices`` (F,V,3) float32, optional ``fps``) under the
    model's blob prefix, so deleting the model removes it. With ``rig`` (mesh-driven kinds)
    the vertices are on that ready input rig's topology, stored as given; the payload adds
    ``{"rig_id", "rig", "registration_blob", "registration_sha256"}`` and the job
    propagates the frames with exactly that registration. ``marker_filter_frames`` > 0 (σ in
    frames) or ``"auto"`` (marker-driven kinds only) adds ``"marker_filter_frames"``: the job
    smooths the markers in time first (:func:`service.geometry.marker_filter.filter_performance`).
    """
    check_result_format(result_format, outputs)
    with services.session() as session:
        model = registry.get_model(session, model_id)
        if model.status != "ready":
            raise Conflict(f"model {model_id!r} is {model.status}, not ready; submit synthesis "
                           "jobs once its training succeeds")
        actor = registry.get_actor(session, model.actor_id)
        names = (uploads.layout_names(registry.read_markers(session, services.blobs, actor.id))
                 if actor.markers_blob else None)
    kind_info = get_kind(model.kind)
    key = "markers" if kind_info.input == "markers" else "vertices"
    expected = Expected(model_id, model.kind, key,
                        actor.marker_count if key == "markers" else actor.vertex_count,
                        reference=services.marker_reference(model.actor_id))
    loaded_rig: LoadedRig | None = None
    if rig is not None:
        if key != "vertices":
            raise InvalidInput(f"rig applies to mesh-driven kinds; a {model.kind} model takes "
                               "markers")
        loaded_rig = load_rig(services, model.actor_id, rig, actor.vertex_count)
        expected = loaded_rig.expected(expected)
    if marker_filter_frames and key != "markers":
        raise InvalidInput(f"marker_filter_frames applies to marker-driven kinds; a {model.kind} "
                           "model takes meshes")
    blob, frames = parse_job_input(kind, data, expected, services.settings, names, filename)
    info = services.blobs.put_bytes(f"models/{model_id}/inputs/{new_token()}.npz", blob)
    try:
        with services.session() as session:
            job = registry.create_job(
                session, SYNTHESIS_JOB, model.actor_id, model_id=model_id,
                payload={"model_id": model_id, f"{key}_blob": info.key,
                         f"{key}_sha256": info.sha256, "frames": frames,
                         "outputs": list(outputs), "format": result_format, "clamp": clamp,
                         **({"marker_filter_frames": marker_filter_frames}
                            if marker_filter_frames else {}),
                         **(loaded_rig.payload() if loaded_rig is not None else {})})
            return submit(session, submit_job, job)
    except Exception:
        services.blobs.delete(info.key)
        raise


def retime(services: Services, synthesizer: Synthesizer, model_id: str, kind: str, data: bytes,
           *, length: int | None, extend: bool | None, rig: str | None) -> Synthesized:
    """Retime keyframes with a ready model of a retiming kind (``/retime``): the response
    NPZ of :func:`service.methods.shape_space.temporal.retime_keyframes` (``vertices`` (m,n,3) float32,
    ``timestamps`` (m,), ``faces``, per-segment diagnostics).

    ``kind`` is the body's media type: JSON (:class:`~service.app.schemas.RetimeBody`) or
    NPZ (``keyframes`` (K,v,3) with ``length``, ``extend``, ``rig`` from the query).
    """
    loaded = services.loaded_model(model_id)
    check_retime_kind(loaded)
    request = parse_retime_request(kind, data, services.settings, length=length, extend=extend,
                                   rig=rig)
    keyframes = resolve_keyframes(services, loaded, request)
    with synthesizer.slot(loaded.kind.name, request.length):
        result = retime_keyframes(loaded.model, keyframes, request.length, request.extend)
    return Synthesized(NPZ, npz_bytes(**result), request.length)


# ---------------------------------------------------------------------------- artifacts
def artifact_file(services: Services, artifact_id: str) -> tuple[Any, Path]:
    """An artifact's row and its file, verified against its sha256 once per process."""
    with services.session() as session:
        artifact = registry.get_artifact(session, artifact_id)
    if artifact.blob not in services.verified_blobs:
        services.blobs.open(artifact.blob, artifact.sha256).close()
        services.verified_blobs.add(artifact.blob)
    return artifact, services.blobs.path(artifact.blob)

