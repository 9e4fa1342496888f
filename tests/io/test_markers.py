"""Marker files: round trips preserving occlusions, unit conversion, layouts and clear errors."""

import io
import json
import warnings

import c3d
import numpy as np
import pytest

from service.io.errors import FormatError, MarkerFormatError, SizeLimitError
from service.io.markers import (
    MarkerSequence,
    read_marker_layout,
    read_markers,
    read_markers_c3d,
    read_markers_csv,
    read_markers_json,
    read_markers_trc,
    write_marker_layout,
    write_markers_c3d,
    write_markers_csv,
    write_markers_json,
    write_markers_trc,
)
from tests.io.corruption import corrupt

NAMES = ("FH1", "L_brow", "nose.tip, left", "Chin_x")


@pytest.fixture
def sequence():
    """5 frames of 4 markers in mm, two occlusions, seeded."""
    positions = np.random.default_rng(7).normal(scale=80.0, size=(5, 4, 3))
    positions[1, 2] = np.nan
    positions[4, 0] = np.nan
    return MarkerSequence(positions, NAMES, fps=120.0)


def _occluded(positions):
    return np.isnan(positions).all(axis=2)


@pytest.mark.parametrize(
    "write, read",
    [
        (write_markers_csv, read_markers_csv),
        (write_markers_trc, read_markers_trc),
        (write_markers_json, read_markers_json),
    ],
)
def test_text_formats_round_trip_values_bit_exactly_and_keep_occlusions(write, read, sequence, tmp_path):
    write(tmp_path / "m", sequence)
    back = read(tmp_path / "m")
    assert back.names == NAMES
    assert _occluded(back.positions).tolist() == _occluded(sequence.positions).tolist()
    assert np.array_equal(back.positions, sequence.positions, equal_nan=True)


def test_trc_and_json_keep_the_frame_rate_and_csv_has_none(sequence):
    for write, read, fps in [
        (write_markers_trc, read_markers_trc, 120.0),
        (write_markers_json, read_markers_json, 120.0),
        (write_markers_csv, read_markers_csv, None),
    ]:
        buffer = io.BytesIO()
        write(buffer, sequence)
        assert read(buffer.getvalue()).fps == fps


def test_c3d_round_trip_matches_to_float32_and_keeps_occlusions(sequence, tmp_path):
    write_markers_c3d(tmp_path / "m.c3d", sequence)
    back = read_markers_c3d(tmp_path / "m.c3d")
    assert back.names == NAMES
    assert back.fps == 120.0
    assert _occluded(back.positions).tolist() == _occluded(sequence.positions).tolist()
    expected = sequence.positions.astype(np.float32).astype(np.float64)
    assert np.array_equal(back.positions, expected, equal_nan=True)


def _c3d_bytes(points, units, labels=("A", "B"), rate=100.0):
    """A float C3D of (F,M,3) points; NaN rows are flagged invalid (residual -1)."""
    writer = c3d.Writer(point_rate=rate, point_units=units)
    writer.set_point_labels(list(labels))
    for frame in points:
        block = np.zeros((len(frame), 5), np.float32)
        block[:, :3] = np.nan_to_num(frame)
        block[np.isnan(frame).any(axis=1), 3] = -1
        writer.add_frames([(block, np.zeros((0, 0), np.float32))])
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        writer.write(buffer)
    return buffer.getvalue()


def test_c3d_in_metres_is_converted_to_millimetres():
    points = np.array([[[0.5, -0.25, 1.0], [np.nan] * 3]])
    back = read_markers(_c3d_bytes(points, "m"), ".c3d")
    assert back.positions[0, 0].tolist() == [500.0, -250.0, 1000.0]
    assert np.isnan(back.positions[0, 1]).all()
    assert back.names == ("A", "B") and back.fps == 100.0


