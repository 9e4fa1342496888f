"""``client.tracking``: performance-flow tracking jobs (``/v1/actors/{actor_id}/tracking-jobs``)."""

from __future__ import annotations

import json as jsonlib
from pathlib import Path
from typing import Any, Mapping, Sequence

from .. import arrays as A
from .._core import Call
from ..types import JobAccepted
from ._base import Resource, file_part

__all__ = ["Tracking", "TRACKING_ARTIFACTS"]

#: the NPZ artifacts of a tracking job (its result's ``artifacts``: file name → id)
TRACKING_ARTIFACTS = ("tracked.npz", "weights.npz", "maps.npz", "scans.npz")
#: media types of the upload's files by suffix
_TYPES = {".json": "application/json", ".obj": "model/obj", ".ply": "application/x-ply",
          ".zip": "application/zip", ".npz": "application/x-npz", ".mp4": "video/mp4",
          ".mov": "video/quicktime", ".avi": "video/x-msvideo", ".mkv": "video/x-matroska"}


def _part(source: Any, default_name: str) -> tuple[str, bytes, str]:
    """A file part from a path, bytes or a ``(filename, bytes, media type)`` tuple."""
    if A.is_path(source):
        path = Path(source)
        return path.name, path.read_bytes(), _TYPES.get(path.suffix.lower(),
                                                        "application/octet-stream")
    return file_part(source, default_name, _TYPES.get(Path(default_name).suffix.lower(),
                                                      "application/octet-stream"))


class Tracking(Resource):
    """``/v1/actors/{actor_id}/tracking-jobs``: performance-flow tracking (Fyffe et al.,
    Digital Ira course 2014; a job). The actor's neutral is the artist mesh tracked."""

    def submit(self, actor_id: str, files: Mapping[str, Any] | Sequence[tuple[str, Any]] | None = None,
               params: Mapping[str, Any] | None = None, *, cameras: Any = None,
               scans: Sequence[Any] | None = None, scan_images: Any = None,
               frames: Any = None, scan_maps: Any = None, format: str | None = None,
               map_resolution: int | None = None) -> JobAccepted:
        """Queue a tracking job.

        Parameters
        ----------
        cameras : path, bytes or dict   the calibration JSON ``{"views": [{"name", "K", "R",
                                        "t", "width", "height"}, ...]}``
        scans : list of paths/bytes     raw static scans (``.obj``/``.ply``), the neutral
                                        expression first; a scan's name is its file stem
        scan_images : path or bytes     zip ``<scan>/<view>.png`` (or ``.exr``)
        frames : path, bytes or list    a zip ``<view>/<frame>.png``, or one video file per
                                        view in the calibration's order
        scan_maps : path or bytes       optional ``.npz`` of per-scan UV maps to blend
        params : dict, optional         tracking parameters (``TrackingParams``)
        format : ``npz`` (default), ``obj-exr-zip`` or ``usd``;  map_resolution : texels
        files : mapping or sequence of (part name, value), optional
            raw parts instead of (or besides) the named ones; a value is a path, bytes, a
            ``(filename, bytes, media type)`` tuple, or a list of them

        Returns
        -------
        JobAccepted   wait for it; its result's ``artifacts`` name :data:`TRACKING_ARTIFACTS`

        Examples
        --------
        >>> accepted = client.tracking.submit(actor.id, cameras="cams.json",
        ...     scans=["neutral.ply", "smile.ply"], scan_images="scan_images.zip",
        ...     frames=["front.mp4", "left.mp4"])                  # doctest: +SKIP
        >>> job = client.wait(accepted, progress=True)             # doctest: +SKIP
        """
        parts: list[tuple[str, tuple[str, bytes, str]]] = []
        if isinstance(cameras, Mapping):
            cameras = ("cameras.json", jsonlib.dumps(dict(cameras)).encode(), "application/json")
        named = {"cameras": cameras, "scans": list(scans) if scans is not None else None,
                 "scan_images": scan_images,
                 "frames": frames if isinstance(frames, list) or frames is None else [frames],
                 "scan_maps": scan_maps}
        defaults = {"cameras": "cameras.json", "scans": "scan.obj", "scan_images": "scan_images.zip",
                    "frames": "frames.zip", "scan_maps": "scan_maps.npz"}
        for name, value in named.items():
            for k, item in enumerate(value if isinstance(value, list) else
                                     ([] if value is None else [value])):
                parts.append((name, _part(item, defaults[name] if name != "scans"
                                          else f"scan{k}.obj")))
        pairs = (files.items() if isinstance(files, Mapping) else files) if files else []
        for name, value in pairs:
            for item in (value if isinstance(value, list) else [value]):
                parts.append((name, file_part(item, name, "application/octet-stream")))
        data = {"params": jsonlib.dumps(dict(params))} if params is not None else None
        query = {k: v for k, v in (("format", format), ("map_resolution", map_resolution))
                 if v is not None}
        return self._run(self._core.call_accepted(
            Call("POST", f"/v1/actors/{actor_id}/tracking-jobs", files=parts, data=data,
                 params=query or None),
            JobAccepted.from_json))
