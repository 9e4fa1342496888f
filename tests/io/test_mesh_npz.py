"""Mesh NPZ: coordinates must be floating point; faces without uv survive a round trip."""

import io

import numpy as np
import pytest

from service.io.errors import MeshFormatError
from service.io.mesh_npz import read_npz, write_npz
from service.io.triangle_mesh import NO_UV, Mesh


def _npz(**arrays):
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


FACES = np.array([[0, 1, 2], [0, 2, 3]])


@pytest.mark.parametrize("dtype", [np.int8, np.int64, np.uint16, np.bool_])
def test_integer_vertices_are_refused_not_cast(dtype):
    data = _npz(vertices=np.ones((4, 3), dtype), faces=FACES)
    with pytest.raises(MeshFormatError, match=rf"'vertices' has dtype {np.dtype(dtype)}, expected floating point.*refused, not cast"):
        read_npz(data)


def test_integer_uv_is_refused():
    with pytest.raises(MeshFormatError, match="'uv' has dtype int8, expected floating point"):
        read_npz(_npz(vertices=np.zeros((4, 3)), faces=FACES, uv=np.zeros((4, 2), np.int8)))


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
def test_float_vertices_of_any_width_are_read_exactly(dtype):
    vertices = np.random.default_rng(0).normal(size=(4, 3)).astype(dtype)
    assert np.array_equal(read_npz(_npz(vertices=vertices, faces=FACES)).vertices, vertices.astype(np.float64))


def test_triangles_without_uv_round_trip():
    mesh = Mesh(np.eye(4, 3), FACES, np.zeros((3, 2)), [[0, 1, 2], [NO_UV] * 3])
    buffer = io.BytesIO()
    write_npz(buffer, mesh)
    back = read_npz(buffer.getvalue())
    assert back.uv_faces.tolist() == [[0, 1, 2], [-1, -1, -1]]