def test_c3d_with_fewer_frames_than_declared_is_rejected():
    data = _c3d_bytes(np.zeros((3, 2, 3)), "mm")
    frames_start = len(data) - 512  # 3 frames of 2 points take 96 bytes of the last block
    with pytest.raises(MarkerFormatError, match="C3D file declares 3 frames but holds 1"):
        read_markers_c3d(data[: frames_start + 32 + 8])


def test_c3d_garbage_is_a_format_error():
    with pytest.raises(MarkerFormatError, match="not a readable C3D file"):
        read_markers_c3d(b"\x02P" + bytes(600))


TRC_IN_METRES = (
    "PathFileType\t4\t(X/Y/Z)\thand.trc\n"
    "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
    "60.00\t60.00\t2\t2\tm\t60.00\t1\t2\n"
    "Frame#\tTime\tTop\t\t\tTip\t\t\n"
    "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n"
    "\n"
    "1\t0.000\t0.1\t0.2\t0.3\t\t\t\n"
    "2\t0.017\t0.5\t-0.25\t1\t0.001\t0.002\t0.004\n"
)


def test_trc_in_metres_with_blank_cells_is_read_in_millimetres():
    back = read_markers(TRC_IN_METRES.encode(), ".trc")
    assert back.names == ("Top", "Tip") and back.fps == 60.0
    assert np.allclose(back.positions[0, 0], [100, 200, 300], rtol=0, atol=1e-12)
    assert np.isnan(back.positions[0, 1]).all()
    assert back.positions[1].tolist() == [[500, -250, 1000], [1, 2, 4]]


def test_trc_rows_may_omit_trailing_empty_cells():
    short = TRC_IN_METRES.replace("0.3\t\t\t\n", "0.3\n")
    assert np.isnan(read_markers_trc(short.encode()).positions[0, 1]).all()


