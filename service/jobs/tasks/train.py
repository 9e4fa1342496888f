"""The ``train`` job: fit a model of the actor to its clips and store it.

Payload ``{"model_id", "clip_ids": [...]}`` (as :func:`models_store.registry.create_model`
writes it); the model row names the kind and holds the parameters. Result ``{"model_id"}``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from models_store import registry
from service.store.actors import load_actor_data, load_clips
from service.jobs.running import RunningJob
from service.methods.inputs import InvalidInput
from service.methods.kinds import get_kind

# the job's progress: inputs, then the method's own progress, then storing the model
LOADED, TRAINED = 0.05, 0.95


def train(job: RunningJob) -> dict[str, Any]:
    """Train the job's model (``job.payload["model_id"]``) on its clips; mark it ready.

    A retry after a worker died between storing the model and finishing the job finds the
    model ready and succeeds without training again.
    """
    model_id, clip_ids = job.payload["model_id"], list(job.payload["clip_ids"])
    store = job.store
    with store.sessions() as session:
        model = registry.get_model(session, model_id)
        if model.status == "ready":
            return {"model_id": model_id}
        kind = get_kind(model.kind)
        try:
            params = kind.parse_params(model.params)
        except ValidationError as error:
            raise InvalidInput(f"invalid {kind.name} parameters: {error}") from None
        job.progress(0.0, "loading inputs")
        actor = load_actor_data(session, store.blobs, model.actor_id)
        clips = load_clips(session, store.blobs, clip_ids, actor)
    trained = kind.train(actor, clips, params, job.sub_progress(LOADED, TRAINED))
    del actor, clips
    job.progress(TRAINED, "storing the model")
    # a hidden temporary directory in the blob root: same filesystem, never a blob key
    with store.blobs.scratch_dir("train") as tmp:  # locked: never swept while in use
        path = Path(tmp) / "model"
        trained.save(path)
        with store.sessions() as session:
            registry.mark_model_ready(session, store.blobs, model_id, path,
                                      metrics=jsonable(trained.metrics))
    return {"model_id": model_id}


def jsonable(value: Any) -> Any:
    """``value`` with NumPy scalars and arrays turned into plain JSON values (NaN → None)."""

    def default(obj: Any) -> Any:
        if isinstance(obj, (np.generic, np.ndarray)):
            return obj.tolist()
        raise TypeError(f"{type(obj).__name__} is not JSON-serializable")

    text = json.dumps(value, default=default)
    return json.loads(text, parse_constant=lambda name: None)
