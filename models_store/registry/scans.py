"""Scans: an actor's facial scans, stored as UV-space maps (one NPZ blob each)."""

from __future__ import annotations

from typing import Sequence

from sqlalchemy import select
from sqlalchemy.orm import Session

from models_store.blobs import BlobStore
from models_store.errors import NotFound
from models_store.ids import new_id
from models_store.registry.paging import after_key
from models_store.registry._common import (Data, actor_prefix, commit, get_row, owned, put_blob,
                                           scoped, storable)
from models_store.registry.actors import get_actor
from models_store.schema import Actor, Scan, utcnow


def add_scan(session: Session, blobs: BlobStore, actor_id: str, data: Data, *, width: int,
             height: int, maps: Sequence[str], name: str | None = None,
             tenant: str | None = None) -> Scan:
    """Store a scan of an actor (the caller validated the content): the blob goes under
    the actor's prefix, so deleting the actor removes it."""
    if width < 1 or height < 1 or not maps:
        raise ValueError(f"a scan has maps of at least 1×1 texel, got {width}×{height}, {maps}")
    get_actor(session, actor_id, tenant=tenant)
    storable(name, "the scan name")
    scan_id = new_id("scan")
    info = put_blob(blobs, f"{actor_prefix(actor_id)}/scans/{scan_id}", data)
    scan = Scan(id=scan_id, actor_id=actor_id, name=name, width=width, height=height,
                maps=sorted(maps), blob=info.key, sha256=info.sha256, size_bytes=info.size,
                created_at=utcnow())
    session.add(scan)
    commit(session, blobs, new_keys=[info.key])
    return scan


def get_scan(session: Session, scan_id: str, actor_id: str | None = None, *,
             tenant: str | None = None) -> Scan:
    """The scan ``scan_id`` (of ``actor_id``, if given; of an actor of ``tenant``, if named;
    NotFound otherwise)."""
    scan = get_row(session, Scan, "scan", scan_id)
    tenant = scoped(tenant)                # first: another tenant's scan is an unknown id
    if tenant is not None and session.scalar(select(Actor.tenant)
                                             .where(Actor.id == scan.actor_id)) != tenant:
        raise NotFound("scan", scan_id)
    return owned(scan, "scan", actor_id)


def list_scans(session: Session, actor_id: str, *, tenant: str | None = None,
               after: Sequence[str] | None = None, limit: int | None = None) -> list[Scan]:
    """The actor's scans, oldest first (NotFound for an unknown actor); a page of them with
    ``after``/``limit`` (:func:`~models_store.registry.paging.after_key`)."""
    get_actor(session, actor_id, tenant=tenant)
    return list(session.scalars(after_key(select(Scan).where(Scan.actor_id == actor_id)
                                          .order_by(Scan.created_at, Scan.id), Scan, after, limit)))


def read_scan(session: Session, blobs: BlobStore, scan_id: str, *,
              tenant: str | None = None) -> bytes:
    """The stored scan's NPZ bytes, verified against its sha256."""
    scan = get_scan(session, scan_id, tenant=tenant)
    return blobs.read_bytes(scan.blob, scan.sha256)


def delete_scan(session: Session, blobs: BlobStore, scan_id: str,
                actor_id: str | None = None, *, tenant: str | None = None) -> None:
    """Delete a scan and its blob (jobs already queued on it fail with a clear error)."""
    scan = get_scan(session, scan_id, actor_id, tenant=tenant)
    session.delete(scan)
    commit(session, blobs, old_keys=[scan.blob])
