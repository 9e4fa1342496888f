"""Jobs: creation, listing, and the lifecycle a worker drives (claim, progress, heartbeat,
finish) with the reaper that recovers jobs whose worker died. See :mod:`models_store.registry`
for the state machine."""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any, Mapping, Sequence

from sqlalchemy import ColumnElement, and_, case, or_, select, update
from sqlalchemy.orm import Session

from models_store.errors import Conflict, NotFound
from models_store.ids import is_valid_id, new_id
from models_store.registry._common import (check_error, commit, fail_training_model, get_row,
                                           error_record, in_tenant, owned, refetch, scoped)
from models_store.schema import DEFAULT_TENANT, JOB_FINAL_STATUSES, Actor, Job, Model, utcnow
from models_store.registry.paging import after_key

#: how often :func:`claim_job` retries when another claimer wins the candidate it picked
MAX_CLAIM_ROUNDS = 100


def new_job(kind: str, actor_id: str, model_id: str | None,
            payload: Mapping[str, Any] | None, *, tenant: str = DEFAULT_TENANT) -> Job:
    """A new queued job row (not yet added to a session)."""
    return Job(id=new_id("job"), tenant=tenant, kind=kind, actor_id=actor_id, model_id=model_id,
               status="queued", progress=0.0, stage="", payload=dict(payload or {}),
               attempts=0, cancel_requested=False, created_at=utcnow())


def create_job(session: Session, kind: str, actor_id: str, *, model_id: str | None = None,
               payload: Mapping[str, Any] | None = None, tenant: str | None = None) -> Job:
    """Create a queued job (NotFound for an unknown actor — or one not of ``tenant`` — or
    a model not the actor's). The job belongs to the actor's tenant.

    ``payload`` holds ids and parameters as JSON, never objects.
    """
    actor = in_tenant(get_row(session, Actor, "actor", actor_id), "actor", tenant)
    if model_id is not None:
        owned(get_row(session, Model, "model", model_id), "model", actor_id)
    job = new_job(kind, actor_id, model_id, payload, tenant=actor.tenant)
    session.add(job)
    commit(session)
    return job


def get_job(session: Session, job_id: str, *, tenant: str | None = None) -> Job:
    """The job ``job_id`` (of ``tenant``, if named)."""
    return in_tenant(get_row(session, Job, "job", job_id), "job", tenant)


def list_jobs(session: Session, *, status: str | None = None, actor_id: str | None = None,
              kind: str | None = None, model_id: str | None = None,
              tenant: str | None = None, after: Sequence[str] | None = None,
              limit: int | None = None) -> list[Job]:
    """Jobs, oldest first, filtered by any of status, actor, kind, model and tenant; a page
    of them with ``after``/``limit`` (:func:`~models_store.registry.paging.after_key`)."""
    query = select(Job).order_by(Job.created_at, Job.id)
    tenant = scoped(tenant)
    for column, value in ((Job.status, status), (Job.actor_id, actor_id), (Job.kind, kind),
                          (Job.model_id, model_id), (Job.tenant, tenant)):
        if value is not None:
            query = query.where(column == value)
    return list(session.scalars(after_key(query, Job, after, limit)))


def _held(job_id: str, worker: str | None) -> ColumnElement[bool]:
    """The job is running (and held by ``worker``, if given)."""
    condition = and_(Job.id == job_id, Job.status == "running")
    return and_(condition, Job.worker == worker) if worker is not None else condition


def _lost(session: Session, job_id: str, worker: str | None) -> Conflict:
    """The Conflict for an update to a job that is not running (under ``worker``)."""
    session.rollback()
    job = get_job(session, job_id)
    if job.status != "running":
        return Conflict(f"job {job_id!r} is {job.status}, not running")
    return Conflict(f"job {job_id!r} lease lost: it is now held by worker {job.worker!r}, "
                    f"not {worker!r}")


def _update_held(session: Session, job_id: str, worker: str | None, **values: Any) -> Job:
    """Apply ``values`` to a running job held by ``worker``; commit; Conflict if not held."""
    changed = session.execute(update(Job).where(_held(job_id, worker)).values(**values)
                              .execution_options(synchronize_session=False)).rowcount
    if changed != 1:
        raise _lost(session, job_id, worker)
    commit(session)
    return refetch(session, Job, job_id)


def update_job_progress(session: Session, job_id: str, progress: float,
                        stage: str | None = None, *, worker: str | None = None,
                        lease_seconds: float | None = None,
                        now: datetime | None = None) -> Job:
    """Record a running job's progress (0..1) and stage; optionally renew its lease.

    Returns the job, whose ``cancel_requested`` the worker checks at this progress point.

    Raises
    ------
    Conflict   the job is not running, or not held by ``worker``
    """
    if not 0.0 <= progress <= 1.0:
        raise ValueError(f"progress must be within [0, 1], got {progress}")
    values: dict[str, Any] = {"progress": float(progress)}
    if stage is not None:
        values["stage"] = stage[:200]
    if lease_seconds is not None:
        values["lease_expires_at"] = (now or utcnow()) + timedelta(seconds=lease_seconds)
    return _update_held(session, job_id, worker, **values)


