"""Workers: a Huey consumer running jobs on threads, plus the reaper.

``facesynth worker`` runs :func:`run_worker` on any machine that sees the deployment's
database, blob store and queue; ``facesynth serve`` runs one in-process with
:func:`start_embedded`. Besides running jobs, every worker

- on start, migrates the database (a worker may start before the API);
- runs :class:`Maintenance` rounds every ``maintenance_interval_seconds`` (at most a
  quarter lease): it reaps jobs whose lease expired (their worker died or hung):
  :func:`models_store.registry.reap_expired` requeues them (or fails them after
  ``job_max_retries`` retries) and resubmits the requeued ones; it resubmits queued jobs
  older than ``job_resubmit_seconds`` that have no message waiting in the queue (the API
  died between committing the job and enqueuing it, a message was lost or a queue
  flushed); and at start and every ``temporary_sweep_seconds`` it removes the temporaries
  that crashes left in the blob store (:meth:`models_store.blobs.BlobStore.sweep_temporaries`).

An API process without an embedded worker runs the same rounds on a thread
(:func:`start_maintenance`), so expired leases are reaped and lost messages resubmitted
even when no worker is alive.

Stopping (SIGINT/SIGTERM for ``facesynth worker``, :meth:`EmbeddedWorker.stop`) is
graceful: no new jobs are taken and running ones get ``grace_seconds`` to finish; after
that they give their job back at their next progress point (the lease is released, and a
reaper requeues the job for another worker — this counts as one of its retries). A second
signal skips the grace period.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from dataclasses import dataclass
from datetime import timedelta
from types import FrameType

from huey.consumer import Consumer, ConsumerStopped

from models_store import db, registry
from models_store.schema import utcnow
from service.config import Settings
from service.store.container import get_store
from service.jobs.queue import JobQueue, get_queue, submit
from service.jobs.queue_storage import worker_storage

log = logging.getLogger(__name__)

#: longest pause between polls of an empty (SQLite) queue, seconds
POLL_MAX_DELAY = 1.0
#: how long running jobs may take to finish when the worker stops, seconds
GRACE_SECONDS = 10.0
#: how long to wait, after the grace period, for jobs to give their job back, seconds
ABANDON_WAIT_SECONDS = 30.0


class _Consumer(Consumer):
    """Huey's consumer, without its signal handlers: :class:`Worker` owns shutdown (and
    may run off the main thread, where handlers cannot be installed)."""

    def _set_signal_handlers(self) -> None:
        pass


def reap_and_resubmit(settings: Settings) -> list[str]:
    """Reap jobs whose lease expired and resubmit the requeued ones; their ids."""
    with get_store(settings).sessions() as session:
        reaped = registry.reap_expired(session, settings.job_max_retries)
    for job_id in reaped.requeued:
        submit(settings, job_id)
    if reaped.requeued or reaped.failed or reaped.cancelled:
        log.warning("reaped jobs whose worker stopped: requeued %s, failed %s, cancelled %s",
                    reaped.requeued, reaped.failed, reaped.cancelled)
    return reaped.requeued


def resubmit_stale(settings: Settings, older_than: float | None = None) -> list[str]:
    """Resubmit queued jobs created more than ``older_than`` seconds ago (default
    ``settings.job_resubmit_seconds``) whose message is not waiting in the queue; their ids.

    A duplicate message is harmless (only one claim of a job can succeed), but checking
    the queue's pending messages keeps a long backlog from being enqueued again and again.
    """
    older_than = settings.job_resubmit_seconds if older_than is None else older_than
    cutoff = utcnow() - timedelta(seconds=older_than)
    with get_store(settings).sessions() as session:
        stale = [job.id for job in registry.list_jobs(session, status="queued")
                 if job.created_at < cutoff]
    if not stale:
        return []
    waiting = _pending_job_ids(settings)
    lost = [job_id for job_id in stale if job_id not in waiting]
    for job_id in lost:
        submit(settings, job_id)
    if lost:
        log.warning("resubmitted %d queued job(s) with no message in the queue: %s",
                    len(lost), lost)
    return lost


def _pending_job_ids(settings: Settings) -> set[str]:
    """Job ids of the ``run_job`` messages waiting in the queue or its schedule (a job
    waiting for others is requeued with a delayed message, :func:`service.jobs.runner._park`)."""
    ids: set[str] = set()
    huey = get_queue(settings).huey
    for task in [*huey.pending(), *huey.scheduled()]:
        if task.args:
            ids.add(str(task.args[0]))
    return ids


def sweep_temporaries(settings: Settings) -> list[str]:
    """Remove temporaries left in the blob store by crashes (see the module docstring)."""
    removed = get_store(settings).blobs.sweep_temporaries(settings.stale_temporary_seconds)
    if removed:
        log.warning("removed %d stale temporary file(s)/directory(ies) from the blob store: %s",
                    len(removed), removed)
    return removed


class Maintenance:
    """One process's maintenance rounds (see the module docstring); :meth:`round` never
    raises (the database may be briefly unreachable: the next round tries again)."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self.interval = min(settings.maintenance_interval_seconds,
                            max(0.2, settings.job_lease_seconds / 4))
        self._next_sweep = 0.0

    def round(self) -> None:
        if get_queue(self.settings).immediate:   # memory://: jobs run when submitted
            return
        _safely(reap_and_resubmit, self.settings)
        _safely(resubmit_stale, self.settings)
        if time.monotonic() >= self._next_sweep:
            _safely(sweep_temporaries, self.settings)
            self._next_sweep = time.monotonic() + self.settings.temporary_sweep_seconds

    def run(self, stop: threading.Event) -> None:
        """Rounds every :attr:`interval` seconds until ``stop`` is set."""
        while True:
            self.round()
            if stop.wait(self.interval):
                return


