"""What a task function sees of the job it runs: :class:`RunningJob` (ids, payload, store,
progress), the exceptions its progress points raise, and the worker's name.

Kept apart from :mod:`service.jobs.runner` (which claims, heartbeats and finishes jobs) so
that the task modules and the runner import it without importing each other.
"""

from __future__ import annotations

import os
import socket
import threading
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from service.methods.inputs import Progress
from service.store.container import Store


class JobCancelled(Exception):
    """Raised at a progress point of a job whose cancellation was requested."""


class LeaseLost(Exception):
    """The job is no longer this worker's (requeued, reaped or ended elsewhere)."""


class WorkerStopping(Exception):
    """The worker is shutting down and gives the job back at this progress point."""


class Requeue(Exception):
    """Raised by a task that waits for other jobs: end this run without finishing the job,
    queue it again (not counted as an attempt, :func:`models_store.registry.park_job`) and
    run it again in ``delay`` seconds — so a waiting job holds no worker slot."""

    def __init__(self, delay: float, reason: str = ""):
        super().__init__(reason or f"requeued for {delay} s")
        self.delay = float(delay)


@dataclass
class RunningJob:
    """What a task function gets: the claimed job's ids and payload, the store, progress.

    Attributes
    ----------
    id, kind, actor_id, model_id : the job row's
    payload : dict      the job's JSON payload (ids and parameters)
    attempt : int       1 for the first run, 2 for the first retry, ...
    store : Store       database sessions and blobs
    progress : Progress ``progress(fraction, stage)``; raises :class:`JobCancelled`
    enqueue : ``enqueue(job_id)`` tells the workers that another (queued) job is waiting —
              for a task that creates jobs (a tracking job's span jobs); None where the
              runner was called without a queue
    """

    id: str
    kind: str
    actor_id: str
    model_id: str | None
    payload: dict[str, Any]
    attempt: int
    store: Store
    progress: Progress = field(repr=False)
    enqueue: Callable[[str], None] | None = field(default=None, repr=False)

    def sub_progress(self, start: float, end: float) -> Progress:
        """A :data:`Progress` mapping 0..1 onto ``start..end`` of this job's progress."""
        return lambda fraction, stage: self.progress(start + (end - start) * fraction, stage)


#: a task function: takes the running job, returns the job's ``result``
Task = Callable[[RunningJob], Mapping[str, Any]]


def worker_name() -> str:
    """This thread's unique worker name, ``host:pid:thread``."""
    thread = threading.current_thread()
    return f"{socket.gethostname()}:{os.getpid()}:{thread.name}-{thread.ident}"
