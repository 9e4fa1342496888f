"""Actors with their neutral mesh and marker layout."""

from __future__ import annotations

from typing import Any, Mapping, Sequence

from sqlalchemy import delete, select, update
from sqlalchemy.orm import Session

from models_store.blobs import BlobStore
from models_store.errors import Conflict, NotFound
from models_store.ids import new_id, new_token, validate_tenant
from models_store.registry._common import (TENANT_OWNER, Data, actor_prefix, commit, get_row,
                                           in_tenant, model_prefix, put_blob, refetch, scoped,
                                           storable)
from models_store.registry.paging import after_key
from models_store.registry.jobs import cancel_active_jobs
from models_store.schema import Actor, Clip, InputRig, Job, Model, Scan, utcnow

#: compare-and-swap attempts of one replacement before giving up with a Conflict
MAX_SWAP_ROUNDS = 100


def create_actor(session: Session, name: str, metadata: Mapping[str, Any] | None = None, *,
                 tenant: str | None = None) -> Actor:
    """Create an actor.

    Parameters
    ----------
    name : str              display name (1-200 characters)
    metadata : mapping      free-form JSON-serializable metadata
    tenant : str            the tenant it belongs to (:func:`models_store.ids.validate_tenant`;
                            default: the current request's, :data:`._common.TENANT_OWNER`)
    """
    if not name or len(name) > 200:
        raise ValueError(f"actor name must have 1 to 200 characters, got {len(name or '')}")
    tenant = TENANT_OWNER.get() if tenant is None else tenant
    actor = Actor(id=new_id("actor"), tenant=validate_tenant(tenant),
                  name=storable(name, "the actor name"),
                  meta=storable(dict(metadata or {}), "the actor metadata"), created_at=utcnow())
    session.add(actor)
    commit(session)
    return actor


def get_actor(session: Session, actor_id: str, *, tenant: str | None = None) -> Actor:
    """The actor ``actor_id`` (NotFound if unknown, or not of ``tenant`` when one is named)."""
    return in_tenant(get_row(session, Actor, "actor", actor_id), "actor", tenant)


def list_actors(session: Session, *, tenant: str | None = None,
                after: Sequence[str] | None = None, limit: int | None = None) -> list[Actor]:
    """All actors (of ``tenant``, if named), oldest first (a page of them with
    ``after``/``limit``: :func:`~models_store.registry.paging.after_key`)."""
    query = select(Actor).order_by(Actor.created_at, Actor.id)
    tenant = scoped(tenant)
    if tenant is not None:
        query = query.where(Actor.tenant == tenant)
    return list(session.scalars(after_key(query, Actor, after, limit)))


def delete_actor(session: Session, blobs: BlobStore, actor_id: str, *,
                 cascade: bool = False, tenant: str | None = None) -> None:
    """Delete an actor with its clips, input rigs, scans and their blobs.

    Its models are deleted too with ``cascade=True``; without it an actor that has models
    is a :class:`Conflict`. Queued or running jobs of the actor are cancelled (see
    :func:`request_cancel`); job records themselves are kept.
    """
    actor = get_actor(session, actor_id, tenant=tenant)
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
                vertex_count: int, triangle_count: int, tenant: str | None = None) -> Actor:
    """Store the actor's high-resolution neutral mesh (the caller validated and counted it).

    Concurrent replacements are safe: see :func:`_swap_blob` (the last commit wins, every
    replaced blob is deleted, none is left unreferenced).

    Raises
    ------
    NotFound   unknown actor
    Conflict   the actor has models (they were trained on the current neutral)
    """
    actor = get_actor(session, actor_id, tenant=tenant)
    _refuse_if_models(session, actor, "neutral")
    info = put_blob(blobs, f"{actor_prefix(actor_id)}/neutral-{new_token()}", data)
    return _swap_blob(session, blobs, actor_id, Actor.neutral_blob, info.key,
                      neutral_blob=info.key, neutral_sha256=info.sha256,
                      vertex_count=vertex_count, triangle_count=triangle_count)


