"""Mesh files: order-preserving OBJ/PLY/NPZ round trips, polygon splits and clear errors."""

import io
import pickle
import struct
from pathlib import Path

import numpy as np
import pytest

from service.io.errors import FormatError, MeshFormatError, SizeLimitError
from service.io.mesh import (
    Mesh,
    read_mesh,
    read_npz,
    read_obj,
    read_ply,
    write_npz,
    write_obj,
    write_ply,
)
from tests.io.corruption import corrupt

RIG = Path(__file__).parents[2] / "service" / "samples" / "data" / "ict_face_rig.npz"


@pytest.fixture(scope="module")
def rig():
    with np.load(RIG) as data:
        return {key: data[key] for key in ("neutral", "quads", "quad_uv", "uv", "triangles", "triangle_uv")}


@pytest.fixture(scope="module")
def rig_mesh(rig):
    """The rig as read from its quads: fan-split triangles, per-corner uv, quad per triangle."""
    return Mesh(
        rig["neutral"], rig["triangles"], rig["uv"], rig["triangle_uv"],
        quad_split=np.repeat(np.arange(len(rig["quads"])), 2),
    )  # fmt: skip


def _random_mesh(seed=0, vertices=40, dtype=np.float64):
    """A small mesh whose values span denormals, negatives and large magnitudes."""
    rng = np.random.default_rng(seed)
    positions = rng.normal(size=(vertices, 3)) * 10.0 ** rng.integers(-30, 30, (vertices, 3))
    positions[0] = [5e-324 if dtype == np.float64 else 1e-45, -0.0, 3.4e38]
    faces = rng.integers(0, vertices, (60, 3))
    return Mesh(positions.astype(dtype), faces, rng.random((vertices, 2)).astype(dtype))


def _bits_equal(a, b):
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a.view(np.uint8), b.view(np.uint8))


# ---------------------------------------------------------------------------- OBJ


def test_obj_round_trip_of_ict_rig_preserves_indices_uv_seams_and_quads(rig, rig_mesh, tmp_path):
    path = tmp_path / "rig.obj"
    write_obj(path, rig_mesh, dtype=np.float32)
    face_lines = [line for line in path.read_text().splitlines() if line.startswith("f ")]
    assert len(face_lines) == 11144 and all(len(line.split()) == 5 for line in face_lines)
    assert face_lines[0].split()[1:] == [
        f"{v + 1}/{t + 1}" for v, t in zip(rig["quads"][0], rig["quad_uv"][0])
    ]

    mesh = read_obj(path)

    assert _bits_equal(mesh.vertices.astype(np.float32), rig["neutral"])
    assert _bits_equal(mesh.uv.astype(np.float32), rig["uv"])
    assert np.array_equal(mesh.faces, rig["triangles"])
    assert np.array_equal(mesh.uv_faces, rig["triangle_uv"])
    assert np.array_equal(mesh.quad_split, np.repeat(np.arange(11144), 2))
    assert len(mesh.seam_vertices()) == 402
    sizes, corners, uv_corners = mesh.polygons()
    assert np.array_equal(sizes, np.full(11144, 4))
    assert np.array_equal(corners, rig["quads"].ravel())
    assert np.array_equal(uv_corners, rig["quad_uv"].ravel())


def test_obj_float64_round_trip_is_bit_exact(tmp_path):
    mesh = _random_mesh()
    write_obj(tmp_path / "m.obj", mesh)
    back = read_obj(tmp_path / "m.obj")
    assert _bits_equal(back.vertices, mesh.vertices)
    assert _bits_equal(back.uv, mesh.uv)
    assert np.array_equal(back.faces, mesh.faces)
    assert np.array_equal(back.uv_faces, mesh.faces)  # per-vertex uv written as one vt per vertex


def test_obj_reads_every_corner_form_and_relative_indices():
    head = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nvn 0 0 1\n"
    for faces, uv_faces in [
        (b"f 1 2 3\n", None),
        (b"f 1/3 2/2 3/1\n", [[2, 1, 0]]),
        (b"f 1/3/1 2/2/1 3/1/1\n", [[2, 1, 0]]),
        (b"f 1//1 2//1 3//1\n", None),
        (b"f -3/-1 -2/-2 -1/-3\n", [[2, 1, 0]]),
    ]:
        mesh = read_obj(head + faces)
        assert mesh.faces.tolist() == [[0, 1, 2]]
        assert (mesh.uv_faces is None and mesh.uv is None) if uv_faces is None else (
            mesh.uv_faces.tolist() == uv_faces
        )


