"""A full and a read-only data disk under a running deployment (issue 16, defects 2 and 4).

The data directory (the blob store) is a 160 MiB tmpfs the test mounts (and unmounts;
skipped with the reason where mounting is impossible); PostgreSQL and Redis are the
machine's. With the disk full, uploads answer 507 and read-only 503 (problem+json, no
server paths), ``/readyz`` says the blob store is not ready, a synthesis job whose result
does not fit fails ``insufficient_storage`` with its scratch files removed and its worker
alive — and once space is freed or the disk is writable again everything works without a
restart.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest

from service.samples.uploads import sample_actor_uploads
from service.io.npz import npz_bytes
from tests.e2e.conftest import Deployment, running_deployment
from tests.e2e.test_faults import (CLIPS, ENV, NPZ, PARAMS, hidden_files, ok, wait_job)
from tests.filesystems import fill, read_only, small_filesystem
from tests.servers import postgres_server, redis_server  # noqa: F401

pytestmark = pytest.mark.e2e

SIZE = 160 << 20     # the trained level-0 PDM (its cache holds the shell bases in both vertex orders), clips, slack


@pytest.fixture(scope="module")
def mount():
    with small_filesystem(SIZE) as point:
        yield point


@pytest.fixture(scope="module")
def deployment(tmp_path_factory, mount, postgres_server, redis_server) -> Iterator[Deployment]:  # noqa: F811
    env = {**ENV, "FACESYNTH_MIN_FREE_BYTES": str(4 << 20)}
    with running_deployment(tmp_path_factory.mktemp("e2e_storage"), postgres_server,
                            redis_server, data_dir=mount / "data", workers=1,
                            env=env) as deployment:
        yield deployment


def no_server_paths(response, mount: Path) -> None:
    assert str(mount) not in response.text and "/blobs" not in response.text, response.text


def test_full_and_read_only_disk(deployment, mount, actor_dir):
    neutral, layout, clips = sample_actor_uploads(actor_dir, CLIPS)
    canonical = json.loads(layout)
    body = {"markers": [{"name": n, "triangle": t, "barycentric": b} for n, t, b in
                        zip(canonical["names"], canonical["triangle"], canonical["barycentric"])]}
    with np.load(actor_dir / "performances" / "heldout_in_range.npz") as d:
        markers = np.concatenate([d["markers"].astype(np.float32)] * 2)
    worker = deployment.workers[0]
    with deployment.client() as client:
        actor_id = ok(client.post("/v1/actors", json={"name": "disk"}), 201)["id"]
        ok(client.put(f"/v1/actors/{actor_id}/neutral", content=neutral, headers=NPZ))
        ok(client.put(f"/v1/actors/{actor_id}/markers", json=body))
        clip_ids = [ok(client.post(f"/v1/actors/{actor_id}/clips", content=clips[n], headers=NPZ,
                                   params={"name": n}), 201)["clip_id"] for n in CLIPS]
        accepted = ok(client.post(f"/v1/actors/{actor_id}/models",
                                  json={"kind": "pdm", "clips": clip_ids, "params": PARAMS}), 202)
        assert wait_job(client, accepted["job_id"], 180)["status"] == "succeeded"
        model_id = accepted["model_id"]
        assert client.get("/readyz").status_code == 200

        # -- full: the input of a job fits, its ~60 MB result does not
        filler = fill(mount, leave_bytes=3 << 20)
        ready = client.get("/readyz")
        assert ready.status_code == 503, ready.text
        assert "nearly full" in ready.json()["checks"]["blobs"]
        no_server_paths(ready, mount)
        job_id = ok(client.post(f"/v1/models/{model_id}/synthesis-jobs",
                                content=npz_bytes(markers=markers), headers=NPZ,
                                params={"outputs": "mesh,displacement,normal_map"}), 202)["job_id"]
        job = wait_job(client, job_id, 120)
        assert job["status"] == "failed" and job["error"]["code"] == "insufficient_storage", job
        assert str(mount) not in job["error"]["message"]
        assert worker.alive(), worker.tail()                    # no SIGBUS
        assert hidden_files(deployment) == []                   # its scratch files are gone
        (mount / "filler").rename(mount / "filler1")
        filler = mount / "filler1"
        fill(mount, leave_bytes=0).rename(mount / "filler2")    # now truly full
        response = client.post(f"/v1/actors/{actor_id}/clips", content=clips[CLIPS[0]],
                               headers=NPZ, params={"name": "full"})
        assert response.status_code == 507, response.text
        assert response.headers["content-type"] == "application/problem+json"
        assert response.json()["type"].endswith("insufficient-storage")
        no_server_paths(response, mount)
        response = client.post(f"/v1/actors", json={"name": "full"})
        assert response.status_code in (201, 507), response.text       # the database is elsewhere
        # -- freed: works again, no restart
        filler.unlink()
        (mount / "filler2").unlink()
        assert client.get("/readyz").status_code == 200
        ok(client.post(f"/v1/actors/{actor_id}/clips", content=clips[CLIPS[0]], headers=NPZ,
                       params={"name": "after-full"}), 201)

        # -- read-only
        with read_only(mount):
            ready = client.get("/readyz")
            assert ready.status_code == 503 and "not writable" in ready.json()["checks"]["blobs"]
            response = client.post(f"/v1/actors/{actor_id}/clips", content=clips[CLIPS[0]],
                                   headers=NPZ, params={"name": "read-only"})
            assert response.status_code == 503, response.text
            assert response.headers.get("retry-after")
            assert response.json()["type"].endswith("storage-unavailable")
            no_server_paths(response, mount)
            job_id = client.post(f"/v1/models/{model_id}/synthesis-jobs",
                                 content=npz_bytes(markers=markers[:3]), headers=NPZ)
            assert job_id.status_code == 503, job_id.text
            no_server_paths(job_id, mount)
        assert client.get("/readyz").status_code == 200
        ok(client.post(f"/v1/actors/{actor_id}/clips", content=clips[CLIPS[0]], headers=NPZ,
                       params={"name": "after-read-only"}), 201)
        job = wait_job(client, ok(client.post(f"/v1/models/{model_id}/synthesis-jobs",
                                              content=npz_bytes(markers=markers[:3]),
                                              headers=NPZ), 202)["job_id"], 60)
        assert job["status"] == "succeeded", job
    assert worker.alive() and deployment.api.alive()
