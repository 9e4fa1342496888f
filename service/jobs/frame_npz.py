"""NPZ results written frame chunk by frame chunk, so a long performance never has to fit
in memory at once.

Each per-frame output (``vertices`` (F,n,3), ``displacement`` (F,H,H), ...) goes into its own
``.npy`` file, memory-mapped and filled chunk by chunk; arrays that do not depend on the
frame (``faces``) are written once. :meth:`FrameNpzWriter.finish` then packs the files into
an uncompressed ``.npz`` that ``np.load`` reads like any other.

Examples
--------
>>> writer = FrameNpzWriter(tmp_dir, frames=len(markers))
>>> for s in range(0, len(markers), 16):
...     writer.write(s, model.synthesize(markers[s:s + 16]))
>>> writer.finish(tmp_dir / "result.npz")
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Collection, Mapping

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
    """

    def __init__(self, directory: Path, frames: int, static: Collection[str] = STATIC_KEYS):
        self.directory, self.frames, self.static = Path(directory), int(frames), frozenset(static)
        self._maps: dict[str, np.memmap] = {}
        self._written: dict[str, int] = {}

    def _path(self, key: str) -> Path:
        return self.directory / f"{key}.npy"

    def write(self, start: int, arrays: Mapping[str, np.ndarray]) -> None:
        """Store frames ``start … start + len`` of each per-frame array in ``arrays``."""
        for key, value in arrays.items():
            value = np.asarray(value)
            if key in self.static:
                if key not in self._written:
                    np.save(self._path(key), value)
                    self._written[key] = 0
                continue
            target = self._maps.get(key)
            if target is None:
                target = self._maps[key] = np.lib.format.open_memmap(
                    self._path(key), mode="w+", dtype=value.dtype,
                    shape=(self.frames, *value.shape[1:]))
                self._written[key] = 0
            target[start:start + len(value)] = value
            self._written[key] += len(value)

    def finish(self, target: Path | None = None) -> Path:
        """Pack every array into the ``.npz`` file ``target`` (default ``result.npz`` in the
        scratch directory) and return it.

        Raises ``ValueError`` if a per-frame array did not get all its frames.
        """
        for key, target_map in self._maps.items():
            if self._written[key] != self.frames:
                raise ValueError(f"'{key}' got {self._written[key]} of {self.frames} frames")
            target_map.flush()
        target = self.directory / "result.npz" if target is None else target
        keys = list(self._written)
        self._maps.clear()  # close the memory maps before reading the files
        with zipfile.ZipFile(target, "w", zipfile.ZIP_STORED, allowZip64=True) as archive:
            for key in keys:
                archive.write(self._path(key), arcname=f"{key}.npy")
        return Path(target)
