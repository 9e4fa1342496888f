"""Clips: an actor's training and database captures."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from models_store.blobs import BlobStore
from models_store.errors import NotFound
from models_store.ids import new_id
from models_store.registry._common import (Data, actor_prefix, commit, get_row, owned, put_blob,
                                           scoped, storable)
from models_store.registry.actors import get_actor
from models_store.schema import Actor, Clip, utcnow


def add_clip(session: Session, blobs: BlobStore, actor_id: str, data: Data, *, frames: int,
             name: str | None = None, tenant: str | None = None) -> Clip:
    """Store a clip of ``frames`` frames for an actor (the caller validated the content)."""
    if frames < 1:
        raise ValueError(f"a clip has at least one frame, got {frames}")
    get_actor(session, actor_id, tenant=tenant)
    storable(name, "the clip name")
    clip_id = new_id("clip")
    info = put_blob(blobs, f"{actor_prefix(actor_id)}/clips/{clip_id}", data)
    clip = Clip(id=clip_id, actor_id=actor_id, name=name, frames=frames, blob=info.key,
                sha256=info.sha256, size_bytes=info.size, created_at=utcnow())
    session.add(clip)
    commit(session, blobs, new_keys=[info.key])
    return clip


def get_clip(session: Session, clip_id: str, actor_id: str | None = None, *,
             tenant: str | None = None) -> Clip:
    """The clip ``clip_id`` (of ``actor_id``, if given; of an actor of ``tenant``, if named)."""
    clip = owned(get_row(session, Clip, "clip", clip_id), "clip", actor_id)
    tenant = scoped(tenant)
    if tenant is not None and session.scalar(select(Actor.tenant)
                                             .where(Actor.id == clip.actor_id)) != tenant:
        raise NotFound("clip", clip_id)
    return clip


def list_clips(session: Session, actor_id: str, *, tenant: str | None = None) -> list[Clip]:
    """The actor's clips, oldest first (NotFound for an unknown actor)."""
    get_actor(session, actor_id, tenant=tenant)
    return list(session.scalars(select(Clip).where(Clip.actor_id == actor_id)
                                .order_by(Clip.created_at, Clip.id)))


def read_clip(session: Session, blobs: BlobStore, clip_id: str, *,
              tenant: str | None = None) -> bytes:
    """The stored clip's bytes, verified."""
    clip = get_clip(session, clip_id, tenant=tenant)
    return blobs.read_bytes(clip.blob, clip.sha256)


def delete_clip(session: Session, blobs: BlobStore, clip_id: str,
                actor_id: str | None = None, *, tenant: str | None = None) -> None:
    """Delete a clip and its blob."""
    clip = get_clip(session, clip_id, actor_id, tenant=tenant)
    session.delete(clip)
    commit(session, blobs, old_keys=[clip.blob])

