"""A large upload is never held whole in memory (issue 16, defect 11): a spooled clip body is
validated from its spool file and its canonical blob written a block of frames at a time."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from models_store import registry
from service.config import Settings
from tests.api.conftest import NPZ, Recorder, grid, layout_body, load_npz, make_client, npz

FRAMES = 1600  # x 1024 vertices x 3 float32 = 19.7 MB of vertices


@pytest.fixture(scope="module")
def spooling(tmp_path_factory):
    """A client whose server spools every body over 1 KiB, and an actor on the 32×32 grid."""
    settings = Settings(data_dir=tmp_path_factory.mktemp("data"), spool_body_bytes=1024,
                        max_body_bytes=64 << 20, max_vertices=50_000, tokens=[],
                        queue_url="memory://")
    V, F, uv = grid(32)
    with make_client(settings, Recorder()) as client:
        actor = client.post("/v1/actors", json={"name": "Ada"}).json()["id"]
        assert client.put(f"/v1/actors/{actor}/neutral", content=npz(vertices=V, faces=F, uv=uv),
                          headers=NPZ).status_code == 200
        assert client.put(f"/v1/actors/{actor}/markers", content=layout_body(),
                          headers={"Content-Type": "application/json"}).status_code == 200
        yield client, actor, V


def test_a_20_mib_clip_is_validated_and_stored_holding_a_fraction_of_it(spooling):
    client, actor, V = spooling
    rng = np.random.default_rng(0)
    vertices = (V[None] + rng.normal(0, 0.01, (FRAMES, len(V), 3))).astype(np.float32)
    markers = vertices[:, [0, 7, 14]]
    body = npz(vertices=vertices, markers=markers, fps=np.float64(25))
    assert len(body) > 18 << 20
    request = client.build_request("POST", f"/v1/actors/{actor}/clips", content=body,
                                   headers=NPZ)  # the body is read here, before tracing
    tracemalloc.start()
    try:
        response = client.send(request)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert response.status_code == 201, response.text
    services = client.app.state.services
    with services.session() as session:
        stored = load_npz(registry.read_clip(session, services.blobs,
                                             response.json()["clip_id"]))
    leftovers = [p.name for p in services.blobs.root.iterdir() if p.name.startswith(".")]
    # before the fix: the body read back (20 MB), its arrays (20 MB) and the blob built in
    # memory (2 x 20 MB) — a peak of over three times the body
    assert peak < len(body) / 4, f"peak {peak / 2**20:.1f} MiB for a {len(body) / 2**20:.1f} MiB body"
    assert np.array_equal(stored["vertices"], vertices)
    assert np.array_equal(stored["markers"], markers) and float(stored["fps"]) == 25.0
    assert not leftovers   # the spool and scratch directories are gone


def test_a_spooled_clip_with_a_bad_frame_is_refused_and_leaves_nothing(spooling):
    client, actor, V = spooling
    vertices = np.repeat(V[None], 40, axis=0).astype(np.float32)
    vertices[33, 5, 1] = np.nan
    before = client.get(f"/v1/actors/{actor}/clips").json()["items"]
    body = npz(vertices=vertices, markers=vertices[:, [0, 7, 14]])
    response = client.post(f"/v1/actors/{actor}/clips", content=body, headers=NPZ)
    assert response.status_code == 422, response.text
    assert response.json()["detail"].startswith(
        "clip frame 33 vertex 5 has a non-finite coordinate (1 such entries in all)")
    assert client.get(f"/v1/actors/{actor}/clips").json()["items"] == before
    root = client.app.state.services.blobs.root
    assert not [p for p in root.rglob("*") if p.name.startswith(".")]
    assert len(list(root.rglob("clips/*"))) == len(before)
