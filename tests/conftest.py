"""Shared fixtures, built once per session: the ICT rig, a small (level-0) sample actor, and a
level-0 sample actor directory with a PDM model trained on it."""

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


# a small trained PDM model (level-0 sample actor, 6 training clips, 256²/128² maps)
PDM_TRAINING = ("train_brow_raise", "train_brow_furrow", "train_smile", "train_surprise",
                "train_sneer", "train_pucker")


@pytest.fixture(scope="session")
def pdm_actor_dir(tmp_path_factory):
    from service.samples.actor import build_sample_actor

    out = tmp_path_factory.mktemp("pdm_actor")
    build_sample_actor(out, seed=2, level=0, with_tracking=False, map_resolution=128,
                       performance_names=PDM_TRAINING + ("heldout_in_range", "heldout_out_of_range"))
    return out


@pytest.fixture(scope="session")
def pdm_data(pdm_actor_dir):
    from service.samples import dataset

    actor = dataset.load_actor(pdm_actor_dir)
    return actor, [dataset.load_clip(pdm_actor_dir, name, actor) for name in PDM_TRAINING]


@pytest.fixture(scope="session")
def pdm_model(pdm_data):
    from service.methods.pdm.model import PdmParams, train

    actor, clips = pdm_data
    stages = []
    # the polynomial medium and fine bands (ma2008), which most PDM tests are about; the
    # defaults' marker regression and strain-driven fine band have their own models in
    # tests/methods/pdm/test_medium_regression.py and test_strain_band.py
    model = train(actor, clips, PdmParams(medium_resolution=256, fine_resolution=128, medium_regression=None,
                                          fine_driver="deformation"),
                  progress=lambda f, s: stages.append((f, s)))
    model.stages = stages
    return model
