"""The piecewise-affine pre-warp of Vuvuzela's first step.

digital_ira_course2014, "Vuvuzela: A Facial Scan Correspondence Tool", §"Correspondence
algorithm": "we construct a Delaunay triangulation between the user supplied points and apply
affine triangles to roughly pre-warp the source diffuse texture to the target."

The triangulation is built on the *target* points, so that every target texel finds its
triangle and its source position by that triangle's affine map (a backward map: the
pre-warped source is ``source(A(x))``). The texels outside the points' convex hull are
covered too: the four corners of the image are added as extra points, carried by the
least-squares affine fit of all landmarks (the paper does not say what happens outside the
hull; this extends the warp continuously).
"""

from __future__ import annotations

import numpy as np

from service.geometry.scan_convert import scan_convert
from service.methods.inputs import InvalidInput

MIN_LANDMARKS = 3


def affine_fit(source_xy: np.ndarray, target_xy: np.ndarray) -> np.ndarray:
    """Least-squares affine map (2,3) taking target points to source points.

    Parameters
    ----------
    source_xy, target_xy : (L,2) float   corresponding points, texel coordinates

    Returns
    -------
    A : (2,3) float64   ``source ≈ A @ [x, y, 1]`` for target (x, y)
    """
    T = np.column_stack([target_xy, np.ones(len(target_xy))])
    A, *_ = np.linalg.lstsq(T, source_xy, rcond=None)
    return A.T


def piecewise_affine_coords(source_xy: np.ndarray, target_xy: np.ndarray, shape: tuple[int, int],
                            extend: bool = True) -> np.ndarray:
    """Source coordinates of every target texel under the Delaunay piecewise-affine warp.

    Parameters
    ----------
    source_xy : (L,2) float   landmark positions in the source, texel (column, row) coordinates
    target_xy : (L,2) float   the same landmarks in the target
    shape : (H, W)            the target grid
    extend : bool             add the image corners (carried by :func:`affine_fit`) so the
                              whole grid is covered; otherwise texels outside the hull are NaN

    Returns
    -------
    coords : (H,W,2) float64   (column, row) in the source; exact at the landmarks and affine
                               inside each triangle

    Raises
    ------
    InvalidInput   fewer than 3 landmarks, non-finite ones, or all collinear
    """
    src = np.asarray(source_xy, dtype=np.float64)
    tgt = np.asarray(target_xy, dtype=np.float64)
    if src.shape != tgt.shape or src.ndim != 2 or src.shape[1] != 2:
        raise InvalidInput(f"landmarks must be two (L,2) arrays of one shape, got {src.shape} "
                           f"and {tgt.shape}")
    if len(src) < MIN_LANDMARKS:
        raise InvalidInput(f"the pre-warp needs at least {MIN_LANDMARKS} landmarks, got {len(src)}")
    if not (np.isfinite(src).all() and np.isfinite(tgt).all()):
        raise InvalidInput("landmarks must be finite")
    _, first = np.unique(np.round(tgt, 6), axis=0, return_index=True)
    if len(first) < len(tgt):
        raise InvalidInput(f"{len(tgt) - len(first)} target landmarks repeat another's position")
    H, W = int(shape[0]), int(shape[1])
    if extend:
        A = affine_fit(src, tgt)
        corners = np.array([[-1.0, -1.0], [W, -1.0], [-1.0, H], [W, H]])
        far = np.linalg.norm(tgt[:, None] - corners[None], axis=2).min(axis=0) > 1e-6
        corners = corners[far]
        tgt = np.vstack([tgt, corners])
        src = np.vstack([src, np.column_stack([corners, np.ones(len(corners))]) @ A.T])
    from scipy.spatial import Delaunay, QhullError  # here: serve's start never needs it (issue 23)

    try:
        tri = Delaunay(tgt)
    except QhullError as e:
        raise InvalidInput(f"the target landmarks are degenerate (collinear?): {e}") from None
    # every texel centre's triangle and barycentrics by vectorized scan conversion (texels on
    # a shared edge get either triangle: the warp is continuous there)
    cover = scan_convert(tgt[tri.simplices], H, W)
    out = np.full((H * W, 2), np.nan)
    out[cover.pixel] = np.einsum("kc,kcd->kd", cover.barycentric, src[tri.simplices[cover.triangle]])
    return out.reshape(H, W, 2)