def _safely(function, settings: Settings) -> None:
    try:
        function(settings)
    except Exception:  # the database may be briefly unreachable: try again next round
        log.exception("%s failed", function.__name__)


@dataclass
class MaintenanceThread:
    """:class:`Maintenance` rounds on a daemon thread of this process."""

    thread: threading.Thread
    stop_event: threading.Event

    def stop(self, timeout: float | None = None) -> None:
        self.stop_event.set()
        self.thread.join(timeout)


def start_maintenance(settings: Settings) -> MaintenanceThread:
    """Run maintenance rounds on a daemon thread (an API process without workers)."""
    stop = threading.Event()
    thread = threading.Thread(target=Maintenance(settings).run, args=(stop,),
                              name="facesynth-maintenance", daemon=True)
    thread.start()
    return MaintenanceThread(thread, stop)


class Worker:
    """A job worker: ``workers`` consumer threads and the reaper (see the module docstring).

    The constructor prepares everything (migrations, queue) so configuration errors surface
    in the caller; :meth:`run` blocks until stopped.

    Parameters
    ----------
    settings : the deployment's settings
    workers : number of job threads (default ``settings.workers``)
    grace_seconds : how long running jobs may take to finish when stopping
    """

    def __init__(self, settings: Settings, workers: int | None = None, *,
                 grace_seconds: float = GRACE_SECONDS):
        self.settings = settings
        self.workers = workers or settings.workers
        if self.workers < 1:
            raise ValueError(f"a worker needs at least one thread, got {self.workers}")
        self.grace_seconds = grace_seconds
        worker_storage(settings)       # ValueError: an unsupported URL, or memory://
        self.queue: JobQueue = get_queue(settings)
        db.upgrade(settings.database_url_resolved)
        self.maintenance = Maintenance(settings)
        self.reap_interval = self.maintenance.interval
        self._hurry = threading.Event()  # a second stop request: skip the grace period

    def run(self, stop: threading.Event | None = None) -> None:
        """Run jobs until ``stop`` is set (or, on the main thread, SIGINT/SIGTERM)."""
        stop = stop or threading.Event()
        restore = self._install_signal_handlers(stop)
        self.queue.abandon.clear()
        consumer = _Consumer(self.queue.huey, workers=self.workers, periodic=False,
                             worker_type="thread", initial_delay=0.05, backoff=1.5,
                             max_delay=POLL_MAX_DELAY, check_worker_health=True)
        consumer.start()
        log.info("worker started: %d thread(s), queue %s, database %s", self.workers,
                 self.settings.queue_url or "sqlite", self.settings.database_url_resolved)
        health = time.monotonic()
        next_reap = 0.0
        try:
            while not stop.is_set():
                try:
                    health = consumer.loop(health)  # waits up to 0.1 s
                except ConsumerStopped:
                    break
                if time.monotonic() >= next_reap:
                    self.maintenance.round()
                    next_reap = time.monotonic() + self.reap_interval
        finally:
            self._shutdown(consumer)
            restore()

    def _shutdown(self, consumer: Consumer) -> None:
        """Stop taking jobs, give running ones the grace period, then make them give back."""
        consumer.stop_flag.set()
        threads = [thread for _, thread in consumer.worker_threads] + [consumer.scheduler]
        deadline = time.monotonic() + self.grace_seconds
        for thread in threads:
            while thread.is_alive() and time.monotonic() < deadline and not self._hurry.is_set():
                thread.join(0.1)
        if any(thread.is_alive() for thread in threads):
            log.warning("jobs still running after the grace period: releasing them")
            self.queue.abandon.set()
            for thread in threads:
                thread.join(ABANDON_WAIT_SECONDS)
        log.info("worker stopped")

    def _install_signal_handlers(self, stop: threading.Event):
        """On the main thread: SIGINT/SIGTERM stop gracefully, a second one hurries."""
        if threading.current_thread() is not threading.main_thread():
            return lambda: None

        def handle(signum: int, frame: FrameType | None) -> None:
            if stop.is_set():
                self._hurry.set()
            log.info("received %s: stopping", signal.Signals(signum).name)
            stop.set()

        previous = {sig: signal.signal(sig, handle) for sig in (signal.SIGINT, signal.SIGTERM)}
        return lambda: [signal.signal(sig, handler) for sig, handler in previous.items()]


