"""UsdSkel export of a bone rig: USD's own skinning (UsdSkel.SkinningQuery) replays the rig."""

from __future__ import annotations

import numpy as np
from pxr import Usd, UsdSkel
from scipy.spatial.transform import Rotation

from service.io.usd_skel import skinned_points, write_skinned_usd
from service.methods.bone_rig.rig import BoneRig


def random_rig(seed: int = 0, V: int = 40, F: int = 5, B: int = 4, K: int = 3) -> BoneRig:
    rng = np.random.default_rng(seed)
    rest = rng.normal(size=(V, 3)) * 20.0
    index = np.stack([rng.permutation(B)[:K] for _ in range(V)])
    weight = rng.random((V, K))
    weight /= weight.sum(axis=1, keepdims=True)
    R = Rotation.random(F * B, random_state=seed).as_matrix().reshape(F, B, 3, 3)
    t = rng.normal(size=(F, B, 3)) * 5.0
    return BoneRig(rest, np.array([[0, 1, 2], [1, 2, 3]]), index, weight, R, t, 24.0)


def test_usd_skinning_of_the_written_stage_equals_the_rigs_linear_blend_skinning(tmp_path):
    rig = random_rig()
    path = tmp_path / "rig.usda"
    rig.write_usd(path)
    expected = rig.reconstruct()
    for f in range(rig.frames):
        # float32 points and quaternions of ~20 mm positions: within 1e-4 mm
        assert np.abs(skinned_points(path, f) - expected[f]).max() < 1e-4


def test_the_stage_carries_the_skeleton_animation_and_timing(tmp_path):
    rig = random_rig(seed=3, B=6)
    path = tmp_path / "rig.usd"
    rig.write_usd(path)
    stage = Usd.Stage.Open(str(path))
    assert stage.GetDefaultPrim().GetPath() == "/Rig"
    assert (stage.GetTimeCodesPerSecond(), stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (
        24.0, 0.0, rig.frames - 1)
    skeleton = UsdSkel.Skeleton(stage.GetPrimAtPath("/Rig/Skeleton"))
    assert len(skeleton.GetJointsAttr().Get()) == 6
    bind = np.array(skeleton.GetBindTransformsAttr().Get())               # (B,4,4), row vectors
    np.testing.assert_allclose(bind[:, 3, :3], rig.joint_rest(), rtol=0, atol=1e-9)
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Rig/Animation"))
    assert len(anim.GetTranslationsAttr().GetTimeSamples()) == rig.frames
