"""TRC files as OpenSim's TRCFileAdapter reads them: rows, not NumFrames; tabs repeated."""

import re

import numpy as np
import pytest

from service.io.errors import MarkerFormatError
from service.io.trc import read_markers_trc


def opensim_trc(text: str):
    """A reference TRC reader following OpenSim's TRCFileAdapter::extendRead.

    Header keys and values: tab-separated with empty fields erased, paired in order. Marker
    labels: line 4 less Frame# and Time, empty fields erased. Data: blank lines after the
    header skipped, then one row per line until an empty line, each of 2 + 3M tab-separated
    cells; a marker with any empty coordinate is NaN. NumFrames is not used. Lengths stay in
    the file's unit.
    """
    lines = text.split("\n")
    keys = [cell for cell in re.split("[\t\r]", lines[1]) if cell]
    values = [cell for cell in re.split("[\t\r]", lines[2]) if cell]
    assert len(keys) == len(values)
    meta = dict(zip(keys, values))
    count = int(meta["NumMarkers"])
    labels = [cell for cell in re.split("[\t\r]", lines[3]) if cell][2:]
    k = 5
    while not lines[k].strip():
        k += 1
    rows = []
    while k < len(lines) and lines[k].strip():
        cells = lines[k].rstrip("\r").split("\t")
        assert len(cells) == 2 + 3 * count
        frame = []
        for m in range(count):
            xyz = cells[2 + 3 * m : 5 + 3 * m]
            frame.append([np.nan] * 3 if "" in xyz else [float(c) for c in xyz])
        rows.append(frame)
        k += 1
    return labels, meta, np.array(rows)


def _trc(num_frames, rows, header_tabs="\t", units="mm"):
    """A TRC with 2 markers and the given data rows, header fields joined by `header_tabs`."""
    keys = ["DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate", "OrigDataStartFrame", "OrigNumFrames"]
    values = ["60.00", "60.00", str(num_frames), "2", units, "60.00", "1", str(num_frames)]
    lines = [
        "PathFileType\t4\t(X/Y/Z)\tface.trc",
        header_tabs.join(keys),
        header_tabs.join(values),
        "Frame#\tTime\tNose\t\t\tChin\t\t",
        "\t\tX1\tY1\tZ1\tX2\tY2\tZ2",
        "",
    ]
    rng = np.random.default_rng(rows)
    for f in range(rows):
        cells = [f"{v:.6f}" for v in rng.uniform(-100, 100, 6)]
        if f == 1:
            cells[3:] = ["", "", ""]  # Chin occluded
        lines.append("\t".join([str(f + 1), f"{f / 60:.6f}"] + cells))
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("declared, rows", [(5, 3), (3, 5)])
def test_rows_are_read_when_num_frames_disagrees_like_opensim(declared, rows):
    text = _trc(declared, rows)
    labels, _, reference = opensim_trc(text)
    back = read_markers_trc(text.encode())
    assert back.names == tuple(labels) == ("Nose", "Chin")
    assert back.positions.shape == (rows, 2, 3)
    assert np.array_equal(back.positions, reference, equal_nan=True)
    assert back.notes == (
        f"the TRC header says NumFrames {declared} but the file has {rows} frame rows; the {rows} rows were read",
    )


def test_a_file_that_agrees_has_no_notes():
    assert read_markers_trc(_trc(4, 4).encode()).notes == ()


def test_header_values_separated_by_repeated_tabs_are_read_like_opensim():
    text = _trc(4, 4, header_tabs="\t\t", units="cm")
    _, meta, reference = opensim_trc(text)
    back = read_markers_trc(text.encode())
    assert meta["Units"] == "cm" and back.fps == 60.0
    assert np.array_equal(back.positions, reference * 10, equal_nan=True)  # cm -> mm


def test_a_garbled_header_value_is_quoted_by_its_key():
    text = _trc(4, 4, header_tabs="\t\t").replace("\t\t2\t\tmm", "\t\tx2\t\tmm")
    with pytest.raises(MarkerFormatError, match="TRC header gives NumMarkers 'x2', expected a whole number"):
        read_markers_trc(text.encode())


def test_keys_and_values_that_do_not_pair_are_refused():
    text = _trc(4, 4).replace("60.00\t60.00\t4", "60.00\t4", 1)
    with pytest.raises(MarkerFormatError, match="TRC header has 8 keys .* but 7 values"):
        read_markers_trc(text.encode())