def test_csv_accepts_dot_and_colon_axis_names_time_column_and_nan_cells():
    text = "Frame,Time,A.x,A.y,A.z,B:X,B:Y,B:Z\n1,0.0,1,2,3,,,\n2,0.1,4,5,6,nan,8,9\n3,0.2,7,8,9,1e3,-2,0.5\n"
    back = read_markers(text.encode(), ".csv")
    assert back.names == ("A", "B")
    assert back.positions[:, 0].tolist() == [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    assert _occluded(back.positions)[:, 1].tolist() == [True, True, False]
    assert back.positions[2, 1].tolist() == [1000, -2, 0.5]


def test_json_frames_accept_null_markers_and_ignore_other_request_keys():
    body = {"markers": [[[1, 2, 3], None], [[4, 5, 6.5], [None, None, None]]], "outputs": ["mesh"]}
    back = read_markers(json.dumps(body).encode(), ".json")
    assert back.positions[:, 0].tolist() == [[1, 2, 3], [4, 5, 6.5]]
    assert _occluded(back.positions)[:, 1].tolist() == [True, True]
    assert back.names is None and back.fps is None


def test_read_markers_dispatches_on_the_path_suffix(sequence, tmp_path):
    writers = {
        ".csv": write_markers_csv, ".trc": write_markers_trc,
        ".c3d": write_markers_c3d, ".json": write_markers_json,
    }  # fmt: skip
    for suffix, write in writers.items():
        write(tmp_path / f"m{suffix.upper()}", sequence)
        assert read_markers(tmp_path / f"m{suffix.upper()}").names == NAMES
    with pytest.raises(MarkerFormatError, match="unsupported marker file type '.bvh'"):
        read_markers(b"HIERARCHY", ".bvh")


@pytest.mark.parametrize(
    "read, data, message",
    [
        (read_markers_csv, "frame,A_x,A_y\n1,2,3\n", r"CSV marker 'A' lacks the column\(s\) \['z'\]"),
        (read_markers_csv, "frame,A_x,A_y,A_z,weird\n1,2,3,4,5\n", "CSV column 5 'weird' is neither frame/time nor <name>_x"),
        (read_markers_csv, "frame,A_x,A_y,A_z\n1,2,3\n", "CSV row 2 has 3 cells, the header has 4"),
        (read_markers_csv, "frame,A_x,A_y,A_z\n1,2,x3,4\n", "CSV frame 0 marker 'A' y: 'x3' is not a number"),
        (read_markers_csv, "frame,A_x,A_y,A_z,A_x\n1,2,3,4,5\n", "CSV has two 'x' columns for marker 'A'"),
        (read_markers_trc, TRC_IN_METRES.replace("\tm\t", "\tin\t"), r"TRC unit 'in' is not one of \['cm', 'm', 'mm'\]"),
        (read_markers_trc, TRC_IN_METRES.replace("Tip\t\t\n", "\n"), "TRC header says 2 markers but names 1"),
        (read_markers_trc, "hello\n", "not a TRC file"),
        (read_markers_json, '{"markers": [[[1, 2, 3]], [[1, 2, 3], [4, 5, 6]]]}', "frame 1 has 2 markers, frame 0 has 1"),
        (read_markers_json, '{"markers": [[[1, 2]]]}', r"frame 0 marker 0 is \[1, 2\], expected \[x, y, z\] numbers or null"),
        (read_markers_json, '{"markers": [[[1, null, 3]]]}', "frame 0 marker 0 is"),
        (read_markers_json, '{"markers": [[["1", 2, 3]]]}', "frame 0 marker 0 is"),
        (read_markers_json, '{"markers": [[[1, 2, Infinity]]]}', "frame 0 marker 0 has an infinite coordinate"),
        (read_markers_json, '{"frames": []}', 'an object with a "markers" list of frames'),
        (read_markers_json, "[1, 2", "marker JSON is not valid JSON"),
    ],
)
def test_bad_marker_files_raise_a_specific_format_error(read, data, message):
    with pytest.raises(MarkerFormatError, match=message):
        read(data.encode())


def test_marker_counts_are_bounded_before_allocating(sequence):
    buffer = io.BytesIO()
    write_markers_trc(buffer, sequence)
    with pytest.raises(SizeLimitError, match="declares 5 frames, more than the limit of 4"):
        read_markers_trc(buffer.getvalue(), max_frames=4)
    write_markers_c3d(buffer := io.BytesIO(), sequence)
    with pytest.raises(SizeLimitError, match="declares 4 markers, more than the limit of 3"):
        read_markers_c3d(buffer.getvalue(), max_markers=3)


def test_writers_need_names_and_a_frame_rate():
    anonymous = MarkerSequence(np.zeros((1, 2, 3)))
    with pytest.raises(ValueError, match="needs marker names"):
        write_markers_csv(io.BytesIO(), anonymous)
    with pytest.raises(ValueError, match="TRC needs a frame rate"):
        write_markers_trc(io.BytesIO(), MarkerSequence(np.zeros((1, 2, 3)), ("a", "b")))
    with pytest.raises(ValueError, match="TRC marker names cannot be blank or hold tabs"):
        write_markers_trc(io.BytesIO(), MarkerSequence(np.zeros((1, 2, 3)), ("a", "b\tc"), 30))


def test_partially_missing_marker_is_occluded_entirely():
    positions = np.array([[[1.0, np.nan, 3.0]]])
    assert np.isnan(MarkerSequence(positions).positions).all()


# ---------------------------------------------------------------------------- layout

LAYOUT = {
    "markers": [
        {"name": "FH1", "vertex": 812},
        {"name": "FH2", "triangle": 9912, "barycentric": [0.2, 0.3, 0.5]},
        {"name": "FH3", "position": [1.5, -2.0, 30.25]},
    ]
}


def test_marker_layout_is_parsed_per_kind_and_round_trips():
    layout = read_marker_layout(json.dumps(LAYOUT).encode(), vertex_count=1000, triangle_count=10000)
    assert layout.names == ("FH1", "FH2", "FH3")
    assert layout.kinds == ("vertex", "triangle", "position")
    assert layout.vertex.tolist() == [812, -1, -1]
    assert layout.triangle.tolist() == [-1, 9912, -1]
    assert layout.barycentric[1].tolist() == [0.2, 0.3, 0.5] and np.isnan(layout.barycentric[[0, 2]]).all()
    assert layout.position[2].tolist() == [1.5, -2.0, 30.25] and np.isnan(layout.position[:2]).all()
    buffer = io.BytesIO()
    write_marker_layout(buffer, layout)
    assert json.loads(buffer.getvalue()) == LAYOUT


def _layout_with(entry):
    return json.dumps({"markers": [LAYOUT["markers"][0], entry]}).encode()


@pytest.mark.parametrize(
    "entry, message",
    [
        ({"name": "FH1", "vertex": 3}, "marker name 'FH1' appears more than once"),
        ({"name": "X", "triangle": 1, "barycentric": [0.2, 0.3, 0.6]}, "must be non-negative and sum to 1 .* the sum is 1.1"),
        ({"name": "X", "triangle": 1, "barycentric": [-0.1, 0.6, 0.5]}, "must be non-negative"),
        ({"name": "X", "triangle": 1, "barycentric": [0.5, 0.5]}, "has barycentric \\[0.5, 0.5\\], expected 3 finite numbers"),
        ({"name": "X", "vertex": 3, "position": [0, 0, 0]}, r"has keys \['position', 'vertex'\]; expected exactly one"),
        ({"name": "X", "vertex": -1}, r"marker 1 \('X'\) has vertex -1, expected an index >= 0"),
        ({"name": "X", "vertex": True}, "has vertex true, expected an index"),
        ({"name": "X", "vertex": 1000}, "references vertex 1000 but the neutral has 1000 vertices"),
        ({"name": "X", "triangle": 10000, "barycentric": [1, 0, 0]}, "references triangle 10000 but the neutral has 10000 triangles"),
        ({"name": "", "vertex": 1}, 'marker 1 needs a non-empty string "name"'),
        ({"name": "X", "position": [0, 0, None]}, "expected 3 finite numbers"),
    ],
)
def test_bad_marker_layout_raises_a_specific_format_error(entry, message):
    with pytest.raises(FormatError, match=message):
        read_marker_layout(_layout_with(entry), vertex_count=1000, triangle_count=10000)


def test_barycentric_sum_tolerance_fits_files_written_with_six_decimals():
    """issue 16, defect 14: 1e-6 refused real exported layouts; the tolerance is 1e-4."""
    for bary in ([0.2, 0.3, 0.5000009], [0.333333, 0.333333, 0.333333], [0.2, 0.3, 0.50009],
                 [-0.00009, 0.5, 0.50009]):
        read_marker_layout(_layout_with({"name": "X", "triangle": 1, "barycentric": bary}))
    for bary in ([0.2, 0.3, 0.5002], [-0.0002, 0.5, 0.5002]):
        with pytest.raises(MarkerFormatError, match="sum to 1"):
            read_marker_layout(_layout_with({"name": "X", "triangle": 1, "barycentric": bary}))


def test_corrupted_marker_files_raise_only_format_errors(sequence):
    rng = np.random.default_rng(12)
    layout = json.dumps(LAYOUT).encode()
    for write, read in [
        (write_markers_csv, read_markers_csv),
        (write_markers_trc, read_markers_trc),
        (write_markers_json, read_markers_json),
        (write_markers_c3d, read_markers_c3d),
        (lambda target, _: target.write(layout), read_marker_layout),
    ]:
        buffer = io.BytesIO()
        write(buffer, sequence)
        for trial in range(90):
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    read(corrupt(buffer.getvalue(), rng, trial, b"0123456789-,\t .\nnan"))
            except FormatError:
                pass
