"""The :class:`AsyncClient` against the real app: the same resources, awaited."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from facesynth_client import Actor, AsyncClient, Job, JobCancelled, NotFound

from conftest import SHEET_MARKERS, sheet


def run(coro):
    return asyncio.run(coro)


def test_async_actor_neutral_and_errors(server):
    async def main():
        async with AsyncClient(server.url) as fs:
            assert await fs.health() == {"status": "ok"}
            assert (await fs.ready()).ready
            assert "# TYPE" in await fs.metrics()
            actor = await fs.actors.create("Async")
            V, F, uv = sheet(16, 13)
            info = await fs.actors.upload_neutral(actor.id, vertices=V, faces=F, uv=uv)
            listed = await fs.actors.list()
            await fs.actors.delete(actor.id)
            with pytest.raises(NotFound):
                await fs.actors.get(actor.id)
            return actor, info, listed

    actor, info, listed = run(main())
    assert isinstance(actor, Actor) and info.vertex_count == 208
    assert actor.id in [a.id for a in listed]


def test_async_synthesis_job_events_wait_and_download(server, sheet_actor, pdm_model, tmp_path):
    markers = sheet_actor.motions["rise"][:, list(SHEET_MARKERS)]

    async def main():
        async with AsyncClient(server.url, poll_interval=0.05) as fs:
            out = await fs.synthesize(pdm_model, markers[:2])
            accepted = await fs.synthesis.submit_job(pdm_model, markers=markers)
            states = [state async for state in fs.jobs.events(accepted)]
            progress = []
            job = await fs.wait(accepted, timeout=60, progress=progress.append)
            path = await fs.download_artifact(job.artifact_ids[0], tmp_path / "take.npz")
            arrays = await fs.artifacts.arrays(job.artifact_ids[0])
            return out, states, job, path, arrays, progress

    out, states, job, path, arrays, progress = run(main())
    assert out["vertices"].shape == (2, 208, 3)
    assert states[-1].status == "succeeded" and isinstance(job, Job)
    assert progress[-1].status == "succeeded"
    assert np.load(path)["vertices"].shape == (12, 208, 3)
    assert arrays["vertices"].shape == (12, 208, 3)


def test_async_cancel_and_wait_raises(idle_server):
    async def main():
        async with AsyncClient(idle_server.url, poll_interval=0.05) as fs:
            actor = await fs.actors.create("AsyncIdle")
            V, F, uv = sheet(9, 7)
            await fs.actors.upload_neutral(actor.id, vertices=V, faces=F, uv=uv)
            accepted = await fs.rigs.upload(actor.id, "lod", vertices=V, faces=F)
            assert (await fs.jobs.get(accepted)).status == "queued"
            await fs.cancel(accepted)
            with pytest.raises(JobCancelled):
                await fs.wait(accepted, timeout=30)

    run(main())
