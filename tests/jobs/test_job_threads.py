"""service.jobs.job_threads: serve's job threads, started at once or once a preload is done."""

from __future__ import annotations

import threading

from models_store.cache import ByteLRUCache
from service.app.services import Services
from service.config import Settings
from service.jobs.job_threads import JobThreads
from service.store.container import get_store


def test_threads_started_after_an_event_run_and_stop(tmp_path):
    jobs = JobThreads(Settings(data_dir=tmp_path, workers=1))
    done = threading.Event()
    waiter = jobs.start_after(done)
    assert not jobs.started
    done.set()
    waiter.join(60)
    assert jobs.started and jobs.error is None and jobs.status() == "ok"
    assert any(t.name == "facesynth-worker" for t in threading.enumerate())
    jobs.stop(timeout=30)
    assert not any(t.name == "facesynth-worker" for t in threading.enumerate())


def test_a_stop_before_the_event_means_no_start(tmp_path):
    jobs = JobThreads(Settings(data_dir=tmp_path, workers=0))
    done = threading.Event()
    waiter = jobs.start_after(done)
    jobs.stop(timeout=5)
    done.set()
    waiter.join(30)
    assert not jobs.started and jobs.error is None


def test_a_failed_start_is_logged_and_fails_readiness(tmp_path, caplog):
    """A start after the preload that fails (here a memory:// queue, which has no workers:
    serve refuses it at start, so only a direct caller gets this far) is logged at error
    level and is the check ``workers`` of ``/readyz``."""
    settings = Settings(data_dir=tmp_path, workers=1, queue_url="memory://")
    jobs = JobThreads(settings)
    done = threading.Event()
    done.set()
    with caplog.at_level("ERROR", logger="service.jobs.job_threads"):
        jobs.start_after(done).join(30)
    assert not jobs.started
    assert jobs.status().startswith("failed to start: ValueError: the memory:// queue runs jobs")
    assert any("did not start" in r.getMessage() and r.exc_info for r in caplog.records)
    services = Services(settings=settings, store=get_store(settings, migrate=True),
                        models=ByteLRUCache(0), job_threads=jobs)
    try:
        checks = services.check()
    finally:
        services.close()
    assert checks["workers"] == jobs.status() and checks["queue"] == "ok"