def set_markers(session: Session, blobs: BlobStore, actor_id: str, data: Data, *,
                marker_count: int, tenant: str | None = None) -> Actor:
    """Store the actor's marker layout (JSON); raises as :func:`set_neutral`."""
    actor = get_actor(session, actor_id, tenant=tenant)
    _refuse_if_models(session, actor, "marker layout")
    info = put_blob(blobs, f"{actor_prefix(actor_id)}/markers-{new_token()}", data)
    return _swap_blob(session, blobs, actor_id, Actor.markers_blob, info.key,
                      markers_blob=info.key, markers_sha256=info.sha256,
                      marker_count=marker_count)


def _swap_blob(session: Session, blobs: BlobStore, actor_id: str, column: Any, new_key: str,
               **values: Any) -> Actor:
    """Point the actor's ``column`` at the just-written ``new_key`` by compare-and-swap,
    then delete exactly the blob it replaced.

    The UPDATE is conditional on ``column`` still holding the key read just before
    (``UPDATE … WHERE id = :actor AND column = :old``). When a concurrent replacement
    committed in between, no row changes; the current key is read again and the swap
    retried, so each writer deletes the blob *it* replaced and no blob is ever left
    unreferenced (issue 16: 24 concurrent PUTs used to leave 13 orphans). The new blob is
    deleted again if the actor vanished or the commit fails.
    """
    old = session.scalar(select(column).where(Actor.id == actor_id))
    for _ in range(MAX_SWAP_ROUNDS):
        same = column.is_(None) if old is None else column == old
        changed = session.execute(update(Actor).where(Actor.id == actor_id, same).values(**values)
                                  .execution_options(synchronize_session=False)).rowcount
        if changed == 1:
            commit(session, blobs, new_keys=[new_key], old_keys=[old])
            return refetch(session, Actor, actor_id)
        session.rollback()
        row = session.execute(select(Actor.id, column).where(Actor.id == actor_id)).first()
        if row is None:
            blobs.delete(new_key)
            raise NotFound("actor", actor_id, "it was deleted meanwhile")
        old = row[1]
    blobs.delete(new_key)
    raise Conflict(f"actor {actor_id!r} was changed concurrently {MAX_SWAP_ROUNDS} times; "
                   "try again")


def read_neutral(session: Session, blobs: BlobStore, actor_id: str, *,
                 tenant: str | None = None) -> bytes:
    """The stored neutral mesh's bytes, verified (NotFound if none was set)."""
    return _read_current(session, blobs, actor_id, "neutral_blob", "neutral_sha256", tenant,
                         NotFound("neutral", actor_id, "the actor has no neutral mesh yet"))


def read_markers(session: Session, blobs: BlobStore, actor_id: str, *,
                 tenant: str | None = None) -> bytes:
    """The stored marker layout's bytes, verified (NotFound if none was set)."""
    return _read_current(session, blobs, actor_id, "markers_blob", "markers_sha256", tenant,
                         NotFound("marker layout", actor_id, "the actor has no marker layout yet"))


def _read_current(session: Session, blobs: BlobStore, actor_id: str, key: str, sha256: str,
                  tenant: str | None, unset: NotFound) -> bytes:
    """The bytes of the blob the actor's ``key`` column names, verified (``unset`` if none).

    A concurrent replacement may commit between this read of the row and the read of the
    blob, and it deletes the blob it replaced (:func:`_swap_blob`): the row is then read
    again in a new transaction and the blob it names now is read (a marker layout's PUT
    answered 404 while a neutral was being replaced). Only a blob the row still names is
    missing for real.
    """
    actor = get_actor(session, actor_id, tenant=tenant)
    for _ in range(MAX_SWAP_ROUNDS):
        named = getattr(actor, key)
        if named is None:
            raise unset
        try:
            return blobs.read_bytes(named, getattr(actor, sha256))
        except NotFound:
            session.rollback()                      # the next read sees the latest commit
            actor = get_actor(session, actor_id, tenant=tenant)
            if getattr(actor, key) == named:
                raise
    raise Conflict(f"actor {actor_id!r} was changed concurrently {MAX_SWAP_ROUNDS} times; "
                   "try again")

