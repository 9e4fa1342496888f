"""glTF 2.0 binary (.glb) export of a linear-blend-skinned mesh with its bone animation.

One mesh (POSITION, triangle indices when faces are given, else points), one skin (one
joint node per bone under a common root, ``inverseBindMatrices``), ``JOINTS_0``/``WEIGHTS_0``
(and ``JOINTS_1``/``WEIGHTS_1`` for 5–8 influences) per vertex, and one animation with a
LINEAR ``translation`` and ``rotation`` channel per joint, one key per frame at ``f / fps``
seconds. Built with ``pygltflib``; vertex order and count are written as given (the
correspondence is the vertex order: DESIGN.md), so positions are not split at UV seams and
no UVs are written.

Bone transforms (R_j^t, T_j^t) map rest space to frame t. Joint j rests at c_j (its
inverse bind matrix is the translation by −c_j) and at frame t has the global transform
``[R_j^t | R_j^t c_j + T_j^t]``, so the skinning matrix ``global · inverseBind`` is
``[R_j^t | T_j^t]`` and an engine reproduces ``v = Σ_j w_ij (R_j^t p_i + T_j^t)``.
Units are the caller's (mm for facesynth); glTF's metres are not imposed.
"""

from __future__ import annotations

import numpy as np
import pygltflib as gl
from scipy.spatial.transform import Rotation

from service.io.atomic import write_bytes

#: influences per JOINTS_n/WEIGHTS_n attribute pair
SET_SIZE = 4


class _Blob:
    """The binary buffer under construction: 4-byte aligned buffer views and accessors."""

    def __init__(self, gltf: gl.GLTF2):
        self.gltf, self.data = gltf, bytearray()

    def add(self, array: np.ndarray, component: int, kind: str, target: int | None = None,
            bounds: bool = False) -> int:
        raw = np.ascontiguousarray(array).tobytes()
        self.data += b"\0" * (-len(self.data) % 4)
        view = gl.BufferView(buffer=0, byteOffset=len(self.data), byteLength=len(raw), target=target)
        self.data += raw
        self.gltf.bufferViews.append(view)
        count = len(array)
        acc = gl.Accessor(bufferView=len(self.gltf.bufferViews) - 1, componentType=component,
                          count=count, type=kind)
        if bounds:
            flat = np.asarray(array).reshape(count, -1)
            acc.min, acc.max = flat.min(axis=0).tolist(), flat.max(axis=0).tolist()
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1


def write_skinned_glb(path, rest: np.ndarray, faces: np.ndarray | None, index: np.ndarray,
                      weight: np.ndarray, R: np.ndarray, t: np.ndarray, joint_rest: np.ndarray,
                      fps: float, name: str = "facesynth_rig") -> str:
    """Write a skinned, animated mesh as a .glb (module docstring); returns its sha256.

    Parameters
    ----------
    path : file to write (atomically)
    rest : (V,3) float      rest-pose positions
    faces : (m,3) int | None
    index : (V,K) int       joint of each influence (K ≤ 8), < 65536 joints
    weight : (V,K) float    non-negative, rows summing to 1
    R : (F,B,3,3) float     rotations rest → frame;  t : (F,B,3) translations
    joint_rest : (B,3)      rest positions of the joints
    fps : float             frames per second of the animation
    """
    rest = np.asarray(rest, np.float32)
    V, K = index.shape
    F, B = R.shape[:2]
    if K > 2 * SET_SIZE:
        raise ValueError(f"at most {2 * SET_SIZE} influences per vertex, got {K}")
    if B >= 65536:
        raise ValueError(f"at most 65535 joints, got {B}")
    sets = -(-K // SET_SIZE)
    J = np.zeros((V, sets * SET_SIZE), np.uint16)
    W = np.zeros((V, sets * SET_SIZE), np.float32)
    J[:, :K], W[:, :K] = index, weight
    J[W == 0] = 0
    W /= W.sum(axis=1, keepdims=True)

    gltf = gl.GLTF2(asset=gl.Asset(version="2.0", generator="facesynth bone_rig"))
    blob = _Blob(gltf)
    attrs = gl.Attributes(POSITION=blob.add(rest, gl.FLOAT, gl.VEC3, gl.ARRAY_BUFFER, bounds=True))
    for s in range(sets):
        setattr(attrs, f"JOINTS_{s}", blob.add(J[:, 4 * s:4 * s + 4], gl.UNSIGNED_SHORT, gl.VEC4, gl.ARRAY_BUFFER))
        setattr(attrs, f"WEIGHTS_{s}", blob.add(W[:, 4 * s:4 * s + 4], gl.FLOAT, gl.VEC4, gl.ARRAY_BUFFER))
    prim = gl.Primitive(attributes=attrs, mode=gl.POINTS)
    if faces is not None and len(faces):
        prim.indices = blob.add(np.asarray(faces, np.uint32).ravel(), gl.UNSIGNED_INT, gl.SCALAR,
                                gl.ELEMENT_ARRAY_BUFFER)
        prim.mode = gl.TRIANGLES
    gltf.meshes.append(gl.Mesh(name=name, primitives=[prim]))

    c = np.asarray(joint_rest, np.float64)
    ibm = np.broadcast_to(np.eye(4), (B, 4, 4)).copy()
    ibm[:, :3, 3] = -c
    ibm_acc = blob.add(np.swapaxes(ibm, 1, 2).reshape(B, 16).astype(np.float32), gl.FLOAT, gl.MAT4)
    gltf.nodes = [gl.Node(name=f"bone_{j:03d}", translation=c[j].tolist()) for j in range(B)]
    root = B
    gltf.nodes.append(gl.Node(name="rig_root", children=list(range(B))))
    gltf.nodes.append(gl.Node(name=name, mesh=0, skin=0))
    gltf.skins.append(gl.Skin(name=name, joints=list(range(B)), skeleton=root,
                              inverseBindMatrices=ibm_acc))
    gltf.scenes.append(gl.Scene(nodes=[root, B + 1]))
    gltf.scene = 0

    times = blob.add((np.arange(F) / float(fps)).astype(np.float32), gl.FLOAT, gl.SCALAR, bounds=True)
    trans = np.einsum("fbij,bj->fbi", R, c) + t                            # (F,B,3)
    quat = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat().reshape(F, B, 4)   # x y z w
    anim = gl.Animation(name="performance")
    for j in range(B):
        for path_name, values, kind in (("translation", trans[:, j], gl.VEC3), ("rotation", quat[:, j], gl.VEC4)):
            out = blob.add(values.astype(np.float32), gl.FLOAT, kind)
            anim.samplers.append(gl.AnimationSampler(input=times, output=out, interpolation="LINEAR"))
            anim.channels.append(gl.AnimationChannel(sampler=len(anim.samplers) - 1,
                                                     target=gl.AnimationChannelTarget(node=j, path=path_name)))
    gltf.animations.append(anim)
    gltf.buffers.append(gl.Buffer(byteLength=len(blob.data)))
    gltf.set_binary_blob(bytes(blob.data))
    return write_bytes(path, b"".join(gltf.save_to_bytes()))
