"""The metadata tables: actors, clips, input rigs, scans, models, jobs, artifacts.

SQLAlchemy 2.0 declarative mapping, portable between SQLite and PostgreSQL. Timestamps are
timezone-aware UTC datetimes in Python (:class:`UTCDateTime`); states are short strings
constrained by CHECK constraints (the allowed values are the ``*_STATUSES`` tuples below).
Blob columns hold :mod:`models_store.blobs` keys, each next to the blob's sha256.

The schema in the database is made by the Alembic migrations in
``models_store/migrations/versions`` (``models_store.db.upgrade``), never by
``create_all``; a test checks that the migrations and these classes agree.

Every actor, model and job has a ``tenant``; clips and input rigs belong to their actor's
tenant and artifacts to their job's (:mod:`models_store.registry` scopes every lookup by it).

A ready model is immutable: flushing any change to a model whose stored status is ``ready``
raises :class:`~models_store.errors.Conflict` (see :func:`_forbid_changes_to_ready_models`).
"""

from __future__ import annotations

from datetime import datetime, timezone
from typing import Any

from sqlalchemy import (JSON, BigInteger, Boolean, CheckConstraint, DateTime, Float, ForeignKey,
                        Index, Integer, MetaData, String, UniqueConstraint, event, inspect)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import TypeDecorator

from models_store.errors import Conflict

MODEL_STATUSES = ("training", "ready", "failed")
JOB_STATUSES = ("queued", "running", "succeeded", "failed", "cancelled")
#: Job states a job never leaves.
JOB_FINAL_STATUSES = ("succeeded", "failed", "cancelled")
RIG_STATUSES = ("registering", "ready", "failed")

ID = String(32)         # prefix + "_" + 26 characters (models_store.ids)
BLOB_KEY = String(512)  # models_store.blobs key
SHA256 = String(64)     # hex digest
NAME = String(200)
TENANT = String(64)     # models_store.ids.validate_tenant
#: the tenant of rows made before tenants existed, and of tokens that name none
DEFAULT_TENANT = "default"

