"""UV-space maps as OpenEXR files (float32 by default, half on request).

Channel names follow API.md: ``Y`` for a scalar map, ``R``, ``G``, ``B`` for colour and vectors,
``<component>.a<k>`` for model coefficient maps (``x.a0`` ... ``z.a5``). Row 0 of every array is
the top scanline of the image (v near 1), as in OpenEXR: nothing is flipped.

Readers take a path, bytes or a binary file object, read the header first and bound the image
size before any pixel data is decoded; malformed files raise
:class:`~service.io.errors.MapFormatError`, oversized ones
:class:`~service.io.errors.SizeLimitError`.
"""

from __future__ import annotations

import ctypes
import io
import os
import sys
import tempfile
import threading
from contextlib import contextmanager
from typing import Mapping

import numpy as np
import OpenEXR

from service.io.errors import MapFormatError, SizeLimitError
from service.io.sources import Source, Target, is_path, read_source

MAX_TEXELS = 8192 * 8192
"""Default bound on H*W of a map a reader accepts."""
MAX_CHANNELS = 64
"""Default bound on the channel count a reader accepts."""

COMPRESSIONS = {
    "none": OpenEXR.NO_COMPRESSION,
    "rle": OpenEXR.RLE_COMPRESSION,
    "zips": OpenEXR.ZIPS_COMPRESSION,
    "zip": OpenEXR.ZIP_COMPRESSION,
    "piz": OpenEXR.PIZ_COMPRESSION,
    "pxr24": OpenEXR.PXR24_COMPRESSION,
    "b44": OpenEXR.B44_COMPRESSION,
    "b44a": OpenEXR.B44A_COMPRESSION,
    "dwaa": OpenEXR.DWAA_COMPRESSION,
    "dwab": OpenEXR.DWAB_COMPRESSION,
}
"""Compression names accepted by :func:`write_exr`. Lossless: none, rle, zips, zip, piz;
pxr24 rounds float32 to 24 bits; b44/b44a (half only) and dwaa/dwab are lossy."""


