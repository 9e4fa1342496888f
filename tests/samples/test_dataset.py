"""Tests for service.samples.dataset: the sample actor's files as method inputs."""

import numpy as np

from service.samples import dataset


def test_clip_maps_are_relative_to_the_clip_mesh(pdm_actor_dir, pdm_data):
    actor, _ = pdm_data
    assert actor.n_markers == 150 and set(actor.regions) == {"narrow_face", "face", "head"}
    assert actor.regions["narrow_face"].sum() < actor.regions["face"].sum() < actor.n_vertices
    clip = dataset.load_clip(pdm_actor_dir, "train_smile", actor, frames=[0, 12])
    with np.load(pdm_actor_dir / "performances" / "train_smile.npz") as d:
        full, medium = d["displacement"][[0, 12]], d["vertices_medium"][[0, 12]].astype(np.float64)
        np.testing.assert_array_equal(clip.markers, d["markers"][[0, 12]])
    # the wrinkles the mesh carries are taken out of the map, and only those
    carried = dataset.vertex_detail_map(actor, clip.vertices, medium, full.shape[1])
    np.testing.assert_allclose(clip.displacement + carried, full, atol=1e-6)
    assert np.abs(carried[0]).max() < 1e-6 < np.abs(carried[1]).max()     # neutral: nothing
    assert clip.albedo.shape == (2, 64, 64, 3) and clip.albedo.dtype == np.float32


def test_held_out_maps_only_where_every_frame_has_one(pdm_actor_dir, pdm_data):
    actor, _ = pdm_data
    frames = dataset.map_frames(pdm_actor_dir, "heldout_in_range")
    assert np.all(np.diff(frames) == 5)
    assert dataset.load_clip(pdm_actor_dir, "heldout_in_range", actor, frames=frames).displacement is not None
    assert dataset.load_clip(pdm_actor_dir, "heldout_in_range", actor, frames=[1, 2]).displacement is None
    assert dataset.performance_names(pdm_actor_dir, "train_")[0] == "train_brow_furrow"
