"""C3D files for the reader's tests, written by ezc3d (the format's reference implementation).

:func:`ezc3d_file` writes points with ezc3d; :func:`ezc3d_points` reads any C3D back with ezc3d
as the reference the reader is compared against. :func:`to_dec_integer` rewrites a float C3D
from ezc3d as the DEC-processor, 16-bit integer C3D that older Vicon systems wrote (ezc3d reads
those, but writes Intel floats only); it walks the parameter section as the C3D manual lays it
out (c3d.org, "The parameter section").
"""

from __future__ import annotations

import struct
from pathlib import Path

import ezc3d
import numpy as np
from ezc3d import ezc3d as swig


def ezc3d_file(path: Path, points: np.ndarray, labels, *, rate: float = 100.0, units=None,
               int_params=(), first_frame_as_zero: bool = False, analogs=None) -> Path:
    """Write (F,M,3) points (NaN rows: invalid, residual -1) as a float C3D with ezc3d.

    ``units`` is a string or one string per point (``POINT:UNITS``); ``int_params`` holds
    ``(group, name, values, dims)`` integer parameters such as a 2-D
    ``TRIAL:ACTUAL_END_FIELD``; ``analogs`` is an optional (channels, samples) array.
    """
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(labels)
    frames, count = points.shape[:2]
    block = np.ones((4, count, frames))
    block[:3] = np.transpose(np.nan_to_num(points), (2, 1, 0))
    c["data"]["points"] = block
    residuals = np.where(np.isnan(points).any(axis=2).T[None], -1.0, 0.0)
    c["data"]["meta_points"]["residuals"] = residuals
    if units is not None:
        c.add_parameter("POINT", "UNITS", [units] if isinstance(units, str) else list(units))
    for group, name, values, dims in int_params:
        param = swig.Parameter(name, "")
        param.set(swig.VecInt(list(values)), swig.VecUInt(list(dims)))
        c["parameters"].add_parameter(group, param)
    if analogs is not None:
        c["parameters"]["ANALOG"]["RATE"]["value"] = [rate * 10]
        c["parameters"]["ANALOG"]["LABELS"]["value"] = [f"A{k}" for k in range(len(analogs))]
        c["data"]["analogs"] = np.asarray(analogs, float)[None]
    c.write(str(path), first_frame_as_zero=first_frame_as_zero)
    return path


def ezc3d_points(path: Path) -> np.ndarray:
    """(F,M,3) float64 points as ezc3d reads them (NaN for invalid points), in the file's unit."""
    return np.transpose(ezc3d.c3d(str(path))["data"]["points"][:3], (2, 1, 0))


def _ieee_to_dec(values: np.ndarray) -> bytes:
    """float32 values as DEC F-floats: the IEEE bits of 4x the value, 16-bit halves swapped."""
    bits = (np.asarray(values, np.float32) * np.float32(4)).view(np.uint32)
    return (((bits & 0xFFFF) << 16) | (bits >> 16)).astype("<u4").tobytes()


def _dec_to_ieee(raw: bytes) -> np.ndarray:
    bits = np.frombuffer(raw, "<u4")
    return (((bits & 0xFFFF) << 16) | (bits >> 16)).astype(np.uint32).view(np.float32) / 4


def _parameters(data: bytes):
    """Yield (group name, parameter name, type, dims, offset of its values) of every parameter."""
    pos = (data[0] - 1) * 512 + 4
    groups, found = {}, []
    while pos + 4 <= len(data):
        chars, group = struct.unpack_from("<bb", data, pos)
        if chars == 0 or group == 0:
            break
        name = data[pos + 2 : pos + 2 + abs(chars)].decode()
        at = pos + 2 + abs(chars)
        (step,) = struct.unpack_from("<h", data, at)
        if group < 0:
            groups[-group] = name
        else:
            kind, ndims = struct.unpack_from("<bb", data, at + 2)
            dims = tuple(data[at + 4 : at + 4 + ndims])
            found.append((group, name, kind, dims, at + 4 + ndims))
        if step == 0:
            break
        pos = at + step
    return [(groups.get(g, "?"), name, kind, dims, offset) for g, name, kind, dims, offset in found]


def to_dec_integer(float_c3d: bytes, scale: float) -> bytes:
    """A float Intel C3D of points only, rewritten as a DEC C3D of int16 words times ``scale``.

    Coordinates become ``round(x / scale)``; the residual word keeps its sign (-1 invalid);
    the header's scale and frame rate, every float parameter and ``POINT:SCALE`` (now
    positive: integer data) are stored as DEC floats, and the processor byte says DEC (85).
    """
    data = bytearray(float_c3d)
    params = _parameters(bytes(data))
    used = next(o for g, n, k, d, o in params if (g, n) == ("POINT", "USED"))
    count = struct.unpack_from("<H", data, used)[0]
    start = (struct.unpack_from("<H", data, 16)[0] - 1) * 512
    words = np.frombuffer(bytes(data[start:]), "<f4")
    frames = len(words) // (4 * count)
    block = words[: frames * 4 * count].reshape(frames, count, 4)
    integer = np.empty(block.shape, "<i2")
    integer[..., :3] = np.round(block[..., :3] / scale)
    integer[..., 3] = np.where(block[..., 3] < 0, -1, 0)
    for group, name, kind, dims, offset in params:
        if kind == 4:
            n = int(np.prod(dims)) if dims else 1
            values = np.frombuffer(bytes(data[offset : offset + 4 * n]), "<f4")
            if (group, name) == ("POINT", "SCALE"):
                values = np.full(n, scale, np.float32)
            data[offset : offset + 4 * n] = _ieee_to_dec(values)
    rate = struct.unpack_from("<f", data, 20)[0]
    data[12:16] = _ieee_to_dec([scale])
    data[20:24] = _ieee_to_dec([rate])
    data[(data[0] - 1) * 512 + 3] = 85
    body = integer.tobytes()
    return bytes(data[:start]) + body + bytes(-len(body) % 512)


def set_parameter(data: bytes, group: str, name: str, values) -> bytes:
    """``data`` with the values of an existing INT or FLOAT parameter overwritten (same count)."""
    data = bytearray(data)
    for g, n, kind, dims, offset in _parameters(bytes(data)):
        if (g, n) == (group, name):
            code = {2: "<u2", 4: "<f4"}[kind]
            raw = np.asarray(values, code).tobytes()
            data[offset : offset + len(raw)] = raw
            return bytes(data)
    raise KeyError(f"{group}:{name}")
