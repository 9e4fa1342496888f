"""Input rigs: an actor's low-resolution input topologies and their registration."""

from __future__ import annotations

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from models_store.blobs import BlobStore
from models_store.errors import Conflict, NotFound
from models_store.ids import new_id, new_token
from models_store.registry._common import (Data, actor_prefix, commit, get_row, error_record,
                                           put_blob, refetch)
from models_store.registry.actors import MAX_SWAP_ROUNDS
from models_store.registry.actors import get_actor
from models_store.schema import InputRig, utcnow


def _find(session: Session, actor_id: str, name: str,
          tenant: str | None = None) -> InputRig | None:
    """The actor's rig called ``name``, or None (NotFound for an unknown actor)."""
    get_actor(session, actor_id, tenant=tenant)
    return session.scalars(select(InputRig).where(InputRig.actor_id == actor_id,
                                                  InputRig.name == name)).one_or_none()


def put_input_rig(session: Session, blobs: BlobStore, actor_id: str, name: str,
                  data: Data, *, tenant: str | None = None) -> InputRig:
    """Create or replace the input rig ``name`` of an actor; its status becomes
    ``registering`` (a registration job then calls :func:`mark_rig_ready`).

    A replacement is a compare-and-swap on the rig's mesh key (as
    :func:`models_store.registry.actors._swap_blob`): concurrent puts of one rig each delete
    exactly the mesh and registration they replaced, and leave no blob unreferenced.
    """
    rig = _find(session, actor_id, name, tenant)
    rig_id = rig.id if rig is not None else new_id("rig")
    info = put_blob(blobs, f"{actor_prefix(actor_id)}/rigs/{rig_id}/mesh-{new_token()}", data)
    if rig is None:
        rig = InputRig(id=rig_id, actor_id=actor_id, name=name, created_at=utcnow(),
                       mesh_blob=info.key, mesh_sha256=info.sha256, status="registering")
        session.add(rig)
        try:
            commit(session, blobs, new_keys=[info.key])
            return rig
        except Conflict:   # created concurrently under the same name (its blob is gone
            rig = _find(session, actor_id, name)    # with the failed commit): replace that rig
            if rig is None:
                raise
            info = put_blob(blobs, f"{actor_prefix(actor_id)}/rigs/{rig.id}/mesh-{new_token()}",
                            data)
    values = {"mesh_blob": info.key, "mesh_sha256": info.sha256, "status": "registering",
              "registration_blob": None, "registration_sha256": None, "error": None}
    for _ in range(MAX_SWAP_ROUNDS):
        old = [rig.mesh_blob, rig.registration_blob]
        changed = session.execute(
            update(InputRig).where(InputRig.id == rig.id, InputRig.mesh_blob == rig.mesh_blob)
            .values(**values).execution_options(synchronize_session=False)).rowcount
        if changed == 1:
            commit(session, blobs, new_keys=[info.key], old_keys=old)
            return refetch(session, InputRig, rig.id)
        session.rollback()
        rig = session.get(InputRig, rig.id, populate_existing=True)
        if rig is None:
            blobs.delete(info.key)
            raise NotFound("input rig", name, "it was deleted meanwhile")
    blobs.delete(info.key)
    raise Conflict(f"input rig {name!r} was changed concurrently {MAX_SWAP_ROUNDS} times; "
                   "try again")


def get_input_rig_by_id(session: Session, rig_id: str) -> InputRig:
    """The input rig with id ``rig_id`` (its row refreshed), or :class:`NotFound`."""
    return get_row(session, InputRig, "rig", rig_id)


def get_input_rig(session: Session, actor_id: str, name: str, *,
                  tenant: str | None = None) -> InputRig:
    """The input rig ``name`` of an actor."""
    rig = _find(session, actor_id, name, tenant)
    if rig is None:
        raise NotFound("input rig", name, f"actor {actor_id!r} has no input rig of that name")
    return rig


def list_input_rigs(session: Session, actor_id: str, *,
                    tenant: str | None = None) -> list[InputRig]:
    """The actor's input rigs, by name."""
    get_actor(session, actor_id, tenant=tenant)
    return list(session.scalars(select(InputRig).where(InputRig.actor_id == actor_id)
                                .order_by(InputRig.name)))


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