def test_obj_relative_index_counts_from_the_faces_own_line():
    mesh = read_obj(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 1 1 0\nf -4 -2 -1\n")
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3]]


def test_obj_splits_polygons_as_fans_and_reports_the_source_polygon():
    text = b"v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv -1 1 0\nf 1 2 3\nf 1 2 3 4 5\nf 2 3 4 1\n"
    mesh = read_obj(text)
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 1, 2], [0, 2, 3], [0, 3, 4], [1, 2, 3], [1, 3, 0]]
    assert mesh.quad_split.tolist() == [0, 1, 1, 1, 2, 2]
    sizes, corners, _ = mesh.polygons()
    assert sizes.tolist() == [3, 5, 4]
    assert corners.tolist() == [0, 1, 2, 0, 1, 2, 3, 4, 1, 2, 3, 0]


def test_obj_of_triangles_only_has_no_quad_split():
    assert read_obj(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").quad_split is None


def test_obj_keeps_duplicate_and_unused_vertices_in_file_order():
    text = b"v 1 2 3\nv 1 2 3\nv 0 0 0\nv 9 9 9 1.0\nv 0 1 0 0.5 0.5 0.5\nf 1 3 5\n"
    mesh = read_obj(text)
    assert mesh.vertices.tolist() == [[1, 2, 3], [1, 2, 3], [0, 0, 0], [9, 9, 9], [0, 1, 0]]
    assert mesh.faces.tolist() == [[0, 2, 4]]


def test_obj_accepts_crlf_indentation_comments_and_line_continuations():
    text = b"# c\r\no head\r\n  v 0 0 0\r\n\tv 1 0 0\r\nv 0 1 0\r\ng g\r\nusemtl m\r\nf 1 \\\r\n2 3\r\n"
    assert read_obj(text).faces.tolist() == [[0, 1, 2]]


def test_obj_write_reads_back_the_same_polygons_it_was_read_from():
    text = b"v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv -1 1 0\nf 1 2 3\nf 1 2 3 4 5\nf 2 3 4 1\n"
    mesh = read_obj(text)
    buffer = io.BytesIO()
    write_obj(buffer, mesh)
    faces = [line for line in buffer.getvalue().decode().splitlines() if line.startswith("f")]
    assert faces == ["f 1 2 3", "f 1 2 3 4 5", "f 2 3 4 1"]


_TRIANGLE = b"v 0 0 0\nv 1 0 0\nv 0 1 0\n"


@pytest.mark.parametrize(
    "text, message",
    [
        (_TRIANGLE + b"f 1 2 4\n", "face 0 (line 4) references vertex 4 but the file has 3 vertices"),
        (_TRIANGLE + b"f 1 2 3\nf 1 -4 3\n", "face 1 (line 5) references vertex -4 but only 3 vertices precede"),
        (_TRIANGLE + b"f 0 1 2\n", "references vertex 0 but OBJ indices start at 1"),
        (_TRIANGLE + b"f 1 2\n", "face 0 (line 4) has 2 corners; a face needs at least 3"),
        (_TRIANGLE + b"vt 0 0\nf 1/1 2/1 3/2\n", "references texture coordinate 2 but the file has 1 texture coordinates"),
        (_TRIANGLE + b"vt 0 0\nf 1/1 2/1 3\n", "has corner '3' but the first corner of the face is '1/1'"),
        (_TRIANGLE + b"vt 0 0\nf 1/1/1 2//1 3/1/1\n", "either every corner has a texture index or none does"),
        (_TRIANGLE + b"f 1 2 3.5\n", "face 0 (line 4) has vertex index '3.5', expected an integer"),
        (b"v 0 0 0\nv inf 0 0\nv 0 1 0\nf 1 2 3\n", "vertex 1 (line 2) has a non-finite coordinate"),
        (b"v 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "line 1: a vertex needs 3 numbers, got '0 0'"),
        (b"v 0 0 x\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "line 1: cannot read vertex numbers from '0 0 x'"),
        (b"f 1 2 3\n", "the OBJ file has no vertices"),
        (_TRIANGLE, "the OBJ file has no faces"),
    ],
)
def test_obj_rejects_bad_input_with_a_specific_message(text, message):
    with pytest.raises(MeshFormatError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_obj(text)


def test_obj_bounds_counts_before_parsing_numbers():
    with pytest.raises(SizeLimitError, match="declares 3 vertices, more than the limit of 2"):
        read_obj(_TRIANGLE + b"f 1 2 3\n", max_vertices=2)
    with pytest.raises(SizeLimitError, match="declares 3 triangles, more than the limit of 2"):
        read_obj(_TRIANGLE + b"v 1 1 0\nv 2 2 0\nf 1 2 3 4 5\n", max_faces=2)


# ---------------------------------------------------------------------------- PLY


def _fan_mesh(vertices, uv, polygons):
    """Reference fan split: polygon (a,b,c,d,...) -> (a,b,c), (a,c,d), ..."""
    faces, split = [], []
    for p, polygon in enumerate(polygons):
        for k in range(1, len(polygon) - 1):
            faces.append([polygon[0], polygon[k], polygon[k + 1]])
            split.append(p)
    return Mesh(vertices, faces, uv, quad_split=split)


_POLYGONS = [[0, 1, 2, 3], [4, 5, 6], [7, 8, 9, 10, 11], [3, 2, 1, 0], [12, 39, 20, 30]]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_ply_binary_round_trip_is_bit_exact_with_polygons_and_uv(dtype, tmp_path):
    source = _random_mesh(seed=1, dtype=dtype)
    mesh = _fan_mesh(source.vertices, source.uv, _POLYGONS)
    write_ply(tmp_path / "m.ply", mesh, dtype=dtype)
    back = read_ply(tmp_path / "m.ply")
    assert _bits_equal(back.vertices.astype(dtype), source.vertices.astype(dtype))
    assert _bits_equal(back.uv.astype(dtype), source.uv.astype(dtype))
    assert np.array_equal(back.faces, mesh.faces)
    assert back.quad_split.tolist() == [0, 0, 1, 2, 2, 2, 3, 3, 4, 4]
    assert back.uv_faces is None


def test_ply_reads_ascii_with_extra_properties_and_wedge_lists():
    text = b"""ply
format ascii 1.0
comment made by hand
element vertex 5
property float x
property float y
property float z
property uchar red
property float texture_u
property float texture_v
element face 2
property list uchar int vertex_indices
property list uchar float texcoord
element edge 1
property int vertex1
property int vertex2
end_header
0 0 0 255 0 0
1 0 0 255 1 0
1 1 0 255 1 1
0 1 0 255 0 1
2 2 2 0 0.5 0.25
3 0 1 2 6 0 0 1 0 1 1
4 0 2 3 4 0
0 1
"""
    mesh = read_ply(text)
    assert mesh.vertices[4].tolist() == [2, 2, 2]
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 3, 4]]
    assert mesh.quad_split.tolist() == [0, 1, 1]
    assert mesh.uv[4].tolist() == [0.5, 0.25]


def test_ply_reads_big_endian_binary_with_mixed_polygon_sizes():
    header = (
        b"ply\nformat binary_big_endian 1.0\nelement vertex 5\nproperty double x\n"
        b"property double y\nproperty double z\nelement face 2\n"
        b"property list uchar uint vertex_index\nend_header\n"
    )
    body = np.arange(15, dtype=">f8").tobytes()
    body += struct.pack(">BIII", 3, 0, 1, 2) + struct.pack(">BIIII", 4, 0, 2, 3, 4)
    mesh = read_ply(header + body)
    assert mesh.vertices[4].tolist() == [12, 13, 14]
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 3, 4]]
    assert mesh.quad_split.tolist() == [0, 1, 1]


