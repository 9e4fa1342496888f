"""The task queue: a Huey instance per settings, its JSON serializer and the one task.

Storage is chosen by ``Settings.queue_url`` (its form read by
:func:`service.jobs.queue_storage.queue_storage`, which also probes it without Huey):

- ``None`` (default): :class:`huey.SqliteHuey` in ``<data_dir>/queue.db`` — one machine, the
  API and its workers share the file;
- ``redis://…`` / ``rediss://…`` / ``unix://…``: :class:`huey.RedisHuey`, for workers on
  many machines, keys ``huey.*.<queue_name>``;
- ``memory://``: immediate mode — :func:`submit` runs the job at once in the calling
  thread (unit tests of the API; no worker needed).

Messages carry a job id and nothing else, serialized as JSON (:class:`JsonSerializer`), never
pickled: a shared Redis must not be a way to run someone's bytes. The queue only says
"job <id> is waiting"; the job row is the truth, and :func:`service.jobs.runner.execute`
claims it before doing anything, so a duplicated message is a no-op and a lost one is
recovered by the worker (:mod:`service.jobs.worker`).
"""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from huey import Huey, MemoryHuey, RedisHuey, SqliteHuey
from huey.api import TaskWrapper
from huey.registry import Message
from huey.serializer import Serializer

from service.config import Settings
from service.jobs.queue_storage import queue_storage
from service.jobs.running import worker_name

log = logging.getLogger(__name__)

#: name of the one Huey task
RUN_JOB = "run_job"
#: Huey retries of a ``run_job`` message whose execution raised (the database was
#: unreachable when claiming); job failures themselves never raise
RUN_JOB_RETRIES = 3
RUN_JOB_RETRY_DELAY = 5.0  # seconds

# tags of the non-JSON values in a serialized message
_MESSAGE = "__huey_message__"
_DATETIME = "__datetime__"


class JsonSerializer(Serializer):
    """Huey serializer writing JSON instead of pickles.

    Handles what Huey stores — task messages (:class:`huey.registry.Message`, nested for
    pipelines), datetimes (ETAs, revocations), tuples (as lists) — and plain JSON values as
    task arguments. Anything else raises ``TypeError``: job payloads are ids.
    """

    def _serialize(self, data: Any) -> bytes:
        return json.dumps(_encode(data), separators=(",", ":"), allow_nan=False).encode()

    def _deserialize(self, data: bytes) -> Any:
        return _decode(json.loads(bytes(data)))


def _encode(value: Any) -> Any:
    if isinstance(value, Message):
        return {_MESSAGE: {name: _encode(getattr(value, name)) for name in Message._fields}}
    if isinstance(value, datetime):
        return {_DATETIME: value.isoformat()}
    if isinstance(value, (list, tuple)):
        return [_encode(v) for v in value]
    if isinstance(value, dict):
        if not all(isinstance(k, str) for k in value):
            raise TypeError(f"queue messages take dicts with string keys only, got {list(value)}")
        return {k: _encode(v) for k, v in value.items()}
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise TypeError(f"{type(value).__name__} cannot travel on the job queue (JSON only: "
                    "pass ids, not objects)")


def _decode(value: Any) -> Any:
    if isinstance(value, list):
        return [_decode(v) for v in value]
    if isinstance(value, dict):
        if set(value) == {_MESSAGE}:
            fields = {k: _decode(v) for k, v in value[_MESSAGE].items() if k in Message._fields}
            fields["args"] = tuple(fields.get("args") or ())
            return Message(**fields)
        if set(value) == {_DATETIME}:
            return datetime.fromisoformat(value[_DATETIME])
        return {k: _decode(v) for k, v in value.items()}
    return value


@dataclass
class JobQueue:
    """A Huey instance with its ``run_job`` task.

    Attributes
    ----------
    huey : Huey
    run_job : TaskWrapper    ``run_job(job_id)`` enqueues; a consumer runs
                             :func:`service.jobs.runner.execute`
    abandon : Event          set by a stopping worker whose grace period ran out: running
                             jobs then release their lease at their next progress point
    """

    huey: Huey
    run_job: TaskWrapper
    abandon: threading.Event = field(default_factory=threading.Event)

    @property
    def immediate(self) -> bool:
        """Whether jobs run at once in the submitting thread (``memory://``)."""
        return self.huey.immediate


def make_queue(settings: Settings) -> JobQueue:
    """A new :class:`JobQueue` for ``settings`` (see the module docstring for the storage)."""
    storage = queue_storage(settings)    # ValueError for an unsupported URL
    options: dict[str, Any] = {"results": False, "serializer": JsonSerializer(), "utc": True}
    if storage.kind == "sqlite":
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        huey: Huey = SqliteHuey(settings.queue_name, filename=storage.location, **options)
    elif storage.kind == "redis":
        huey = RedisHuey(settings.queue_name, url=storage.location, **options)
    else:
        huey = MemoryHuey(settings.queue_name, immediate=True, **options)
    queue = JobQueue(huey, None)  # type: ignore[arg-type]  # the task needs the queue

    def run_job(job_id: str) -> None:
        from service.jobs.runner import execute  # the runner imports the tasks and their deps

        def schedule(delay: float) -> None:      # a waiting job's next run (runner.Requeue)
            if queue.immediate:                  # no scheduler: what it waits for is done
                queue.run_job(job_id)
            else:
                queue.run_job.schedule(args=(job_id,), delay=delay)

        execute(settings, job_id, worker_name(), abandon=queue.abandon, schedule=schedule,
                enqueue=queue.run_job)

    queue.run_job = huey.task(name=RUN_JOB, retries=RUN_JOB_RETRIES,
                              retry_delay=RUN_JOB_RETRY_DELAY)(run_job)
    return queue


_queues: dict[tuple[Any, ...], JobQueue] = {}
_lock = threading.Lock()


def _queue_key(settings: Settings) -> tuple[Any, ...]:
    """What identifies a queue (and the settings its task runs jobs with)."""
    return (settings.queue_url, str(settings.data_dir.absolute()), settings.queue_name,
            settings.database_url_resolved, settings.job_lease_seconds, settings.job_max_retries)


def get_queue(settings: Settings) -> JobQueue:
    """The process-wide :class:`JobQueue` for ``settings`` (made on first use)."""
    key = _queue_key(settings)
    with _lock:
        queue = _queues.get(key)
        if queue is None:
            queue = _queues[key] = make_queue(settings)
        return queue


def close_queues() -> None:
    """Forget the cached queues and close their storage connections (tests)."""
    with _lock:
        for queue in _queues.values():
            try:
                queue.huey.storage.close()
                pool = getattr(queue.huey.storage, "pool", None)  # Redis
                if pool is not None:
                    pool.disconnect()
            except Exception:  # a Redis pool or SQLite file already gone
                log.debug("closing queue storage failed", exc_info=True)
        _queues.clear()


def submit(settings: Settings, job_id: str) -> None:
    """Tell the workers that job ``job_id`` (a queued row) is waiting.

    In immediate mode (``memory://``) the job runs to its end before this returns.
    """
    get_queue(settings).run_job(job_id)
