"""An app on a temporary data directory, a client, small meshes, and uploaded actors.

Jobs are not run here: ``get_submit`` is overridden to record the submitted job ids (the
job tests live in tests/jobs). A trained model is put into the store directly
(``registry.mark_model_ready`` with the session's ``pdm_model``).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.api import create_app
from service.api.deps import get_submit
from service.config import Settings
from service.io.npz import npz_arrays as load_npz, npz_bytes as npz  # noqa: F401 (used by the tests)

NPZ = {"Content-Type": "application/x-npz"}


def grid(n: int = 6):
    """A gently curved n×n vertex grid: vertices (n²,3), faces (2(n-1)²,3), uv (n²,2) in [0,1]²."""
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="xy")
    V = np.stack([10 * u, 10 * v, np.sin(3 * u) + np.cos(2 * v)], axis=-1).reshape(-1, 3)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    uv = np.stack([u, v], axis=-1).reshape(-1, 2)
    return V, F, uv


def layout_body(vertices=(0, 7, 14)) -> bytes:
    """A marker layout JSON with one marker per given vertex."""
    return json.dumps({"markers": [{"name": f"M{k}", "vertex": int(v)}
                                   for k, v in enumerate(vertices)]}).encode()


class Recorder(list):
    """Stands in for the job queue: records submitted job ids; ``fail`` makes it raise."""

    fail = False

    def __call__(self, job_id: str) -> None:
        if self.fail:
            raise ConnectionError("queue down")
        self.append(job_id)


@pytest.fixture
def settings(tmp_path) -> Settings:
    return Settings(data_dir=tmp_path, max_body_bytes=8 << 20, max_frames_per_request=4,
                    max_vertices=50_000, tokens=[])


@pytest.fixture
def submitted() -> Recorder:
    return Recorder()


def make_client(settings: Settings, submitted: Recorder) -> TestClient:
    app = create_app(settings)
    app.dependency_overrides[get_submit] = lambda: submitted
    return TestClient(app)


@pytest.fixture
def client(settings, submitted):
    with make_client(settings, submitted) as client:
        yield client


@pytest.fixture
def actor_id(client) -> str:
    return client.post("/v1/actors", json={"name": "Ada"}).json()["id"]


@pytest.fixture
def grid_actor(client, actor_id) -> str:
    """An actor with the 6×6 grid as its neutral and three markers."""
    V, F, uv = grid()
    assert client.put(f"/v1/actors/{actor_id}/neutral", content=npz(vertices=V, faces=F, uv=uv),
                      headers=NPZ).status_code == 200
    assert client.put(f"/v1/actors/{actor_id}/markers", content=layout_body(),
                      headers={"Content-Type": "application/json"}).status_code == 200
    return actor_id


def assert_problem(response, status: int, *fragments: str) -> dict:
    """The response is a problem+json of ``status`` whose detail contains ``fragments``."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/problem+json")
    body = response.json()
    assert body["status"] == status and body["type"].startswith("urn:facesynth:problem:")
    for fragment in fragments:
        assert fragment in body["detail"], (fragment, body["detail"])
    return body