def heartbeat(session: Session, job_id: str, worker: str, lease_seconds: float,
              now: datetime | None = None) -> Job:
    """Renew ``worker``'s lease on a running job for ``lease_seconds`` from ``now``.

    Returns the job (check ``cancel_requested``); Conflict if the lease was lost.
    """
    return _update_held(session, job_id, worker,
                        lease_expires_at=(now or utcnow()) + timedelta(seconds=lease_seconds))


def request_cancel(session: Session, job_id: str, *, tenant: str | None = None) -> Job:
    """Cancel a job: a queued job becomes ``cancelled`` at once, a running one is flagged
    and stops at its next progress point; a finished job is returned unchanged."""
    job = get_job(session, job_id, tenant=tenant)
    if job.status in JOB_FINAL_STATUSES:
        return job
    cancel_active_jobs(session, Job.id == job_id, "cancelled by request")
    commit(session)
    return refetch(session, Job, job_id)


def cancel_active_jobs(session: Session, where: ColumnElement[bool], reason: str) -> None:
    """Within the current transaction: cancel matching queued jobs (failing their training
    models) and flag matching running jobs for cancellation.

    One ``UPDATE`` decides per row from the status it finds, so a job that a worker parks
    (running → queued) or claims (queued → running) at the same moment is still either
    cancelled or flagged: a select followed by two updates let a job parked between them
    slip through unflagged (a tracking job then met its span jobs cancelled and failed).
    """
    now = utcnow()
    was_queued = Job.status == "queued"
    rows = session.execute(
        update(Job).where(where, Job.status.in_(("queued", "running")))
        .values(cancel_requested=True,
                status=case((was_queued, "cancelled"), else_=Job.status),
                finished_at=case((was_queued, now), else_=Job.finished_at))
        .returning(Job.status, Job.model_id)
        .execution_options(synchronize_session=False)).all()
    error = error_record("cancelled", reason)
    for status, model_id in rows:
        if status == "cancelled":
            fail_training_model(session, model_id, error)


def _claimable(now: datetime, max_retries: int) -> ColumnElement[bool]:
    """A job a worker may take: queued, or running with an expired lease and retries left."""
    return and_(Job.cancel_requested.is_(False),
                or_(Job.status == "queued",
                    and_(Job.status == "running", Job.lease_expires_at < now,
                         Job.attempts <= max_retries)))


def claim_job(session: Session, worker: str, *, lease_seconds: float, max_retries: int,
              job_id: str | None = None, kinds: Sequence[str] | None = None,
              now: datetime | None = None) -> Job | None:
    """Take a job for ``worker`` with a lease; at most one claimer can win a given job.

    Parameters
    ----------
    worker : str            the claiming worker's unique name (host:pid:thread, ...)
    lease_seconds : float   lease length; renew it with :func:`heartbeat`
    max_retries : int       a running job whose lease expired may be re-taken while its
                            ``attempts`` <= ``max_retries`` (a first run plus that many retries)
    job_id : str            claim this job (e.g. the one a queue message names); default:
                            the oldest claimable job (of ``kinds``, if given)
    now : datetime          the current time (for tests)

    Returns
    -------
    Job | None   the claimed job (status running, ``attempts`` incremented, progress reset),
                 or None when there is nothing to claim

    Notes
    -----
    The claim is one ``UPDATE … WHERE id = :candidate AND <claimable>``: concurrent
    claimers that picked the same candidate serialize on the row (PostgreSQL) or the
    database write lock (SQLite) and the losers update no row. On PostgreSQL candidates
    are selected ``FOR UPDATE SKIP LOCKED``, so claimers do not queue up on one row.
    """
    now = now or utcnow()
    if job_id is not None and not is_valid_id("job", job_id):
        raise NotFound("job", str(job_id), "not a valid job id")
    eligible = _claimable(now, max_retries)
    candidates = select(Job.id).where(eligible)
    if job_id is not None:
        candidates = candidates.where(Job.id == job_id)
    if kinds is not None:
        candidates = candidates.where(Job.kind.in_(list(kinds)))
    candidates = (candidates.order_by(Job.created_at, Job.id).limit(1)
                  .with_for_update(skip_locked=True))
    for _ in range(MAX_CLAIM_ROUNDS):
        candidate = session.scalars(candidates).first()
        if candidate is None:
            session.commit()  # end the transaction without expiring the caller's rows
            return None
        changed = session.execute(
            update(Job).where(Job.id == candidate, eligible)
            .values(status="running", worker=worker, attempts=Job.attempts + 1,
                    lease_expires_at=now + timedelta(seconds=lease_seconds), started_at=now,
                    progress=0.0, stage="", finished_at=None)
            .execution_options(synchronize_session=False)).rowcount
        if changed == 1:
            commit(session)
            return refetch(session, Job, candidate)
        session.commit()  # another claimer won this one (nothing changed); look again
    raise Conflict(f"could not claim a job in {MAX_CLAIM_ROUNDS} rounds of contention")


