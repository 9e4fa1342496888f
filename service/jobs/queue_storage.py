"""Where the task queue's messages are stored, and whether that storage answers, without Huey.

``Settings.queue_url`` names the storage (:mod:`service.jobs.queue` builds the Huey instance
on it): ``None`` the SQLite file ``<data_dir>/queue.db``, ``redis://…`` / ``rediss://…`` /
``unix://…`` a Redis server, ``memory://`` no storage at all (jobs run when submitted).

This module reads that form and asks the storage itself whether it answers (the ``queue``
check of ``/readyz`` and ``facesynth check``). It imports no Huey: Huey imports redis and
psycopg whatever the storage (~0.18 s CPU on a quiet machine, ~0.24 s under load), which a
``facesynth serve`` with models to preload then paid while it loaded them (issue 23's cold
start). So ``serve`` checks the URL's form here at start (a misspelt scheme is one line and
exit status 2, before anything loads), ``/readyz`` probes the storage here, and Huey is
imported only where messages are sent or taken (a job submitted, the embedded workers
started once the preload is done: :mod:`service.jobs.job_threads`).
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from service.config import Settings

#: file of the embedded queue in the data directory
QUEUE_FILE = "queue.db"
#: ``queue_url`` of immediate mode
MEMORY_URL = "memory://"
#: URL schemes served by Redis
REDIS_SCHEMES = ("redis://", "rediss://", "unix://")
#: seconds a probe waits for the storage (a locked SQLite file, a Redis that does not answer)
PROBE_TIMEOUT_SECONDS = 2.0


@dataclass(frozen=True)
class QueueStorage:
    """The queue's storage as ``Settings.queue_url`` names it.

    Attributes
    ----------
    kind : ``"sqlite"`` | ``"redis"`` | ``"memory"``
    location : str   the SQLite file (absolute), the Redis URL, or ``memory://``
    """

    kind: Literal["sqlite", "redis", "memory"]
    location: str


def queue_storage(settings: Settings) -> QueueStorage:
    """The storage ``settings.queue_url`` names (its form only: nothing is contacted).

    Raises
    ------
    ValueError   a URL of another scheme
    """
    url = settings.queue_url
    if url is None:
        return QueueStorage("sqlite", str((Path(settings.data_dir) / QUEUE_FILE).absolute()))
    if url.startswith(REDIS_SCHEMES):
        return QueueStorage("redis", url)
    if url == MEMORY_URL:
        return QueueStorage("memory", url)
    raise ValueError(f"unsupported queue URL {url!r}: expected redis://..., "
                     f"{MEMORY_URL} or none (the SQLite queue in the data directory)")


def worker_storage(settings: Settings) -> QueueStorage:
    """The storage workers take jobs from (:func:`queue_storage`), which ``memory://`` is not.

    Raises
    ------
    ValueError   an unsupported URL, or ``memory://`` (it has no workers)
    """
    storage = queue_storage(settings)
    if storage.kind == "memory":
        raise ValueError("the memory:// queue runs jobs when they are submitted; it has "
                         "no workers (set FACESYNTH_QUEUE_URL to redis://... or unset it)")
    return storage


def probe(settings: Settings, timeout: float = PROBE_TIMEOUT_SECONDS) -> None:
    """Ask the queue's storage whether it answers: the SQLite file opens and reads (it is
    created if missing, as Huey creates it), Redis answers PING (connecting and
    authenticating as the URL says). ``memory://`` always answers.

    Raises
    ------
    ValueError   an unsupported URL
    Exception    whatever the storage raised (sqlite3.Error, redis's ConnectionError, ...)
    """
    storage = queue_storage(settings)
    if storage.kind == "sqlite":
        connection = sqlite3.connect(storage.location, timeout=timeout)
        try:
            connection.execute("SELECT count(*) FROM sqlite_master").fetchone()
        finally:
            connection.close()
    elif storage.kind == "redis":
        import redis   # only for a Redis queue (~0.1 s), which Huey would import anyway

        client = redis.Redis.from_url(storage.location, socket_timeout=timeout,
                                      socket_connect_timeout=timeout)
        try:
            client.ping()
        finally:
            client.close()
