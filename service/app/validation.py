"""Checks an uploaded surface must pass before the service stores it.

:class:`service.io.mesh.Mesh` already refuses non-finite coordinates and out-of-range
indices; these add what a mesh that drives training must also satisfy. Each raises
:class:`~service.methods.inputs.InvalidInput` (422) naming how many elements fail and the
first of them.
"""

from __future__ import annotations

import numpy as np

from service.app.limits import DEGENERATE_AREA_RTOL
from service.geometry.laplacian import triangle_areas
from service.geometry.topology import edge_face_counts
from service.io.arrays import OCCLUDED_NOTE, check_finite
from service.io.mesh import Mesh
from service.io.triangle_mesh import NO_UV
from service.methods.inputs import InvalidInput

#: UVs may lie this far outside the unit tile (rounding in exporters)
UV_TOLERANCE = 1e-6


def check_triangles(V: np.ndarray, F: np.ndarray, what: str = "mesh") -> None:
    """Refuse degenerate triangles and non-manifold edges.

    Parameters
    ----------
    V : (n,3) float   vertices
    F : (m,3) int     triangles (indices already in range)
    what : str        the mesh's name in messages, e.g. ``"neutral"``

    Raises
    ------
    InvalidInput
        - a triangle with a repeated corner or zero area (at most
          :data:`~service.app.limits.DEGENERATE_AREA_RTOL` times its longest edge squared);
        - an edge shared by more than two triangles.
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    repeated = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 0] == F[:, 2])
    longest = np.max([np.einsum("ij,ij->i", d, d) for d in
                      (V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 1]], V[F[:, 0]] - V[F[:, 2]])],
                     axis=0)
    degenerate = repeated | (triangle_areas(V, F) <= DEGENERATE_AREA_RTOL * longest)
    bad = np.flatnonzero(degenerate)
    if len(bad):
        t = int(bad[0])
        raise InvalidInput(
            f"the {what} has {len(bad)} degenerate triangle(s) (zero area or a repeated "
            f"vertex); the first is triangle {t} with vertices {F[t].tolist()}")
    E, count = edge_face_counts(F)
    over = np.flatnonzero(count > 2)
    if len(over):
        a, b = (int(x) for x in E[over[0]])
        faces = np.flatnonzero(np.isin(F, (a, b)).sum(axis=1) == 2)
        raise InvalidInput(
            f"the {what} has {len(over)} non-manifold edge(s) shared by more than two "
            f"triangles; the first is edge ({a}, {b}), shared by triangles {faces.tolist()}")


def check_uv_tile(mesh: Mesh, what: str = "neutral") -> None:
    """Refuse a mesh without UVs, with triangles that have none (``uv_faces`` rows of
    :data:`~service.io.triangle_mesh.NO_UV`: an OBJ mixing ``v/vt`` corners with bare ``v``
    or ``v//vn`` ones), or with UVs outside the unit tile [0,1]² (API.md's maps cover
    exactly that tile, through the UVs of every triangle; UDIM layouts must be repacked into
    it)."""
    if mesh.uv is None:
        raise InvalidInput(f"the {what} has no UV layout: send 'uv' (and 'uv_faces' for "
                           "seams) in the .npz, or 'vt' coordinates in the .obj")
    if mesh.uv_faces is not None:
        missing = np.flatnonzero(mesh.uv_faces[:, 0] == NO_UV)
        if len(missing):
            raise InvalidInput(
                f"{len(missing)} of the {what}'s {len(mesh.faces)} triangles have no UVs (the "
                f"first is triangle {int(missing[0])}; in an OBJ, faces written with bare 'v' "
                f"or 'v//vn' corners); every triangle of a {what} needs UVs, as its maps cover "
                "the surface through them: export the mesh with texture coordinates ('v/vt') "
                "on every face")
    outside = np.flatnonzero(((mesh.uv < -UV_TOLERANCE) | (mesh.uv > 1 + UV_TOLERANCE)).any(axis=1))
    if len(outside):
        k = int(outside[0])
        raise InvalidInput(f"the {what} has {len(outside)} uv coordinate(s) outside the unit "
                           f"tile [0,1]²; the first is uv {k} = {mesh.uv[k].tolist()} "
                           "(repack UDIM tiles into one tile)")


def check_finite_frames(values: np.ndarray, what: str, element: str,
                        allow_nan: bool = False) -> None:
    """Refuse non-finite values in (F,N,3) frames (or one (N,3) frame), naming the first
    frame and element (:func:`service.io.arrays.check_finite`).

    Parameters
    ----------
    values : (F,N,3) float   e.g. clip vertices or markers (in memory or in a file)
    what : str               e.g. ``"clip"``; messages read "clip frame 3 vertex 17 ..."
    element : str            what the N axis holds, e.g. ``"vertex"``, ``"marker"``
    allow_nan : bool         NaN is allowed (an occluded marker), infinity is not
    """
    labels = ("frame", element) if len(values.shape) >= 3 else (element,)
    check_finite(values, what, labels, allow_nan=allow_nan,
                 note=OCCLUDED_NOTE if allow_nan else "")


def check_text(value: str, what: str) -> str:
    """``value`` if it can be stored and served back: encodable as UTF-8 (no lone surrogate
    such as ``"\\udfff"``, which JSON can carry but neither the database nor the response
    encoder can) and free of NUL characters (PostgreSQL text and JSON refuse them).

    Every user string that is stored — actor names, metadata keys and values, clip and rig
    names — passes this *before* anything is written, so no row is committed that the API
    cannot serialize (issue 16: one such row made every actor listing a 500).

    Raises
    ------
    InvalidInput   naming ``what``, the offending character and its position
    """
    try:
        value.encode("utf-8")
    except UnicodeEncodeError as error:
        raise InvalidInput(f"{what} is not valid Unicode: it holds the lone surrogate "
                           f"U+{ord(value[error.start]):04X} at position {error.start}") from None
    if "\x00" in value:
        raise InvalidInput(f"{what} contains a NUL character at position {value.index(chr(0))}")
    return value


def check_json_text(value, what: str):
    """``value`` (parsed JSON) if every string in it, keys included, passes
    :func:`check_text`; the message names the path, e.g. ``metadata['a'][0]``."""
    if isinstance(value, str):
        return check_text(value, what)
    if isinstance(value, dict):
        for key, item in value.items():
            check_text(str(key), f"a key of {what}")
            check_json_text(item, f"{what}[{key!r}]")
    elif isinstance(value, (list, tuple)):
        for index, item in enumerate(value):
            check_json_text(item, f"{what}[{index}]")
    return value
