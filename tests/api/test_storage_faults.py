"""A full or read-only data directory answers 507 / 503 problem+json without server paths,
and /readyz says so (issue 16, defect 4). The data directory is a small tmpfs the test
mounts (tests/filesystems.py; skipped where mounting is impossible)."""

from __future__ import annotations

import numpy as np
import pytest

from service.config import Settings
from tests.api.conftest import NPZ, Recorder, grid, layout_body, make_client, npz
from tests.filesystems import fill, read_only, small_filesystem


@pytest.fixture
def disk():
    with small_filesystem(16 << 20) as point:
        yield point


def neutral() -> bytes:
    V, F, uv = grid(40)
    return npz(vertices=V, faces=F, uv=uv)


def check_problem(response, status: int, slug: str, point) -> dict:
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/problem+json")
    body = response.json()
    assert body["type"].endswith(slug), body
    assert str(point) not in response.text and "blobs" not in body["detail"], body
    return body


def test_a_full_disk_is_507_and_readyz_503_until_space_is_freed(disk, tmp_path):
    settings = Settings(data_dir=disk / "data", database_url=f"sqlite:///{tmp_path}/db.sqlite",
                        min_free_bytes=1 << 20, queue_url="memory://")
    with make_client(settings, Recorder()) as client:
        actor = client.post("/v1/actors", json={"name": "Ada"}).json()["id"]
        assert client.get("/readyz").status_code == 200
        filler = fill(disk)
        ready = client.get("/readyz")
        assert ready.status_code == 503 and "full" in ready.json()["checks"]["blobs"]
        assert str(disk) not in ready.text
        body = check_problem(client.put(f"/v1/actors/{actor}/neutral", content=neutral(),
                                        headers=NPZ), 507, "insufficient-storage", disk)
        assert "full" in body["detail"]
        filler.unlink()
        assert client.get("/readyz").status_code == 200
        assert client.put(f"/v1/actors/{actor}/neutral", content=neutral(),
                          headers=NPZ).status_code == 200


def test_a_read_only_disk_is_503_with_retry_after(disk, tmp_path):
    settings = Settings(data_dir=disk / "data", database_url=f"sqlite:///{tmp_path}/db.sqlite",
                        min_free_bytes=1 << 20, queue_url="memory://")
    with make_client(settings, Recorder()) as client:
        actor = client.post("/v1/actors", json={"name": "Ada"}).json()["id"]
        with read_only(disk):
            ready = client.get("/readyz")
            assert ready.status_code == 503 and "not writable" in ready.json()["checks"]["blobs"]
            response = client.put(f"/v1/actors/{actor}/neutral", content=neutral(), headers=NPZ)
            check_problem(response, 503, "storage-unavailable", disk)
            assert int(response.headers["retry-after"]) > 0
        assert client.put(f"/v1/actors/{actor}/neutral", content=neutral(),
                          headers=NPZ).status_code == 200


def test_a_spooled_clip_that_does_not_fit_is_507_and_leaves_no_partial_file(disk, tmp_path):
    """The body fits on the disk, its canonical blob (written beside it, a block at a time)
    does not: 507, no clip, no blob, no spool or scratch file left (issue 16, defect 11)."""
    settings = Settings(data_dir=disk / "data", database_url=f"sqlite:///{tmp_path}/db.sqlite",
                        spool_body_bytes=1024, queue_url="memory://")
    V, F, uv = grid(6)
    vertices = np.repeat(V[None], 8000, axis=0).astype(np.float32)     # 3.5 MB
    body = npz(vertices=vertices, markers=vertices[:, [0, 7, 14]])
    with make_client(settings, Recorder()) as client:
        actor = client.post("/v1/actors", json={"name": "Ada"}).json()["id"]
        client.put(f"/v1/actors/{actor}/neutral", content=npz(vertices=V, faces=F, uv=uv),
                   headers=NPZ)
        client.put(f"/v1/actors/{actor}/markers", content=layout_body(),
                   headers={"Content-Type": "application/json"})
        filler = fill(disk, leave_bytes=len(body) + (1 << 20))
        check_problem(client.post(f"/v1/actors/{actor}/clips", content=body, headers=NPZ),
                      507, "insufficient-storage", disk)
        root = client.app.state.services.blobs.root
        assert not [p for p in root.rglob("*") if p.name.startswith(".")]
        assert not list(root.rglob("clips/*"))
        assert client.get(f"/v1/actors/{actor}/clips").json()["items"] == []
        filler.unlink()
        assert client.post(f"/v1/actors/{actor}/clips", content=body,
                           headers=NPZ).status_code == 201
