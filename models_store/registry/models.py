"""Models: created with their training job, marked ready (then immutable) or failed."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

from sqlalchemy import ColumnElement, and_, func, not_, select, update
from sqlalchemy.orm import Session

from models_store.blobs import BlobStore
from models_store.errors import Conflict
from models_store.ids import new_id, new_token
from models_store.registry._common import (commit, fail_training_model, get_row, error_record,
                                           in_tenant, model_prefix, owned, refetch, scoped)
from models_store.registry.paging import after_key
from models_store.registry.actors import get_actor
from models_store.registry.clips import get_clip
from models_store.registry.jobs import cancel_active_jobs, new_job
from models_store.schema import Job, Model, utcnow


def create_model(session: Session, actor_id: str, kind: str,
                 params: Mapping[str, Any] | None = None, *, clip_ids: Sequence[str] = (),
                 job_kind: str = "train", payload: Mapping[str, Any] | None = None,
                 tenant: str | None = None) -> tuple[Model, Job]:
    """Create a model in status ``training`` together with the queued job that makes it
    (a training job; or e.g. a transfer, ``job_kind="transfer"``).

    Both rows are committed at once, so a model never exists without the job that trains
    it. The job's payload is ``{"model_id", "clip_ids"}`` plus ``payload``.

    Raises
    ------
    NotFound   unknown actor (or not of ``tenant``), or a clip that is not the actor's

    The model and its job belong to the actor's tenant.
    """
    actor = get_actor(session, actor_id, tenant=tenant)
    clip_ids = list(clip_ids)
    for clip_id in clip_ids:
        get_clip(session, clip_id, actor_id)
    model = Model(id=new_id("model"), tenant=actor.tenant, actor_id=actor_id, kind=kind,
                  status="training", params=dict(params or {}), created_at=utcnow())
    job = new_job(job_kind, actor_id, model.id,
                  {"model_id": model.id, "clip_ids": clip_ids, **dict(payload or {})},
                  tenant=actor.tenant)
    session.add_all([model, job])
    commit(session)
    return model, job


def get_model(session: Session, model_id: str, actor_id: str | None = None, *,
              tenant: str | None = None) -> Model:
    """The model ``model_id`` (of ``actor_id``, if given; of ``tenant``, if named)."""
    model = in_tenant(get_row(session, Model, "model", model_id), "model", tenant)
    return owned(model, "model", actor_id)


def _status_is(status: str) -> ColumnElement[bool]:
    """The models of reported ``status``: a cancelled training is stored ``failed`` with the
    error code ``cancelled`` and reported ``cancelled``, not ``failed``."""
    cancelled = and_(Model.status == "failed",
                     func.coalesce(Model.error["code"].as_string(), "") == "cancelled")
    if status == "cancelled":
        return cancelled
    if status == "failed":
        return and_(Model.status == "failed", not_(cancelled))
    return Model.status == status


def list_models(session: Session, actor_id: str | None = None,
                status: str | None = None, *, tenant: str | None = None,
                after: Sequence[str] | None = None, limit: int | None = None) -> list[Model]:
    """Models, oldest first, optionally of one actor (NotFound if unknown), status or tenant;
    a page of them with ``after``/``limit`` (:func:`~models_store.registry.paging.after_key`)."""
    query = select(Model).order_by(Model.created_at, Model.id)
    tenant = scoped(tenant)
    if tenant is not None:
        query = query.where(Model.tenant == tenant)
    if actor_id is not None:
        get_actor(session, actor_id, tenant=tenant)
        query = query.where(Model.actor_id == actor_id)
    if status is not None:
        query = query.where(_status_is(status))
    return list(session.scalars(after_key(query, Model, after, limit)))


def mark_model_ready(session: Session, blobs: BlobStore, model_id: str, model_dir: Path, *,
                     metrics: Mapping[str, Any]) -> Model:
    """Store a trained model's directory and mark the model ready.

    A ready model is immutable: this raises :class:`Conflict` unless the model is
    ``training`` (so a second call, or a call after it failed, is refused), also when two
    workers race to finish it.
    """
    model = get_model(session, model_id)
    if model.status != "training":
        raise Conflict(f"model {model_id!r} is {model.status}, not training; "
                       "only a training model can become ready")
    info = blobs.put_dir(f"{model_prefix(model_id)}/{new_token()}", model_dir)
    changed = session.execute(
        update(Model).where(Model.id == model_id, Model.status == "training")
        .values(status="ready", metrics=dict(metrics), size_bytes=info.size, blob=info.key,
                sha256=info.sha256, error=None)
        .execution_options(synchronize_session=False)).rowcount
    if changed != 1:
        session.rollback()
        blobs.delete(info.key)
        raise Conflict(f"model {model_id!r} stopped training while its files were stored")
    commit(session, blobs, new_keys=[info.key])
    return refetch(session, Model, model_id)


def mark_model_failed(session: Session, model_id: str, code: str, message: str) -> Model:
    """Mark a training model failed with ``{code, message}`` (Conflict unless training)."""
    if not fail_training_model(session, model_id, error_record(code, message)):
        session.rollback()  # release the write lock the UPDATE took (SQLite)
        model = get_model(session, model_id)
        raise Conflict(f"model {model_id!r} is {model.status}, not training")
    commit(session)
    return refetch(session, Model, model_id)


def model_dir(session: Session, blobs: BlobStore, model_id: str, *,
              tenant: str | None = None, background: bool = False) -> Path:
    """The verified directory of a ready model (Conflict if it is not ready); with
    ``background``, being verified (:meth:`BlobStore.open_dir`)."""
    model = get_model(session, model_id, tenant=tenant)
    if model.status != "ready":
        raise Conflict(f"model {model_id!r} is {model.status}, not ready")
    return blobs.open_dir(model.blob, model.sha256, background)  # type: ignore[arg-type]


def delete_model(session: Session, blobs: BlobStore, model_id: str,
                 actor_id: str | None = None, *, tenant: str | None = None) -> None:
    """Delete a model and its files; its queued or running jobs are cancelled."""
    model = get_model(session, model_id, actor_id, tenant=tenant)
    cancel_active_jobs(session, Job.model_id == model_id, "its model was deleted")
    session.delete(model)
    commit(session, blobs, old_keys=[model_prefix(model_id)])

