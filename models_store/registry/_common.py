"""Helpers shared by the registry modules: row lookup, blob puts, commits, error records."""

from __future__ import annotations

import contextlib
import os
from contextvars import ContextVar
from typing import Any, Iterable, Iterator, Mapping, TypeVar

from sqlalchemy import update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from models_store.blobs import BlobInfo, BlobStore, ScratchFile
from models_store.errors import Conflict, NotFound
from models_store.ids import is_valid_id
from models_store.schema import DEFAULT_TENANT, Base, Model

Row = TypeVar("Row", bound=Base)
#: blob content: bytes in memory, the path of a file to copy, or a
#: :class:`~models_store.blobs.ScratchFile` to move into place
Data = bytes | bytearray | memoryview | os.PathLike


def get_row(session: Session, row_type: type[Row], kind: str, row_id: str) -> Row:
    """The row of ``row_type`` with id ``row_id``, or :class:`NotFound`."""
    if not is_valid_id(kind, row_id):
        raise NotFound(kind, str(row_id), f"not a valid {kind} id")
    row = session.get(row_type, row_id, populate_existing=True)
    if row is None:
        raise NotFound(kind, row_id)
    return row


#: the tenant the current request acts for: every lookup and listing of the registry is
#: scoped to it (None, the default: every tenant — jobs, maintenance, admins). Set it for a
#: block with :func:`acting_for`; an explicit ``tenant=`` argument narrows further.
TENANT_SCOPE: ContextVar[str | None] = ContextVar("facesynth_tenant_scope", default=None)
#: the tenant that new actors of the current request belong to
TENANT_OWNER: ContextVar[str] = ContextVar("facesynth_tenant_owner", default=DEFAULT_TENANT)


@contextlib.contextmanager
def acting_for(owner: str, scope: str | None) -> Iterator[None]:
    """Within the block, new actors belong to ``owner`` and lookups see only ``scope``
    (None: every tenant, for an admin)."""
    tokens = TENANT_OWNER.set(owner), TENANT_SCOPE.set(scope)
    try:
        yield
    finally:
        TENANT_SCOPE.reset(tokens[1])
        TENANT_OWNER.reset(tokens[0])


def scoped(tenant: str | None) -> str | None:
    """The tenant a lookup is limited to: ``tenant`` if given, else :data:`TENANT_SCOPE`."""
    return tenant if tenant is not None else TENANT_SCOPE.get()


def in_tenant(row: Row, kind: str, tenant: str | None) -> Row:
    """``row`` if it belongs to ``tenant`` (default: :data:`TENANT_SCOPE`; None: any), else
    NotFound — the same NotFound as for an unknown id, so ids of other tenants reveal
    nothing."""
    tenant = scoped(tenant)
    if tenant is not None and row.tenant != tenant:  # type: ignore[attr-defined]
        raise NotFound(kind, row.id)  # type: ignore[attr-defined]
    return row


def owned(row: Row, kind: str, actor_id: str | None) -> Row:
    """``row`` if it belongs to ``actor_id`` (or no actor was named), else NotFound."""
    if actor_id is not None and row.actor_id != actor_id:  # type: ignore[attr-defined]
        raise NotFound(kind, row.id, f"it belongs to another actor than {actor_id!r}")  # type: ignore[attr-defined]
    return row


def put_blob(blobs: BlobStore, key: str, data: Data) -> BlobInfo:
    """Store bytes or a file's content under ``key`` (a :class:`ScratchFile` is moved)."""
    if isinstance(data, (bytes, bytearray, memoryview)):
        return blobs.put_bytes(key, bytes(data))
    return blobs.put_file(key, data, move=isinstance(data, ScratchFile))


def commit(session: Session, blobs: BlobStore | None = None, new_keys: Iterable[str] = (),
           old_keys: Iterable[str | None] = ()) -> None:
    """Commit; on failure roll back and delete the blobs written for this unit of work, on
    success delete the blobs it stopped referencing.

    An integrity violation at commit means a concurrent change got there first (a row
    added to an actor being deleted, a second rig of the same name): it becomes a Conflict.
    """
    try:
        try:
            session.commit()
        except IntegrityError as exc:
            raise Conflict(f"the change conflicts with a concurrent one: {exc.orig}") from exc
    except BaseException:
        session.rollback()
        for key in new_keys:
            blobs.delete(key)  # type: ignore[union-attr]
        raise
    for key in old_keys:
        if key:
            blobs.delete(key)  # type: ignore[union-attr]


def refetch(session: Session, row_type: type[Row], row_id: str) -> Row:
    """Reload a row after a bulk UPDATE (the identity map is refreshed)."""
    row = session.get(row_type, row_id, populate_existing=True)
    assert row is not None, f"{row_type.__name__} {row_id} vanished"
    return row


def storable(value: Any, what: str) -> Any:
    """``value`` if every string in it (dict keys included) is encodable as UTF-8 and free of
    NUL characters, else ValueError: a row holding one could be committed but never read
    back through the API (callers validate user input first; this is the last guard)."""
    if isinstance(value, str):
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:
            raise ValueError(f"{what} holds a lone surrogate; refused before writing") from None
        if "\x00" in value:
            raise ValueError(f"{what} holds a NUL character; refused before writing")
    elif isinstance(value, Mapping):
        for key, item in value.items():
            storable(str(key), what)
            storable(item, what)
    elif isinstance(value, (list, tuple)):
        for item in value:
            storable(item, what)
    return value


def error_record(code: str, message: str) -> dict[str, str]:
    """A job or model error, ``{code, message}``."""
    return {"code": code, "message": message}


def check_error(error: Mapping[str, Any]) -> dict[str, str]:
    """``error`` as a ``{code, message}`` record, or ValueError if it lacks either."""
    if not isinstance(error, Mapping) or not {"code", "message"} <= set(error):
        raise ValueError(f"an error must be a mapping with 'code' and 'message', got {error!r}")
    return {"code": str(error["code"]), "message": str(error["message"])}


def actor_prefix(actor_id: str) -> str:
    """Blob-key prefix of everything an actor owns but its models (deleted with the actor)."""
    return f"actors/{actor_id}"


def model_prefix(model_id: str) -> str:
    """Blob-key prefix of a model's directory (one per training attempt)."""
    return f"models/{model_id}"


def fail_training_model(session: Session, model_id: str | None,
                        error: Mapping[str, str]) -> bool:
    """Within the current transaction, mark ``model_id`` failed if it is still training."""
    if model_id is None:
        return False
    return session.execute(
        update(Model).where(Model.id == model_id, Model.status == "training")
        .values(status="failed", error=dict(error))
        .execution_options(synchronize_session=False)).rowcount == 1

