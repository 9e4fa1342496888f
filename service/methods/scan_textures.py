"""Reflectance maps of registered static scans from their camera images (fyffe,
digital_ira_course2014, §7.3: per-frame maps "by blending the static pose data").

Once tracking has registered a static scan to the artist topology (§5, Fig. 11), each texel
of the artist mesh's UV layout has a 3-D point on the scan: its texel centre's barycentric
interpolation of the registered vertices. The scan's reflectance map samples the scan's
images at that point's projection in every view, weighted per view by the soft visibility
v_p^c of eq. 4 (z-buffer test, one-ring blur, cosine to the camera;
:func:`service.methods.tracking.solve.visibility`) interpolated to the texel:

    ρ(texel) = Σ_c v^c(texel) · I_c(π_c(x(texel))) / Σ_c v^c(texel)

The maps are 8-bit sRGB-encoded luminance scaled to [0, 1] (what the tracking's images
are); texels no view sees are 0. These are the per-scan maps that
:func:`service.methods.tracking.maps.blend_maps` blends per frame when the user uploads no
maps of their own. (Kept outside ``service.methods.tracking`` so that package's public
functions are the only ones the tracking job calls there.)
"""

from __future__ import annotations

import numpy as np

from service.geometry import optical_flow as of
from service.geometry.uv_raster import interpolation_matrix, rasterize_uv
from service.methods.tracking.solve import TrackingMesh, visibility


def scan_reflectance(mesh: TrackingMesh, cameras: list, images: np.ndarray, world: np.ndarray,
                     uv: np.ndarray, uv_faces: np.ndarray, size: int,
                     tolerance_mm: float = 2.0) -> np.ndarray:
    """One registered scan's reflectance map (size,size) float32 in [0, 1].

    Parameters
    ----------
    mesh : the artist mesh (its faces and one-ring smoothing)
    cameras : C :class:`~service.geometry.camera.Camera`;  images : (C,H,W) uint8
    world : (n,3) float   the scan registered to the artist topology (world, actor's unit)
    uv : (K,2), uv_faces : (m,3)   the artist mesh's UV layout
    size : texels per side;  tolerance_mm : the z-buffer test's depth tolerance
    """
    raster = rasterize_uv(uv, uv_faces, size, size)
    M = interpolation_matrix(raster, mesh.faces, mesh.n)
    covered = np.flatnonzero(raster.mask.ravel())
    Mc = M[covered]
    X = np.asarray(Mc @ world)
    total = np.zeros(len(covered))
    value = np.zeros(len(covered))
    for camera, image in zip(cameras, images):
        w = np.asarray(Mc @ visibility(mesh, camera, world, tolerance_mm))
        xy = camera.project(X)[:, :2] - 0.5
        value += w * of.sample(image.astype(np.float32) / 255.0, xy, border=0.0)
        total += w
    out = np.zeros(size * size, np.float32)
    out[covered] = np.where(total > 1e-6, value / np.maximum(total, 1e-12), 0.0)
    return out.reshape(size, size)
