"""service.methods.shape_space.registration: an input rig registered to the actor's neutral
(bermano2014 §5.1) and its frames propagated to the actor's topology."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.methods.inputs import InvalidInput
from service.methods.shape_space.registration import RigRegistration, register_rig


@pytest.fixture(scope="module")
def own_rig(tmp_path_factory):
    """Level-0 sample actor (its neutral is the rig's topology): rig neutral + faces, the
    actor's neutral + faces, and the held-out performance's lowres and vertices_medium."""
    from service.samples.actor import build_sample_actor

    out = tmp_path_factory.mktemp("rig_actor")
    build_sample_actor(out, seed=2, level=0, with_tracking=False, map_resolution=64,
                       performance_names=("heldout_in_range",))
    with np.load(out / "neutral.npz") as n, np.load(out / "input_rig.npz") as r, \
            np.load(out / "performances" / "heldout_in_range.npz") as p:
        return dict(rig=n["rig_vertices"].astype(np.float64), rig_faces=r["faces"].astype(np.int64),
                    neutral=n["vertices"].astype(np.float64), faces=n["faces"].astype(np.int64),
                    lowres=p["lowres"][::10].astype(np.float64),
                    medium=p["vertices_medium"][::10].astype(np.float64))


def test_own_rig_propagates_to_the_medium_surface(own_rig):
    d = own_rig
    stages = []
    reg = register_rig(d["rig"], d["rig_faces"], d["neutral"], d["faces"],
                       progress=lambda f, s: stages.append((f, s)))
    assert reg.operator.shape == (len(d["neutral"]), len(d["rig"]))
    np.testing.assert_allclose(np.asarray(reg.operator.sum(axis=1)).ravel(), 1.0, atol=1e-9)
    out = reg.propagate(d["lowres"])
    err = np.linalg.norm(out - d["medium"], axis=2)
    motion = np.linalg.norm(d["medium"] - d["neutral"], axis=2)
    # measured: the level-0 neutral is the rig's own surface, rms 1e-4 mm (float32 inputs)
    assert np.sqrt((err ** 2).mean()) < 0.01 * np.sqrt((motion ** 2).mean())
    assert err.max() < 0.05
    assert reg.stats["actor_to_rig_rms"] < 0.01 and abs(reg.stats["scale"] - 1) < 1e-3
    assert stages[-1] == (1.0, "registered") and all(0 <= f <= 1 for f, _ in stages)


@pytest.fixture(scope="module")
def subdivided():
    """The ICT rig and a Loop-subdivided actor (its neutral S a0 and frames S r)."""
    from service.geometry.subdivision import subdivide
    from service.samples.rig import load_ict_rig

    rig = load_ict_rig()
    sub = subdivide(rig.triangles, rig.n_vertices, iterations=1, scheme="loop")
    rng = np.random.default_rng(4)
    frames = rig.neutral + rig.expression_offsets(rng.uniform(0, 0.6, (3, 53)))
    truth = np.stack([sub.S @ f for f in frames])
    return rig, sub.S @ rig.neutral, sub.faces, frames, truth


def test_rig_in_its_own_frame_and_scale_registers_with_landmarks(subdivided):
    rig, neutral, faces, frames, truth = subdivided
    R = Rotation.from_euler("xyz", [8, -12, 5], degrees=True).as_matrix()
    s, t = 0.1, np.array([3.0, -20.0, 7.0])       # the rig in cm, turned and shifted
    idx = np.random.default_rng(0).choice(rig.n_vertices, 12, replace=False)
    reg = register_rig(rig.neutral @ R.T * s + t, rig.triangles, neutral, faces,
                       landmarks=np.stack([idx, idx], axis=1))
    out = reg.propagate(frames @ R.T * s + t)
    err = np.linalg.norm(out - truth, axis=2)
    # measured: rms 0.12 mm, p99 0.13 mm against 4.6 mm rms motion; a few vertices inside
    # the mouth and eyes project onto a neighbouring part (max ≈ 8 mm)
    assert np.sqrt((err ** 2).mean()) < 0.2
    assert np.quantile(err, 0.99) < 0.2
    assert abs(reg.stats["scale"] - 10) < 0.05 and reg.stats["landmark_rms"] < 0.3

    back = RigRegistration.load(reg.save())
    np.testing.assert_array_equal(back.propagate(frames[:1] @ R.T * s + t), out[:1])
    assert back.stats == reg.stats


def test_malformed_input_is_refused(own_rig):
    d = own_rig
    with pytest.raises(InvalidInput, match="landmark"):
        register_rig(d["rig"], d["rig_faces"], d["neutral"], d["faces"],
                     landmarks=[[len(d["rig"]), 0]] * 3)
    with pytest.raises(InvalidInput, match="faces"):
        register_rig(d["rig"], d["rig_faces"] + len(d["rig"]), d["neutral"], d["faces"])
    with pytest.raises(InvalidInput, match="not a rig registration"):
        RigRegistration.load(b"not an npz")
