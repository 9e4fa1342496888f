"""UsdSkel export of a linear-blend-skinned mesh with its bone animation (the USD twin of
:mod:`service.io.gltf`).

The stage's default prim ``/Rig`` is a ``SkelRoot`` holding

- ``/Rig/Skeleton``: one root joint per bone (``bone_000`` …, no hierarchy: SSDR's bones are
  independent rigid bodies), ``bindTransforms`` = ``restTransforms`` = the translation to the
  joint's rest position c_j;
- ``/Rig/Animation``: a ``SkelAnimation`` with ``translations``, ``rotations`` and
  ``scales`` time-sampled at time codes 0 … F-1 (``timeCodesPerSecond`` = fps);
- ``/Rig/Mesh``: the rest mesh with ``primvars:skel:jointIndices`` / ``jointWeights``
  (vertex interpolation, elementSize K) and ``skel:skeleton`` bound to the skeleton.

Bone transforms (R_j^t, T_j^t) map rest space to frame t. USD skins a point p with
``p · inverse(bind_j) · world_j`` (row vectors); with ``bind_j`` the translation by c_j and
``world_j`` the rotation R_j^t followed by the translation ``R_j^t c_j + T_j^t``, that is
``R_j^t (p − c_j) + R_j^t c_j + T_j^t = R_j^t p + T_j^t``: an application reading the file
(``UsdSkel.SkinningQuery``) replays ``v = Σ_j w_ij (R_j^t p_i + T_j^t)`` exactly as
:meth:`service.methods.bone_rig.rig.BoneRig.reconstruct`. Vertex order and count are
written as given (the correspondence is the vertex order: DESIGN.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt
from scipy.spatial.transform import Rotation

from service.io.usd import export_stage


def write_skinned_usd(path, rest: np.ndarray, faces: np.ndarray | None, index: np.ndarray,
                      weight: np.ndarray, R: np.ndarray, t: np.ndarray, joint_rest: np.ndarray,
                      fps: float, meters_per_unit: float = 0.001) -> None:
    """Write a skinned, animated mesh as a USD stage (module docstring), atomically.

    Parameters
    ----------
    path : file to write; ``.usd`` (binary crate) or ``.usda`` (text)
    rest : (V,3) float      rest-pose positions
    faces : (m,3) int | None   triangles (None: the mesh is written as points only)
    index : (V,K) int       bone of each influence
    weight : (V,K) float    non-negative, rows summing to 1
    R : (F,B,3,3) float     rotations rest → frame;  t : (F,B,3) translations
    joint_rest : (B,3)      rest positions of the joints
    fps : float             frames per second
    meters_per_unit : float the unit of every length (0.001: mm, facesynth's)
    """
    path = Path(path)
    rest = np.asarray(rest, np.float64)
    V, K = index.shape
    F, B = R.shape[:2]
    stage = Usd.Stage.CreateInMemory(path.name)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    stage.SetTimeCodesPerSecond(float(fps))
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(max(F - 1, 0))

    root = UsdSkel.Root.Define(stage, "/Rig")
    stage.SetDefaultPrim(root.GetPrim())
    joints = Vt.TokenArray([f"bone_{j:03d}" for j in range(B)])
    c = np.asarray(joint_rest, np.float64)
    bind = [Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(*map(float, cj))) for cj in c]

    skeleton = UsdSkel.Skeleton.Define(stage, "/Rig/Skeleton")
    skeleton.CreateJointsAttr(joints)
    skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray(bind))
    skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray(bind))

    anim = UsdSkel.Animation.Define(stage, "/Rig/Animation")
    anim.CreateJointsAttr(joints)
    translations = anim.CreateTranslationsAttr()
    rotations = anim.CreateRotationsAttr()
    anim.CreateScalesAttr().Set(Vt.Vec3hArray.FromNumpy(np.ones((B, 3), np.float16)))
    world_t = np.einsum("fbij,bj->fbi", R, c) + t                          # (F,B,3)
    quat = Rotation.from_matrix(np.asarray(R, np.float64).reshape(-1, 3, 3)).as_quat()
    quat = quat.reshape(F, B, 4).astype(np.float32)                       # x y z w = Gf's layout
    for f in range(F):
        translations.Set(Vt.Vec3fArray.FromNumpy(world_t[f].astype(np.float32)), Usd.TimeCode(f))
        rotations.Set(Vt.QuatfArray.FromNumpy(np.ascontiguousarray(quat[f])), Usd.TimeCode(f))
    UsdSkel.BindingAPI.Apply(root.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [anim.GetPath()])

    mesh = UsdGeom.Mesh.Define(stage, "/Rig/Mesh")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(rest.astype(np.float32)))
    tris = np.zeros((0, 3), np.int32) if faces is None else np.asarray(faces, np.int32)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(tris), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(tris.ravel()))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    binding.CreateJointIndicesPrimvar(False, K).Set(
        Vt.IntArray.FromNumpy(np.asarray(index, np.int32).ravel()))
    binding.CreateJointWeightsPrimvar(False, K).Set(
        Vt.FloatArray.FromNumpy(np.asarray(weight, np.float32).ravel()))
    mesh.GetPrim().CreateAttribute("facesynth:vertexCount", Sdf.ValueTypeNames.Int).Set(V)
    export_stage(stage, path)


def skinned_points(path, frame: int) -> np.ndarray:
    """The mesh of a file written by :func:`write_skinned_usd` skinned by UsdSkel itself at
    ``frame`` — (V,3) float64, the reference reader's answer, for checks."""
    stage = Usd.Stage.Open(str(path))
    cache = UsdSkel.Cache()
    root = UsdSkel.Root(stage.GetPrimAtPath("/Rig"))
    cache.Populate(root, Usd.PrimDefaultPredicate)
    skel_query = cache.GetSkelQuery(UsdSkel.Skeleton(stage.GetPrimAtPath("/Rig/Skeleton")))
    time = Usd.TimeCode(frame)
    xforms = skel_query.ComputeSkinningTransforms(time)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Rig/Mesh"))
    points = mesh.GetPointsAttr().Get(time)
    query = cache.GetSkinningQuery(mesh.GetPrim())
    if not query.ComputeSkinnedPoints(xforms, points, time):
        raise ValueError(f"UsdSkel could not skin {path} at frame {frame}")
    return np.asarray(points, np.float64)
