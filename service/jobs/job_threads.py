"""The job threads of a ``facesynth serve`` process, started when the server says so.

``serve`` runs beside its API either embedded workers (``workers`` > 0:
:func:`service.jobs.worker.start_embedded`) or, in an API-only process, the maintenance rounds
(:func:`service.jobs.worker.start_maintenance`: expired leases reaped, lost messages
resubmitted). Both live in :mod:`service.jobs.worker`, which imports Huey, and Huey imports
redis and psycopg whatever the storage (~0.18 s CPU quiet); their first round also reads the
database and walks the blob store's temporaries. A server with models to preload starts them
:data:`AFTER_PRELOAD_SECONDS` after the preload is done (issue 23's cold start: that work then
competes neither with the model load nor with the first frames a probe sends as soon as
``/readyz`` answers 200; all of it holds the interpreter), a server without at once.

This module imports no Huey. A start that fails after the server is up is logged (level
error, with the traceback) and kept as :attr:`JobThreads.error`; the server reports it as the
check ``workers`` of ``/readyz`` (503). The URL's form was checked when the server started
(:func:`service.jobs.queue_storage.worker_storage`), and an unreachable queue fails
``/readyz``'s ``queue`` check either way.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from service.config import Settings

log = logging.getLogger(__name__)

#: seconds between the end of a preload and the start of the job threads: the first frames
#: after readiness are served without them (measured on the level-1 PDM under load 5, a
#: start right at readiness added 0.05-0.15 s CPU to the first frame's 0.15 s); a job
#: submitted meanwhile waits in the queue that long
AFTER_PRELOAD_SECONDS = 2.0


class JobThreads:
    """The embedded workers (``settings.workers`` > 0) or the maintenance thread of one
    ``serve`` process: :meth:`start` (once), :meth:`start_after` (once an event is set),
    :meth:`stop`.

    Attributes
    ----------
    settings : Settings
    error : str or None   why a start failed (``"TypeName: message"``)
    """

    def __init__(self, settings: Settings):
        self.settings = settings
        self.error: str | None = None
        self._running: Any = None      # EmbeddedWorker | MaintenanceThread once started
        self._stopped = False
        self._stop_event = threading.Event()
        self._lock = threading.Lock()

    @property
    def started(self) -> bool:
        """Whether the threads run (or ran: :meth:`stop` does not reset it)."""
        return self._running is not None

    def start(self) -> None:
        """Start the threads now (a no-op once started, or after :meth:`stop`).

        Raises
        ------
        ValueError, Exception   what :func:`~service.jobs.worker.start_embedded` raises (a
                                ``memory://`` queue with workers, an unreachable database)
        """
        with self._lock:
            if self._stopped or self._running is not None:
                return
            from service.jobs.worker import start_embedded, start_maintenance

            workers = self.settings.workers
            self._running = (start_embedded(self.settings, workers) if workers > 0
                             else start_maintenance(self.settings))

    def start_after(self, event: threading.Event, delay: float = 0.0) -> threading.Thread:
        """Start the threads ``delay`` seconds after ``event`` is set (on a daemon thread,
        returned; :meth:`stop` meanwhile cancels the start); a start that fails there is
        logged and kept in :attr:`error` instead of raised."""

        def run() -> None:
            event.wait()
            if self._stop_event.wait(delay):
                return
            try:
                self.start()
            except Exception as error:  # noqa: BLE001 - reported by /readyz and the log
                self.error = f"{type(error).__name__}: {error}"
                log.error("the job threads did not start: %s", self.error, exc_info=True)

        thread = threading.Thread(target=run, name="facesynth-jobs-start", daemon=True)
        thread.start()
        return thread

    def status(self) -> str:
        """``"ok"`` unless a start failed (then ``"failed to start: …"``): the check
        ``workers`` of ``/readyz`` (a start still waiting for the preload is not a failure;
        the check ``models`` holds readiness back until then)."""
        return "ok" if self.error is None else f"failed to start: {self.error}"

    def stop(self, timeout: float | None = None) -> None:
        """Stop the threads if they run (waiting up to ``timeout`` s: a worker's grace
        period) and make any later start a no-op."""
        self._stop_event.set()
        with self._lock:
            self._stopped = True
            running = self._running
        if running is not None:
            running.stop(timeout=timeout)
