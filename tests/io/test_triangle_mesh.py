"""The Mesh type: triangles without texture coordinates are whole rows of NO_UV."""

import numpy as np
import pytest

from service.io.errors import MeshFormatError
from service.io.triangle_mesh import NO_UV, Mesh

V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
F = [[0, 1, 2], [0, 2, 3]]


def test_a_triangle_without_uv_is_a_row_of_no_uv_and_is_no_seam():
    mesh = Mesh(V, F, np.zeros((3, 2)), [[0, 1, 2], [NO_UV] * 3])
    assert mesh.uv_faces[1].tolist() == [-1, -1, -1]
    assert mesh.seam_vertices().tolist() == []  # vertex 0 has one uv (-1 is no uv)
    sizes, corners, uv_corners = mesh.polygons()
    assert uv_corners.tolist() == [0, 1, 2, -1, -1, -1]


def test_a_triangle_with_uv_at_some_corners_only_is_refused():
    with pytest.raises(MeshFormatError, match=r"uv_faces row 1 is \[0, -1, 2\]; a triangle has uv at every corner or none"):
        Mesh(V, F, np.zeros((3, 2)), [[0, 1, 2], [0, NO_UV, 2]])


def test_indices_below_no_uv_are_still_out_of_range():
    with pytest.raises(MeshFormatError, match="face 1 references uv -2"):
        Mesh(V, F, np.zeros((3, 2)), [[0, 1, 2], [-2, -2, -2]])
