"""The ``transfer`` job: a source pose-space model's details carried to another actor
(bickel2008 §5.4, :func:`service.methods.pose_space.transfer.transfer`).

Payload ``{"model_id", "source_model_id", "landmarks": [[source_vertex, target_vertex], ...],
"params": {"pose_weights"?}}`` (as :func:`service.app.transfer.submit_transfer` writes it):
``model_id`` is the new model of the target actor (the job's actor), created ``training``
with the job; it becomes ``ready`` exactly as a trained model does
(:func:`models_store.registry.mark_model_ready`), so ``/synthesize`` drives it with the
target's own markers. Result ``{"model_id"}``.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field, ValidationError

from models_store import registry
from service.io.npz import npz_arrays
from service.jobs.running import RunningJob
from service.jobs.tasks.train import jsonable
from service.methods.inputs import InvalidInput
from service.methods.kinds import get_kind
from service.methods.params import MethodParams
from service.methods.pdm.base_surface import head_alignment, stability_weights
from service.methods.pose_space.model import PoseSpaceModel
from service.methods.pose_space.transfer import transfer as transfer_details
from service.store.actors import load_actor_data

#: the job kind
TRANSFER_JOB = "transfer"
#: model kinds whose details transfer
TRANSFER_KINDS = ("psd", "wpsd")
# the job's progress: inputs, then the transfer's own stages, then storing the model
LOADED, TRANSFERRED = 0.1, 0.9


class TransferParams(MethodParams):
    """Parameters of a detail transfer (bickel2008 §5.4) beyond the landmarks."""

    pose_weights: tuple[float, ...] | None = Field(
        default=None,
        description="Head-alignment weights of the target actor's markers, in layout order "
                    "(one per marker, >= 0): markers on rigid parts of the head (forehead, "
                    "nose bridge) get high weights, those on the jaw and lips low ones. "
                    "Default: the source model's own when the target is the source's actor; "
                    "else the stability weights of the target's clips' markers, as training "
                    "computes them (ma2008 §4.1); else 1 each.")


def clip_pose_weights(session, blobs, actor_id: str, actor) -> np.ndarray | None:
    """Stability weights (M,) of the actor's markers from all its clips, as pose-space
    training computes them (an unweighted head alignment, then each marker's RMS motion about
    it); None when the actor has no clips or its frames cannot be aligned."""
    rows = registry.list_clips(session, actor_id)
    if not rows:
        return None
    markers = np.concatenate([np.asarray(npz_arrays(registry.read_clip(session, blobs, row.id))
                                         ["markers"], np.float64) for row in rows])
    rest = actor.marker_positions()
    try:
        return stability_weights(head_alignment(markers, rest).remove(markers), rest)
    except InvalidInput:          # frames too occluded to align: fall back to uniform
        return None


def transfer(job: RunningJob) -> dict[str, Any]:
    """Transfer the payload's source model to the job's actor and mark the new model ready.

    A retry after the model was stored finds it ready and succeeds without redoing it.
    """
    payload = job.payload
    model_id, source_id = payload["model_id"], payload["source_model_id"]
    store = job.store
    try:
        params = TransferParams.model_validate(payload.get("params") or {})
    except ValidationError as error:
        raise InvalidInput(f"invalid transfer parameters: {error}") from None
    job.progress(0.0, "loading the source model and the target actor")
    with store.sessions() as session:
        model = registry.get_model(session, model_id)
        if model.status == "ready":
            return {"model_id": model_id}
        source = registry.get_model(session, source_id)
        if source.kind not in TRANSFER_KINDS:
            raise InvalidInput(f"model {source_id!r} is a {source.kind} model; details transfer "
                               f"from {' and '.join(TRANSFER_KINDS)} models")
        if source.status != "ready":
            raise InvalidInput(f"the source model {source_id!r} is {source.status}, not ready")
        kind = get_kind(source.kind)
        path = registry.model_dir(session, store.blobs, source_id)
        target = load_actor_data(session, store.blobs, model.actor_id)
    loaded = kind.load(path)
    if not isinstance(loaded, PoseSpaceModel):
        raise InvalidInput(f"model {source_id!r} did not load as a pose-space model")
    if params.pose_weights is not None:
        weights, origin = np.asarray(params.pose_weights, np.float64), "given"
    elif model.actor_id == source.actor_id and loaded.n_markers == target.n_markers:
        weights, origin = loaded.data.pose_weights, "source model"
    else:
        with store.sessions() as session:
            weights = clip_pose_weights(session, store.blobs, model.actor_id, target)
        origin = "uniform" if weights is None else "target clips"
    moved = transfer_details(loaded, target, np.asarray(payload["landmarks"], np.int64),
                             weights, job.sub_progress(LOADED, TRANSFERRED))
    del loaded, target
    job.progress(TRANSFERRED, "storing the model")
    moved.metrics["transfer"].update(source_model_id=source_id, source_actor_id=source.actor_id,
                                     pose_weights=origin)
    with tempfile.TemporaryDirectory(dir=store.blobs.root, prefix=".transfer-") as tmp:
        out = Path(tmp) / "model"
        moved.save(out)
        with store.sessions() as session:
            registry.mark_model_ready(session, store.blobs, model_id, out,
                                      metrics=jsonable(moved.metrics))
    return {"model_id": model_id}
