"""A tiny synthetic tracking scene: a textured spherical cap deforming in front of 1–2 cameras.

The same kind of inputs as :func:`service.samples.tracking.build_tracking_sample` (fyffe,
digital_ira_course2014, §3: an artist mesh, static scans whose raw geometry is re-meshed as
range scans so it shares no vertices with the artist mesh, one image per view per scan,
calibrated cameras and the performance's frames per view) at a size a unit test runs in a
second or two: a k×k-vertex cap (radius 80 mm, planar UVs), a seeded multi-scale noise
texture, a smooth bump deformation that grows and relaxes over the performance with a small
rigid head motion, and images of ``size``² pixels rendered with
:func:`~service.samples.render.shade_textured`. Scan 0 is the neutral; scan 1 is the peak of
the deformation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from service.geometry.camera import Camera
from service.samples.render import face_cameras, shade_textured
from service.samples.tracking import range_scan


@dataclass
class TrackingScene:
    """Inputs and ground truth of a tiny tracking scene (world, mm); the attribute names are
    those of :class:`service.samples.tracking.TrackingSample` (duck-typed by
    ``TrackingInput.from_sample``)."""

    artist_vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    uv_faces: np.ndarray
    region: np.ndarray
    cameras: list
    scan_names: np.ndarray
    scan_images: np.ndarray
    scan_vertices: list
    scan_faces: list
    scan_truth: np.ndarray
    frame_images: np.ndarray
    frame_truth: np.ndarray
    texture: np.ndarray = field(repr=False, default=None)


def cap_mesh(k: int = 14, size_mm: float = 60.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A spherical cap of k·k vertices facing +z: vertices (k²,3), faces (2(k−1)²,3)
    (counter-clockwise seen from +z), planar UVs (k²,2) in [0,1]²."""
    u = np.linspace(-size_mm / 2, size_mm / 2, k)
    x, y = np.meshgrid(u, u)
    z = np.sqrt(80.0 ** 2 - x ** 2 - y ** 2) - 80.0
    V = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    idx = np.arange(k * k).reshape(k, k)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    uv = np.column_stack([(x.ravel() + size_mm / 2) / size_mm, (y.ravel() + size_mm / 2) / size_mm])
    return V, F, uv


def deform(V: np.ndarray, amount: float, t: float) -> np.ndarray:
    """The expression at strength ``amount`` ∈ [0,1] (a 4 mm bump and a 2 mm sway) and the
    head's rigid motion at phase ``t`` ∈ [0,1] (±2° and ±1.5 mm)."""
    r2 = (V[:, 0] - 5) ** 2 + (V[:, 1] + 5) ** 2
    D = amount * np.column_stack([3.0 * np.sin(V[:, 1] / 25.0), np.zeros(len(V)),
                                  8.0 * np.exp(-r2 / (2 * 12.0 ** 2))])
    R = Rotation.from_euler("xyz", [2.0 * np.sin(2 * np.pi * t), 1.5 * t, 0.0], degrees=True)
    return R.apply(V + D) + np.array([1.5 * t, -0.5 * t, 0.0])


def _texture(seed: int, size: int = 256) -> np.ndarray:
    rng = np.random.default_rng([seed, 2201])
    tex = np.zeros((size, size), np.float32)
    for sigma, amp in ((1.5, 0.10), (4.0, 0.10), (10.0, 0.08)):
        n = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), sigma)
        tex += amp * n / max(float(n.std()), 1e-9)
    return np.repeat(np.clip(0.55 + tex, 0.1, 1.0)[..., None], 3, axis=2)


def _render(camera: Camera, V, F, uv, texture, rng, noise: float) -> np.ndarray:
    y = shade_textured(camera, V, F, uv, F, texture)[..., 1]
    srgb = np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(np.clip(y, 0, 1), 1 / 2.4) - 0.055)
    return np.clip(np.rint(255 * srgb + rng.normal(0.0, noise, y.shape)), 0, 255).astype(np.uint8)