def run_worker(settings: Settings, workers: int | None = None,
               stop: threading.Event | None = None, *,
               grace_seconds: float = GRACE_SECONDS) -> None:
    """Run a worker until ``stop`` is set or, on the main thread, SIGINT/SIGTERM arrives.

    Parameters
    ----------
    settings : the deployment's settings (database, blobs, queue, lease, retries)
    workers : number of job threads (default ``settings.workers``)
    stop : set it to stop the worker (from another thread)
    grace_seconds : how long running jobs may take to finish when stopping
    """
    Worker(settings, workers, grace_seconds=grace_seconds).run(stop)


@dataclass
class EmbeddedWorker:
    """A worker running on a background thread of this process (``facesynth serve``)."""

    thread: threading.Thread
    stop_event: threading.Event
    worker: Worker

    @property
    def running(self) -> bool:
        return self.thread.is_alive()

    def stop(self, timeout: float | None = None) -> None:
        """Stop taking jobs and wait (up to ``timeout`` s) for the worker to end."""
        self.stop_event.set()
        self.thread.join(timeout)


def start_embedded(settings: Settings, workers: int | None = None, *,
                   grace_seconds: float = GRACE_SECONDS) -> EmbeddedWorker:
    """Start a worker on a daemon thread; stop it with ``.stop()``.

    Configuration errors (a ``memory://`` queue, an unreachable database) raise here.
    """
    worker = Worker(settings, workers, grace_seconds=grace_seconds)
    stop = threading.Event()
    thread = threading.Thread(target=worker.run, args=(stop,), name="facesynth-worker",
                              daemon=True)
    thread.start()
    return EmbeddedWorker(thread, stop, worker)
