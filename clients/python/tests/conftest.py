"""Fixtures of the SDK tests: the real facesynth app served by uvicorn on a free loopback
port in a thread, with an embedded job worker (SQLite queue in a temporary data directory),
and a tiny actor — the 16×13 "sheet" of tests/api/conftest.py, whose models train in about
a second.

The server side is imported here only; the SDK under test never imports it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator

import numpy as np
import pytest

from facesynth_client import Client
# the server side and its test helpers (the sheet actor of the API tests, the app on a port)
from tests.api.conftest import SHEET_MARKERS, sheet, sheet_motion
from tests.servers import AppServer as Server, serve_app as serve


# ---------------------------------------------------------------------------- a tiny face
#: training parameters of the tiny models
SHAPE_SPACE_PARAMS = {"regions": "whole", "smoothing": "rest", "patch_size": 10, "lam_dt": 5.0}
PDM_PARAMS = {"medium_resolution": 32, "fine_resolution": 32}


@pytest.fixture(scope="session")
def server(tmp_path_factory) -> Iterator[Server]:
    """The app with an embedded worker."""
    running = serve(tmp_path_factory.mktemp("sdk-server"), worker=True)
    yield running
    running.stop()


@pytest.fixture(scope="session")
def idle_server(tmp_path_factory) -> Iterator[Server]:
    """The app without a worker: submitted jobs stay ``queued``."""
    running = serve(tmp_path_factory.mktemp("sdk-idle"), worker=False)
    yield running
    running.stop()


@pytest.fixture
def client(server) -> Iterator[Client]:
    with Client(server.url, poll_interval=0.05, timeout=60) as fs:
        yield fs


# ---------------------------------------------------------------------------- the actor
@dataclass
class SheetActor:
    """The tiny actor uploaded through the SDK, with its clips (name → clip id)."""

    actor_id: str
    clips: dict[str, str]
    V: np.ndarray
    F: np.ndarray
    uv: np.ndarray
    motions: dict[str, np.ndarray] = field(default_factory=dict)


def upload_sheet_actor(fs: Client, name: str) -> SheetActor:
    """A new actor with the 16×13 sheet as neutral (from arrays), four vertex markers and
    two 12-frame clips ("rise", "fall"), all through the SDK."""
    V, F, uv = sheet(16, 13)
    actor = fs.actors.create(name)
    fs.actors.upload_neutral(actor.id, vertices=V, faces=F, uv=uv)
    fs.actors.set_markers(actor.id, {f"M{k}": v for k, v in enumerate(SHEET_MARKERS)})
    sheet_actor = SheetActor(actor.id, {}, V, F, uv)
    for clip_name, phase in (("rise", 0.0), ("fall", 0.3)):
        frames = sheet_motion(V, 12, phase).astype(np.float32)
        clip = fs.clips.upload(actor.id, frames, frames[:, list(SHEET_MARKERS)], fps=30.0,
                               name=clip_name)
        sheet_actor.clips[clip_name] = clip.clip_id
        sheet_actor.motions[clip_name] = frames
    return sheet_actor


@pytest.fixture(scope="session")
def sheet_actor(server) -> SheetActor:
    with Client(server.url) as fs:
        return upload_sheet_actor(fs, "Sheet")


@pytest.fixture(scope="session")
def shape_model(server, sheet_actor) -> str:
    """A ready ``shape_space`` model of the sheet actor, trained by the worker."""
    with Client(server.url, poll_interval=0.05) as fs:
        accepted = fs.models.train(sheet_actor.actor_id, "shape_space",
                                   list(sheet_actor.clips.values()), SHAPE_SPACE_PARAMS)
        job = fs.wait(accepted, timeout=120)
        assert job.result.model_id == accepted.model_id
        return accepted.model_id


@pytest.fixture(scope="session")
def pdm_model(server, sheet_actor) -> str:
    """A ready ``pdm`` model (32² maps) of the sheet actor, trained by the worker."""
    with Client(server.url, poll_interval=0.05) as fs:
        accepted = fs.models.train(sheet_actor.actor_id, "pdm",
                                   list(sheet_actor.clips.values()), PDM_PARAMS)
        fs.wait(accepted, timeout=120)
        return accepted.model_id


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: takes tens of seconds (still run in CI)")
