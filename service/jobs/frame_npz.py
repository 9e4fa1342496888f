"""NPZ results written frame chunk by frame chunk, so a long performance never has to fit
in memory at once.

Each per-frame output (``vertices`` (F,n,3), ``displacement`` (F,H,H), ...) goes into its own
``.npy`` file, filled chunk by chunk with ordinary writes; arrays that do not depend on the
frame (``faces``) are written once. :meth:`FrameNpzWriter.finish` then packs the files into
an uncompressed ``.npz`` that ``np.load`` reads like any other.

A full disk is an ``OSError`` (``ENOSPC``/``EDQUOT``), never a signal: the files are written
with ``write(2)``, not through memory maps (a store into a memory-mapped page the
filesystem cannot back kills the process with SIGBUS), and each ``.npy`` file's whole size
is reserved with ``posix_fallocate`` when it is created, so a disk too small for the result
fails at the first chunk rather than the last. On any error the writer removes every file
it made (the ``.npy`` files and a partial ``.npz``) before the error propagates.

Examples
--------
>>> writer = FrameNpzWriter(tmp_dir, frames=len(markers))
>>> for s in range(0, len(markers), 16):
...     writer.write(s, model.synthesize(markers[s:s + 16]))
>>> writer.finish(tmp_dir / "result.npz")
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path
from typing import BinaryIO, Collection, Mapping

import numpy as np

#: outputs that are the same for every frame, stored once
STATIC_KEYS = frozenset({"faces"})


class FrameNpzWriter:
    """Collects per-frame arrays (F,…) in chunks into ``.npy`` files under ``directory``.

    Parameters
    ----------
    directory : Path      scratch directory (exists; the caller removes it)
    frames : int          F, the number of frames of every per-frame array
    static : set of str   keys written once (their first value is kept)

    Raises
    ------
    OSError   from :meth:`write` and :meth:`finish` when the disk is full, read-only, ...;
              the writer's files are removed first
    """

    def __init__(self, directory: Path, frames: int, static: Collection[str] = STATIC_KEYS):
        self.directory, self.frames, self.static = Path(directory), int(frames), frozenset(static)
        self._files: dict[str, BinaryIO] = {}
        self._offsets: dict[str, tuple[int, int]] = {}   # key → (header bytes, bytes/frame)
        self._shapes: dict[str, tuple[int, ...]] = {}
        self._dtypes: dict[str, np.dtype] = {}
        self._written: dict[str, int] = {}
        self._made: list[Path] = []

    def _path(self, key: str) -> Path:
        return self.directory / f"{key}.npy"

    def write(self, start: int, arrays: Mapping[str, np.ndarray]) -> None:
        """Store frames ``start … start + len`` of each per-frame array in ``arrays``."""
        try:
            self._write(start, arrays)
        except BaseException:
            self.discard()
            raise

    def _write(self, start: int, arrays: Mapping[str, np.ndarray]) -> None:
        for key, value in arrays.items():
            value = np.asarray(value)
            if key in self.static:
                if key not in self._written:
                    self._made.append(self._path(key))
                    with open(self._path(key), "wb") as f:
                        np.save(f, value)
                    self._written[key] = 0
                continue
            out = self._files.get(key)
            if out is None:
                out = self._create(key, value)
            header, frame_bytes = self._offsets[key]
            if value.shape[1:] != self._shapes[key] or value.dtype != self._dtypes[key]:
                raise ValueError(f"'{key}' chunk is {value.dtype}{value.shape[1:]} per frame, "
                                 f"the first was {self._dtypes[key]}{self._shapes[key]}")
            out.seek(header + start * frame_bytes)
            out.write(np.ascontiguousarray(value).tobytes())
            self._written[key] += len(value)

    def _create(self, key: str, value: np.ndarray) -> BinaryIO:
        """Create ``<key>.npy`` with its header and its whole size reserved."""
        path = self._path(key)
        self._made.append(path)
        out = self._files[key] = open(path, "wb")
        shape = (self.frames, *value.shape[1:])
        np.lib.format.write_array_header_2_0(
            out, {"descr": np.lib.format.dtype_to_descr(value.dtype), "fortran_order": False,
                  "shape": shape})
        header = out.tell()
        frame_bytes = int(np.prod(value.shape[1:], dtype=np.int64)) * value.dtype.itemsize
        self._offsets[key] = (header, frame_bytes)
        self._shapes[key], self._dtypes[key] = value.shape[1:], value.dtype
        out.flush()
        os.posix_fallocate(out.fileno(), 0, header + self.frames * frame_bytes)
        self._written[key] = 0
        return out

    def discard(self) -> None:
        """Close and remove every file this writer made (after an error)."""
        self._close()
        for path in self._made:
            path.unlink(missing_ok=True)
        self._made.clear()

    def _close(self) -> None:
        files, self._files = list(self._files.values()), {}
        for f in files:
            try:
                f.close()
            except OSError:  # the data of a file being discarded: nothing to keep
                pass

    def finish(self, target: Path | None = None) -> Path:
        """Pack every array into the ``.npz`` file ``target`` (default ``result.npz`` in the
        scratch directory) and return it.

        Raises ``ValueError`` if a per-frame array did not get all its frames, ``OSError``
        if the disk is full (every file of the writer, the ``.npz`` too, is then removed).
        """
        for key in self._files:
            if self._written[key] != self.frames:
                raise ValueError(f"'{key}' got {self._written[key]} of {self.frames} frames")
        target = self.directory / "result.npz" if target is None else Path(target)
        keys = list(self._written)
        try:
            files = list(self._files.values())
            self._files = {}
            for f in files:
                f.close()                                 # a write error can surface here
            self._made.append(target)
            with zipfile.ZipFile(target, "w", zipfile.ZIP_STORED, allowZip64=True) as archive:
                for key in keys:
                    archive.write(self._path(key), arcname=f"{key}.npy")
        except BaseException:
            self.discard()
            raise
        self._made.remove(target)
        return target