def finish_job(session: Session, job_id: str, status: str, *, worker: str | None = None,
               result: Mapping[str, Any] | None = None,
               error: Mapping[str, Any] | None = None, now: datetime | None = None) -> Job:
    """End a running job as ``succeeded``, ``failed`` (``error`` ``{code, message}``
    required) or ``cancelled``. A training job that fails or is cancelled fails its model.

    Raises
    ------
    Conflict   the job is not running, or not held by ``worker``
    """
    if status not in JOB_FINAL_STATUSES:
        raise ValueError(f"a job finishes as one of {JOB_FINAL_STATUSES}, not {status!r}")
    if status == "failed" and error is None:
        raise ValueError("a failed job needs an error {code, message}")
    if status == "cancelled" and error is None:
        error = error_record("cancelled", "cancelled by request")
    values: dict[str, Any] = {
        "status": status, "finished_at": now or utcnow(), "lease_expires_at": None,
        "result": dict(result) if result is not None else None,
        "error": check_error(error) if error is not None and status != "succeeded" else None,
    }
    if status == "succeeded":
        values["progress"] = 1.0
    changed = session.execute(update(Job).where(_held(job_id, worker)).values(**values)
                              .execution_options(synchronize_session=False)).rowcount
    if changed != 1:
        raise _lost(session, job_id, worker)
    if status != "succeeded":
        model_id = session.scalar(select(Job.model_id).where(Job.id == job_id))
        fail_training_model(session, model_id, values["error"])
    commit(session)
    return refetch(session, Job, job_id)


def park_job(session: Session, job_id: str, *, worker: str) -> Job:
    """Give a running job back to the queue without counting an attempt: ``queued`` again,
    its lease dropped, ``attempts`` one less, progress and stage kept.

    For a job that waits for others (a tracking job joining its span jobs): rather than
    hold a worker slot while it waits, its task ends the current run and the job is queued
    again (with a delayed queue message, :class:`service.jobs.running.Requeue`); the next
    claim continues where it stopped. A cancellation requested meanwhile makes it
    ``cancelled`` at once.

    Raises
    ------
    Conflict   the job is not running, or not held by ``worker``
    """
    changed = session.execute(update(Job).where(_held(job_id, worker))
                              .values(status="queued", attempts=Job.attempts - 1, worker=None,
                                      lease_expires_at=None)
                              .execution_options(synchronize_session=False)).rowcount
    if changed != 1:
        raise _lost(session, job_id, worker)
    commit(session)
    # a cancellation flagged while it ran (before the update above) would leave a queued
    # job no worker may claim: end it now; one requested after it cancels the queued job
    session.execute(update(Job).where(Job.id == job_id, Job.status == "queued",
                                      Job.cancel_requested.is_(True))
                    .values(status="cancelled", finished_at=utcnow(),
                            error=error_record("cancelled", "cancelled by request"))
                    .execution_options(synchronize_session=False))
    commit(session)
    return refetch(session, Job, job_id)


@dataclass
class Reaped:
    """What :func:`reap_expired` did: ids of requeued, failed and cancelled jobs."""

    requeued: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    cancelled: list[str] = field(default_factory=list)


def reap_expired(session: Session, max_retries: int, now: datetime | None = None) -> Reaped:
    """Deal with running jobs whose lease expired (their worker died or hung).

    A job with ``attempts <= max_retries`` is requeued; beyond that it fails with code
    ``lease_expired``; one whose cancellation was requested becomes ``cancelled``. Each
    transition is conditional on the lease still being expired, so a heartbeat that
    arrives first wins.
    """
    now = now or utcnow()
    expired = and_(Job.status == "running", Job.lease_expires_at < now)
    rows = session.execute(select(Job.id, Job.attempts, Job.worker, Job.model_id,
                                  Job.cancel_requested).where(expired)
                           .order_by(Job.created_at)).all()
    reaped = Reaped()
    for job_id, attempts, worker, model_id, cancel in rows:
        error = None
        if cancel:
            values, bucket = {"status": "cancelled", "finished_at": now}, reaped.cancelled
            error = error_record("cancelled", "cancelled by request (worker stopped responding)")
        elif attempts <= max_retries:
            values, bucket = {"status": "queued"}, reaped.requeued
        else:
            error = error_record("lease_expired",
                                 f"worker {worker!r} stopped renewing its lease; gave up after "
                                 f"{attempts} attempt(s) (max_retries={max_retries})")
            values, bucket = {"status": "failed", "finished_at": now}, reaped.failed
        values.update(worker=None, lease_expires_at=None, error=error)
        changed = session.execute(update(Job).where(Job.id == job_id, expired).values(**values)
                                  .execution_options(synchronize_session=False)).rowcount
        if changed == 1:
            if error is not None:
                fail_training_model(session, model_id, error)
            commit(session)
            bucket.append(job_id)
        else:
            session.rollback()
    return reaped

