"""Running one job: claim, heartbeat, progress and cancellation, finish.

:func:`execute` is all a queue message leads to. It claims the job row for this worker
(nothing happens if another worker has it or it already ended), keeps the lease alive from
a heartbeat thread, hands the task function a :class:`RunningJob` whose ``progress``
callback records progress and stage and is where cancellation takes effect, and finishes
the row:

=====================================  ===============================================
the task …                             the job ends …
=====================================  ===============================================
returns a result dict                  ``succeeded`` with that ``result``, progress 1
reaches a progress point after         ``cancelled`` (a training job's model becomes
``DELETE /jobs/{id}``                  failed)
raises :class:`InvalidInput`           ``failed``, error ``{code: "invalid_input",
                                       message}`` — the user's input was the problem
raises ``NotFound``                    ``failed``, ``not_found`` (e.g. a clip deleted
                                       while queued)
raises ``OSError`` ENOSPC / EDQUOT     ``failed``, ``insufficient_storage`` (no server
                                       paths in the message)
raises ``OSError`` EROFS / EACCES      ``failed``, ``storage_unavailable``
raises anything else                   ``failed``, ``internal``, the exception's text
has a kind no task function runs       ``failed``, ``unsupported_job_kind``
=====================================  ===============================================

If the lease is lost (the worker stalled longer than ``job_lease_seconds`` and the job was
requeued for another worker, or reaped), the heartbeat or the next progress point notices
and the task is stopped quietly: the row now belongs to someone else.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable, Mapping

from models_store import registry
from models_store.errors import Conflict, NotFound
from service.config import Settings
from service.store.container import Store, get_store
from service.methods.inputs import InvalidInput
from service.jobs.running import (JobCancelled, LeaseLost, Requeue, RunningJob, Task,
                                  WorkerStopping)
from service.jobs.tasks import TASKS
from service.logs import job_id_var

log = logging.getLogger(__name__)

#: progress is written at most this often (seconds), and always when the stage changes
PROGRESS_INTERVAL = 0.5
#: heartbeats per lease period
HEARTBEATS_PER_LEASE = 3


class _Reporter:
    """The job's progress callback and lease keeper (thread-safe).

    ``__call__`` is the task's :data:`Progress`; :meth:`beat` renews the lease (heartbeat
    thread). Both note ``cancel_requested`` from the row they get back, and a lost lease.
    """

    def __init__(self, store: Store, job_id: str, worker: str, lease_seconds: float,
                 abandon: threading.Event | None):
        self.store, self.job_id, self.worker = store, job_id, worker
        self.lease_seconds = lease_seconds
        self.abandon = abandon
        self.cancel = threading.Event()
        self.lost = threading.Event()
        self._lock = threading.Lock()
        self._stage: str | None = None
        self._written = 0.0

    def __call__(self, fraction: float, stage: str) -> None:
        if self.lost.is_set():
            raise LeaseLost(self.job_id)
        if self.abandon is not None and self.abandon.is_set():
            raise WorkerStopping(self.job_id)
        fraction = min(max(float(fraction), 0.0), 1.0)
        with self._lock:
            now = time.monotonic()
            due = stage != self._stage or now - self._written >= PROGRESS_INTERVAL
            if due:
                self._stage, self._written = stage, now
        if due:
            self._write(lambda session: registry.update_job_progress(
                session, self.job_id, fraction, stage, worker=self.worker,
                lease_seconds=self.lease_seconds))
        if self.lost.is_set():
            raise LeaseLost(self.job_id)
        if self.cancel.is_set():
            raise JobCancelled(self.job_id)

    def beat(self) -> None:
        """Renew the lease (and learn of a cancellation)."""
        self._write(lambda session: registry.heartbeat(session, self.job_id, self.worker,
                                                       self.lease_seconds))

    def release(self) -> None:
        """Give the job back: let its lease expire now, so a reaper requeues it at once."""
        self._write(lambda session: registry.heartbeat(session, self.job_id, self.worker, 0.0))

    def _write(self, update: Callable[[Any], Any]) -> None:
        try:
            with self.store.sessions() as session:
                job = update(session)
        except Conflict as error:
            log.warning("job %s: %s; stopping", self.job_id, error)
            self.lost.set()
            return
        except Exception:  # a database hiccup: the next write or heartbeat tries again
            log.warning("job %s: could not record progress/heartbeat", self.job_id, exc_info=True)
            return
        if job.cancel_requested:
            self.cancel.set()


class _Heartbeat(threading.Thread):
    """Calls ``reporter.beat()`` every ``interval`` seconds until stopped or the lease is lost."""

    def __init__(self, reporter: _Reporter, interval: float):
        super().__init__(name=f"heartbeat-{reporter.job_id}", daemon=True)
        self.reporter, self.interval = reporter, interval
        self.stopped = threading.Event()

    def run(self) -> None:
        while not self.stopped.wait(self.interval) and not self.reporter.lost.is_set():
            self.reporter.beat()

    def stop(self) -> None:
        self.stopped.set()
        self.join()


def _error(code: str, message: str) -> dict[str, str]:
    return {"code": code, "message": message}


#: :func:`_run_task`'s outcome for a job to give back to the queue
_RELEASE = object()


def _run_task(running: RunningJob, tasks: Mapping[str, Task]) -> Any:
    """Run the job's task function and classify how it ended.

    Returns ``(status, result, error)`` to finish the job with, None when the job is no
    longer ours, or ``_RELEASE`` when the worker is stopping and gives it back.
    """
    task = tasks.get(running.kind)
    if task is None:
        return "failed", None, _error(
            "unsupported_job_kind", f"this worker cannot run {running.kind!r} jobs "
                                    f"(it runs {', '.join(sorted(tasks))})")
    try:
        return "succeeded", dict(task(running)), None
    except JobCancelled:
        return "cancelled", None, None
    except LeaseLost:
        log.warning("job %s: lease lost; another worker or the reaper has it", running.id)
        return None
    except WorkerStopping:
        log.warning("job %s: worker stopping; releasing the job for another worker", running.id)
        return _RELEASE
    except Requeue as requeue:
        return requeue
    except InvalidInput as exc:
        return "failed", None, _error("invalid_input", str(exc))
    except NotFound as exc:
        return "failed", None, _error("not_found", str(exc))
    except Exception as exc:
        from models_store.errors import storage_fault

        fault = storage_fault(exc)
        if fault is not None:   # a full or read-only disk: a clear code, no server paths
            code, reason = fault
            log.error("job %s failed: storage %s (%s)", running.id, code, reason)
            if code == "insufficient_storage":
                return "failed", None, _error(code, f"the server's storage is full ({reason}); "
                                              "the job can be submitted again once space is "
                                              "freed")
            return "failed", None, _error(code, f"the server's storage cannot be written "
                                          f"({reason}); the job can be submitted again once "
                                          "it is writable")
        log.exception("job %s failed", running.id)
        return "failed", None, _error("internal", f"{type(exc).__name__}: {exc}")


def _park(store: Store, job_id: str, worker: str, delay: float,
          schedule: Callable[[float], None] | None) -> None:
    """Queue a job that waits for others again and have its message sent in ``delay``
    seconds (:class:`~service.jobs.running.Requeue`) by ``schedule(delay)``; without one
    the maintenance rounds resubmit it (:func:`service.jobs.worker.resubmit_stale`)."""
    with store.sessions() as session:
        try:
            job = registry.park_job(session, job_id, worker=worker)
        except Conflict as exc:
            log.warning("job %s: not requeued: %s", job_id, exc)
            return None
    if job.status != "queued":
        log.info("job %s %s while waiting", job_id, job.status)
        return None
    if schedule is not None:
        schedule(delay)
    log.debug("job %s waits; requeued for %.1f s", job_id, delay)
    return None


def execute(settings: Settings, job_id: str, worker: str, *,
            abandon: threading.Event | None = None,
            schedule: Callable[[float], None] | None = None,
            enqueue: Callable[[str], None] | None = None) -> str | None:
    """Run job ``job_id`` as ``worker`` if it can be claimed.

    Parameters
    ----------
    settings : the deployment's settings (database, blobs, lease length, retries)
    job_id : the job to run (a queue message's payload)
    worker : this worker's unique name (``host:pid:thread``)
    abandon : when set (a worker shutting down), the job releases its lease at its next
              progress point instead of running on
    schedule : ``schedule(delay)`` sends this job's queue message again in ``delay``
               seconds (for a task that raises :class:`~service.jobs.running.Requeue`)
    enqueue : ``enqueue(job_id)`` sends another job's queue message (the task's
              :attr:`~service.jobs.running.RunningJob.enqueue`)

    Returns
    -------
    str | None   the job's final status, or None if it was not run (not claimable) or
                 stopped without finishing it (lease lost, abandoned)

    Raises
    ------
    Exception    only when the database cannot be reached to claim the job (the queue
                 retries the message); every failure of the job itself ends the job
    """
    token = job_id_var.set(job_id)                 # every log record of the job carries its id
    try:
        return _execute(settings, job_id, worker, abandon, schedule, enqueue)
    finally:
        job_id_var.reset(token)


def _execute(settings: Settings, job_id: str, worker: str,
             abandon: threading.Event | None,
             schedule: Callable[[float], None] | None = None,
             enqueue: Callable[[str], None] | None = None) -> str | None:

    store = get_store(settings)
    with store.sessions() as session:
        try:
            job = registry.claim_job(session, worker, lease_seconds=settings.job_lease_seconds,
                                     max_retries=settings.job_max_retries, job_id=job_id)
        except NotFound:
            log.warning("queue message for unknown job %r ignored", job_id)
            return None
        if job is None:
            log.debug("job %s is not claimable (taken, finished or cancelled)", job_id)
            return None
        log.info("job %s (%s) claimed by %s, attempt %d", job.id, job.kind, worker, job.attempts)
        reporter = _Reporter(store, job.id, worker, settings.job_lease_seconds, abandon)
        running = RunningJob(job.id, job.kind, job.actor_id, job.model_id, dict(job.payload),
                             job.attempts, store, reporter, enqueue)
    heartbeat = _Heartbeat(reporter, settings.job_lease_seconds / HEARTBEATS_PER_LEASE)
    heartbeat.start()
    try:
        outcome = _run_task(running, TASKS)
    finally:
        heartbeat.stop()
    if outcome is _RELEASE:
        reporter.release()
        return None
    if isinstance(outcome, Requeue):
        return _park(store, job_id, worker, outcome.delay, schedule)
    if outcome is None:
        return None
    status, result, error = outcome
    with store.sessions() as session:
        try:
            registry.finish_job(session, job_id, status, worker=worker, result=result, error=error)
        except Conflict as exc:
            log.warning("job %s: not finished as %s: %s", job_id, status, exc)
            return None
    log.info("job %s %s%s", job_id, status, f": {error['message']}" if error else "")
    return status
