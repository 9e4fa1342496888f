"""Per-frame OBJ meshes and EXR maps in one zip, written frame chunk by frame chunk.

The ``obj-exr-zip`` result format of API.md's synthesis jobs, for pipelines that load one
file per frame: for frame ``i`` (zero-padded to the digits of the frame count)

    frame_0000.obj               ``vertices`` (medium scale), with the model's UV layout
    frame_0000_detailed.obj      ``vertices_detailed`` (fine scale baked in)
    frame_0000_displacement.exr  channel ``Y``, the actor's unit
    frame_0000_albedo.exr        ``R``, ``G``, ``B``, linear
    frame_0000_normal_map.exr    ``R``, ``G``, ``B``, tangent space

(as asked in the job's outputs), plus ``clamped.csv`` (frame, fraction of texels at the
extrapolation limit) and ``confidence.json`` (``{"frame": [...], "confidence": [...]}``, the
per-frame confidence of :mod:`service.methods.confidence`) when the model reports them. Members are stored uncompressed (EXR is
compressed already) and appended as the frames come, so memory stays bounded.
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Mapping

import numpy as np

from service.io.exr import write_map
from service.io.mesh import Mesh, write_obj
from service.methods.confidence import CONFIDENCE

#: the zip member of the per-frame confidence
CONFIDENCE_MEMBER = "confidence.json"

#: output array → member suffix and writer kind
MEMBERS = {
    "vertices": ("", "obj"),
    "vertices_detailed": ("_detailed", "obj"),
    "displacement": ("_displacement", "exr"),
    "albedo": ("_albedo", "exr"),
    "normal_map": ("_normal_map", "exr"),
}


class FrameZipWriter:
    """Writes synthesized frames into the zip ``target`` as they come.

    Parameters
    ----------
    target : Path                 the zip to create
    frames : int                  F, the total frame count (fixes the name padding)
    uv, uv_faces : arrays or None the model's UV layout, written into every OBJ
    """

    def __init__(self, target: Path, frames: int, uv: np.ndarray | None = None,
                 uv_faces: np.ndarray | None = None):
        self.target, self.frames = Path(target), int(frames)
        self.uv, self.uv_faces = uv, uv_faces
        self._digits = max(4, len(str(self.frames - 1)))
        self._zip = zipfile.ZipFile(self.target, "w", zipfile.ZIP_STORED, allowZip64=True)
        self._clamped: list[str] = []
        self._confidence: list[tuple[int, float]] = []
        self._written = 0

    def write(self, start: int, arrays: Mapping[str, np.ndarray]) -> None:
        """Frames ``start … start + len`` of the synthesize output ``arrays``."""
        faces = arrays.get("faces")
        count = next(len(arrays[k]) for k in arrays if k in MEMBERS or k == "clamped")
        for k in range(count):
            for key, (suffix, kind) in MEMBERS.items():
                if key not in arrays:
                    continue
                buffer = io.BytesIO()
                if kind == "obj":
                    write_obj(buffer, Mesh(np.asarray(arrays[key][k], np.float64), faces,
                                           self.uv, self.uv_faces), dtype=np.float32)
                else:
                    write_map(buffer, arrays[key][k])
                self._zip.writestr(self.member(start + k, key), buffer.getvalue())
            if "clamped" in arrays:
                self._clamped.append(f"{start + k},{float(arrays['clamped'][k]):.6g}")
            if CONFIDENCE in arrays:
                self._confidence.append((start + k, float(arrays[CONFIDENCE][k])))
        self._written += count

    def member(self, frame: int, key: str) -> str:
        """The member name of output array ``key`` (a key of :data:`MEMBERS`) of ``frame``:
        ``frame_0007_displacement.exr``."""
        suffix, kind = MEMBERS[key]
        return f"frame_{frame:0{self._digits}d}{suffix}.{kind}"

    def add_file(self, path: Path, arcname: str) -> None:
        """Copy the file ``path`` into the zip as ``arcname`` (streamed, not read whole)."""
        self._zip.write(path, arcname=arcname)

    def finish(self) -> Path:
        """Close the zip and return its path (``ValueError`` if frames are missing)."""
        if self._written != self.frames:
            self._zip.close()
            raise ValueError(f"got {self._written} of {self.frames} frames")
        if self._clamped:
            self._zip.writestr("clamped.csv", "frame,clamped\n" + "\n".join(self._clamped) + "\n")
        if self._confidence:
            frames, values = zip(*sorted(self._confidence))
            self._zip.writestr(CONFIDENCE_MEMBER, json.dumps({"frame": list(frames),
                                                              "confidence": list(values)}))
        self._zip.close()
        return self.target
