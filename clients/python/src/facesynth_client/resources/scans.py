"""``client.scans``: an actor's facial scans as UV-space maps (``/v1/actors/{actor_id}/scans``)
and scan correspondence jobs (``/v1/actors/{actor_id}/correspondence-jobs``)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from .. import arrays as A
from .._core import Call
from ..types import JobAccepted, Scan
from ._base import Resource

__all__ = ["Scans"]


class Scans(Resource):
    """``/v1/actors/{actor_id}/scans`` and ``/correspondence-jobs``: scans and their
    correspondence (Vuvuzela: a scan warped into another scan's UV space, as a job)."""

    def upload(self, actor_id: str, albedo: Any, position: Any, *, specular: Any = None,
               normal: Any = None, mask: Any = None, name: str | None = None) -> Scan:
        """Upload a scan from arrays (sent as NPZ).

        Parameters
        ----------
        albedo : (H,W,3) float     linear diffuse albedo (the correspondence runs on it)
        position : (H,W,3) float   the point cloud in UV space, in the actor's unit
        specular, normal : (H,W,3) float, optional
        mask : (H,W) bool, optional   covered texels (default: albedo non-zero)
        name : str, optional

        Examples
        --------
        >>> scan = client.scans.upload(actor.id, albedo, position, mask=mask,
        ...                            name="smile")                      # doctest: +SKIP
        """
        body = A.npz_bytes(
            albedo=np.asarray(albedo, np.float32), position=np.asarray(position, np.float32),
            specular=None if specular is None else np.asarray(specular, np.float32),
            normal=None if normal is None else np.asarray(normal, np.float32),
            mask=None if mask is None else np.asarray(mask, bool))
        return self._post(actor_id, name, body)

    def upload_file(self, actor_id: str, path: str | os.PathLike, *,
                    name: str | None = None) -> Scan:
        """Upload a scan from an ``.npz`` file (``albedo``, ``position``[, ``specular``,
        ``normal``, ``mask``])."""
        return self._post(actor_id, name, Path(path).read_bytes())

    def _post(self, actor_id: str, name: str | None, body: bytes) -> Scan:
        return self._run(self._core.call_json(Call(
            "POST", f"/v1/actors/{actor_id}/scans", params={"name": name}, content=body,
            headers={"Content-Type": A.NPZ}), Scan.from_json))

    def list(self, actor_id: str) -> list[Scan]:
        """The actor's scans, oldest first."""
        return self._run(self._core.call_items(
            Call("GET", f"/v1/actors/{actor_id}/scans"), Scan.from_json))

    def get(self, actor_id: str, scan_id: str) -> Scan:
        """One scan of the actor."""
        return self._run(self._core.call_json(
            Call("GET", f"/v1/actors/{actor_id}/scans/{scan_id}"), Scan.from_json))

    def delete(self, actor_id: str, scan_id: str) -> None:
        """Delete a scan."""
        return self._run(self._core.call_empty(
            Call("DELETE", f"/v1/actors/{actor_id}/scans/{scan_id}")))

    def correspond(self, actor_id: str, source_scan_id: str, target_scan_id: str,
                   landmarks: Any, *, pinned: Sequence[int] | None = None,
                   params: Mapping[str, Any] | None = None,
                   artist_uv: bool = False) -> JobAccepted:
        """Queue a correspondence job: the source scan warped into the target's UV space.

        Parameters
        ----------
        landmarks : (L,2,2) float   ``[[u_s, v_s], [u_t, v_t]]`` per clicked point, unit-tile
                                    UV of the source and the target; L >= 3
        pinned : indices of pinned landmarks, optional
        params : dict, optional     correspondence parameters (OpenAPI's
                                    ``CorrespondenceParams``)
        artist_uv : bool            the actor's neutral has the target scan's UVs: also
                                    store its blendshape

        Returns
        -------
        JobAccepted   wait for it with ``client.wait``; its result's ``artifacts`` maps file
                      names (``albedo.exr``, ``warp.npz``, ``blendshape.npz``, ...) to ids

        Examples
        --------
        >>> job = client.scans.correspond(actor.id, smile.id, neutral.id, clicks)  # doctest: +SKIP
        >>> client.wait(job, progress=True)                                      # doctest: +SKIP
        """
        body: dict[str, Any] = {"source_scan_id": source_scan_id,
                                "target_scan_id": target_scan_id,
                                "landmarks": np.asarray(landmarks, float).tolist(),
                                "artist_uv": bool(artist_uv)}
        if pinned is not None:
            body["pinned"] = [int(i) for i in pinned]
        if params is not None:
            body["params"] = dict(params)
        return self._run(self._core.call_accepted(
            Call("POST", f"/v1/actors/{actor_id}/correspondence-jobs", json=body),
            JobAccepted.from_json))
