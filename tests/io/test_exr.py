"""EXR maps: bit-exact float32, half rounding, channel naming, no flips, bounded reads."""

import io

import numpy as np
import OpenEXR
import pytest

from service.io.errors import MapFormatError, SizeLimitError
from service.io.exr import read_exr, read_map, write_exr, write_map

COEFFICIENTS = [f"{axis}.a{k}" for axis in "xyz" for k in range(6)]


def _awkward_floats(shape, seed):
    """float32 values spanning denormals, negatives, +-0, huge magnitudes and inf."""
    rng = np.random.default_rng(seed)
    values = rng.standard_normal(shape) * 10.0 ** rng.integers(-44, 38, shape)
    values = values.astype(np.float32)
    values.flat[:5] = [1e-45, -1e-40, -0.0, 3.4028235e38, np.inf]
    return values


def _same_bits(a, b):
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a.view(np.uint32), b.view(np.uint32))


def test_eighteen_coefficient_channels_round_trip_bit_exactly(tmp_path):
    channels = {name: _awkward_floats((9, 13), seed) for seed, name in enumerate(COEFFICIENTS)}
    write_exr(tmp_path / "pdm.exr", channels)
    back = read_exr(tmp_path / "pdm.exr")
    assert list(back) == sorted(COEFFICIENTS)
    assert all(_same_bits(back[name], channels[name]) for name in COEFFICIENTS)


@pytest.mark.parametrize("compression", ["none", "rle", "zips", "zip", "piz"])
def test_lossless_compressions_are_bit_exact(compression):
    channels = {"Y": _awkward_floats((17, 5), 1)}
    buffer = io.BytesIO()
    write_exr(buffer, channels, compression=compression)
    assert _same_bits(read_exr(buffer.getvalue())["Y"], channels["Y"])


def test_half_round_trip_equals_float16_rounding(tmp_path):
    values = np.random.default_rng(2).normal(scale=100.0, size=(8, 6, 3)).astype(np.float32)
    values[0, 0] = [1e-6, 70000.0, -0.0]  # a half denormal and a half overflow
    write_map(tmp_path / "albedo.exr", values, half=True)
    back = read_map(tmp_path / "albedo.exr")
    assert back.dtype == np.float32
    with np.errstate(over="ignore"):
        assert _same_bits(back, values.astype(np.float16).astype(np.float32))
    channels = OpenEXR.File(str(tmp_path / "albedo.exr"), separate_channels=True).channels()
    assert {name: c.type() for name, c in channels.items()} == dict.fromkeys("BGR", OpenEXR.HALF)


def test_scalar_map_is_channel_y_and_colour_map_is_r_g_b(tmp_path):
    scalar = np.arange(12, dtype=np.float32).reshape(3, 4)
    colour = np.arange(36, dtype=np.float32).reshape(3, 4, 3)
    write_map(tmp_path / "d.exr", scalar)
    write_map(tmp_path / "c.exr", colour)
    assert list(read_exr(tmp_path / "d.exr")) == ["Y"]
    assert list(read_exr(tmp_path / "c.exr")) == ["B", "G", "R"]
    assert _same_bits(read_map(tmp_path / "d.exr"), scalar)
    assert _same_bits(read_map(tmp_path / "c.exr"), colour)
    assert _same_bits(read_exr(tmp_path / "c.exr")["G"], colour[:, :, 1])


def test_row_zero_is_the_first_scanline_in_the_file(tmp_path):
    ramp = np.repeat(np.arange(5, dtype=np.float32)[:, None], 3, axis=1)  # row r holds r
    write_map(tmp_path / "ramp.exr", ramp, compression="none")
    stored = OpenEXR.File(str(tmp_path / "ramp.exr"), separate_channels=True)
    assert stored.header()["lineOrder"] == OpenEXR.INCREASING_Y
    assert stored.channels()["Y"].pixels[:, 0].tolist() == [0, 1, 2, 3, 4]
    assert read_map(tmp_path / "ramp.exr")[:, 0].tolist() == [0, 1, 2, 3, 4]


def test_read_accepts_bytes_and_binary_streams():
    buffer = io.BytesIO()
    write_map(buffer, np.ones((2, 3)))
    assert read_map(buffer.getvalue()).shape == (2, 3)
    assert read_map(io.BytesIO(buffer.getvalue())).shape == (2, 3)


def test_read_map_rejects_coefficient_files_naming_the_channels(tmp_path):
    write_exr(tmp_path / "c.exr", {name: np.zeros((2, 2)) for name in ("x.a0", "x.a1")})
    expected = r"expected channel Y or channels R, G, B in a map, found \['x.a0', 'x.a1'\]"
    with pytest.raises(MapFormatError, match=expected):
        read_map(tmp_path / "c.exr")


