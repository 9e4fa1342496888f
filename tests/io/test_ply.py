"""PLY per-face texcoord lists (MeshLab/VCG) read as per-corner uv, like trimesh reads them."""

import io

import numpy as np
import plyfile
import pytest
import trimesh

from service.io.errors import MeshFormatError
from service.io.ply import read_ply

FACES = [[0, 1, 2], [0, 2, 3, 4], [1, 4, 3]]
TRIANGLES = [[0, 1, 2], [0, 2, 3], [1, 4, 3], [3, 4, 0]]


def _meshlab_ply(texcoord, text=False, vertex_uv=False, faces=FACES) -> bytes:
    """A PLY as MeshLab writes per-wedge uv: face lists vertex_indices and texcoord, by plyfile."""
    rng = np.random.default_rng(5)
    columns = [("x", "f4"), ("y", "f4"), ("z", "f4")] + ([("s", "f4"), ("t", "f4")] if vertex_uv else [])
    vertex = np.zeros(5, columns)
    for name, _ in columns:
        vertex[name] = rng.normal(size=5)
    face = np.empty(len(faces), [("vertex_indices", object), ("texcoord", object)])
    face["vertex_indices"] = [np.array(f, np.int32) for f in faces]
    face["texcoord"] = [np.asarray(t, np.float32) for t in texcoord]
    ply = plyfile.PlyData(
        [plyfile.PlyElement.describe(vertex, "vertex"),
         plyfile.PlyElement.describe(face, "face", val_types={"vertex_indices": "i4", "texcoord": "f4"},
                                     len_types={"vertex_indices": "u1", "texcoord": "u1"})],
        text=text,
    )  # fmt: skip
    buffer = io.BytesIO()
    ply.write(buffer)
    return buffer.getvalue()


def _texcoord(seed=6, faces=FACES):
    rng = np.random.default_rng(seed)
    return [rng.random(2 * len(f)).astype(np.float32) for f in faces]


@pytest.mark.parametrize("text", [False, True])
def test_face_texcoord_lists_are_per_corner_uv_like_trimesh(text):
    data = _meshlab_ply(_texcoord(faces=TRIANGLES), text=text, faces=TRIANGLES)
    mesh = read_ply(data)
    reference = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
    # trimesh splits every corner into its own vertex; compare corner by corner
    assert len(mesh.faces) == len(reference.faces) == 4
    assert np.array_equal(mesh.vertices[mesh.faces], reference.vertices[reference.faces])
    assert np.array_equal(mesh.uv[mesh.uv_faces], reference.visual.uv[reference.faces])
    assert len(mesh.vertices) == 5  # our vertices stay the file's five, in order


def test_face_texcoord_of_polygons_follow_their_corners_like_plyfile():
    """trimesh cannot read texcoord lists of mixed polygon sizes; plyfile reads them as written."""
    data = _meshlab_ply(_texcoord())
    mesh = read_ply(data)
    reference = plyfile.PlyData.read(io.BytesIO(data))["face"]["texcoord"]
    sizes, corners, uv_corners = mesh.polygons()
    assert sizes.tolist() == [3, 4, 3] and corners.tolist() == sum(FACES, [])
    assert np.array_equal(mesh.uv[uv_corners], np.concatenate(reference).reshape(-1, 2))


def test_a_face_with_an_empty_texcoord_list_has_no_uv():
    texcoord = _texcoord()
    texcoord[2] = np.zeros(0, np.float32)
    mesh = read_ply(_meshlab_ply(texcoord))
    assert mesh.uv_faces[-1].tolist() == [-1, -1, -1] and (mesh.uv_faces[:3] >= 0).all()
    assert np.array_equal(mesh.uv[mesh.uv_faces[0]], texcoord[0].reshape(3, 2))


def test_per_vertex_uv_is_kept_when_the_faces_also_have_texcoord():
    data = _meshlab_ply(_texcoord(), vertex_uv=True)
    mesh = read_ply(data)
    assert mesh.uv_faces is None and len(mesh.uv) == 5


def test_a_texcoord_list_of_the_wrong_length_is_refused():
    texcoord = _texcoord()
    texcoord[1] = texcoord[1][:6]
    with pytest.raises(MeshFormatError, match=r"PLY face 1 has 6 texcoord values for its 4 corners; expected 2 per corner"):
        read_ply(_meshlab_ply(texcoord))
