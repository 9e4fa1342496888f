"""An app on a temporary data directory, a client, small meshes, and uploaded actors.

Jobs are not run here: ``get_submit`` is overridden to record the submitted job ids (the
job tests live in tests/jobs). A trained model is put into the store directly
(``registry.mark_model_ready`` with the session's ``pdm_model``).
"""

from __future__ import annotations

import json
from typing import Sequence

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


# ---------------------------------------------------------------------------- a tiny face
#: training parameters of the tiny shape_space model (one region, one factorization,
#: 32² displacement maps)
SHEET_PARAMS = {"regions": "whole", "smoothing": "rest", "patch_size": 10, "lam_dt": 5.0,
                "map_resolution": 32}
#: vertices of the tiny actor's marker layout
SHEET_MARKERS = (0, 40, 100, 150)


def sheet(nx: int, ny: int, size: float = 40.0):
    """A smooth open sheet (a stand-in for a face) in mm: vertices (nx·ny,3), faces
    (2(nx-1)(ny-1),3) int64, uv (nx·ny,2) in [0,1]²; sheets of other resolutions share
    its surface (a low-resolution 'input rig' of it)."""
    x, y = np.meshgrid(np.linspace(0, size, nx), np.linspace(0, 0.8 * size, ny))
    x, y = x.ravel(), y.ravel()
    V = np.stack([x, y, 3.0 * np.sin(x / 7.0) * np.cos(y / 9.0)], axis=1)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
    a = (j * nx + i).ravel()
    F = np.concatenate([np.stack([a, a + 1, a + nx + 1], 1), np.stack([a, a + nx + 1, a + nx], 1)])
    uv = np.stack([x / size, y / (0.8 * size)], axis=1)
    return V, F.astype(np.int64), uv


def sheet_motion(V: np.ndarray, frames: int, phase: float) -> np.ndarray:
    """(frames,n,3) float64: a bump rising and falling over the sheet's vertices V (n,3),
    with fine ripples that grow with it (the detail a model learns), seeded by ``phase``."""
    s = np.sin(np.pi * (np.linspace(0.0, 1.0, frames) + phase))[:, None]
    bump = np.exp(-((V[:, 0] - 20.0) ** 2 + (V[:, 1] - 16.0) ** 2) / 60.0)[None]
    out = np.repeat(V[None], frames, axis=0)
    out[..., 2] += 4.0 * s * bump + 0.2 * s * np.sin(2.0 * V[:, 0])[None] * bump
    out[..., 0] += 0.5 * s * bump
    return out


def sheet_clips(V: np.ndarray) -> dict[str, bytes]:
    """Two 12-frame training clips of the 16×13 sheet as upload NPZs."""
    clips = {}
    for name, phase in (("rise", 0.0), ("fall", 0.3)):
        frames = sheet_motion(V, 12, phase).astype(np.float32)
        clips[name] = npz(vertices=frames, markers=frames[:, list(SHEET_MARKERS)], fps=30.0)
    return clips


def upload_sheet_actor(client: TestClient, name: str) -> tuple[str, dict[str, str]]:
    """A new actor with the 16×13 sheet as its neutral, four markers and the two
    :func:`sheet_clips`, uploaded through the API: (actor id, clip name → clip id)."""
    V, F, uv = sheet(16, 13)
    actor_id = client.post("/v1/actors", json={"name": name}).json()["id"]
    assert client.put(f"/v1/actors/{actor_id}/neutral", content=npz(vertices=V, faces=F, uv=uv),
                      headers=NPZ).status_code == 200
    assert client.put(f"/v1/actors/{actor_id}/markers", content=layout_body(SHEET_MARKERS),
                      headers={"Content-Type": "application/json"}).status_code == 200
    clip_ids = {}
    for clip_name, data in sheet_clips(V).items():
        response = client.post(f"/v1/actors/{actor_id}/clips", content=data, headers=NPZ,
                               params={"name": clip_name})
        assert response.status_code == 201, response.text
        clip_ids[clip_name] = response.json()["clip_id"]
    return actor_id, clip_ids


def upload_sample_actor(client: TestClient, actor_dir, clip_names: Sequence[str]) -> tuple[str, dict[str, str]]:
    """Upload a built sample actor (neutral, marker layout, the named clips) through the API:
    (actor id, clip name → clip id)."""
    from service.samples.uploads import sample_actor_uploads

    neutral, layout, clips = sample_actor_uploads(actor_dir, tuple(clip_names))
    actor_id = client.post("/v1/actors", json={"name": "sample"}).json()["id"]
    assert client.put(f"/v1/actors/{actor_id}/neutral", content=neutral,
                      headers=NPZ).status_code == 200
    canonical = json.loads(layout)
    markers = [{"name": n, "triangle": t, "barycentric": b} for n, t, b in
               zip(canonical["names"], canonical["triangle"], canonical["barycentric"])]
    assert client.put(f"/v1/actors/{actor_id}/markers", json={"markers": markers}).status_code == 200
    ids = {}
    for name in clip_names:
        response = client.post(f"/v1/actors/{actor_id}/clips", content=clips[name], headers=NPZ)
        assert response.status_code == 201, response.text
        ids[name] = response.json()["clip_id"]
    return actor_id, ids


def put_rig(client: TestClient, actor_id: str, name: str, V: np.ndarray, F: np.ndarray) -> dict:
    """``PUT`` an input rig (its registration job is only recorded): the 202 body."""
    response = client.put(f"/v1/actors/{actor_id}/input-rigs/{name}",
                          content=npz(vertices=V, faces=F), headers=NPZ)
    assert response.status_code == 202, response.text
    return response.json()


def ready_sheet_model(client: TestClient, actor_id: str, clip_ids: Sequence[str], directory):
    """A ``shape_space`` model of an uploaded sheet actor, trained in-process (as its job
    would) with :data:`SHEET_PARAMS` and marked ready: (model id, the trained model)."""
    from models_store import registry
    from service.store import actors as actor_store
    from service.jobs.tasks.train import jsonable
    from service.methods.inputs import no_progress
    from service.methods.kinds import get_kind

    model_id = client.post(f"/v1/actors/{actor_id}/models", json={
        "kind": "shape_space", "clips": list(clip_ids), "params": SHEET_PARAMS}).json()["model_id"]
    services = client.app.state.services
    with services.session() as session:
        actor = actor_store.load_actor_data(session, services.blobs, actor_id)
        clips = actor_store.load_clips(session, services.blobs, list(clip_ids), actor)
    kind = get_kind("shape_space")
    model = kind.train(actor, clips, kind.parse_params(SHEET_PARAMS), no_progress)
    model.save(directory)
    with services.session() as session:
        registry.mark_model_ready(session, services.blobs, model_id, directory,
                                  metrics=jsonable(model.metrics))
    return model_id, model


def ready_sheet_rig(client: TestClient, actor_id: str, name: str):
    """The 9×7 sheet uploaded as input rig ``name`` of a sheet actor, registered in-process
    (as its job would) and marked ready: (the 202 body, the rig's vertices (v,3), the
    registration)."""
    from models_store import registry
    from service.methods.shape_space.registration import register_rig

    V, F, _ = sheet(16, 13)
    Vr, Fr, _ = sheet(9, 7)
    accepted = put_rig(client, actor_id, name, Vr, Fr)
    registration = register_rig(Vr, Fr, V, F)
    services = client.app.state.services
    with services.session() as session:
        registry.mark_rig_ready(session, services.blobs, accepted["rig_id"], registration.save())
    return accepted, Vr, registration
