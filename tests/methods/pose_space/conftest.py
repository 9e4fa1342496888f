"""Fixtures of the pose-space tests: small PSD/WPSD models on the shared level-0 sample actor
(``pdm_data`` of tests/conftest.py: seed 2, 128² maps), three clips, small bases."""

from __future__ import annotations

import pytest

CLIPS = ("train_brow_raise", "train_smile", "train_pucker")


@pytest.fixture(scope="session")
def ps_data(pdm_data):
    actor, clips = pdm_data
    return actor, [c for c in clips if c.name in CLIPS]


@pytest.fixture(scope="session")
def wpsd_exact(ps_data):
    from service.methods.pose_space import WpsdParams, train

    actor, clips = ps_data
    return train(actor, clips, WpsdParams(fit="exact", basis_size=5, smoothing=0.0, selection_vertices=512,
                                          marker_regression=None))


@pytest.fixture(scope="session")
def psd_lsq(ps_data):
    from service.methods.pose_space import PsdParams, train

    actor, clips = ps_data
    stages = []
    model = train(actor, clips, PsdParams(basis_size=5, selection_vertices=512),
                  progress=lambda f, s: stages.append((f, s)))
    model.stages = stages
    return model


@pytest.fixture(scope="session")
def wpsd_regression(ps_data):
    """Exact WPSD whose corrections are learned after the marker regression (s = 2 spacings)."""
    from service.methods.pose_space import WpsdParams, train

    actor, clips = ps_data
    return train(actor, clips, WpsdParams(fit="exact", basis_size=5, smoothing=0.0, selection_vertices=512,
                                          marker_regression=2.0))
