"""Lambert-shaded renders of the sample actor through its cameras.

The cameras and the z-buffer rasterizer are :mod:`service.geometry.camera` (OpenCV
convention, pixel centres at integer + 0.5); they are re-exported here.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

from service.geometry.camera import Camera, rasterize  # noqa: F401  (re-exported: the renders' API)
from service.geometry.normals import vertex_normals
from service.geometry.optical_flow import sample
from service.io.atomic import atomic_open, sha256_file, write_bytes, write_npz

IMAGE_SIZE = 384


def face_cameras(target: np.ndarray, distance: float = 520.0, size: int = IMAGE_SIZE,
                 yaws_deg=(-30.0, 0.0, 30.0), field_mm: float = 300.0) -> list[Camera]:
    """Cameras on an arc in front of the face, looking at ``target`` (3,) mm."""
    f = size * distance / field_mm
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    flip = np.diag([1.0, -1.0, -1.0])            # world (y up, z to viewer) → OpenCV
    cams = []
    for yaw in yaws_deg:
        R = flip @ Rotation.from_euler("y", -yaw, degrees=True).as_matrix()
        centre = target + Rotation.from_euler("y", yaw, degrees=True).apply([0, 0, distance])
        cams.append(Camera(K, R, -R @ centre, size, size))
    return cams


def shade(camera: Camera, V: np.ndarray, F: np.ndarray, albedo: np.ndarray,
          light_dir=(0.3, 0.5, 1.0), ambient: float = 0.15,
          background: float = 0.0) -> np.ndarray:
    """Lambert-shaded linear RGB image (H,W,3) of a mesh with per-vertex albedo (n,3).

    The light is directional, given in world coordinates (toward the light).
    """
    triangle, bary = rasterize(camera, V, F)
    fg = triangle >= 0
    corners = F[triangle[fg]]
    alb = np.einsum("pk,pkd->pd", bary[fg], albedo[corners])
    return _lambert(V, F, triangle, bary, alb, light_dir, ambient, background)


def shade_textured(camera: Camera, V: np.ndarray, F: np.ndarray, uv: np.ndarray,
                   uv_faces: np.ndarray, texture: np.ndarray, light_dir=(0.3, 0.5, 1.0),
                   ambient: float = 0.15, background: float = 0.0) -> np.ndarray:
    """Lambert-shaded linear RGB image (H,W,3) of a mesh with an albedo texture.

    Parameters
    ----------
    uv : (u,2) float in [0,1]², uv_faces : (m,3) int   the mesh's texture coordinates
    texture : (h,w,3) float   linear albedo; row 0 is v = 1 (the maps' convention:
                              texel (r, c) has uv ((c + 0.5)/w, 1 − (r + 0.5)/h))
    light_dir, ambient, background : as :func:`shade`
    """
    triangle, bary = rasterize(camera, V, F)
    fg = triangle >= 0
    t = np.einsum("pk,pkd->pd", bary[fg], uv[uv_faces[triangle[fg]]])
    h, w = texture.shape[:2]
    xy = np.column_stack([t[:, 0] * w - 0.5, (1.0 - t[:, 1]) * h - 0.5])
    alb = sample(texture, xy)
    return _lambert(V, F, triangle, bary, alb.astype(np.float64), light_dir, ambient, background)


def _lambert(V, F, triangle, bary, alb, light_dir, ambient, background) -> np.ndarray:
    """Shade the foreground pixels' albedo (p,3) by the interpolated vertex normals."""
    N = vertex_normals(V, F, weighting="area")
    fg = triangle >= 0
    n = np.einsum("pk,pkd->pd", bary[fg], N[F[triangle[fg]]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    light = np.asarray(light_dir, dtype=np.float64)
    light /= np.linalg.norm(light)
    img = np.full(triangle.shape + (3,), background)
    img[fg] = alb * (ambient + (1 - ambient) * np.clip(n @ light, 0, None))[:, None]
    return img


def to_srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear RGB in [0,1] → 8-bit sRGB."""
    x = np.clip(linear, 0, 1)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255).astype(np.uint8)


def write_png(path: str | Path, image: np.ndarray) -> str:
    """Write an (H,W) or (H,W,3) uint8 image as PNG atomically; return its sha256."""
    with atomic_open(path) as f:
        Image.fromarray(image).save(f, format="PNG")
    return sha256_file(path)


def write_tracking_data(actor, out: Path, static: dict[str, tuple[np.ndarray, np.ndarray]],
                        performance: tuple[np.ndarray, np.ndarray], fps: float,
                        workers: int = 2) -> dict[str, str]:
    """Cameras plus rendered images for performance-flow tracking (Fyffe et al.).

    Parameters
    ----------
    static : name → (vertices (n,3), vertex albedo (n,3)) of a few static expressions
    performance : (vertices (F,n,3), vertex albedo (F,n,3)) of a performance

    Writes ``tracking/cameras.json``, ``tracking/static.npz`` (ground-truth meshes and their
    images per camera, (E,C,H,W,3) uint8 sRGB) and ``tracking/performance.npz`` (meshes and
    images (F,C,H,W,3)). Returns file → sha256.
    """
    import json

    skin = actor.skin
    target = skin.rig_neutral[actor.rig.landmarks68[30]] - [0, 10, 40]
    cams = face_cameras(target)
    files = {"tracking/cameras.json": write_bytes(
        out / "tracking/cameras.json", json.dumps([c.to_json() for c in cams], indent=1).encode())}

    def images(vertices, albedo):
        jobs = [(v, a, c) for v, a in zip(vertices, albedo) for c in cams]
        with ThreadPoolExecutor(workers) as pool:      # NumPy releases the GIL: both cores
            shots = list(pool.map(lambda j: to_srgb8(shade(j[2], j[0], skin.faces, j[1])), jobs))
        return np.stack(shots).reshape(len(vertices), len(cams), *shots[0].shape)

    names = list(static)
    static_v = np.stack([static[k][0] for k in names])
    files["tracking/static.npz"] = write_npz(out / "tracking/static.npz", {
        "names": np.array(names), "vertices": static_v,
        "images": images(static_v, [static[k][1] for k in names])})
    vertices, albedo = performance
    files["tracking/performance.npz"] = write_npz(out / "tracking/performance.npz", {
        "vertices": vertices, "images": images(vertices, albedo), "fps": np.float32(fps)})
    return files
