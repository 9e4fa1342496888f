"""C3D motion-capture files: the 3-D points, converted to millimetres.

The reader parses the file itself (header, parameter section, point data) rather than through a
library: the ``c3d`` package refuses valid files (it counts frames from the header's first
frame number, joins per-point units, fails on 2-D ``TRIAL`` fields and on its own metadata
assertions, and converts a DEC zero to -1.7e38), and ezc3d, the reference implementation, loops
forever at full CPU on a file truncated inside its parameter section (1 of the 90 corrupted
files of the reader's robustness test), which an upload must never do. ezc3d is the reference
the tests compare against. The writer uses the ``c3d`` package.
"""

from __future__ import annotations

import io
import math
import struct
import warnings

import c3d
import numpy as np

from service.io.errors import MarkerFormatError
from service.io.marker_sequence import (
    MAX_FRAMES,
    MAX_MARKERS,
    MM_PER_UNIT,
    MarkerSequence,
    check_counts,
    require_names,
)
from service.io.sources import Source, Target, read_source, write_target


def read_markers_c3d(
    source: Source, *, max_frames: int = MAX_FRAMES, max_markers: int = MAX_MARKERS
) -> MarkerSequence:
    """Read the 3-D points of a C3D file, converting to mm.

    The header, the parameter section and the point data are read here, as the C3D manual
    lays them out (c3d.org), for the three processor formats (Intel, DEC, MIPS) and both
    storages (float, or 16-bit integers times ``POINT:SCALE``); all frames are read at once.
    Values equal ezc3d's (the format's reference implementation), which the tests check. A
    point whose residual word is negative (the C3D "invalid" flag) or whose coordinates are not
    finite is occluded. Analog channels are skipped.

    The frame count follows the C3D guidance (c3d.org, "The C3D frame count"): ``POINT:FRAMES``
    (16-bit, or a float for more than 65535 frames), then ``POINT:LONG_FRAMES``, then
    ``TRIAL:ACTUAL_START_FIELD``/``ACTUAL_END_FIELD`` (two 16-bit words each, whatever their
    declared dimensions), and the header's frame range only when none is present. The header's
    first frame number is not used, so a file numbering its frames from 0 (as DEC integer
    files do) reads as the frames it holds.

    ``POINT:UNITS`` may be one string or one string per point (NDI/Optotrak writes ``mm`` for
    every point); every point must then name the same unit, one of ``mm``, ``cm`` or ``m``
    (mm when absent).

    Parameters
    ----------
    source : path, bytes or binary file
    max_frames, max_markers : int

    Returns
    -------
    MarkerSequence
        Positions in mm (float32 in the file, or int16 times the float32 scale, computed in
        float64 as ezc3d does), names from ``POINT:LABELS`` (then ``LABELS2``, ``LABELS3``...
        past 255 points; ``M<k>`` for unlabelled points), fps from ``POINT:RATE``.

    Raises
    ------
    MarkerFormatError
        For unreadable bytes, a file without 3-D points (``POINT:USED`` 0: analog or force
        plates only), an unknown or mixed unit, or fewer frames than declared.
    SizeLimitError
    """
    data = read_source(source)
    try:
        c3d_file = _C3dFile(data)
        count = c3d_file.integer("POINT", "USED", c3d_file.header_word(1))
        names = []
        for key in ["LABELS"] + [f"LABELS{k}" for k in range(2, 100)]:
            labels = c3d_file.strings("POINT", key)
            if labels is None:
                break
            names += labels
        units = _c3d_units(c3d_file.strings("POINT", "UNITS"))
        fps = c3d_file.real("POINT", "RATE", c3d_file.header_real(10))
        scale = c3d_file.real("POINT", "SCALE", c3d_file.header_real(6))
        analog_words = c3d_file.analog_words(fps)
        frames = c3d_file.frame_count()
        data_start = (c3d_file.integer("POINT", "DATA_START", c3d_file.header_word(8)) - 1) * 512
    except (struct.error, IndexError, ValueError, OverflowError, ZeroDivisionError) as error:
        if isinstance(error, MarkerFormatError):
            raise
        raise MarkerFormatError(f"not a readable C3D file: {error}") from None
    if count == 0:
        raise MarkerFormatError(
            "the C3D file has no 3-D points (POINT:USED is 0; it holds only analog data such "
            "as force plates); a marker file needs at least one point"
        )
    if frames < 0:
        raise MarkerFormatError(f"C3D file gives a negative frame count {frames}")
    check_counts(frames, count, max_frames, max_markers)
    if units not in MM_PER_UNIT:
        raise MarkerFormatError(f"C3D POINT:UNITS '{units}' is not one of {sorted(MM_PER_UNIT)}")
    if len(names) < count:
        names += [f"M{k + 1}" for k in range(len(names), count)]
    if not (math.isfinite(scale) and scale != 0):
        raise MarkerFormatError(f"C3D POINT:SCALE is {scale}, expected a non-zero number")
    if data_start < 512:
        raise MarkerFormatError(f"C3D data start block {data_start // 512 + 1} is not >= 2")
    positions = _c3d_points(data, data_start, frames, count, analog_words, scale, c3d_file.processor)
    fps = fps if math.isfinite(fps) and fps > 0 else None
    return MarkerSequence(positions * MM_PER_UNIT[units], names[:count], fps)


