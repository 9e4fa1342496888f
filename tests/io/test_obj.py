"""OBJ files that mix corner forms across objects, read as trimesh reads them (order kept)."""

import io

import numpy as np
import pytest
import trimesh

from service.io.errors import MeshFormatError
from service.io.obj import read_obj, write_obj

TEXTURED = """o textured
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
vt 0.125 0.25
vt 0.75 0.0625
vt 0.875 0.625
vt 0.0 1.0
vn 0 0 1
f 1/1 2/2 3/3
f 1/1/1 3/3/1 4/4/1
"""
BARE = """o bare
v 2 0 0
v 3 0 0
v 3 1 0
f 5 6 7
"""
NORMALS = """o normals
v 4 0 0
v 5 0 0
v 5 1 0
v 4 1 0
f 8//1 9//1 10//1 11//1
"""
MIXED = (TEXTURED + BARE + NORMALS + "f -11/-4 -9/-2 -8/-1\n").encode()  # a textured face last


def _trimesh(text: bytes) -> trimesh.Trimesh:
    return trimesh.load(io.BytesIO(text), file_type="obj", process=False, maintain_order=True)


def test_mixed_corner_forms_keep_vertex_order_like_trimesh():
    mesh = read_obj(MIXED)
    reference = _trimesh(MIXED)
    assert np.array_equal(mesh.vertices, reference.vertices)  # every vertex, in file order
    triangles = [0, 1, 2, 5]  # the file's triangles, in file order
    assert np.array_equal(mesh.faces[triangles], reference.faces[triangles])
    # the quad: our fan (a,b,c),(a,c,d); trimesh splits it (a,b,c),(c,d,a): the same two triangles
    assert mesh.faces[3:5].tolist() == [[7, 8, 9], [7, 9, 10]]
    assert sorted(map(sorted, reference.faces[3:5].tolist())) == [[7, 8, 9], [7, 9, 10]]
    assert mesh.quad_split.tolist() == [0, 1, 2, 3, 3, 4]


def test_mixed_corner_forms_give_uv_where_the_file_gives_them_like_trimesh():
    mesh = read_obj(MIXED)
    assert mesh.uv_faces.tolist() == [[0, 1, 2], [0, 2, 3], [-1] * 3, [-1] * 3, [-1] * 3, [0, 2, 3]]
    # trimesh drops the uv of a file that mixes forms; it reads the textured object alone
    reference = _trimesh(TEXTURED.encode())
    textured = mesh.uv_faces[:, 0] >= 0
    assert np.array_equal(mesh.uv[mesh.uv_faces[textured]], reference.visual.uv[mesh.faces[textured]])


def test_mixed_corner_forms_round_trip_through_write_obj():
    mesh = read_obj(MIXED)
    buffer = io.BytesIO()
    write_obj(buffer, mesh)
    faces = [line for line in buffer.getvalue().decode().splitlines() if line.startswith("f")]
    assert faces == ["f 1/1 2/2 3/3", "f 1/1 3/3 4/4", "f 5 6 7", "f 8 9 10 11", "f 1/1 3/3 4/4"]
    back = read_obj(buffer.getvalue())
    for name in ("vertices", "faces", "uv", "uv_faces", "quad_split"):
        assert np.array_equal(getattr(back, name), getattr(mesh, name)), name


def test_a_file_of_bare_and_normal_corners_has_no_uv():
    mesh = read_obj((BARE.replace("f 5 6 7", "f 1 2 3") + "vn 0 0 1\nf 1//1 2//1 3//1\n").encode())
    assert mesh.uv is None and mesh.uv_faces is None


@pytest.mark.parametrize(
    "faces, message",
    [
        ("f 1/1 2 3\n", "face 0 (line 7) has corner '2' but the first corner of the face is '1/1'"),
        ("f 1 2 3\nf 1//1 2/1/1 3//1\n", "face 1 (line 8) has corner '2/1/1' but the first corner of the face is '1//1'"),
        ("f 1/1/1/1 2 3\n", "has corner '1/1/1/1'; a corner is one of v, v/vt, v/vt/vn, v//vn"),
    ],
)
def test_mixing_forms_within_one_face_is_refused(faces, message):
    head = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvn 0 0 1\n"
    with pytest.raises(MeshFormatError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_obj((head + faces).encode())
