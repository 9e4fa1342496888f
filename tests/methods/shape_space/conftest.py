"""Fixtures of the shape-space tests: small synthetic meshes, and a level-0 sample actor with
the long ``database`` performance (bermano2014 §4.1) and the held-out in-range performance,
with a model trained on a subsample of the database (shared by the model and store tests)."""

from __future__ import annotations

import numpy as np
import pytest

#: database subsampling of the trained fixture model (630 frames → 63)
DATABASE_STRIDE = 10


def grid_mesh(nx: int = 12, ny: int = 10, size: float = 40.0, seed: int = 0):
    """A bumpy open sheet: vertices (nx·ny,3) mm and triangles, jittered, seeded."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(0, size, nx), np.linspace(0, size * ny / nx, ny))
    V = np.stack([x.ravel(), y.ravel(), np.zeros(nx * ny)], axis=1)
    V[:, :2] += rng.uniform(-0.15, 0.15, (nx * ny, 2)) * size / nx
    V[:, 2] = 3.0 * np.sin(V[:, 0] / 7.0) * np.cos(V[:, 1] / 9.0)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
    a = (j * nx + i).ravel()
    F = np.concatenate([np.stack([a, a + 1, a + nx + 1], 1), np.stack([a, a + nx + 1, a + nx], 1)])
    return V, F.astype(np.int64)


@pytest.fixture(scope="session")
def sheet():
    return grid_mesh()


@pytest.fixture(scope="session")
def shape_space_actor_dir(tmp_path_factory):
    """A level-0 sample actor with only the ``database`` and ``heldout_in_range`` performances."""
    from service.samples.actor import build_sample_actor

    out = tmp_path_factory.mktemp("shape_space_actor")
    build_sample_actor(out, seed=2, level=0, with_tracking=False, map_resolution=64,
                       performance_names=("database", "heldout_in_range"))
    return out


@pytest.fixture(scope="session")
def shape_space_data(shape_space_actor_dir):
    """(actor, database clip with its maps, held-out arrays: vertices_medium, vertices, markers)."""
    from service.samples import dataset

    actor = dataset.load_actor(shape_space_actor_dir)
    perf = shape_space_actor_dir / "performances"
    clip = dataset.load_clip(shape_space_actor_dir, "database", actor)     # with 64² maps
    with np.load(perf / "heldout_in_range.npz") as d:
        heldout = {k: d[k].astype(np.float64) for k in ("vertices_medium", "vertices", "markers")}
    return actor, clip, heldout


@pytest.fixture(scope="session")
def shape_space_model(shape_space_data):
    from service.methods.shape_space import ShapeSpaceParams, train

    actor, clip, _ = shape_space_data
    stages = []
    model = train(actor, [clip], ShapeSpaceParams(frame_stride=DATABASE_STRIDE),
                  progress=lambda f, s: stages.append((f, s)))
    model.stages = stages
    return model