NAMING_CONVENTION = {
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


def utcnow() -> datetime:
    """The current time, timezone-aware UTC."""
    return datetime.now(timezone.utc)


class UTCDateTime(TypeDecorator[datetime]):
    """A timezone-aware UTC timestamp on every backend.

    PostgreSQL stores ``timestamp with time zone``; SQLite, which has no time zones, stores
    the UTC wall time. Naive datetimes are refused on the way in (they are ambiguous), and
    values come back aware, in UTC.
    """

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None or value.utcoffset() is None:
            raise ValueError(f"naive datetime {value.isoformat()} given; timestamps must be "
                             "timezone-aware (use datetime.now(timezone.utc))")
        value = value.astimezone(timezone.utc)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            return value.replace(tzinfo=timezone.utc)
        return value.astimezone(timezone.utc)


def _one_of(column: str, values: tuple[str, ...]) -> str:
    """SQL for a CHECK constraint ``column IN (values)``."""
    return f"{column} IN ({', '.join(repr(v) for v in values)})"


class Base(DeclarativeBase):
    """Declarative base with a constraint naming convention (stable names in migrations)."""

    metadata = MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map = {datetime: UTCDateTime(), dict[str, Any]: JSON()}


class Actor(Base):
    """A person whose face the service learns; owns clips, input rigs and models."""

    __tablename__ = "actors"

    id: Mapped[str] = mapped_column(ID, primary_key=True)
    tenant: Mapped[str] = mapped_column(TENANT, default=DEFAULT_TENANT,
                                        server_default=DEFAULT_TENANT, index=True)
    name: Mapped[str] = mapped_column(NAME)
    #: free-form user metadata (the column is named ``metadata``)
    meta: Mapped[dict[str, Any]] = mapped_column("metadata", default=dict)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    # the high-resolution neutral mesh with its UV layout (.npz)
    neutral_blob: Mapped[str | None] = mapped_column(BLOB_KEY)
    neutral_sha256: Mapped[str | None] = mapped_column(SHA256)
    vertex_count: Mapped[int | None] = mapped_column(Integer)
    triangle_count: Mapped[int | None] = mapped_column(Integer)
    # the marker layout (JSON)
    markers_blob: Mapped[str | None] = mapped_column(BLOB_KEY)
    markers_sha256: Mapped[str | None] = mapped_column(SHA256)
    marker_count: Mapped[int | None] = mapped_column(Integer)


class Clip(Base):
    """A training or database clip of an actor: high-resolution frames with markers (.npz)."""

    __tablename__ = "clips"

    id: Mapped[str] = mapped_column(ID, primary_key=True)
    actor_id: Mapped[str] = mapped_column(ForeignKey("actors.id"), index=True)
    name: Mapped[str | None] = mapped_column(NAME)
    frames: Mapped[int] = mapped_column(Integer)
    blob: Mapped[str] = mapped_column(BLOB_KEY)
    sha256: Mapped[str] = mapped_column(SHA256)
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class InputRig(Base):
    """A low-resolution input topology of an actor, registered to the actor's neutral.

    ``name`` is the user's name for it (the ``{rig}`` of the API path), unique per actor.
    """

    __tablename__ = "input_rigs"
    __table_args__ = (
        UniqueConstraint("actor_id", "name"),
        CheckConstraint(_one_of("status", RIG_STATUSES), name="status"),
    )

    id: Mapped[str] = mapped_column(ID, primary_key=True)
    actor_id: Mapped[str] = mapped_column(ForeignKey("actors.id"), index=True)
    name: Mapped[str] = mapped_column(NAME)
    status: Mapped[str] = mapped_column(String(16), default="registering")
    mesh_blob: Mapped[str] = mapped_column(BLOB_KEY)
    mesh_sha256: Mapped[str] = mapped_column(SHA256)
    registration_blob: Mapped[str | None] = mapped_column(BLOB_KEY)
    registration_sha256: Mapped[str | None] = mapped_column(SHA256)
    error: Mapped[dict[str, Any] | None] = mapped_column()
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Scan(Base):
    """A facial scan of an actor stored as UV-space maps (one canonical NPZ blob).

    ``maps`` lists the arrays it holds (``albedo``, ``position`` and optionally
    ``specular``, ``normal``, ``mask``), all ``height`` × ``width``.
    """

    __tablename__ = "scans"

    id: Mapped[str] = mapped_column(ID, primary_key=True)
    actor_id: Mapped[str] = mapped_column(ForeignKey("actors.id"), index=True)
    name: Mapped[str | None] = mapped_column(NAME)
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    maps: Mapped[list[str]] = mapped_column(JSON, default=list)
    blob: Mapped[str] = mapped_column(BLOB_KEY)
    sha256: Mapped[str] = mapped_column(SHA256)
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Model(Base):
    """A trained (or training) model of an actor; its files are one blob directory."""

    __tablename__ = "models"
    __table_args__ = (CheckConstraint(_one_of("status", MODEL_STATUSES), name="status"),)

    id: Mapped[str] = mapped_column(ID, primary_key=True)
    tenant: Mapped[str] = mapped_column(TENANT, default=DEFAULT_TENANT,
                                        server_default=DEFAULT_TENANT, index=True)
    actor_id: Mapped[str] = mapped_column(ForeignKey("actors.id"), index=True)
    kind: Mapped[str] = mapped_column(String(32))
    status: Mapped[str] = mapped_column(String(16), default="training")
    params: Mapped[dict[str, Any]] = mapped_column(default=dict)
    metrics: Mapped[dict[str, Any] | None] = mapped_column()
    size_bytes: Mapped[int | None] = mapped_column(BigInteger)
    blob: Mapped[str | None] = mapped_column(BLOB_KEY)
    sha256: Mapped[str | None] = mapped_column(SHA256)
    #: ``{code, message}`` when failed
    error: Mapped[dict[str, Any] | None] = mapped_column()
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Job(Base):
    """A unit of long work (training, tracking, registration, synthesis).

    The row is the truth about the job for clients; a worker holds it through a lease
    (``worker``, ``lease_expires_at``) renewed by heartbeats. ``actor_id`` and ``model_id``
    are plain indexed columns, not foreign keys: a job's record outlives the deletion of its
    actor or model.
    """

    __tablename__ = "jobs"
    __table_args__ = (
        CheckConstraint(_one_of("status", JOB_STATUSES), name="status"),
        CheckConstraint("progress >= 0 AND progress <= 1", name="progress"),
        Index(None, "status", "created_at"),
    )

    id: Mapped[str] = mapped_column(ID, primary_key=True)
    tenant: Mapped[str] = mapped_column(TENANT, default=DEFAULT_TENANT,
                                        server_default=DEFAULT_TENANT, index=True)
    kind: Mapped[str] = mapped_column(String(32), index=True)
    actor_id: Mapped[str] = mapped_column(ID, index=True)
    model_id: Mapped[str | None] = mapped_column(ID, index=True)
    status: Mapped[str] = mapped_column(String(16), default="queued")
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    stage: Mapped[str] = mapped_column(NAME, default="")
    payload: Mapped[dict[str, Any]] = mapped_column(default=dict)
    result: Mapped[dict[str, Any] | None] = mapped_column()
    #: ``{code, message}`` when failed
    error: Mapped[dict[str, Any] | None] = mapped_column()
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    worker: Mapped[str | None] = mapped_column(NAME)
    lease_expires_at: Mapped[datetime | None] = mapped_column()
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column()
    finished_at: Mapped[datetime | None] = mapped_column()


class Artifact(Base):
    """A downloadable result of a job (one blob file)."""

    __tablename__ = "artifacts"

    id: Mapped[str] = mapped_column(ID, primary_key=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id"), index=True)
    media_type: Mapped[str] = mapped_column(NAME)
    filename: Mapped[str | None] = mapped_column(NAME)
    blob: Mapped[str] = mapped_column(BLOB_KEY)
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str] = mapped_column(SHA256)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


@event.listens_for(Model, "before_update")
def _forbid_changes_to_ready_models(mapper: Any, connection: Any, target: Model) -> None:
    """Refuse to flush any change to a model that is stored as ``ready``."""
    state = inspect(target)
    status = state.attrs.status.history
    stored = (status.deleted or status.unchanged or [None])[0]
    if stored != "ready":
        return
    changed = [attr.key for attr in mapper.column_attrs
               if state.attrs[attr.key].history.has_changes()]
    if changed:
        raise Conflict(f"model {target.id!r} is ready and immutable; refused to change "
                       f"{', '.join(sorted(changed))}")
