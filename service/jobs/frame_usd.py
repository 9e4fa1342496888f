"""The ``usd`` result format of API.md's synthesis jobs: a performance as one USD point
cache (:func:`service.io.usd.write_usd_cache`), written frame chunk by frame chunk.

The artifact is

- **one ``.usd`` file** (binary crate) when the job asks for one mesh output (``mesh`` or
  ``mesh_detailed``) and no maps: ``/Face/Mesh`` with the model's triangles and UVs (the
  ``st`` primvar) authored once and float32 ``points`` time-sampled at time codes 0 … F-1,
  ``timeCodesPerSecond`` the performance's frame rate, ``metersPerUnit`` the actor's unit;
- **a zip** when maps are asked (or both meshes): ``performance.usd`` (points of
  ``vertices``) and/or ``performance_detailed.usd`` (``vertices_detailed``) at the top, beside
  the per-frame EXR maps named as in the ``obj-exr-zip`` format
  (``frame_0000_displacement.exr``, ... :class:`~service.jobs.frame_zip.FrameZipWriter`), and
  ``clamped.csv``. Each cache binds a UsdPreviewSurface whose ``displacement``,
  ``diffuseColor`` (albedo) and ``normal`` (tangent-space normal map) inputs read those maps
  through ``UsdUVTexture`` shaders, their ``inputs:file`` time-sampled per frame and relative
  to the cache (``./frame_0000_displacement.exr``), so the unpacked folder opens as is.

A bare ``.usd`` does not carry the per-frame clamped fractions (the zip's ``clamped.csv``
does; the ``npz`` format has them as ``clamped``).

Memory: the points of each chunk go to a float32 ``.npy`` memory map on disk (as
:class:`~service.jobs.frame_npz.FrameNpzWriter` does) and the maps straight into the zip, so
synthesis holds one chunk at a time. :meth:`FrameUsdWriter.finish` then builds the stage from
the memory map: the stage (``usd-core`` builds a layer in memory before it exports it) is the
one in-memory copy of the points; the map's pages are file-backed and reclaimable. With two
caches the stages are built one after the other. Measured (``benchmarks/usd_cache.py``,
11 248 vertices, resident memory added by the time the built stage is exported):

    frames  points MiB  heap added MiB  file-backed added MiB  finish s
    600     77          81              83                     6.6
    1800    232         148             232                    11.7

(heap at most one copy of the points; the writer also makes a transient (F,V,3) bool
``isfinite`` mask, a quarter of the points' size.)
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from service.io.triangle_mesh import Mesh
from service.io.usd import write_usd_cache
from service.methods.confidence import CONFIDENCE
from service.jobs.frame_zip import FrameZipWriter

#: output array → the cache's file name
CACHES = {"vertices": "performance.usd", "vertices_detailed": "performance_detailed.usd"}
#: map output array → the UsdPreviewSurface input that reads it
TEXTURES = {"displacement": "displacement", "albedo": "diffuseColor", "normal_map": "normal"}
#: the frame rate of a performance that states none (as for clip uploads)
DEFAULT_FPS = 30.0


class FrameUsdWriter:
    """Collects synthesized frames in chunks and writes the ``usd`` artifact.

    Parameters
    ----------
    directory : Path              scratch directory (exists; the caller removes it)
    frames : int                  F, the total frame count
    uv, uv_faces : arrays or None the model's UV layout ((K,2), (T,3) or None)
    fps : float                   frames per second of the performance
    unit : {"mm", "cm", "m"}      the actor's length unit
    as_zip : bool                 a zip of cache(s) and maps (see the module) rather than
                                  one ``.usd`` file
    """

    def __init__(self, directory: Path, frames: int, uv: np.ndarray | None = None,
                 uv_faces: np.ndarray | None = None, *, fps: float = DEFAULT_FPS,
                 unit: str = "mm", as_zip: bool = False):
        self.directory, self.frames = Path(directory), int(frames)
        self.uv, self.uv_faces, self.fps, self.unit = uv, uv_faces, float(fps), unit
        self._maps = (FrameZipWriter(self.directory / "result.zip", self.frames)
                      if as_zip else None)
        self._points: dict[str, np.memmap] = {}
        self._textures: dict[str, list[str]] = {}
        self._faces: np.ndarray | None = None
        self._written = 0

    def write(self, start: int, arrays: Mapping[str, np.ndarray]) -> None:
        """Frames ``start … start + len`` of the synthesize output ``arrays``."""
        if self._faces is None and "faces" in arrays:
            self._faces = np.asarray(arrays["faces"])
        count = next(len(arrays[k]) for k in arrays if k in CACHES or k in TEXTURES
                     or k == "clamped")
        for key in CACHES:
            if key not in arrays:
                continue
            target = self._points.get(key)
            if target is None:
                shape = (self.frames, *np.shape(arrays[key])[1:])
                target = self._points[key] = np.lib.format.open_memmap(
                    self.directory / f"{key}.npy", mode="w+", dtype=np.float32, shape=shape)
            target[start:start + count] = arrays[key]
        maps = {k: arrays[k] for k in (*TEXTURES, "clamped", CONFIDENCE) if k in arrays}
        if self._maps is not None and maps:
            self._maps.write(start, maps)
            for key in TEXTURES:
                if key in arrays:
                    self._textures.setdefault(key, []).extend(
                        self._maps.member(start + k, key) for k in range(count))
        self._written += count

    def finish(self) -> Path:
        """Write the cache(s) and return the artifact's path (the ``.usd``, or the zip).

        Raises ``ValueError`` if frames are missing or no mesh output was written.
        """
        if self._written != self.frames:
            raise ValueError(f"got {self._written} of {self.frames} frames")
        if not self._points or self._faces is None:
            raise ValueError("a USD cache needs a mesh output (vertices and faces)")
        textures = {TEXTURES[key]: names for key, names in self._textures.items()}
        paths = []
        for key, points in self._points.items():
            points.flush()
            mesh = Mesh(points[0], self._faces, self.uv, self.uv_faces)
            path = self.directory / CACHES[key]
            write_usd_cache(path, mesh, points, fps=self.fps, unit=self.unit,
                            textures=textures or None)
            paths.append(path)
        self._points.clear()                 # close the memory maps
        if self._maps is None:
            (path,) = paths
            return path
        for path in paths:
            self._maps.add_file(path, path.name)
        return self._maps.finish()
