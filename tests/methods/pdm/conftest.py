"""A small trained PDM model (level-0 sample actor, 6 training clips, 256²/128² maps), built once."""

from __future__ import annotations

import pytest

TRAINING = ("train_brow_raise", "train_brow_furrow", "train_smile", "train_surprise",
            "train_sneer", "train_pucker")


@pytest.fixture(scope="session")
def pdm_actor_dir(tmp_path_factory):
    from service.samples.actor import build_sample_actor

    out = tmp_path_factory.mktemp("pdm_actor")
    build_sample_actor(out, seed=2, level=0, with_tracking=False, map_resolution=128,
                       performance_names=TRAINING + ("heldout_in_range", "heldout_out_of_range"))
    return out


@pytest.fixture(scope="session")
def pdm_data(pdm_actor_dir):
    from service.samples import dataset

    actor = dataset.load_actor(pdm_actor_dir)
    return actor, [dataset.load_clip(pdm_actor_dir, name, actor) for name in TRAINING]


@pytest.fixture(scope="session")
def pdm_model(pdm_data):
    from service.methods.pdm.model import PdmParams, train

    actor, clips = pdm_data
    stages = []
    model = train(actor, clips, PdmParams(medium_resolution=256, fine_resolution=128),
                  progress=lambda f, s: stages.append((f, s)))
    model.stages = stages
    return model
