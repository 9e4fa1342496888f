"""The rendered tracking performance: re-meshed scans, shapes, round trip."""

from __future__ import annotations

import numpy as np
import pytest

from service.geometry.camera import Camera
from service.samples.tracking import TrackingSample, build_tracking_sample, range_scan


def _camera(size: int = 32) -> Camera:
    K = np.array([[32.0, 0, size / 2], [0, 32.0, size / 2], [0, 0, 1.0]])
    R = np.diag([1.0, -1.0, -1.0])
    return Camera(K, R, -R @ np.array([0.0, 0.0, 100.0]), size, size)


def test_range_scan_of_a_plane_samples_it_on_the_grid_with_no_shared_vertices():
    V = np.array([[-50.0, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    P, T = range_scan(_camera(), V, F, grid=32, seed=0, noise_mm=0.0)
    # the plane covers the whole 32×32 image: one vertex per pixel, two triangles per block
    assert len(P) == 32 * 32 and len(T) == 2 * 31 * 31
    np.testing.assert_allclose(P[:, 2], 0.0, atol=1e-9)
    # pixel spacing on the plane at 100 mm with f = 32 px: 100/32 mm
    assert np.ptp(P[:, 0]) == pytest.approx(31 * 100 / 32, rel=1e-6)
    # counter-clockwise seen from the camera on +z: normals point at it
    n = np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]])
    assert (n[:, 2] > 0).all()


def test_tracking_sample_from_an_actor_directory_round_trips(pdm_actor_dir, tmp_path):
    s = build_tracking_sample(pdm_actor_dir, size=48, frames=2, views=1, scans=("train_smile",),
                              scan_grid=48, out=tmp_path / "t.npz")
    assert list(s.scan_names) == ["neutral", "train_smile"]
    assert s.scan_images.shape == (2, 1, 48, 48) and s.frame_images.shape == (2, 1, 48, 48)
    assert s.frame_truth.shape == (2, len(s.artist_vertices), 3)
    # raw scans are re-meshed: another vertex count than the artist mesh
    assert all(len(v) != len(s.artist_vertices) for v in s.scan_vertices)
    # the smile scan differs from the neutral by millimetres
    assert np.abs(s.scan_truth[1] - s.scan_truth[0]).max() > 2.0
    back = TrackingSample.load(tmp_path / "t.npz")
    np.testing.assert_array_equal(back.frame_images, s.frame_images)
    np.testing.assert_allclose(back.scan_vertices[1], s.scan_vertices[1], atol=1e-4)
    np.testing.assert_allclose(back.cameras[0].K, s.cameras[0].K)
    assert back.info["views"] == 1


def test_a_rest_holds_the_last_pose_while_light_and_noise_go_on(pdm_actor_dir):
    s = build_tracking_sample(pdm_actor_dir, size=32, frames=3, views=1, scans=("train_smile",),
                              scan_grid=32, rest_frames=2)
    assert s.frame_truth.shape[0] == len(s.frame_images) == 5 and s.info["rest_frames"] == 2
    np.testing.assert_array_equal(s.frame_truth[3], s.frame_truth[2])
    np.testing.assert_array_equal(s.frame_truth[4], s.frame_truth[2])
    # the held frames are new images (camera noise, light), not copies
    assert np.abs(s.frame_images[4].astype(int) - s.frame_images[3].astype(int)).max() > 0
