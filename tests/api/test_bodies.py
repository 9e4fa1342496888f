"""service.api.bodies: large bodies are spooled while hashed, and large uploads at once are
bounded (issue 16, defect 11)."""

from __future__ import annotations

import asyncio
import hashlib
import threading
import time

import httpx
import pytest

from service.api.bodies import LargeUploadLimiter
from service.config import Settings
from tests.api.conftest import NPZ, Recorder, grid, make_client, npz


def test_a_large_body_is_spooled_hashed_and_leaves_no_file(tmp_path):
    V, F, uv = grid(30)
    body = npz(vertices=V, faces=F, uv=uv)
    settings = Settings(data_dir=tmp_path, spool_body_bytes=1024, queue_url="memory://")
    seen = {}
    with make_client(settings, Recorder()) as client:
        import service.api.bodies as bodies

        real = bodies._spool

        async def spy(request, path):
            digest = await real(request, path)
            seen["spooled"], seen["sha256"] = path.read_bytes() == body, digest
            return digest

        bodies._spool = spy
        try:
            actor = client.post("/v1/actors", json={"name": "Ada"}).json()["id"]
            response = client.put(f"/v1/actors/{actor}/neutral", content=body, headers=NPZ)
        finally:
            bodies._spool = real
        assert response.status_code == 200, response.text
        assert response.json()["vertex_count"] == 900
        files = sorted(p.name for p in client.app.state.services.blobs.root.iterdir())
    assert seen["spooled"]
    assert seen["sha256"] == hashlib.sha256(body).hexdigest()
    assert not [n for n in files if n.startswith(".upload-")]   # removed once the request ends


def test_concurrent_large_uploads_wait_their_turn_then_503():
    active, peak = 0, 0
    release = asyncio.Event()

    async def app(scope, receive, send):
        nonlocal active, peak
        active += 1
        peak = max(peak, active)
        await release.wait()
        active -= 1
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})

    async def scenario():
        limiter = LargeUploadLimiter(app, limit=2, threshold=100, wait_seconds=0.3)
        transport = httpx.ASGITransport(app=limiter)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as client:
            big = {"content-length": "1000"}
            calls = [asyncio.create_task(client.post("/", content=b"x" * 1000, headers=big))
                     for _ in range(3)]
            small = asyncio.create_task(client.post("/", content=b"x"))
            await asyncio.sleep(0.5)            # the third big one waited 0.3 s and gave up
            assert peak == 3                    # 2 big + the small one, which never waits
            release.set()
            return [r.status_code for r in await asyncio.gather(*calls)], (await small).status_code

    statuses, small = asyncio.run(scenario())
    assert sorted(statuses) == [200, 200, 503] and small == 200
