"""Actors with their neutral mesh and marker layout."""

from __future__ import annotations

from typing import Any, Mapping

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from models_store.blobs import BlobStore
from models_store.errors import Conflict, NotFound
from models_store.ids import new_id, new_token
from models_store.registry._common import (Data, actor_prefix, commit, get_row, model_prefix,
                                           put_blob)
from models_store.registry.jobs import cancel_active_jobs
from models_store.schema import Actor, Clip, InputRig, Job, Model, Scan, utcnow


def create_actor(session: Session, name: str, metadata: Mapping[str, Any] | None = None) -> Actor:
    """Create an actor.

    Parameters
    ----------
    name : str              display name (1-200 characters)
    metadata : mapping      free-form JSON-serializable metadata
    """
    if not name or len(name) > 200:
        raise ValueError(f"actor name must have 1 to 200 characters, got {len(name or '')}")
    actor = Actor(id=new_id("actor"), name=name, meta=dict(metadata or {}), created_at=utcnow())
    session.add(actor)
    commit(session)
    return actor


def get_actor(session: Session, actor_id: str) -> Actor:
    """The actor ``actor_id`` (NotFound if unknown)."""
    return get_row(session, Actor, "actor", actor_id)


def list_actors(session: Session) -> list[Actor]:
    """All actors, oldest first."""
    return list(session.scalars(select(Actor).order_by(Actor.created_at, Actor.id)))


def delete_actor(session: Session, blobs: BlobStore, actor_id: str, *,
                 cascade: bool = False) -> None:
    """Delete an actor with its clips, input rigs, scans and their blobs.

    Its models are deleted too with ``cascade=True``; without it an actor that has models
    is a :class:`Conflict`. Queued or running jobs of the actor are cancelled (see
    :func:`request_cancel`); job records themselves are kept.
    """
    actor = get_actor(session, actor_id)
    models = list(session.scalars(select(Model).where(Model.actor_id == actor_id)))
    if models and not cascade:
        raise Conflict(f"actor {actor_id!r} has {len(models)} model(s) "
                       f"({', '.join(m.id for m in models)}); delete them first or cascade")
    cancel_active_jobs(session, Job.actor_id == actor_id, "its actor was deleted")
    for row_type in (Model, Clip, InputRig, Scan):  # children first: the foreign keys
        session.execute(delete(row_type).where(row_type.actor_id == actor_id)
                        .execution_options(synchronize_session=False))
    session.execute(delete(Actor).where(Actor.id == actor_id)
                    .execution_options(synchronize_session=False))
    for row in [actor, *models]:
        session.expunge(row)
    commit(session, blobs, old_keys=[actor_prefix(actor_id)]
           + [model_prefix(m.id) for m in models])


def _refuse_if_models(session: Session, actor: Actor, what: str) -> None:
    """Conflict if the actor has models: they were trained on its current neutral/markers."""
    ids = session.scalars(select(Model.id).where(Model.actor_id == actor.id)).all()
    if ids:
        raise Conflict(f"cannot replace the {what} of actor {actor.id!r}: its models "
                       f"{', '.join(ids)} depend on it; delete them first")


def set_neutral(session: Session, blobs: BlobStore, actor_id: str, data: Data, *,
                vertex_count: int, triangle_count: int) -> Actor:
    """Store the actor's high-resolution neutral mesh (the caller validated and counted it).

    Raises
    ------
    NotFound   unknown actor
    Conflict   the actor has models (they were trained on the current neutral)
    """
    actor = get_actor(session, actor_id)
    _refuse_if_models(session, actor, "neutral")
    info = put_blob(blobs, f"{actor_prefix(actor_id)}/neutral-{new_token()}", data)
    old = actor.neutral_blob
    actor.neutral_blob, actor.neutral_sha256 = info.key, info.sha256
    actor.vertex_count, actor.triangle_count = vertex_count, triangle_count
    commit(session, blobs, new_keys=[info.key], old_keys=[old])
    return actor


def set_markers(session: Session, blobs: BlobStore, actor_id: str, data: Data, *,
                marker_count: int) -> Actor:
    """Store the actor's marker layout (JSON); raises as :func:`set_neutral`."""
    actor = get_actor(session, actor_id)
    _refuse_if_models(session, actor, "marker layout")
    info = put_blob(blobs, f"{actor_prefix(actor_id)}/markers-{new_token()}", data)
    old = actor.markers_blob
    actor.markers_blob, actor.markers_sha256 = info.key, info.sha256
    actor.marker_count = marker_count
    commit(session, blobs, new_keys=[info.key], old_keys=[old])
    return actor


def read_neutral(session: Session, blobs: BlobStore, actor_id: str) -> bytes:
    """The stored neutral mesh's bytes, verified (NotFound if none was set)."""
    actor = get_actor(session, actor_id)
    if actor.neutral_blob is None:
        raise NotFound("neutral", actor_id, "the actor has no neutral mesh yet")
    return blobs.read_bytes(actor.neutral_blob, actor.neutral_sha256)  # type: ignore[arg-type]


def read_markers(session: Session, blobs: BlobStore, actor_id: str) -> bytes:
    """The stored marker layout's bytes, verified (NotFound if none was set)."""
    actor = get_actor(session, actor_id)
    if actor.markers_blob is None:
        raise NotFound("marker layout", actor_id, "the actor has no marker layout yet")
    return blobs.read_bytes(actor.markers_blob, actor.markers_sha256)  # type: ignore[arg-type]