_PLY_HEADER = (
    b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
    b"property float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\n"
    b"end_header\n"
)
_PLY_VERTICES = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], "<f4").tobytes()


@pytest.mark.parametrize(
    "data, message",
    [
        (_PLY_HEADER + _PLY_VERTICES + struct.pack("<Biii", 3, 0, 1, 3), "face 0 references vertex 3 but the file has 3 vertices"),
        (_PLY_HEADER + _PLY_VERTICES + struct.pack("<Bii", 2, 0, 1), "face 0 has 2 corners; a face needs at least 3"),
        (_PLY_HEADER + _PLY_VERTICES + struct.pack("<Bi", 3, 0), "PLY data ends inside face 0 of the 1 declared"),
        (_PLY_HEADER + _PLY_VERTICES[:-4], "PLY data ends inside element 'vertex'"),
        (_PLY_HEADER.replace(b"binary_little_endian", b"binary_middle_endian"), "PLY format 'binary_middle_endian' is not"),
        (
            _PLY_HEADER.replace(b"property float z\n", b"") + np.zeros((3, 2), "<f4").tobytes()
            + struct.pack("<Biii", 3, 0, 1, 2),
            "PLY vertex element lacks the scalar properties ['z']",
        ),
        (b"solid cube\n", "not a PLY file"),
        (_PLY_HEADER.replace(b"end_header", b"end"), "PLY header has no 'end_header' line"),
        (
            _PLY_HEADER.replace(b"uchar int", b"uchar float") + _PLY_VERTICES + struct.pack("<Bfff", 3, 0, 1, 1.5),
            "face 0 references vertex 1.5",
        ),
    ],
)
def test_ply_rejects_bad_input_with_a_specific_message(data, message):
    with pytest.raises(MeshFormatError, match=message.replace("(", r"\(").replace("[", r"\[")):
        read_ply(data)


