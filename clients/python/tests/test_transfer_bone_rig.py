"""``client.models.transfer`` and ``client.bone_rigs.submit`` against the real app (embedded
worker), sync and async."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from facesynth_client import AsyncClient, Unprocessable

from conftest import sheet, sheet_motion

#: markers spread over the 16×13 sheet (pose-space models want a feature graph of some size)
MARKERS = (0, 7, 15, 48, 56, 64, 100, 104, 110, 150, 160, 167, 192, 200, 207)
WPSD = {"basis_size": 4, "selection_vertices": 128, "map_resolution": None}


@pytest.fixture(scope="module")
def wpsd(server):
    """An actor with 15 markers and two clips, and a ready wpsd model of it."""
    from facesynth_client import Client

    with Client(server.url, poll_interval=0.05) as fs:
        V, F, uv = sheet(16, 13)
        actor = fs.actors.create("Transfer source")
        fs.actors.upload_neutral(actor.id, vertices=V, faces=F, uv=uv)
        fs.actors.set_markers(actor.id, {f"M{k}": v for k, v in enumerate(MARKERS)})
        clips = []
        for phase in (0.0, 0.3):
            frames = sheet_motion(V, 12, phase).astype(np.float32)
            clips.append(fs.clips.upload(actor.id, frames, frames[:, list(MARKERS)]).clip_id)
        accepted = fs.models.train(actor.id, "wpsd", clips, WPSD)
        fs.wait(accepted, timeout=120)
        return actor.id, clips, accepted.model_id


def test_transfer_and_bone_rig_sync(client, wpsd, tmp_path):
    actor_id, clips, model_id = wpsd
    V = sheet(16, 13)[0]
    lm = np.linspace(0, len(V) - 1, 40).astype(int)
    accepted = client.models.transfer(model_id, actor_id, np.stack([lm, lm], 1))
    job = client.wait(accepted, timeout=120)
    assert job.kind == "transfer" and job.result.model_id == accepted.model_id
    model = client.models.get(accepted.model_id)
    assert (model.kind, model.status, model.actor_id) == ("wpsd", "ready", actor_id)
    markers = sheet_motion(V, 3, 0.2)[:, list(MARKERS)]
    a = client.synthesize(model_id, markers, outputs="mesh")["vertices"]
    b = client.synthesize(accepted.model_id, markers, outputs="mesh")["vertices"]
    assert np.abs(a - b).max() < 1e-6
    with pytest.raises(Unprocessable, match="out of range"):
        client.models.transfer(model_id, actor_id, [[0, 0], [1, 1], [2, 2], [9999, 3]])

    rig = client.bone_rigs.submit(actor_id, clip=clips[0], params={"bones": 4, "iterations": 3})
    job = client.wait(rig, timeout=120)
    assert job.kind == "bone_rig" and len(job.artifact_ids) == 2
    npz_path = client.download_artifact(job.artifact_ids[0], tmp_path / "rig.npz")
    glb_path = client.download_artifact(job.artifact_ids[1], tmp_path / "rig.glb")
    with np.load(npz_path) as data:
        assert data["rotations"].shape[0] == 12 and data["weights"].shape == (len(V), 4)
    assert glb_path.read_bytes()[:4] == b"glTF"
    with pytest.raises(ValueError, match="exactly one"):
        client.bone_rigs.submit(actor_id)


def test_transfer_and_bone_rig_async(server, wpsd):
    actor_id, clips, model_id = wpsd

    async def main():
        async with AsyncClient(server.url, poll_interval=0.05) as fs:
            lm = np.arange(0, 200, 5)
            accepted = await fs.models.transfer(model_id, actor_id, np.stack([lm, lm], 1))
            transferred = await fs.wait(accepted, timeout=120)
            rig = await fs.bone_rigs.submit(actor_id, clip=clips[1], params={"bones": 4},
                                            fps=60)
            return transferred, await fs.wait(rig, timeout=120)

    transferred, rig_job = asyncio.run(main())
    assert transferred.status == "succeeded" and rig_job.status == "succeeded"
    assert len(rig_job.artifact_ids) == 2
