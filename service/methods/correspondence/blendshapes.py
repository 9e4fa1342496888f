"""Blendshapes and artist-UV maps from corresponded scans (Vuvuzela's by-product).

digital_ira_course2014, "Vuvuzela: A Facial Scan Correspondence Tool", §"Blend shapes": the
neutral scan is remeshed into an artist mesh with artist UVs; the blendshapes of all scans
come "by looking up vertex positions in the warped point clouds", and "all the texture maps
are also warped into the artist UV space, which is simply an additional affine triangles 2D
warp".

An artist mesh is given here by where its vertices lie in the *neutral scan's* UV space
(``scan_uv`` (n,2)), and its own UV layout. Once an expression is corresponded (its maps in
the neutral's UV space), its blendshape is the warped position map at ``scan_uv``.
"""

from __future__ import annotations

import numpy as np

from service.geometry import optical_flow as of
from service.geometry.uv_raster import rasterize_uv, uv_sampling_matrix, uv_to_texel
from service.methods.inputs import InvalidInput


def blendshape_vertices(position_map: np.ndarray, mask: np.ndarray, scan_uv: np.ndarray) -> np.ndarray:
    """Artist-mesh vertex positions looked up in a warped position map.

    Bilinear lookup that reads covered texels only (:func:`~service.geometry.uv_raster.
    uv_sampling_matrix`: a vertex at the border of the covered texels is not pulled towards
    the empty background).

    Parameters
    ----------
    position_map : (H,W,3) float   the expression's point cloud in the neutral's UV space, mm
    mask : (H,W) bool              its valid texels (``CorrespondenceResult.mask``)
    scan_uv : (n,2) float          each artist vertex's UV in the neutral scan (NaN: none)

    Returns
    -------
    vertices : (n,3) float64   NaN for vertices without a scan UV
    """
    P = np.asarray(position_map, dtype=np.float64)
    mask = np.asarray(mask, bool)
    if P.ndim != 3 or P.shape[2] != 3 or P.shape[:2] != mask.shape:
        raise InvalidInput(f"position_map must be (H,W,3) with a (H,W) mask, got {P.shape} and "
                           f"{mask.shape}")
    if not mask.any():
        raise InvalidInput("the position map has no valid texel")
    uv = np.asarray(scan_uv, dtype=np.float64)
    ok = np.isfinite(uv).all(axis=1)
    out = np.full((len(uv), 3), np.nan)
    S = uv_sampling_matrix(uv[ok], mask)
    out[ok] = S @ P.reshape(-1, 3)
    return out


def to_artist_uv(maps: dict, scan_uv: np.ndarray, faces: np.ndarray, artist_uv: np.ndarray,
                 artist_uv_faces: np.ndarray, shape: tuple[int, int]) -> tuple[dict, np.ndarray]:
    """Maps in the neutral scan's UV space → the artist mesh's UV space (affine triangles).

    Every artist-UV texel lies in one artist triangle with barycentric coordinates b; its
    source is ``Σ b_k scan_uv[faces[t, k]]`` in the neutral scan's maps.

    Parameters
    ----------
    maps : name → (h,w) or (h,w,C) float   maps in the neutral scan's UV space
    scan_uv : (n,2) float          artist vertex → UV in the neutral scan (NaN: none)
    faces : (m,3) int              artist position triangles
    artist_uv : (K,2) float; artist_uv_faces : (m,3) int   the artist UV layout
    shape : (H, W)                 size of the artist-UV maps

    Returns
    -------
    maps : name → (H,W[,C]) float32   0 where no triangle (or one without scan UVs) covers
    covered : (H,W) bool
    """
    H, W = shape
    raster = rasterize_uv(artist_uv, artist_uv_faces, H, W)
    F = np.asarray(faces, np.int64)
    coords = np.full((H, W, 2), -1e6, np.float32)
    r, c = np.nonzero(raster.mask)
    uv = np.einsum("kc,kcd->kd", raster.barycentric[r, c], np.asarray(scan_uv)[F[raster.triangle[r, c]]])
    ok = np.isfinite(uv).all(axis=1)
    covered = np.zeros((H, W), bool)
    covered[r[ok], c[ok]] = True
    out = {}
    for name, m in maps.items():
        h, w = np.shape(m)[:2]
        coords[r[ok], c[ok]] = uv_to_texel(uv[ok], h, w)
        o = of.remap(m, coords, border=0.0)
        o[~covered] = 0.0
        out[name] = o
    return out, covered
