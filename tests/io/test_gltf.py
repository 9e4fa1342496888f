"""The .glb skin written by service.io.gltf, read back with pygltflib and replayed."""

import numpy as np
import pygltflib as gl
import pytest
from scipy.spatial.transform import Rotation

from service.geometry.deformation_gradient import rotation_exp
from service.io.gltf import write_skinned_glb
from service.methods.bone_rig.skinning import skin

DTYPES = {gl.FLOAT: np.float32, gl.UNSIGNED_SHORT: np.uint16, gl.UNSIGNED_INT: np.uint32,
          gl.UNSIGNED_BYTE: np.uint8}
WIDTH = {gl.SCALAR: 1, gl.VEC3: 3, gl.VEC4: 4, gl.MAT4: 16}


def accessor(g: gl.GLTF2, i: int) -> np.ndarray:
    a = g.accessors[i]
    view = g.bufferViews[a.bufferView]
    blob = g.binary_blob()
    dt = np.dtype(DTYPES[a.componentType])
    start = view.byteOffset + (a.byteOffset or 0)
    data = np.frombuffer(blob, dt, count=a.count * WIDTH[a.type], offset=start)
    return data.reshape(a.count, WIDTH[a.type]) if WIDTH[a.type] > 1 else data


def replay(path) -> tuple[np.ndarray, np.ndarray]:
    """Linear blend skinning of every animation key, as a glTF engine evaluates it:
    joint global = root (identity) · TRS(key), skin matrix = global · inverseBind."""
    g = gl.GLTF2().load(str(path))
    prim = g.meshes[0].primitives[0]
    P = accessor(g, prim.attributes.POSITION).astype(np.float64)
    sets = [(accessor(g, getattr(prim.attributes, f"JOINTS_{s}")).astype(np.int64),
             accessor(g, getattr(prim.attributes, f"WEIGHTS_{s}")).astype(np.float64))
            for s in range(2) if getattr(prim.attributes, f"JOINTS_{s}", None) is not None]
    J = np.concatenate([s[0] for s in sets], axis=1)
    W = np.concatenate([s[1] for s in sets], axis=1)
    skin_ = g.skins[g.nodes[-1].skin]
    ibm = accessor(g, skin_.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)   # column-major
    B = len(skin_.joints)
    anim = g.animations[0]
    times = None
    trans, rot = {}, {}
    for ch in anim.channels:
        s = anim.samplers[ch.sampler]
        times = accessor(g, s.input)
        (trans if ch.target.path == "translation" else rot)[skin_.joints.index(ch.target.node)] = accessor(g, s.output)
    F = len(times)
    out = np.zeros((F, len(P), 3))
    for f in range(F):
        M = np.empty((B, 4, 4))
        for j in range(B):
            G = np.eye(4)
            G[:3, :3] = Rotation.from_quat(rot[j][f]).as_matrix()
            G[:3, 3] = trans[j][f]
            M[j] = G @ ibm[j]
        Ph = np.column_stack([P, np.ones(len(P))])
        for k in range(J.shape[1]):
            out[f] += W[:, k, None] * np.einsum("vij,vj->vi", M[J[:, k]], Ph)[:, :3]
    faces = accessor(g, prim.indices).reshape(-1, 3) if prim.indices is not None else None
    return out, faces


@pytest.mark.parametrize("K", [3, 6])
def test_glb_round_trip_replays_the_skinning(tmp_path, K):
    rng = np.random.default_rng(5)
    V, B, F = 40, 9, 7
    rest = rng.normal(scale=30.0, size=(V, 3))
    faces = np.array([[i, i + 1, i + 2] for i in range(V - 2)])
    index = np.stack([rng.choice(B, K, replace=False) for _ in range(V)])
    weight = rng.dirichlet(np.ones(K), size=V)
    R = rotation_exp(rng.normal(scale=0.5, size=(F, B, 3)))
    t = rng.normal(scale=10.0, size=(F, B, 3))
    centres = rng.normal(scale=20.0, size=(B, 3))
    path = tmp_path / "rig.glb"
    write_skinned_glb(path, rest, faces, index, weight, R, t, centres, fps=24.0)
    replayed, back_faces = replay(path)
    expected = skin(rest, index, weight, R, t)
    # float32 storage: positions ~30 mm, so ~1e-5 mm
    assert np.abs(replayed - expected).max() < 1e-3
    np.testing.assert_array_equal(back_faces, faces)
    g = gl.GLTF2().load(str(path))
    assert g.accessors[g.animations[0].samplers[0].input].max == [pytest.approx((F - 1) / 24.0)]
    assert len(g.skins[0].joints) == B
    assert g.meshes[0].primitives[0].mode == gl.TRIANGLES


def test_glb_loads_in_trimesh_with_vertex_order(tmp_path):
    import trimesh

    rest = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0]])
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    R = np.broadcast_to(np.eye(3), (2, 1, 3, 3))
    t = np.array([[[0.0, 0, 0]], [[0, 0, 5]]])
    write_skinned_glb(tmp_path / "q.glb", rest, faces, np.zeros((4, 1), int), np.ones((4, 1)), R, t,
                      np.zeros((1, 3)), fps=30)
    scene = trimesh.load(tmp_path / "q.glb", process=False)
    mesh = list(scene.geometry.values())[0]
    np.testing.assert_allclose(mesh.vertices, rest)
    np.testing.assert_array_equal(mesh.faces, faces)