def build_tracking_scene(frames: int = 8, views: int = 1, size: int = 48, k: int = 14,
                         noise: float = 0.5, seed: int = 3) -> TrackingScene:
    """Render the scene: ``frames`` frames whose expression rises to the peak at the middle
    and relaxes, ``views`` cameras (frontal first), two static scans (neutral, peak).

    Returns
    -------
    TrackingScene (images (S,C,size,size) and (T,C,size,size) uint8)
    """
    V, F, uv = cap_mesh(k)
    cams = face_cameras(np.zeros(3), distance=300.0, size=size,
                        yaws_deg=(0.0, -25.0)[:views], field_mm=75.0)
    texture = _texture(seed)
    phase = np.linspace(0.0, 1.0, frames)
    truth = np.stack([deform(V, float(np.sin(np.pi * p)), float(p)) for p in phase])
    scans = [V, deform(V, 1.0, 0.0)]
    rng = np.random.default_rng([seed, 2202])
    scan_images = np.stack([[_render(c, S, F, uv, texture, rng, noise) for c in cams] for S in scans])
    frame_images = np.stack([[_render(c, X, F, uv, texture, rng, noise) for c in cams] for X in truth])
    raw = [range_scan(cams[0], S, F, 2 * size, seed + 31 * s) for s, S in enumerate(scans)]
    return TrackingScene(V, F, uv, F.copy(), np.zeros(len(V), np.int64), cams,
                         np.array(["neutral", "peak"]), scan_images, [r[0] for r in raw],
                         [r[1] for r in raw], np.stack(scans), frame_images, truth, texture)


def tracking_uploads(sample, views: int | None = None, frames: int | None = None,
                     scans: int | None = None) -> list[tuple[str, tuple[str, bytes, str]]]:
    """The multipart parts of ``POST /v1/actors/{id}/tracking-jobs`` for a tracking sample
    (:class:`TrackingScene` or :class:`~service.samples.tracking.TrackingSample`): ``cameras``
    JSON (views ``v0``, ``v1``, …), one ``.obj`` per scan (``scan0.obj`` is the neutral), the
    ``scan_images`` zip ``scan<s>/v<c>.png`` and the ``frames`` zip ``v<c>/<t>.png``;
    optionally only the first ``views``, ``frames``, ``scans``.

    Returns
    -------
    [(part name, (filename, bytes, media type)), ...] in order (the form of ``httpx``'s
    ``files=``)
    """
    import io as _io
    import json as _json
    import zipfile as _zipfile

    from service.io.mesh import Mesh, write_obj

    C = len(sample.cameras) if views is None else views
    T = len(sample.frame_images) if frames is None else frames
    S = len(sample.scan_images) if scans is None else scans
    names = [f"v{c}" for c in range(C)]
    cams = {"views": [{"name": n, **cam.to_json()} for n, cam in zip(names, sample.cameras[:C])]}
    parts: list = [("cameras", ("cameras.json", _json.dumps(cams).encode(), "application/json"))]
    for s in range(S):
        buffer = _io.BytesIO()
        write_obj(buffer, Mesh(np.asarray(sample.scan_vertices[s], np.float64),
                               np.asarray(sample.scan_faces[s], np.int64)), dtype=np.float32)
        parts.append(("scans", (f"scan{s}.obj", buffer.getvalue(), "model/obj")))

    def png(image: np.ndarray) -> bytes:
        ok, data = cv2.imencode(".png", np.asarray(image, np.uint8))
        return data.tobytes()

    def zipped(members: dict[str, bytes]) -> bytes:
        buffer = _io.BytesIO()
        with _zipfile.ZipFile(buffer, "w", _zipfile.ZIP_STORED) as archive:
            for name, data in members.items():
                archive.writestr(name, data)
        return buffer.getvalue()

    parts.append(("scan_images", ("scan_images.zip", zipped(
        {f"scan{s}/{names[c]}.png": png(sample.scan_images[s, c])
         for s in range(S) for c in range(C)}), "application/zip")))
    parts.append(("frames", ("frames.zip", zipped(
        {f"{names[c]}/{t:05d}.png": png(sample.frame_images[t, c])
         for t in range(T) for c in range(C)}), "application/zip")))
    return parts
