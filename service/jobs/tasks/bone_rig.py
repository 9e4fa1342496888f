"""The ``bone_rig`` job: a performance of an actor compressed to a linear-blend-skinned bone
rig (Le & Deng 2012, :func:`service.methods.bone_rig.decomposition.decompose`; the "Game
Rig" of the Digital Ira course), exported as NPZ and as a binary glTF 2.0 skin.

Payload ``{"clip_id"}`` (one of the actor's clips: its ``vertices`` (F,V,3)) or
``{"artifact_id"}`` (a synthesis job's ``.npz`` result: its ``vertices`` (F,V,3)), with
``"params"`` (:class:`~service.methods.bone_rig.params.BoneRigParams`) and optional
``"fps"`` (default: the clip's, else 30), as :func:`service.app.bone_rigs.submit_bone_rig`
writes it. The rest pose is the actor's neutral; its faces go into the glTF mesh.

Result ``{"artifact_ids": [the rig .npz, the .glb]}`` (layouts:
:mod:`service.methods.bone_rig.rig`, :func:`service.io.gltf.write_skinned_glb`) and the
rig's ``metrics`` (reconstruction RMS and max error in the actor's unit, bones kept,
iterations, seconds).
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from models_store import registry
from models_store.errors import NotFound
from service.jobs.formats import RESULT_FORMATS
from service.jobs.running import RunningJob
from service.jobs.tasks.train import jsonable
from service.methods.bone_rig.decomposition import decompose
from service.methods.bone_rig.params import BoneRigParams
from service.methods.inputs import InvalidInput
from service.store.actors import clip_from_blob, load_neutral_arrays, open_npz

#: the job kind
BONE_RIG_JOB = "bone_rig"
#: media types of the two artifacts
NPZ_MEDIA_TYPE, GLB_MEDIA_TYPE = RESULT_FORMATS["npz"][0], "model/gltf-binary"
USD_MEDIA_TYPE = RESULT_FORMATS["usd"][0]     # a binary USD crate
#: frame rate of a performance that states none
DEFAULT_FPS = 30.0
# the job's progress: inputs, then the decomposition, then writing the artifacts
LOADED, SOLVED = 0.05, 0.9


def bone_rig(job: RunningJob) -> dict[str, Any]:
    """Decompose the payload's performance into a bone rig; store its .npz and .glb."""
    payload = job.payload
    store = job.store
    with store.sessions() as session:
        done = registry.list_artifacts(session, job.id)
    formats = (("npz", NPZ_MEDIA_TYPE), ("glb", GLB_MEDIA_TYPE)) + (
        (("usd", USD_MEDIA_TYPE),) if payload.get("usd") else ())
    if len(done) == len(formats):               # a retry after every artifact was stored
        return {"artifact_ids": [a.id for a in done]}
    try:
        params = BoneRigParams.model_validate(payload.get("params") or {})
    except ValidationError as error:
        raise InvalidInput(f"invalid bone_rig parameters: {error}") from None
    job.progress(0.0, "loading the performance")
    with store.sessions() as session:
        neutral = load_neutral_arrays(session, store.blobs, job.actor_id, "the bone rig")
        frames, fps = read_performance(session, store.blobs, payload, job.actor_id)
    rest, faces = neutral["vertices"].astype(np.float64), neutral["faces"].astype(np.int64)
    if frames.shape[1:] != rest.shape:
        raise InvalidInput(f"the performance has {frames.shape[1]} vertices per frame; the "
                           f"actor's neutral has {len(rest)}")
    fps = float(payload.get("fps") or fps)
    rig = decompose(frames, rest, faces, params, fps, job.sub_progress(LOADED, SOLVED))
    del frames
    job.progress(SOLVED, "writing the rig")
    with tempfile.TemporaryDirectory(dir=store.blobs.root, prefix=".bone-rig-") as tmp:
        writers = {"npz": rig.save_npz, "glb": rig.write_glb, "usd": rig.write_usd}
        paths = []
        for suffix, media in formats:
            paths.append((Path(tmp) / f"rig.{suffix}", media, suffix))
            writers[suffix](paths[-1][0])
        with store.sessions() as session:
            ids = [registry.add_artifact(session, store.blobs, job.id, path, media_type=media,
                                         filename=f"{job.id}.{suffix}").id
                   for path, media, suffix in paths]
    metrics = {key: value for key, value in rig.metrics.items() if key != "params"}
    return {"artifact_ids": ids, "metrics": jsonable(metrics)}


def read_performance(session, blobs, payload, actor_id: str) -> tuple[np.ndarray, float]:
    """The payload's animation: vertices (F,V,3) float64 and its frame rate.

    Raises NotFound for a clip or artifact that is gone (or not the actor's), InvalidInput
    for one without usable ``vertices``.
    """
    if payload.get("clip_id"):
        clip_id = payload["clip_id"]
        row = registry.get_clip(session, clip_id, actor_id)
        clip = clip_from_blob(registry.read_clip(session, blobs, clip_id), row.name or row.id)
        return clip.vertices, clip.fps
    if payload.get("artifact_id"):
        artifact_id = payload["artifact_id"]
        artifact = registry.get_artifact(session, artifact_id)
        if registry.get_job(session, artifact.job_id).actor_id != actor_id:
            raise NotFound("artifact", artifact_id, f"it is not a result of a job of actor "
                                                    f"{actor_id!r}")
        artifact, stream = registry.open_artifact(session, blobs, artifact_id)
        with stream:
            arrays = open_npz(stream.read(), f"artifact {artifact_id!r}")
        if "vertices" not in arrays:
            raise InvalidInput(f"artifact {artifact_id!r} has no 'vertices' array (a synthesis "
                               f"job's .npz result has one); it holds {sorted(arrays)}")
        frames = np.asarray(arrays["vertices"], np.float64)
        fps = float(arrays["fps"]) if "fps" in arrays and np.size(arrays["fps"]) == 1 else DEFAULT_FPS
        return frames, fps
    raise InvalidInput("the job names no performance: give clip_id or artifact_id")