def write_exr(
    target: Target,
    channels: Mapping[str, np.ndarray],
    *,
    half: bool = False,
    compression: str = "zip",
) -> None:
    """Write named (H,W) channels as a single-part scanline EXR.

    Parameters
    ----------
    target : path or binary file (needs write, seek and tell)
    channels : dict of str -> (H,W) float array
        All the same shape; row 0 is the top of the image. Stored in the file sorted by name
        (the EXR rule).
    half : bool
        Store 16-bit half floats instead of 32-bit floats (values rounded to nearest; beyond
        +-65504 they become +-inf).
    compression : str
        One of :data:`COMPRESSIONS`; the default ``zip`` is lossless.

    Raises
    ------
    ValueError
        For no channels, an empty name, non-2-D or mismatched shapes, or an unknown compression.
    """
    if compression not in COMPRESSIONS:
        raise ValueError(f"compression '{compression}' is not one of {sorted(COMPRESSIONS)}")
    if not channels:
        raise ValueError("an EXR needs at least one channel")
    dtype = np.float16 if half else np.float32
    pixels, shape = {}, None
    for name, values in channels.items():
        values = np.asarray(values)
        if not isinstance(name, str) or not name:
            raise ValueError(f"channel names must be non-empty strings, got {name!r}")
        if values.ndim != 2 or 0 in values.shape:
            raise ValueError(
                f"channel '{name}' must be a non-empty (H,W) array, got {values.shape}"
            )
        if shape is not None and values.shape != shape:
            raise ValueError(f"channel '{name}' has shape {values.shape}, the others {shape}")
        shape = values.shape
        with np.errstate(over="ignore"):  # beyond the half range is +-inf, as in OpenEXR
            pixels[name] = np.ascontiguousarray(values, dtype=dtype)
    header = {"compression": COMPRESSIONS[compression], "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, pixels).write(os.fspath(target) if is_path(target) else target)


def read_exr(
    source: Source,
    *,
    max_texels: int = MAX_TEXELS,
    max_channels: int = MAX_CHANNELS,
) -> dict[str, np.ndarray]:
    """Read every channel of an EXR's first part as float32.

    Parameters
    ----------
    source : path, bytes or binary file
    max_texels : int
        Bound on H*W, checked from the header before pixel data is read.
    max_channels : int
        Bound on the channel count, checked from the header.

    Returns
    -------
    dict of str -> (H,W) float32
        In the file's channel order (sorted by name); row 0 is the top scanline. Half channels
        are widened exactly.

    Raises
    ------
    MapFormatError
        If the file is not a readable EXR or is damaged (the library's own report quoted), is
        a deep image ("deep EXR is not supported"), has unsigned-int or subsampled channels,
        or its data window differs from its display window.
    SizeLimitError
    """
    data = read_source(source)
    header, _ = _read(data, header_only=True)
    if header.get("type") in (OpenEXR.deepscanline, OpenEXR.deeptile):
        raise MapFormatError(
            "deep EXR is not supported: the file stores a varying number of samples per pixel; "
            "a UV-space map needs one value per texel (a flat scanline or tiled EXR)"
        )
    try:
        (x0, y0), (x1, y1) = (tuple(map(int, corner)) for corner in header["dataWindow"])
        display = tuple(tuple(map(int, corner)) for corner in header["displayWindow"])
        channel_count = len(header["channels"])
    except (KeyError, TypeError, ValueError) as error:
        raise MapFormatError(f"not a readable EXR file: its header lacks {error}") from None
    if display != ((x0, y0), (x1, y1)):
        raise MapFormatError(
            f"EXR data window {((x0, y0), (x1, y1))} differs from its display window {display}; "
            "a UV-space map must cover the whole image"
        )
    height, width = y1 - y0 + 1, x1 - x0 + 1
    if height * width > max_texels:
        raise SizeLimitError("texels", height * width, max_texels)
    if channel_count > max_channels:
        raise SizeLimitError("channels", channel_count, max_channels)
    out = {}
    for name, channel in _read(data, header_only=False)[1].items():
        if channel.xSampling != 1 or channel.ySampling != 1:
            raise MapFormatError(f"EXR channel '{name}' is subsampled; maps need full resolution")
        if channel.pixels.dtype.kind != "f":
            raise MapFormatError(
                f"EXR channel '{name}' holds {channel.pixels.dtype} values, expected float or half"
            )
        out[name] = np.asarray(channel.pixels, dtype=np.float32)
    return out


#: what the OpenEXR binding raises on malformed bytes (UnicodeDecodeError is a ValueError)
_EXR_ERRORS = (RuntimeError, ValueError, TypeError, KeyError, IndexError, OverflowError, SystemError)
#: how the library's own lines start or what they hold (the core library writes
#: "<python_buffer>: (EXR_ERR_...) ..." to stderr, the binding "Warning: Exception raised
#: reading pixel data ..." to stdout, and then returns what it could read)
_LIBRARY_MARKS = ("<python_buffer>", "EXR_ERR", "Warning: Exception raised")
_CAPTURE_LOCK = threading.Lock()


def _flush_all() -> None:
    """Flush Python's and the C library's buffered output (``fflush(NULL)``)."""
    for stream in (sys.stdout, sys.stderr):
        if stream is not None:
            stream.flush()
    if _LIBC is not None:
        _LIBC.fflush(None)


try:
    _LIBC = ctypes.CDLL(None)
except OSError:  # no C library to flush (not on Linux/macOS): Python's streams only
    _LIBC = None


def _read(data: bytes, header_only: bool) -> tuple[dict, dict]:
    """The header and (unless `header_only`) the channels of an EXR's first part.

    The OpenEXR library reports damage by printing to standard output and standard error
    and returning what it could read; its lines are captured here, never printed, and a
    read that printed one raises MapFormatError quoting it.
    """
    failure = None
    with _captured_output() as printed:
        try:
            exr = OpenEXR.File(io.BytesIO(data), separate_channels=True, header_only=header_only)
            header = dict(exr.header())
            channels = {} if header_only else dict(exr.channels())
            for channel in channels.values():
                channel.pixels  # the binding decodes pixels on first access: inside the capture
        except _EXR_ERRORS as error:
            failure = error
    if failure is not None:
        detail = f" ({printed[0]})" if printed else ""
        raise MapFormatError(f"not a readable EXR file: {failure}{detail}")
    if printed:
        raise MapFormatError(f"the EXR file is damaged: {printed[0]}")
    return header, channels


@contextmanager
def _captured_output():
    """Collect the OpenEXR library's lines printed meanwhile, to file descriptors 1 and 2 (the
    core library, C++ streams) or to ``sys.stdout``/``sys.stderr`` (the Python binding).

    One capture at a time (a lock). Lines that are not the library's (another thread's
    output) are written back where they were going when the block ends. Without usable
    descriptors only the Python streams are captured.
    """
    library: list[str] = []

    def sort(text: str, put) -> None:
        for line in text.splitlines(keepends=True):
            if any(mark in line for mark in _LIBRARY_MARKS):
                library.append(line.strip())
            else:
                put(line)

    with _CAPTURE_LOCK:
        _flush_all()
        try:
            saved = {fd: os.dup(fd) for fd in (1, 2)}
        except OSError:
            saved = {}
        sinks = {fd: tempfile.TemporaryFile() for fd in saved}
        python = {"stdout": sys.stdout, "stderr": sys.stderr}
        texts = {name: io.StringIO() for name in python}
        try:
            for fd, sink in sinks.items():
                os.dup2(sink.fileno(), fd)
            sys.stdout, sys.stderr = texts["stdout"], texts["stderr"]
            yield library
        finally:
            sys.stdout, sys.stderr = python["stdout"], python["stderr"]
            _flush_all()  # C streams buffer what the core library prints: out before restoring
            for fd, sink in sinks.items():
                os.dup2(saved[fd], fd)
                os.close(saved[fd])
                sink.seek(0)
                sort(sink.read().decode("utf-8", "replace"),
                     lambda line, fd=fd: os.write(fd, line.encode("utf-8")))
                sink.close()
            for name, stream in python.items():
                if stream is not None:
                    sort(texts[name].getvalue(), stream.write)


def write_map(
    target: Target, values: np.ndarray, *, half: bool = False, compression: str = "zip"
) -> None:
    """Write one map: (H,W) as channel ``Y``, (H,W,3) as channels ``R``, ``G``, ``B``.

    Parameters
    ----------
    target : path or binary file
    values : (H,W) or (H,W,3) float array, row 0 the top of the image
    half, compression
        As for :func:`write_exr`.
    """
    values = np.asarray(values)
    if values.ndim == 2:
        channels = {"Y": values}
    elif values.ndim == 3 and values.shape[2] == 3:
        channels = {name: values[:, :, k] for k, name in enumerate("RGB")}
    else:
        raise ValueError(f"a map must have shape (H,W) or (H,W,3), got {values.shape}")
    write_exr(target, channels, half=half, compression=compression)


def read_map(source: Source, *, max_texels: int = MAX_TEXELS) -> np.ndarray:
    """Read one map written by :func:`write_map` (or any EXR with channels Y or R,G,B).

    Parameters
    ----------
    source : path, bytes or binary file
    max_texels : int
        Bound on H*W.

    Returns
    -------
    (H,W) float32 for a ``Y`` file, (H,W,3) float32 for an ``R,G,B`` file.

    Raises
    ------
    MapFormatError
        If the channels are neither exactly ``Y`` nor exactly ``R, G, B``.
    SizeLimitError
    """
    channels = read_exr(source, max_texels=max_texels)
    if set(channels) == {"Y"}:
        return channels["Y"]
    if set(channels) == {"R", "G", "B"}:
        return np.stack([channels[name] for name in "RGB"], axis=2)
    raise MapFormatError(
        f"expected channel Y or channels R, G, B in a map, found {sorted(channels)}"
    )
