"""Two tenants and an admin on a real deployment: no route lets one tenant see, change or
even detect another's actors, clips, input rigs, models, jobs or artifacts (issue 16,
defect 13); another tenant's id answers exactly what an unknown id answers."""

from __future__ import annotations

import json
from typing import Iterator

import httpx
import numpy as np
import pytest

from service.samples.uploads import sample_actor_uploads
from service.io.npz import npz_bytes
from tests.e2e.conftest import Deployment, running_deployment
from tests.e2e.test_faults import CLIPS, ENV, NPZ, PARAMS, ok, wait_job
from tests.servers import postgres_server, redis_server  # noqa: F401

pytestmark = pytest.mark.e2e

TOKENS = {"a": "token-of-studio-a", "b": "token-of-studio-b", "admin": "token-of-ops"}
UNKNOWN = {"actor": "act_" + "0" * 26, "clip": "clp_" + "0" * 26, "model": "mdl_" + "0" * 26,
           "job": "job_" + "0" * 26, "artifact": "art_" + "0" * 26}


@pytest.fixture(scope="module")
def deployment(tmp_path_factory, postgres_server, redis_server) -> Iterator[Deployment]:  # noqa: F811
    import hashlib

    hashed = hashlib.sha256(TOKENS["b"].encode()).hexdigest()
    env = {**ENV, "FACESYNTH_TOKENS": f"studio-a:{TOKENS['a']},studio-b:sha256:{hashed},"
                                      f"ops:{TOKENS['admin']}:admin"}
    with running_deployment(tmp_path_factory.mktemp("e2e_tenants"), postgres_server,
                            redis_server, workers=1, env=env) as deployment:
        yield deployment


def client(deployment: Deployment, who: str) -> httpx.Client:
    return httpx.Client(base_url=deployment.base_url, timeout=120,
                        headers={"Authorization": f"Bearer {TOKENS[who]}"})


def test_no_route_crosses_tenants(deployment, actor_dir):
    neutral, layout, clips = sample_actor_uploads(actor_dir, CLIPS)
    canonical = json.loads(layout)
    body = {"markers": [{"name": n, "triangle": t, "barycentric": b} for n, t, b in
                        zip(canonical["names"], canonical["triangle"], canonical["barycentric"])]}
    with np.load(actor_dir / "performances" / "heldout_in_range.npz") as d:
        markers = npz_bytes(markers=d["markers"][:2].astype(np.float32))
    with client(deployment, "a") as a, client(deployment, "b") as b, \
            client(deployment, "admin") as admin:
        actor = ok(a.post("/v1/actors", json={"name": "A's actor"}), 201)["id"]
        ok(a.put(f"/v1/actors/{actor}/neutral", content=neutral, headers=NPZ))
        ok(a.put(f"/v1/actors/{actor}/markers", json=body))
        clip_ids = [ok(a.post(f"/v1/actors/{actor}/clips", content=clips[n], headers=NPZ,
                              params={"name": n}), 201)["clip_id"] for n in CLIPS]
        trained = ok(a.post(f"/v1/actors/{actor}/models",
                            json={"kind": "pdm", "clips": clip_ids, "params": PARAMS}), 202)
        assert wait_job(a, trained["job_id"], 180)["status"] == "succeeded"
        model = trained["model_id"]
        job = ok(a.post(f"/v1/models/{model}/synthesis-jobs", content=markers, headers=NPZ), 202)
        done = wait_job(a, job["job_id"], 60)
        (artifact,) = done["result"]["artifact_ids"]
        b_actor = ok(b.post("/v1/actors", json={"name": "B's actor"}), 201)["id"]

        # listings: each tenant its own, the admin everything
        assert [x["id"] for x in ok(a.get("/v1/actors"))["items"]] == [actor]
        assert [x["id"] for x in ok(b.get("/v1/actors"))["items"]] == [b_actor]
        assert {x["id"] for x in ok(admin.get("/v1/actors"))["items"]} == {actor, b_actor}
        assert ok(b.get("/v1/jobs"))["items"] == []
        assert ok(b.get("/v1/jobs", params={"actor_id": actor}))["items"] == []
        assert len(ok(a.get("/v1/jobs"))["items"]) == 2

        routes = [
            ("GET", f"/v1/actors/{actor}", {}), ("DELETE", f"/v1/actors/{actor}", {}),
            ("PUT", f"/v1/actors/{actor}/neutral", {"content": neutral, "headers": NPZ}),
            ("PUT", f"/v1/actors/{actor}/markers", {"json": body}),
            ("GET", f"/v1/actors/{actor}/clips", {}),
            ("POST", f"/v1/actors/{actor}/clips", {"content": clips[CLIPS[0]], "headers": NPZ}),
            ("DELETE", f"/v1/actors/{actor}/clips/{clip_ids[0]}", {}),
            ("PUT", f"/v1/actors/{actor}/input-rigs/low", {"content": neutral, "headers": NPZ}),
            ("GET", f"/v1/actors/{actor}/models", {}),
            ("POST", f"/v1/actors/{actor}/models", {"json": {"kind": "pdm", "clips": clip_ids}}),
            ("GET", f"/v1/models/{model}", {}), ("GET", f"/v1/models/{model}/maps", {}),
            ("GET", f"/v1/models/{model}/maps/medium.exr", {}),
            ("POST", f"/v1/models/{model}/synthesize", {"content": markers, "headers": NPZ}),
            ("POST", f"/v1/models/{model}/synthesis-jobs", {"content": markers, "headers": NPZ}),
            ("DELETE", f"/v1/models/{model}", {}),
            ("GET", f"/v1/jobs/{job['job_id']}", {}), ("DELETE", f"/v1/jobs/{job['job_id']}", {}),
            ("GET", f"/v1/jobs/{job['job_id']}/events", {}),
            ("GET", f"/v1/artifacts/{artifact}", {}),
            ("POST", f"/v1/actors/{actor}/bone-rig-jobs", {"json": {"clip_id": clip_ids[0]}}),
            ("POST", f"/v1/models/{model}/transfer",
             {"json": {"target_actor_id": b_actor, "landmarks": [[i, i] for i in range(40)]}}),
        ]
        for method, path, kwargs in routes:
            response = b.request(method, path, **kwargs)
            assert response.status_code == 404, (method, path, response.status_code, response.text)
            # indistinguishable from an unknown id of the same kind
            fakes = {real: UNKNOWN[kind] for kind, real in (
                ("actor", actor), ("model", model), ("job", job["job_id"]),
                ("artifact", artifact), ("clip", clip_ids[0]))}
            unknown = path
            for real, fake in fakes.items():
                unknown = unknown.replace(real, fake)
            twin = b.request(method, unknown, **kwargs)
            assert twin.status_code == 404, (method, unknown, twin.text)
            seen = {k: response.json().get(k) for k in ("type", "title", "status", "detail")}
            for real, fake in fakes.items():
                seen["detail"] = str(seen["detail"]).replace(real, fake)
            assert seen == {k: twin.json().get(k) for k in ("type", "title", "status", "detail")}
        # nothing of A's changed
        assert ok(a.get(f"/v1/models/{model}"))["status"] == "ready"
        assert len(ok(a.get(f"/v1/actors/{actor}/clips"))["items"]) == 2
        assert a.get(f"/v1/artifacts/{artifact}").status_code == 200
        # the admin reaches A's rows
        assert ok(admin.get(f"/v1/models/{model}"))["id"] == model
        # an unknown token is 401, not a tenant
        assert httpx.get(f"{deployment.base_url}/v1/actors",
                         headers={"Authorization": "Bearer nope"}).status_code == 401
