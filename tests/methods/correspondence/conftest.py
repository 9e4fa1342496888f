"""Sample scans (level-0 sample actor, 512² maps (pores resolve from about 512² on)) shared by the correspondence tests."""

import pytest


@pytest.fixture(scope="session")
def scans512(pdm_actor_dir):
    from service.samples.uv_scans import build_uv_scans

    return build_uv_scans(pdm_actor_dir, resolution=512, expressions=["train_smile"],
                          landmarks=24, seed=0)
