"""Large-scale deformation and the fine-scale corrections of example poses (bickel2008 §4, §5.2).

Large scale (§4): the rigid head pose is removed from a frame's markers (weighted Kabsch,
:func:`~service.methods.pdm.base_surface.head_alignment`), and the **detailed** rest mesh 𝓕
is deformed by the linear thin shell with the precomputed basis, ``X = 𝓕 + B u_H``, u_H the
markers' displacements at their handle vertices (occluded markers completed at minimum
shell energy). Unlike ma2008's base surface this deforms the detailed neutral itself, as
bickel2008 §3 does ("we use a single high-resolution face mesh 𝓕 of the rest pose").

Fine scale (§3, §5.2): the correction of an example pose is what the shell misses,

    c = Frame(X) · (V − X)            (n,3), per vertex, in X's tangent frames (T, B, N),

"stored per-vertex in local tangent frames" so that it is invariant to the local rotation of
the skin; at run time ``V ≈ X + Frame(X)ᵀ c``.
"""

from __future__ import annotations

import numpy as np

from service.methods.inputs import ActorData, InvalidInput
from service.methods.pdm.base_surface import BaseSurface, handle_vertices

#: frames per chunk when corrections are computed (bounds the (f,n,3,3) frames)
FRAME_CHUNK = 8


def large_scale_surface(actor: ActorData, basis: np.ndarray | None = None,
                        energy: np.ndarray | None = None) -> BaseSurface:
    """The thin shell of the actor's detailed neutral over its marker handles (§4).

    ``basis`` (n,M) float32 and ``energy`` (M,M), if given, are a stored basis of the same
    inputs (skips the solves). Raises :class:`InvalidInput` if two markers share a handle.
    """
    try:
        handles = handle_vertices(actor.faces, actor.marker_triangle, actor.marker_barycentric,
                                  actor.marker_names)
    except ValueError as e:
        raise InvalidInput(str(e)) from None
    return BaseSurface.from_smooth(actor.vertices, actor.faces, actor.uv, actor.uv_faces, handles,
                                   actor.marker_positions(), basis=basis, energy=energy)


def corrections(base: BaseSurface, u_H: np.ndarray, aligned: np.ndarray) -> np.ndarray:
    """Fine-scale corrections c (T,n,3) float32 of example poses (§5.2).

    Parameters
    ----------
    base : BaseSurface     the large-scale shell (:func:`large_scale_surface`)
    u_H : (T,M,3) float    complete handle displacements of the examples, mm
    aligned : (T,n,3)      the example meshes with the head pose removed, mm
    """
    T, n = aligned.shape[:2]
    out = np.empty((T, n, 3), np.float32)
    for s in range(0, T, FRAME_CHUNK):
        X = base.deform(u_H[s:s + FRAME_CHUNK])
        out[s:s + FRAME_CHUNK] = np.einsum("fnij,fnj->fni", base.frames(X), aligned[s:s + FRAME_CHUNK] - X)
    return out


def apply_corrections(base: BaseSurface, X: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``X + Frame(X)ᵀ c``: shells X (…,n,3) plus corrections c (…,n,3) in their frames."""
    return X + base.to_world(X, c)