def test_image_size_is_bounded_from_the_header():
    buffer = io.BytesIO()
    write_map(buffer, np.zeros((40, 50)))
    with pytest.raises(SizeLimitError, match="declares 2000 texels, more than the limit of 1999"):
        read_map(buffer.getvalue(), max_texels=1999)
    with pytest.raises(SizeLimitError, match="declares 1 channels, more than the limit of 0"):
        read_exr(buffer.getvalue(), max_channels=0)


def test_unreadable_files_raise_map_format_error():
    buffer = io.BytesIO()
    write_map(buffer, np.random.default_rng(3).random((64, 64)), compression="none")
    data = buffer.getvalue()
    for data in (b"not an exr at all", data[:200], data[: len(data) // 2]):
        with pytest.raises(MapFormatError, match="not a readable EXR file"):
            read_exr(data)


def test_offset_data_window_is_rejected():
    buffer = io.BytesIO()
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "dataWindow": (np.array([1, 1], np.int32), np.array([2, 2], np.int32)),
        "displayWindow": (np.array([0, 0], np.int32), np.array([3, 3], np.int32)),
    }
    OpenEXR.File(header, {"Y": np.zeros((2, 2), np.float32)}).write(buffer)
    with pytest.raises(MapFormatError, match="data window .* differs from its display window"):
        read_exr(buffer.getvalue())


@pytest.mark.parametrize(
    "channels, message",
    [
        ({}, "at least one channel"),
        ({"Y": np.zeros(4)}, r"channel 'Y' must be a non-empty \(H,W\) array"),
        ({"R": np.zeros((2, 2)), "G": np.zeros((2, 3))}, r"channel 'G' has shape \(2, 3\)"),
        ({"": np.zeros((2, 2))}, "channel names must be non-empty strings"),
    ],
)
def test_write_rejects_malformed_channel_sets(channels, message, tmp_path):
    with pytest.raises(ValueError, match=message):
        write_exr(tmp_path / "bad.exr", channels)


def test_write_rejects_unknown_compression_and_map_shapes(tmp_path):
    with pytest.raises(ValueError, match="compression 'lzma' is not one of"):
        write_exr(tmp_path / "a.exr", {"Y": np.zeros((2, 2))}, compression="lzma")
    with pytest.raises(ValueError, match=r"a map must have shape \(H,W\) or \(H,W,3\), got \(2, 2, 4\)"):
        write_map(tmp_path / "a.exr", np.zeros((2, 2, 4)))


def test_corrupted_exr_files_raise_only_map_format_errors():
    rng = np.random.default_rng(13)
    for compression in ("none", "zip"):
        buffer = io.BytesIO()
        write_exr(buffer, {"Y": rng.random((8, 8)), "x.a0": rng.random((8, 8))}, compression=compression)
        data = buffer.getvalue()
        for trial in range(60):
            corrupted = bytearray(data)
            if trial % 2:
                corrupted = corrupted[: rng.integers(0, len(data))]
            else:
                corrupted[rng.integers(0, len(data))] = rng.integers(0, 256)
            try:
                read_exr(bytes(corrupted))
            except (MapFormatError, SizeLimitError):
                pass


def test_deep_exr_is_refused_as_not_supported(tmp_path):
    """A deep scanline image (a varying number of samples per pixel), written by OpenEXR."""
    depth = np.empty((4, 5), dtype=object)
    for i, j in np.ndindex(depth.shape):
        depth[i, j] = np.arange(1 + (i + j) % 3, dtype=np.float32)
    header = {"type": OpenEXR.deepscanline, "compression": OpenEXR.ZIPS_COMPRESSION}
    OpenEXR.File(header, {"Z": depth}).write(str(tmp_path / "deep.exr"))
    with pytest.raises(MapFormatError, match="deep EXR is not supported"):
        read_exr(tmp_path / "deep.exr")


def test_header_string_that_is_not_utf8_is_a_map_format_error():
    buffer = io.BytesIO()
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, "owner": "facesynth-owner"}
    OpenEXR.File(header, {"Y": np.ones((3, 4), np.float32)}).write(buffer)
    data = buffer.getvalue()
    assert data.count(b"facesynth-owner") == 1
    damaged = data.replace(b"facesynth-owner", b"\xff\xfe\xfd" * 5)
    with pytest.raises(MapFormatError, match="not a readable EXR file"):
        read_exr(damaged)


def test_damage_the_library_reports_is_a_map_format_error_and_nothing_is_printed(capfd):
    buffer = io.BytesIO()
    write_exr(buffer, {"Y": _awkward_floats((32, 8), 3)}, compression="none")
    data = buffer.getvalue()
    damaged = data[:-40] + bytes(40)  # the last scanline chunk's leader and pixels zeroed
    capfd.readouterr()
    with pytest.raises(MapFormatError, match="EXR file is damaged|not a readable EXR file"):
        read_exr(damaged)
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    assert read_exr(data)["Y"].shape == (32, 8)  # the intact file still reads, printing nothing
    assert capfd.readouterr() == ("", "")
