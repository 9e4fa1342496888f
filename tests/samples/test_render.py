"""The small z-buffer renderer: projection, occlusion, barycentrics, shading."""

from __future__ import annotations

import numpy as np

from service.samples.render import Camera, face_cameras, rasterize, shade, to_srgb8

SIZE = 64


def _camera() -> Camera:
    """Looking down −z from z = 100 (OpenCV axes: x right, y down): world y up → image up."""
    f = 64.0
    K = np.array([[f, 0, SIZE / 2], [0, f, SIZE / 2], [0, 0, 1.0]])
    R = np.diag([1.0, -1.0, -1.0])
    return Camera(K, R, -R @ np.array([0.0, 0.0, 100.0]), SIZE, SIZE)


def _quad(z: float, half: float) -> tuple[np.ndarray, np.ndarray]:
    """A square at depth z facing +z (counter-clockwise seen from the camera)."""
    V = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    return V, np.array([[0, 1, 2], [0, 2, 3]])


def test_projection_puts_the_axis_at_the_image_centre():
    cam = _camera()
    p = cam.project(np.array([[0.0, 0, 0], [10.0, 10.0, 0]]))
    np.testing.assert_allclose(p[0], [SIZE / 2, SIZE / 2, 100.0])
    # x right, world-up is image-up (smaller row), f·x/z = 64·10/100
    np.testing.assert_allclose(p[1], [SIZE / 2 + 6.4, SIZE / 2 - 6.4, 100.0])


def test_nearer_surface_wins_whatever_the_triangle_order():
    cam = _camera()
    Vn, Fn = _quad(20.0, 15.0)        # near, small
    Vf, Ff = _quad(0.0, 40.0)         # far, large
    for near_first in (True, False):
        parts = [(Vn, Fn, 0), (Vf, Ff, 1)] if near_first else [(Vf, Ff, 1), (Vn, Fn, 0)]
        V = np.concatenate([p[0] for p in parts])
        F = np.concatenate([parts[0][1], parts[1][1] + 4])
        label = np.repeat([p[2] for p in parts], 2)
        tri, bary = rasterize(cam, V, F)
        # centre pixel sees the near quad, a pixel outside it the far one
        assert label[tri[SIZE // 2, SIZE // 2]] == 0
        assert label[tri[SIZE // 2, 10]] == 1
        covered = tri >= 0
        np.testing.assert_allclose(bary[covered].sum(axis=1), 1.0, atol=1e-12)
        assert bary[covered].min() >= -1e-9
        # barycentrics reproduce the pixel centres
        P = cam.project(V)[F[tri[covered]]][..., :2]                  # (p,3,2)
        xy = np.einsum("pk,pkd->pd", bary[covered], P)
        r, c = np.nonzero(covered)
        np.testing.assert_allclose(xy, np.column_stack([c + 0.5, r + 0.5]), atol=1e-9)


def test_back_faces_are_culled_and_coverage_matches_the_projected_area():
    cam = _camera()
    V, F = _quad(0.0, 25.0)           # projects to a 32×32 pixel square
    tri, _ = rasterize(cam, V, F)
    assert (tri >= 0).sum() == 32 * 32
    back, _ = rasterize(cam, V, F[:, ::-1])
    assert (back >= 0).sum() == 0


def test_shading_follows_lambert():
    cam = _camera()
    V, F = _quad(0.0, 25.0)
    albedo = np.full((4, 3), 0.5)
    light = np.array([0.0, 0.6, 0.8])
    img = shade(cam, V, F, albedo, light_dir=light, ambient=0.1)
    inside = img[SIZE // 2, SIZE // 2]
    np.testing.assert_allclose(inside, 0.5 * (0.1 + 0.9 * 0.8), rtol=1e-12)
    assert img[0, 0].tolist() == [0.0, 0.0, 0.0]
    # the sRGB curve: linear toe below 0.0031308 (×12.92), mid-grey 0.5 → 0.7354 → 188
    assert to_srgb8(np.array([0.0, 0.0031308, 0.5, 1.0])).tolist() == [0, 10, 188, 255]


def test_face_cameras_look_at_the_target():
    target = np.array([0.0, 10.0, 50.0])
    for cam in face_cameras(target):
        p = cam.project(target[None])[0]
        np.testing.assert_allclose(p[:2], [cam.width / 2, cam.height / 2], atol=1e-9)
        np.testing.assert_allclose(p[2], 520.0, rtol=1e-12)
