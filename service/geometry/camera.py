"""Calibrated pinhole cameras and a z-buffer rasterizer of triangle meshes through them.

Cameras are pinhole, OpenCV convention: a world point X maps to camera coordinates
``x = R X + t`` (x right, y down, z forward) and to pixel ``(u, v) = (K x)[:2] / x_z``,
pixel centres at integer + 0.5. Shared by the sample actor's renders
(:mod:`service.samples.render`) and the performance tracking
(:mod:`service.methods.tracking`), which casts view rays through flowed pixels (fyffe,
digital_ira_course2014, §5.2 eq. 3) and tests vertex visibility.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.geometry.scan_convert import scan_convert


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

    @property
    def centre(self) -> np.ndarray:
        """The nodal point (3,) in world coordinates, mm: ``−Rᵀ t``."""
        return -self.R.T @ self.t

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Unit world-space directions (n,3) of the view rays through pixels ``uv`` (n,2)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        d = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(self.K).T @ self.R
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def scaled(self, factor: float) -> "Camera":
        """The same camera for images resized by ``factor`` (pixel centres at integer + 0.5)."""
        S = np.diag([factor, factor, 1.0])
        return Camera(S @ self.K, self.R, self.t, int(round(self.width * factor)),
                      int(round(self.height * factor)))

    def to_json(self) -> dict:
        return {"K": self.K.tolist(), "R": self.R.tolist(), "t": self.t.tolist(),
                "width": self.width, "height": self.height}

    @classmethod
    def from_json(cls, d: dict) -> "Camera":
        return cls(np.asarray(d["K"], float), np.asarray(d["R"], float),
                   np.asarray(d["t"], float), int(d["width"]), int(d["height"]))


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