def test_ply_bounds_declared_counts_before_allocating():
    huge = _PLY_HEADER.replace(b"vertex 3", b"vertex 1000000000000")
    with pytest.raises(SizeLimitError, match="1000000000000 vertices"):
        read_ply(huge + _PLY_VERTICES)
    many_edges = _PLY_HEADER.replace(
        b"end_header", b"element edge 4000000000\nproperty list uchar int v\nend_header"
    )
    with pytest.raises(MeshFormatError, match="PLY data ends inside element 'edge'"):
        read_ply(many_edges + _PLY_VERTICES + struct.pack("<Biii", 3, 0, 1, 2))


def test_ply_refuses_to_write_per_corner_uv(rig_mesh, tmp_path):
    with pytest.raises(ValueError, match="PLY holds per-vertex uv only"):
        write_ply(tmp_path / "rig.ply", rig_mesh)


# ---------------------------------------------------------------------------- NPZ


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_npz_round_trip_of_ict_rig_is_bit_exact(rig, rig_mesh, dtype, tmp_path):
    write_npz(tmp_path / "rig.npz", rig_mesh, dtype=dtype)
    with np.load(tmp_path / "rig.npz") as stored:
        assert sorted(stored.files) == ["faces", "quad_split", "uv", "uv_faces", "vertices"]
        assert stored["faces"].dtype == np.int32 and stored["vertices"].dtype == dtype
    back = read_npz(tmp_path / "rig.npz")
    assert _bits_equal(back.vertices.astype(np.float32), rig["neutral"])
    assert np.array_equal(back.faces, rig["triangles"])
    assert np.array_equal(back.uv_faces, rig["triangle_uv"])
    assert np.array_equal(back.quad_split, rig_mesh.quad_split)


def test_npz_float64_round_trip_is_bit_exact():
    mesh = _random_mesh(seed=2)
    buffer = io.BytesIO()
    write_npz(buffer, mesh, compress=True)
    back = read_npz(buffer.getvalue())
    assert _bits_equal(back.vertices, mesh.vertices) and _bits_equal(back.uv, mesh.uv)
    assert back.uv_faces is None and back.quad_split is None


def _npz(**arrays):
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


_V = np.zeros((4, 3))
_F = np.array([[0, 1, 2], [0, 2, 3]])


