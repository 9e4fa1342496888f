"""Shared fixtures: the ICT rig and a small (level-0) sample actor, built once per session."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def rig():
    from service.samples.rig import load_ict_rig

    return load_ict_rig()


@pytest.fixture(scope="session")
def rig_mesh(rig):
    """The rig's neutral as plain arrays: vertices (n,3) float64 mm, triangles (m,3) int64."""
    return rig.neutral, rig.triangles


@pytest.fixture(scope="session")
def actor0():
    """The level-0 sample actor with 256² maps (fast; same code path as level 1)."""
    from service.samples.actor import make_actor

    return make_actor(seed=3, level=0, map_resolution=256)
