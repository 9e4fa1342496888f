"""A small z-buffer rasterizer (Lambert-shaded) and the sample actor's camera images.

Cameras are pinhole, OpenCV convention: a world point X maps to camera coordinates
``x = R X + t`` (x right, y down, z forward) and to pixel ``(u, v) = (K x)[:2] / x_z``,
pixel centres at integer + 0.5.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

from service.geometry.normals import vertex_normals
from service.geometry.scan_convert import scan_convert
from service.io.atomic import atomic_open, sha256_file, write_bytes, write_npz

IMAGE_SIZE = 384


@dataclass(frozen=True)
class Camera:
    """Pinhole camera: K (3,3) intrinsics in pixels, R (3,3), t (3,) world→camera (mm)."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int

    def project(self, X: np.ndarray) -> np.ndarray:
        """Pixel coordinates and depth (n,3) = (u, v, z_mm) of world points X (n,3)."""
        x = X @ self.R.T + self.t
        uv = x @ self.K.T
        return np.column_stack([uv[:, :2] / uv[:, 2:3], x[:, 2]])

    def to_json(self) -> dict:
        return {"K": self.K.tolist(), "R": self.R.tolist(), "t": self.t.tolist(),
                "width": self.width, "height": self.height}


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


def rasterize(camera: Camera, V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Visible triangle (H,W) int (−1 for background) and barycentrics (H,W,3) per pixel.

    Z-buffer over :func:`~service.geometry.scan_convert.scan_convert`: triangles wholly in
    front of the camera and facing it (counter-clockwise in the world is clockwise on the
    y-down image) are scan-converted, and per pixel the nearest covering triangle wins
    (ties to the lowest triangle index). Barycentrics are in image space, which is what a
    z-buffer samples at this scale.
    """
    W, H = camera.width, camera.height
    p = camera.project(V)
    tri = p[F]                                              # (m,3,3): u, v, depth
    e1, e2 = tri[:, 1, :2] - tri[:, 0, :2], tri[:, 2, :2] - tri[:, 0, :2]
    facing = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] < 0
    keep = np.flatnonzero(facing & (tri[:, :, 2].min(axis=1) > 0))
    cover = scan_convert(tri[keep, :, :2] - 0.5, H, W)     # pixel centres at integer + 0.5
    t = keep[cover.triangle]
    depth = np.einsum("pk,pk->p", cover.barycentric, tri[t, :, 2])
    order = np.lexsort((t, depth, cover.pixel))
    first = order[np.diff(cover.pixel[order], prepend=-1) != 0]     # nearest per pixel
    triangle = np.full(H * W, -1, dtype=np.int64)
    bary = np.zeros((H * W, 3))
    triangle[cover.pixel[first]] = t[first]
    bary[cover.pixel[first]] = cover.barycentric[first]
    return triangle.reshape(H, W), bary.reshape(H, W, 3)


def shade(camera: Camera, V: np.ndarray, F: np.ndarray, albedo: np.ndarray,
          light_dir=(0.3, 0.5, 1.0), ambient: float = 0.15,
          background: float = 0.0) -> np.ndarray:
    """Lambert-shaded linear RGB image (H,W,3) of a mesh with per-vertex albedo (n,3).

    The light is directional, given in world coordinates (toward the light).
    """
    triangle, bary = rasterize(camera, V, F)
    N = vertex_normals(V, F, weighting="area")
    fg = triangle >= 0
    corners = F[triangle[fg]]
    n = np.einsum("pk,pkd->pd", bary[fg], N[corners])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    alb = np.einsum("pk,pkd->pd", bary[fg], albedo[corners])
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