@pytest.mark.parametrize(
    "data, message",
    [
        (_npz(vertices=_V, faces=_F + 1), "face 1 references vertex 4 but the mesh has 4 vertices"),
        (_npz(vertices=np.r_[_V[:3], [[np.nan, 0, 0]]], faces=_F), "vertex 3 has a non-finite coordinate"),
        (_npz(vertices=_V, faces=_F[:, :2]), r"'faces' has shape \(2, 2\), expected \(T, 3\)"),
        (_npz(vertices=_V, faces=_F.astype(float)), "faces has dtype float64, expected integers"),
        (_npz(vertices=_V, faces=_F, uv=np.zeros((3, 2))), "uv has 3 rows but the mesh has 4 vertices"),
        (_npz(vertices=_V, faces=_F, uv=np.zeros((5, 2)), uv_faces=_F[:1]), r"uv_faces has 1 triangles \(axis 0\) but faces has 2"),
        (_npz(vertices=_V, faces=_F, uv=np.zeros((3, 2)), uv_faces=_F), "face 1 references uv 3 but the mesh has 3 uv"),
        (_npz(vertices=_V, faces=_F, uv_faces=_F), "uv_faces given without uv"),
        (_npz(vertices=_V), "the mesh .npz lacks the key 'faces'"),
        (_npz(vertices=_V, faces=_F, normals=_V), r"unexpected keys \['normals'\]"),
        (_npz(vertices=_V, faces=_F, quad_split=np.array([0, 2])), "quad_split must number polygons"),
        (_npz(vertices=_V, faces=_F[:, ::-1], quad_split=np.array([0, 0])), "do not form a fan"),
        (_npz(vertices=np.empty((4, 3), dtype=object), faces=_F), "'vertices' has dtype object, expected floating point"),
        (b"PK\x03\x04 not a zip", "not a readable .npz archive"),
    ],
)
def test_npz_rejects_bad_input_with_a_specific_message(data, message):
    with pytest.raises(MeshFormatError, match=message):
        read_npz(data)


def test_npz_bounds_shapes_from_headers_before_loading():
    with pytest.raises(SizeLimitError, match="declares 4 vertices, more than the limit of 3"):
        read_npz(_npz(vertices=_V, faces=_F), max_vertices=3)


def test_npz_refuses_pickled_data():
    with pytest.raises(MeshFormatError, match="not a readable .npz archive"):
        read_npz(pickle.dumps({"vertices": _V, "faces": _F}))


# ---------------------------------------------------------------------------- dispatch and Mesh


def test_read_mesh_dispatches_on_suffix(tmp_path):
    mesh = _random_mesh(seed=3)
    write_obj(tmp_path / "m.OBJ", mesh)
    write_npz(tmp_path / "m.npz", mesh)
    write_ply(tmp_path / "m.ply", mesh)
    for name in ("m.OBJ", "m.npz", "m.ply"):
        assert _bits_equal(read_mesh(tmp_path / name).vertices, mesh.vertices)
    assert _bits_equal(read_mesh((tmp_path / "m.ply").read_bytes(), ".ply").vertices, mesh.vertices)
    with pytest.raises(MeshFormatError, match="unsupported mesh file type '.stl'"):
        read_mesh(tmp_path / "m.stl")
    with pytest.raises(MeshFormatError, match="unsupported mesh file type None"):
        read_mesh(b"v 0 0 0")


def test_mesh_errors_are_format_errors_and_value_errors():
    with pytest.raises(FormatError) as caught:
        Mesh(np.zeros((3, 3)), [[0, 1, 5]])
    assert isinstance(caught.value, ValueError)
    assert "face 0 references vertex 5 but the mesh has 3 vertices" in str(caught.value)


def test_mesh_seam_vertices_are_those_with_several_uv():
    mesh = Mesh(np.zeros((4, 3)), [[0, 1, 2], [0, 2, 3]], np.zeros((5, 2)), [[0, 1, 2], [4, 2, 3]])
    assert mesh.seam_vertices().tolist() == [0]


def test_corrupted_mesh_files_raise_only_format_errors():
    rng = np.random.default_rng(11)
    mesh = _fan_mesh(_random_mesh(seed=4).vertices, _random_mesh(seed=4).uv, _POLYGONS)
    for write, read in [(write_obj, read_obj), (write_ply, read_ply), (write_npz, read_npz)]:
        buffer = io.BytesIO()
        write(buffer, mesh)
        for trial in range(90):
            try:
                read(corrupt(buffer.getvalue(), rng, trial, b"0123456789-/ .\nnan"))
            except FormatError:
                pass


@pytest.mark.parametrize("key, dtype", [("vertices", np.int8), ("vertices", np.int64),
                                        ("vertices", np.bool_), ("uv", np.int32)])
def test_npz_meshes_with_non_float_coordinates_are_refused(key, dtype):
    """issue 16, defect 9: int8 vertices used to be accepted (and replaced a neutral)."""
    from service.io.npz import npz_bytes

    arrays = {"vertices": np.zeros((3, 3), np.float32), "faces": np.array([[0, 1, 2]], np.int32),
              "uv": np.zeros((3, 2), np.float32)}
    arrays[key] = arrays[key].astype(dtype)
    with pytest.raises(MeshFormatError, match=f"'{key}' has dtype .*expected floating point"):
        read_npz(npz_bytes(**arrays))
