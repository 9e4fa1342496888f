"""Artifacts: the downloadable results of jobs."""

from __future__ import annotations

from typing import BinaryIO

from sqlalchemy import select
from sqlalchemy.orm import Session

from models_store.blobs import BlobStore
from models_store.errors import NotFound
from models_store.ids import new_id
from models_store.registry._common import Data, commit, get_row, put_blob, scoped
from models_store.registry.jobs import get_job
from models_store.schema import Artifact, Job, utcnow


def add_artifact(session: Session, blobs: BlobStore, job_id: str, data: Data, *,
                 media_type: str, filename: str | None = None) -> Artifact:
    """Store a result file of a job."""
    get_job(session, job_id)
    artifact_id = new_id("artifact")
    info = put_blob(blobs, f"artifacts/{job_id}/{artifact_id}", data)
    artifact = Artifact(id=artifact_id, job_id=job_id, media_type=media_type, filename=filename,
                        blob=info.key, size_bytes=info.size, sha256=info.sha256,
                        created_at=utcnow())
    session.add(artifact)
    commit(session, blobs, new_keys=[info.key])
    return artifact


def get_artifact(session: Session, artifact_id: str, *, tenant: str | None = None) -> Artifact:
    """The artifact ``artifact_id`` (of a job of ``tenant``, if named)."""
    artifact = get_row(session, Artifact, "artifact", artifact_id)
    tenant = scoped(tenant)
    if tenant is not None and session.scalar(select(Job.tenant)
                                             .where(Job.id == artifact.job_id)) != tenant:
        raise NotFound("artifact", artifact_id)
    return artifact


def list_artifacts(session: Session, job_id: str, *, tenant: str | None = None) -> list[Artifact]:
    """A job's artifacts, oldest first."""
    get_job(session, job_id, tenant=tenant)
    return list(session.scalars(select(Artifact).where(Artifact.job_id == job_id)
                                .order_by(Artifact.created_at, Artifact.id)))


def open_artifact(session: Session, blobs: BlobStore, artifact_id: str, *,
                  tenant: str | None = None) -> tuple[Artifact, BinaryIO]:
    """An artifact's row and its verified content as an open binary file."""
    artifact = get_artifact(session, artifact_id, tenant=tenant)
    return artifact, blobs.open(artifact.blob, artifact.sha256)