_PROCESSORS = {84: "INTEL", 85: "DEC", 86: "MIPS"}
_CHAR, _BYTE, _INT, _FLOAT = -1, 1, 2, 4


class _C3dFile:
    """The header and parameters of a C3D file (c3d.org: "The header", "The parameter section").

    Parameters are kept as (type, dimensions, value bytes), keyed by ``(GROUP, NAME)``; every
    read is bounds-checked, so malformed bytes raise ``ValueError``/``struct.error``/
    ``IndexError`` (turned into MarkerFormatError by the caller).
    """

    def __init__(self, data: bytes):
        if len(data) < 512 or data[1] != 0x50:
            raise ValueError("it has no C3D header (byte 2 must be 0x50)")
        section = (data[0] - 1) * 512
        if data[0] < 2 or section + 4 > len(data):
            raise ValueError(f"its parameter section (block {data[0]}) is past the end of the file")
        blocks, processor = data[section + 2], data[section + 3]
        if processor not in _PROCESSORS:
            raise ValueError(
                f"processor type {processor} is not Intel (84), DEC (85) or MIPS (86)"
            )
        self.data = data
        self.processor = _PROCESSORS[processor]
        self.endian = ">" if self.processor == "MIPS" else "<"
        self.params = self._parameters(section + 4, min(len(data), section + 512 * max(blocks, 1)))

    def _parameters(self, pos: int, end: int) -> dict:
        data, groups, found = self.data, {}, []
        while pos + 4 <= end:
            chars, group = struct.unpack_from("<bb", data, pos)
            if chars == 0 or group == 0:
                break
            name = data[pos + 2 : pos + 2 + abs(chars)].decode("latin-1").strip().upper()
            at = pos + 2 + abs(chars)
            (step,) = struct.unpack_from(self.endian + "h", data, at)
            if group < 0:
                groups[-group] = name
            else:
                kind, ndims = struct.unpack_from("<bb", data, at + 2)
                if kind not in (_CHAR, _BYTE, _INT, _FLOAT) or ndims < 0:
                    raise ValueError(f"parameter {name} has type {kind} and {ndims} dimensions")
                dims = tuple(data[at + 4 : at + 4 + ndims])
                if len(dims) != ndims:
                    raise ValueError(f"parameter {name} ends inside its dimensions")
                size = abs(kind) * math.prod(dims)
                value = data[at + 4 + ndims : at + 4 + ndims + size]
                if len(value) != size:
                    raise ValueError(f"parameter {name} ends inside its {size} bytes of values")
                found.append((group, name, kind, dims, value))
            if step <= 0:
                break
            pos = at + step
        return {(groups.get(g, f"#{g}"), name): (kind, dims, value) for g, name, kind, dims, value in found}

    def header_word(self, word: int) -> int:
        """16-bit unsigned header word (0-based word index)."""
        return struct.unpack_from(self.endian + "H", self.data, 2 * word)[0]

    def header_real(self, word: int) -> float:
        """Header float spanning words ``word`` and ``word + 1`` (0-based)."""
        return float(self._floats(self.data[2 * word : 2 * word + 4])[0])

    def _floats(self, raw: bytes) -> np.ndarray:
        if self.processor != "DEC":
            return np.frombuffer(raw, self.endian + "f4").astype(np.float64)
        return _dec_floats(raw).astype(np.float64)

    def numbers(self, group: str, name: str) -> np.ndarray | None:
        """A numeric parameter's values, flat (float64), or None when absent or not numeric."""
        entry = self.params.get((group, name))
        if entry is None or entry[0] == _CHAR:
            return None
        kind, _, value = entry
        if kind == _FLOAT:
            return self._floats(value)
        return np.frombuffer(value, {1: "u1", 2: self.endian + "u2"}[kind]).astype(np.float64)

    def integer(self, group: str, name: str, default: int) -> int:
        values = self.numbers(group, name)
        return default if values is None or len(values) == 0 else int(values[0])

    def real(self, group: str, name: str, default: float) -> float:
        values = self.numbers(group, name)
        return default if values is None or len(values) == 0 else float(values[0])

    def strings(self, group: str, name: str) -> list[str] | None:
        """A character parameter as its strings (the first dimension is the string length)."""
        entry = self.params.get((group, name))
        if entry is None or entry[0] != _CHAR:
            return None
        _, dims, value = entry
        length = dims[0] if dims else len(value)
        if length == 0:
            return []
        text = value.decode("latin-1")
        return [text[k : k + length].strip() for k in range(0, len(text), length)]

    def analog_words(self, point_rate: float) -> int:
        """Analog samples stored after the points of every frame."""
        used = self.integer("ANALOG", "USED", -1)
        rate = self.real("ANALOG", "RATE", -1.0)
        if used < 0 or rate < 0 or not point_rate > 0:
            return self.header_word(2)  # total analog samples per 3-D frame
        return used * int(round(rate / point_rate)) if used else 0

    def frame_count(self) -> int:
        """Frames of point data declared (see :func:`read_markers_c3d`)."""
        frames = self.numbers("POINT", "FRAMES")
        if frames is not None and len(frames) and frames[0] != 65535:  # 65535: 16-bit overflow
            return int(frames[0]) if math.isfinite(frames[0]) else -1
        long_frames = self.numbers("POINT", "LONG_FRAMES")
        if long_frames is not None and len(long_frames):
            return int(long_frames[0]) if math.isfinite(long_frames[0]) else -1
        start = self.numbers("TRIAL", "ACTUAL_START_FIELD")
        end = self.numbers("TRIAL", "ACTUAL_END_FIELD")
        if start is not None and end is not None and len(start) >= 2 and len(end) >= 2:
            return int(end[0] + end[1] * 65536 - start[0] - start[1] * 65536) + 1
        if frames is not None and len(frames):
            return 65535
        return self.header_word(4) - self.header_word(3) + 1


