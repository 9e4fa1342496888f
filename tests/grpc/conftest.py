"""A real Synthesis server on a free loopback port, serving the session's trained PDM model."""

from __future__ import annotations

import contextlib
import socket
from typing import Iterator

import grpc
import numpy as np
import pytest

from service.errors import Conflict
from service.grpc.client import channel_options
from service.grpc.server import serve

MODEL_ID = "pdm-level0"
TRAINING_ID = "pdm-still-training"


class NotReady(Conflict):
    """What the model store raises for a model that is still training (a Conflict)."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def running(load_model, **serve_kwargs) -> Iterator[grpc.Channel]:
    """A started server (``serve`` on 127.0.0.1) and a channel to it; both closed on exit."""
    port = free_port()
    server = serve(load_model, "127.0.0.1", port, max_workers=2, **serve_kwargs)
    channel = grpc.insecure_channel(f"127.0.0.1:{port}", options=channel_options())
    try:
        yield channel
    finally:
        channel.close()
        server.stop(grace=None)


@pytest.fixture(scope="session")
def load_model(pdm_model):
    """The injected store: the trained model under MODEL_ID, TRAINING_ID not ready, else KeyError."""
    def load(model_id: str):
        if model_id == TRAINING_ID:
            raise NotReady(f"model {model_id} is training")
        return {MODEL_ID: pdm_model}[model_id]
    return load


@pytest.fixture(scope="module")
def channel(load_model) -> Iterator[grpc.Channel]:
    with running(load_model) as channel:
        yield channel


@pytest.fixture(scope="session")
def heldout_markers(pdm_actor_dir) -> np.ndarray:
    """12 frames (12,M,3) float32 of the held-out in-range performance, mm."""
    with np.load(pdm_actor_dir / "performances" / "heldout_in_range.npz") as d:
        return d["markers"][:12].astype(np.float32)
