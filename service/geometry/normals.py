"""Unit face and vertex normals of triangle meshes, for one mesh or a batch of frames.

Vertex normals are angle-weighted (Thürmer & Wüthrich 1998, "Computing vertex normals from
polygonal meshes"): each incident triangle contributes its unit normal times its interior
angle at the vertex. Unlike area weighting, the result does not depend on how a polygon is
triangulated (the ICT rig's quads are split along one diagonal, which would tilt
area-weighted normals towards the side with the larger triangle), and a vertex normal of a
finely sampled sphere is the radial direction to second order.

Degenerate triangles (zero area) get a zero face normal and contribute nothing; a vertex
with no non-degenerate incident triangle (e.g. unreferenced) gets a zero normal.
Everything is float64.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def _flatten_frames(V: np.ndarray) -> tuple[np.ndarray, tuple[int, ...]]:
    """(B,n,3) float64 view of (n,3) or (...,n,3) vertices, and the leading shape."""
    V = np.asarray(V, dtype=np.float64)
    if V.ndim < 2 or V.shape[-1] != 3:
        raise ValueError(f"vertices must be (n,3) or (...,n,3), got {V.shape}")
    return V.reshape(-1, *V.shape[-2:]), V.shape[:-2]


def _normalize(X: np.ndarray) -> np.ndarray:
    """Rows of X (...,3) scaled to unit length; zero rows stay zero."""
    norm = np.linalg.norm(X, axis=-1, keepdims=True)
    return np.divide(X, norm, out=np.zeros_like(X), where=norm > 0)


def face_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Unit normals of the triangles, oriented by the corner order (counter-clockwise = front).

    Parameters
    ----------
    V : (n,3) or (frames,n,3) float   vertices (any unit)
    F : (m,3) int                     triangles

    Returns
    -------
    N : (m,3) or (frames,m,3) float64   unit normals; zero for degenerate triangles
    """
    F = np.asarray(F, dtype=np.int64)
    P = np.asarray(V, dtype=np.float64)
    return _normalize(np.cross(P[..., F[:, 1], :] - P[..., F[:, 0], :],
                               P[..., F[:, 2], :] - P[..., F[:, 0], :]))


def corner_angles(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Interior angle at every triangle corner, radians.

    Parameters
    ----------
    V : (n,3) or (frames,n,3) float
    F : (m,3) int

    Returns
    -------
    angles : (m,3) or (frames,m,3) float64   ``angles[..., f, k]`` at corner ``F[f,k]``;
             0 for degenerate triangles
    """
    F = np.asarray(F, dtype=np.int64)
    P = np.asarray(V, dtype=np.float64)[..., F, :]            # (...,m,3,3)
    a = np.roll(P, -1, axis=-2) - P
    b = np.roll(P, -2, axis=-2) - P
    # atan2(|a×b|, a·b) is accurate for all angles, unlike acos of the normalized dot
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("...d,...d->...", a, b))


def vertex_normals(V: np.ndarray, F: np.ndarray, weighting: str = "angle") -> np.ndarray:
    """Unit vertex normals, the weighted mean of the incident face normals.

    Parameters
    ----------
    V : (n,3) or (frames,n,3) float   vertices (any unit)
    F : (m,3) int                     triangles
    weighting : ``"angle"`` (default; Thürmer & Wüthrich 1998, tessellation-independent)
                or ``"area"`` (cross products summed, the classical Gouraud normal)

    Returns
    -------
    N : (n,3) or (frames,n,3) float64   unit normals; zero where no non-degenerate
                                        triangle touches the vertex
    """
    F = np.asarray(F, dtype=np.int64)
    Vb, lead = _flatten_frames(V)
    nb, n = Vb.shape[:2]
    m = len(F)
    if weighting == "angle":
        w = corner_angles(Vb, F)                                # (B,m,3)
        Nf = face_normals(Vb, F)                                # (B,m,3)
        contrib = w[..., None] * Nf[:, :, None, :]              # (B,m,3 corners,3)
    elif weighting == "area":
        P = Vb[:, F]                                            # (B,m,3,3)
        c = np.cross(P[:, :, 1] - P[:, :, 0], P[:, :, 2] - P[:, :, 0])
        contrib = np.broadcast_to(c[:, :, None, :], (nb, m, 3, 3))
    else:
        raise ValueError(f"weighting must be 'angle' or 'area', got {weighting!r}")
    # scatter corners to vertices as one sparse product for all frames
    S = sp.csr_matrix((np.ones(3 * m), (F.ravel(), np.arange(3 * m))), shape=(n, 3 * m))
    acc = S @ np.ascontiguousarray(contrib.transpose(1, 2, 0, 3)).reshape(3 * m, nb * 3)
    N = _normalize(acc.reshape(n, nb, 3).transpose(1, 0, 2))
    return N.reshape(*lead, n, 3)
