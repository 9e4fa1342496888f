"""Tests for service.methods.pdm.remap: novel marker placement (ma2008 §5)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.methods.pdm.remap import register_markers, remap_model
from service.samples import dataset
from service.samples.actor import make_actor
from service.samples.markers import place_markers


@pytest.fixture(scope="module")
def heldout(pdm_actor_dir, pdm_data):
    actor, _ = pdm_data
    frames = dataset.map_frames(pdm_actor_dir, "heldout_in_range")
    return dataset.load_clip(pdm_actor_dir, "heldout_in_range", actor, frames=frames)


def _face_error(out, clip, actor):
    return np.linalg.norm(out["vertices"] - clip.vertices, axis=-1)[:, actor.regions["face"]].mean()


def test_remap_onto_the_training_markers_changes_nothing(pdm_model, pdm_data, heldout):
    actor, _ = pdm_data
    same = remap_model(pdm_model, actor.marker_triangle, actor.marker_barycentric, actor.marker_names)
    a = pdm_model.synthesize(heldout.markers[:4])
    b = same.synthesize(heldout.markers[:4])
    np.testing.assert_allclose(b["vertices"], a["vertices"], atol=1e-4)
    np.testing.assert_allclose(b["displacement"], a["displacement"], atol=1e-5)


def test_a_new_and_a_sparser_marker_set_drive_the_model(pdm_model, pdm_data, heldout):
    actor, _ = pdm_data
    sample = make_actor(seed=2, level=0, with_maps=False)
    lm = sample.skin.rig_neutral[sample.rig.landmarks68]
    base_error = _face_error(pdm_model.synthesize(heldout.markers), heldout, actor)
    errors = {}
    for count in (150, 100):
        layout = place_markers(actor.vertices, actor.faces, sample.skin.region == 0, lm[36:48],
                               lm[60:68], count, seed=11)
        model = remap_model(pdm_model, layout.triangle, layout.barycentric)
        markers = layout.positions(heldout.vertices, actor.faces)          # the new set, on the truth
        errors[count] = _face_error(model.synthesize(markers), heldout, actor)
    # measured (level 0, seed 2): training layout 0.236, new 150 markers 0.297, new 100 0.344 mm;
    # with the medium band's rest onset (issue 17) the training layout 0.202 and new 100 0.325 mm
    # (both better; the ratio 1.46 → 1.61)
    assert errors[150] < 1.4 * base_error
    assert errors[100] < 1.7 * base_error


def test_register_markers_recovers_the_capture_space(pdm_data):
    actor, _ = pdm_data
    rest = actor.marker_positions()
    R = Rotation.from_euler("xyz", [4, -3, 2], degrees=True).as_matrix()
    t = np.array([3.0, -2.0, 1.5])
    observed = (rest - rest.mean(0)) @ R.T + rest.mean(0) + t          # the new session's space
    reg = register_markers(actor.vertices, actor.faces, observed)
    moved = np.linalg.norm(reg.transform.apply(observed) - rest, axis=1)
    assert moved.max() < 0.01 and reg.distance.max() < 0.01        # measured 1.3e-4 mm
    snapped = actor.vertices[actor.faces[reg.triangle]]
    np.testing.assert_allclose(np.einsum("mkd,mk->md", snapped, reg.barycentric),
                               reg.transform.apply(observed), atol=0.05)
