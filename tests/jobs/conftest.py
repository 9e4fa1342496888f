"""Fixtures of the job tests: a deployment (SQLite database and blobs in a temporary
directory) with the small sample actor uploaded through :mod:`service.store.actors`, worker
threads running a real Huey consumer, and helpers to create and wait for jobs.

Jobs train small PDMs (64² maps, two clips: ~10 s each); the trained model is shared by
every job test (``trained``).
"""

from __future__ import annotations

import io
import time
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import pytest

from models_store import registry
from models_store.db import upgrade
from service.store import actors as actor_store
from service.samples.uploads import sample_actor_uploads
from service.config import Settings
from service.jobs import worker as worker_module
from service.store.container import Store, close_stores, get_store
from service.jobs.queue import close_queues, submit
from tests.servers import redis_server  # noqa: F401

#: training clips of the job tests
CLIPS = ("train_smile", "train_brow_raise")
#: small, fast PDM parameters
PARAMS = {"order": "biquadratic", "medium_resolution": 64, "fine_resolution": 64}
#: lease of the test deployments: heartbeats every second, reaping every ~0.75 s
LEASE_SECONDS = 3.0
FINAL = ("succeeded", "failed", "cancelled")


@dataclass
class Deployment:
    """A test deployment with the sample actor uploaded."""

    settings: Settings
    store: Store
    actor_id: str
    clip_ids: list[str]

    def session(self):
        return self.store.sessions()

    def create_model(self, clip_ids: list[str] | None = None, params: dict | None = None):
        """A ``pdm`` model in training and its queued job (not submitted)."""
        with self.session() as session:
            return registry.create_model(session, self.actor_id, "pdm", params or PARAMS,
                                         clip_ids=self.clip_ids if clip_ids is None else clip_ids)

    def add_clip(self, name: str, data: bytes) -> str:
        with self.session() as session:
            frames = len(np.load(io.BytesIO(data))["markers"])
            return registry.add_clip(session, self.store.blobs, self.actor_id, data, name=name,
                                     frames=frames).id

    def create_synthesis_job(self, model_id: str, markers: np.ndarray, **payload) -> str:
        """A queued synthesis job whose input markers are an artifact of the job itself."""
        buffer = io.BytesIO()
        np.savez(buffer, markers=markers.astype(np.float32))
        with self.session() as session:
            job = registry.create_job(session, "synthesize", self.actor_id, model_id=model_id)
            artifact = registry.add_artifact(session, self.store.blobs, job.id, buffer.getvalue(),
                                             media_type="application/x-npz")
            # the payload names the input artifact, which needs the job's id first
            job.payload = {"model_id": model_id, "markers_artifact_id": artifact.id, **payload}
            session.commit()
            return job.id

    def job(self, job_id: str):
        with self.session() as session:
            return registry.get_job(session, job_id)

    def model(self, model_id: str):
        with self.session() as session:
            return registry.get_model(session, model_id)

    def wait(self, job_id: str, timeout: float = 60.0, until=lambda job: job.status in FINAL):
        """The job once ``until(job)`` holds (default: it ended); fails after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while True:
            job = self.job(job_id)
            if until(job):
                return job
            if time.monotonic() > deadline:
                pytest.fail(f"job {job_id} still {job.status} ({job.stage!r}, "
                            f"{job.progress:.2f}) after {timeout} s")
            time.sleep(0.05)


@pytest.fixture(scope="session")
def uploads(pdm_actor_dir):
    """The sample actor's canonical uploads (two training clips)."""
    return sample_actor_uploads(pdm_actor_dir, CLIPS)


@pytest.fixture(scope="session")
def deployment(tmp_path_factory, uploads) -> Iterator[Deployment]:
    """A deployment in a temporary data directory with the sample actor uploaded."""
    settings = Settings(data_dir=tmp_path_factory.mktemp("deployment"),
                        job_lease_seconds=LEASE_SECONDS, job_max_retries=2)
    upgrade(settings.database_url_resolved)
    store = get_store(settings)
    neutral, layout, clips = uploads
    actor = actor_store.actor_from_blobs(neutral, layout)
    with store.sessions() as session:
        row = registry.create_actor(session, "sample")
        registry.set_neutral(session, store.blobs, row.id, neutral,
                             vertex_count=actor.n_vertices, triangle_count=len(actor.faces))
        registry.set_markers(session, store.blobs, row.id, layout, marker_count=actor.n_markers)
    deployment = Deployment(settings, store, row.id, [])
    deployment.clip_ids = [deployment.add_clip(name, data) for name, data in clips.items()]
    yield deployment
    close_queues()
    close_stores()


@pytest.fixture
def start_worker():
    """``start_worker(settings, workers=1, grace_seconds=...)``: an embedded worker, stopped
    at the end of the test."""
    started = []

    def start(settings: Settings, workers: int = 1, grace_seconds: float = 5.0):
        handle = worker_module.start_embedded(settings, workers, grace_seconds=grace_seconds)
        started.append(handle)
        return handle

    yield start
    for handle in started:
        handle.stop(timeout=60)
        assert not handle.running


@pytest.fixture(scope="session")
def trained(deployment):
    """A model trained through a worker on the SQLite queue: (model id, its training job)."""
    model, job = deployment.create_model()
    handle = worker_module.start_embedded(deployment.settings, 1)
    try:
        submit(deployment.settings, job.id)
        finished = deployment.wait(job.id, timeout=120)
    finally:
        handle.stop(timeout=60)
    return model.id, finished