def _dec_floats(raw: bytes) -> np.ndarray:
    """DEC F-floats (VAX single precision) as float32.

    A DEC F-float is the IEEE single of 4x its value with its two 16-bit halves swapped (the
    exponent bias is 128, not 127, and the hidden bit stands for 0.5); exponent 0 is zero.
    """
    bits = np.frombuffer(raw, "<u4")
    ieee = (((bits & 0xFFFF) << 16) | (bits >> 16)).astype(np.uint32)
    with np.errstate(invalid="ignore"):
        values = ieee.view(np.float32) / np.float32(4)
    return np.where((ieee & 0x7F800000) == 0, np.float32(0), values)


def _c3d_units(units: list[str] | None) -> str:
    """The one length unit of ``POINT:UNITS`` (a string, or one string per point)."""
    units = sorted({unit.lower() for unit in units or ()} - {""})
    if len(units) > 1:
        raise MarkerFormatError(
            f"C3D POINT:UNITS gives the points different units {units}; expected one unit"
        )
    return units[0] if units else "mm"


def _c3d_points(
    data: bytes, start: int, frames: int, count: int, analog_words: int, scale: float,
    processor: str,
) -> np.ndarray:
    """(F,M,3) float64 point coordinates in the file's unit, NaN for invalid points.

    Each frame holds ``count`` points of 4 words (x, y, z, residual/camera word) then
    ``analog_words`` analog samples; a word is a float32 when ``scale < 0``, else an int16
    coordinate to multiply by ``scale``.
    """
    is_float = scale < 0
    word = 4 if is_float else 2
    frame_words = 4 * count + analog_words
    held = max(0, len(data) - start) // (frame_words * word)
    if held < frames:
        raise MarkerFormatError(f"C3D file declares {frames} frames but holds {held}")
    endian = ">" if processor == "MIPS" else "<"
    size = frames * frame_words * word
    if is_float and processor == "DEC":
        raw = _dec_floats(data[start : start + size])
    else:
        code = "f4" if is_float else "i2"
        raw = np.frombuffer(data, endian + code, frames * frame_words, start)
    block = raw.reshape(frames, frame_words)[:, : 4 * count].reshape(frames, count, 4)
    if is_float:
        with np.errstate(invalid="ignore"):  # signalling NaNs in damaged files
            xyz = block[..., :3].astype(np.float64)
            invalid = ~(block[..., 3] > -1)  # the residual word, an integer stored as a float
    else:  # scaled in float64, as ezc3d does: the exact product of the int16 and the float32
        xyz = block[..., :3].astype(np.float64) * abs(scale)
        invalid = block[..., 3] < 0
    invalid |= ~np.isfinite(xyz).all(axis=2)
    return np.where(invalid[..., None], np.nan, xyz)


def write_markers_c3d(target: Target, markers: MarkerSequence, *, fps: float | None = None) -> None:
    """Write a C3D file of float32 points in mm (occluded markers flagged invalid).

    Parameters
    ----------
    target : path or binary file
    markers : MarkerSequence
        Positions taken as mm; needs names.
    fps : float, optional
        Frame rate; defaults to ``markers.fps``. C3D requires one.

    Raises
    ------
    ValueError
        Without names, without a frame rate, or with no frames.
    """
    names = require_names(markers)
    fps = fps if fps is not None else markers.fps
    if fps is None:
        raise ValueError("C3D needs a frame rate: pass fps or set markers.fps")
    if len(markers.positions) == 0:
        raise ValueError("C3D needs at least one frame")
    writer = c3d.Writer(point_rate=float(fps), point_units="mm")
    writer.set_point_labels(list(names))
    no_analog = np.zeros((0, 0), np.float32)
    for frame in markers.positions:
        points = np.zeros((len(names), 5), np.float32)
        occluded = np.isnan(frame).any(axis=1)
        points[:, :3] = np.where(occluded[:, None], 0.0, frame)
        points[occluded, 3] = -1.0
        writer.add_frames([(points, no_analog)])
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "No analog data found in file."
        writer.write(buffer)
    write_target(target, buffer.getvalue())
