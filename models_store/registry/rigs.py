"""Input rigs: an actor's low-resolution input topologies and their registration."""

from __future__ import annotations

from typing import Sequence

from sqlalchemy import select
from sqlalchemy.orm import Session

from models_store.blobs import BlobStore
from models_store.errors import Conflict, NotFound
from models_store.ids import new_id, new_token
from models_store.registry._common import (Data, actor_prefix, commit, get_row, error_record,
                                           put_blob)
from models_store.registry.paging import after_key
from models_store.registry.actors import get_actor
from models_store.schema import InputRig, utcnow


def _find(session: Session, actor_id: str, name: str) -> InputRig | None:
    """The actor's rig called ``name``, or None (NotFound for an unknown actor)."""
    get_actor(session, actor_id)
    return session.scalars(select(InputRig).where(InputRig.actor_id == actor_id,
                                                  InputRig.name == name)).one_or_none()


def put_input_rig(session: Session, blobs: BlobStore, actor_id: str, name: str,
                  data: Data) -> InputRig:
    """Create or replace the input rig ``name`` of an actor; its status becomes
    ``registering`` (a registration job then calls :func:`mark_rig_ready`)."""
    rig = _find(session, actor_id, name)
    rig_id = rig.id if rig is not None else new_id("rig")
    info = put_blob(blobs, f"{actor_prefix(actor_id)}/rigs/{rig_id}/mesh-{new_token()}", data)
    if rig is None:
        rig = InputRig(id=rig_id, actor_id=actor_id, name=name, created_at=utcnow())
        session.add(rig)
        old: list[str | None] = []
    else:
        old = [rig.mesh_blob, rig.registration_blob]
    rig.mesh_blob, rig.mesh_sha256, rig.status = info.key, info.sha256, "registering"
    rig.registration_blob = rig.registration_sha256 = rig.error = None
    commit(session, blobs, new_keys=[info.key], old_keys=old)
    return rig


def get_input_rig_by_id(session: Session, rig_id: str) -> InputRig:
    """The input rig with id ``rig_id`` (its row refreshed), or :class:`NotFound`."""
    return get_row(session, InputRig, "rig", rig_id)


def get_input_rig(session: Session, actor_id: str, name: str) -> InputRig:
    """The input rig ``name`` of an actor."""
    rig = _find(session, actor_id, name)
    if rig is None:
        raise NotFound("input rig", name, f"actor {actor_id!r} has no input rig of that name")
    return rig


def list_input_rigs(session: Session, actor_id: str, *, after: Sequence[str] | None = None,
                    limit: int | None = None) -> list[InputRig]:
    """The actor's input rigs, by name; a page of them with ``after``/``limit``
    (:func:`~models_store.registry.paging.after_key`)."""
    get_actor(session, actor_id)
    return list(session.scalars(after_key(select(InputRig).where(InputRig.actor_id == actor_id)
                                          .order_by(InputRig.name), InputRig, after, limit)))


def mark_rig_ready(session: Session, blobs: BlobStore, rig_id: str, data: Data) -> InputRig:
    """Store a rig's registration result and mark it ready (Conflict unless registering)."""
    rig = get_row(session, InputRig, "rig", rig_id)
    if rig.status != "registering":
        raise Conflict(f"input rig {rig_id!r} is {rig.status}, not registering")
    info = put_blob(blobs, f"{actor_prefix(rig.actor_id)}/rigs/{rig_id}/registration-{new_token()}",
                data)
    rig.registration_blob, rig.registration_sha256 = info.key, info.sha256
    rig.status = "ready"
    commit(session, blobs, new_keys=[info.key])
    return rig


def mark_rig_failed(session: Session, rig_id: str, code: str, message: str) -> InputRig:
    """Mark a rig's registration failed (Conflict unless registering)."""
    rig = get_row(session, InputRig, "rig", rig_id)
    if rig.status != "registering":
        raise Conflict(f"input rig {rig_id!r} is {rig.status}, not registering")
    rig.status, rig.error = "failed", error_record(code, message)
    commit(session)
    return rig

