"""``client.clips``: an actor's captured clips (``/v1/actors/{actor_id}/clips``)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from .. import arrays as A
from .._core import Call
from ..types import Clip
from ._base import Resource, file_part

__all__ = ["Clips"]


def _obj_text(mesh: Any) -> bytes:
    """A mesh (trimesh-like or arrays) as minimal OBJ text (``v`` and ``f`` lines)."""
    arrays = A.mesh_arrays(mesh)
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in arrays["vertices"]]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in arrays.get("faces", [])]
    return ("\n".join(lines) + "\n").encode()


class Clips(Resource):
    """``/v1/actors/{actor_id}/clips``: captured training and database clips."""

    def upload(self, actor_id: str, vertices: Any, markers: Any, *, fps: float | None = None,
               albedo: Any = None, displacement: Any = None, name: str | None = None) -> Clip:
        """Add a clip from arrays (sent as NPZ).

        Parameters
        ----------
        vertices : (F,V,3) float or sequence of F meshes
            high-resolution frames in vertex correspondence with the neutral
        markers : (F,M,3) float   in layout order, NaN for an occluded marker
        fps : float, optional
        albedo : (F,H,W,3) float32, optional     linear RGB
        displacement : (F,H,H) float32, optional
        name : str, optional

        Returns
        -------
        Clip

        Examples
        --------
        >>> clip = client.clips.upload(actor.id, frames, frames[:, marker_vertices],
        ...                            fps=30.0, name="smile")              # doctest: +SKIP
        """
        body = A.npz_bytes(vertices=A.frames_array(vertices), markers=np.asarray(markers),
                           albedo=albedo, displacement=displacement,
                           fps=None if fps is None else np.float64(fps))
        return self._post(actor_id, name, content=body, headers={"Content-Type": A.NPZ})

    def upload_file(self, actor_id: str, path: str | os.PathLike, *,
                    name: str | None = None) -> Clip:
        """Add a clip from an ``.npz`` file (``vertices``, ``markers``[, ``albedo``,
        ``fps``])."""
        return self._post(actor_id, name, content=Path(path).read_bytes(),
                          headers={"Content-Type": A.NPZ})

    def upload_frames(self, actor_id: str, frames: Iterable[Any], markers: Any, *,
                      fps: float | None = None, name: str | None = None) -> Clip:
        """Add a clip from per-frame ``.obj`` files and a marker file, as multipart.

        Parameters
        ----------
        frames : iterable of paths, bytes or meshes   one OBJ per frame, in order
        markers : path, bytes or (filename, bytes, media type)
            a ``.c3d``, ``.trc``, ``.csv`` or ``.json`` marker file; the server reads it
            and matches named markers to the layout
        fps : float, optional   overrides the marker file's rate

        Examples
        --------
        >>> client.clips.upload_frames(actor.id, sorted(Path("take3").glob("*.obj")),
        ...                            "take3.c3d")                        # doctest: +SKIP
        """
        files = []
        for k, frame in enumerate(frames):
            if A.is_path(frame) or isinstance(frame, (bytes, bytearray, tuple)):
                part = file_part(frame, f"frame{k:05d}.obj", A.OBJ)
            else:
                part = (f"frame{k:05d}.obj", _obj_text(frame), A.OBJ)
            files.append(("frames", (part[0], part[1], A.OBJ)))
        files.append(("markers", file_part(markers, "markers.csv", "text/csv")))
        data = {"fps": str(float(fps))} if fps is not None else None
        return self._post(actor_id, name, files=files, data=data)

    def _post(self, actor_id: str, name: str | None, **body: Any) -> Clip:
        return self._run(self._core.call_json(Call(
            "POST", f"/v1/actors/{actor_id}/clips", params={"name": name}, **body),
            Clip.from_json))

    def list(self, actor_id: str) -> list[Clip]:
        """The actor's clips, oldest first."""
        return self._run(self._core.call_items(
            Call("GET", f"/v1/actors/{actor_id}/clips"), Clip.from_json))

    def get(self, actor_id: str, clip_id: str) -> Clip:
        """One clip of the actor."""
        return self._run(self._core.call_json(
            Call("GET", f"/v1/actors/{actor_id}/clips/{clip_id}"), Clip.from_json))

    def delete(self, actor_id: str, clip_id: str) -> None:
        """Delete a clip (models trained on it keep what they learnt)."""
        return self._run(self._core.call_empty(
            Call("DELETE", f"/v1/actors/{actor_id}/clips/{clip_id}")))
