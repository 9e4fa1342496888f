"""Tests for service.methods.shape_space.params: validation of the training parameters."""

import pytest

from service.methods.inputs import InvalidInput
from service.methods.shape_space.params import ShapeSpaceParams


def test_defaults_are_the_papers_numbers():
    p = ShapeSpaceParams()
    assert (p.lam_dt, p.patch_size, p.boundary_weight, p.smoothing) == (125.0, 100, 0.05, "rest")
    assert ShapeSpaceParams(**p.model_dump()) == p


def test_axes_from_json_lists_become_tuples():
    p = ShapeSpaceParams(up_axis=[0, 0, 1], left_axis=[1, 0, 0])
    assert p.up_axis == (0.0, 0.0, 1.0) and hash(p)


@pytest.mark.parametrize("bad", [
    {"lam_dt": 0}, {"smoothing": "once"}, {"regions": "mine"}, {"frame_stride": 0},
    {"patch_size": 2}, {"patch_size": 10.5}, {"region_falloff": -1}, {"region_motion_fraction": 1.0},
    {"up_axis": (0, 0, 0)}, {"up_axis": (1, 0, 0)}, {"left_axis": "x"}, {"boundary_weight": -0.1},
    {"sequence_seconds": -1}, {"restore_low_frequencies": "yes"}, {"marker_correction": 1}, {"patch_seed": True},
    {"lam_dt": "125"}, {"region_falloff": None},
])
def test_bad_values_are_refused(bad):
    with pytest.raises(InvalidInput):
        ShapeSpaceParams(**bad)
