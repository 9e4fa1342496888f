"""C3D reader against ezc3d (the reference implementation) on files real systems write."""

import numpy as np
import pytest

from service.io.c3d import read_markers_c3d
from service.io.errors import MarkerFormatError
from tests.io.c3d_files import ezc3d_file, ezc3d_points, set_parameter, to_dec_integer

LABELS = ("FH1", "NOSE", "CHIN")


def _points(frames=6, seed=3):
    """(F,3,3) mm positions, marker 1 occluded in frame 2, seeded."""
    points = np.random.default_rng(seed).uniform(-300, 300, (frames, len(LABELS), 3))
    points[2, 1] = np.nan
    return points


def test_one_unit_string_per_point_reads_like_ezc3d(tmp_path):
    """NDI/Optotrak files store POINT:UNITS once per point ('mm', 'mm', ...)."""
    path = ezc3d_file(tmp_path / "ndi.c3d", _points(), LABELS, units=["mm"] * 3)
    back = read_markers_c3d(path)
    assert np.array_equal(back.positions, ezc3d_points(path), equal_nan=True)
    assert back.names == LABELS and back.fps == 100.0
    metres = ezc3d_file(tmp_path / "m.c3d", _points() / 1000, LABELS, units=["m", "m ", "M"])
    assert np.array_equal(read_markers_c3d(metres).positions, ezc3d_points(metres) * 1000, equal_nan=True)



def test_points_in_different_units_are_refused_naming_the_units(tmp_path):
    path = ezc3d_file(tmp_path / "mixed.c3d", _points(), LABELS, units=["mm", "m", "mm"])
    with pytest.raises(MarkerFormatError, match=r"different units \['m', 'mm'\]; expected one unit"):
        read_markers_c3d(path)


def test_dec_integer_file_numbered_from_frame_0_reads_every_frame_like_ezc3d(tmp_path):
    """The DEC integer file of the report: first frame 0, POINT:FRAMES 670 (the c3d package read
    671 frames and refused it)."""
    float_file = ezc3d_file(tmp_path / "f.c3d", _points(670), LABELS, rate=60.0, first_frame_as_zero=True)
    assert np.array_equal(read_markers_c3d(float_file).positions, ezc3d_points(float_file), equal_nan=True)
    dec = tmp_path / "dec.c3d"
    dec.write_bytes(to_dec_integer(float_file.read_bytes(), scale=0.05))
    reference = ezc3d_points(dec)
    back = read_markers_c3d(dec)
    assert back.positions.shape == (670, 3, 3)
    assert np.array_equal(back.positions, reference, equal_nan=True)  # int16 * scale, bit for bit
    assert np.isnan(back.positions[2, 1]).all() and np.isfinite(np.delete(back.positions, 1, 1)).all()
    assert np.nanmax(np.abs(back.positions - _points(670))) < 0.0251  # half a step of the float32 scale
    assert back.fps == 60.0


def test_two_dimensional_trial_fields_give_the_frame_count_like_ezc3d(tmp_path):
    """TRIAL:ACTUAL_START_FIELD / ACTUAL_END_FIELD stored as (2,1) arrays of 16-bit words."""
    fields = [("TRIAL", "ACTUAL_START_FIELD", [1, 0], [2, 1]), ("TRIAL", "ACTUAL_END_FIELD", [6, 0], [2, 1])]
    path = ezc3d_file(tmp_path / "trial.c3d", _points(), LABELS, int_params=fields)
    reference = ezc3d_points(path)
    assert np.array_equal(read_markers_c3d(path).positions, reference, equal_nan=True)
    # POINT:FRAMES saturated at 65535 (more frames than 16 bits hold): the TRIAL fields count
    saturated = set_parameter(path.read_bytes(), "POINT", "FRAMES", [65535])
    assert np.array_equal(read_markers_c3d(saturated).positions, reference, equal_nan=True)


def test_file_without_points_is_refused_naming_it(tmp_path):
    """A force-plate recording: analog channels, no 3-D points."""
    path = ezc3d_file(tmp_path / "plates.c3d", np.zeros((5, 0, 3)), (),
                      analogs=np.random.default_rng(1).normal(size=(2, 50)))
    with pytest.raises(MarkerFormatError, match=r"no 3-D points \(POINT:USED is 0.*force plates"):
        read_markers_c3d(path)


def test_points_with_analog_channels_skip_the_analog_samples_like_ezc3d(tmp_path):
    analogs = np.random.default_rng(2).normal(size=(2, 60))  # 10 samples a frame, 2 channels
    path = ezc3d_file(tmp_path / "both.c3d", _points(), LABELS, analogs=analogs)
    assert np.array_equal(read_markers_c3d(path).positions, ezc3d_points(path), equal_nan=True)


def test_parameter_section_past_the_end_is_a_format_error():
    header = bytearray(512)
    header[0], header[1] = 9, 0x50
    with pytest.raises(MarkerFormatError, match="not a readable C3D file: its parameter section"):
        read_markers_c3d(bytes(header))
