"""``client.actors``: actors, their neutral mesh and marker layout (``/v1/actors``)."""

from __future__ import annotations

import json as jsonlib
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .. import arrays as A
from .._core import Call
from ..types import Actor, MarkersInfo, NeutralInfo
from ._base import Resource

__all__ = ["Actors"]


def _layout(layout: Any) -> dict[str, Any]:
    """A marker layout as its JSON body (see :meth:`Actors.set_markers`)."""
    if A.is_path(layout):
        return jsonlib.loads(Path(layout).read_text())
    if isinstance(layout, Mapping) and "markers" in layout and not isinstance(
            layout["markers"], (int, np.integer)):
        return {"markers": list(layout["markers"])}
    if isinstance(layout, Mapping):
        markers = []
        for name, where in layout.items():
            if isinstance(where, Mapping):
                markers.append({"name": name, **where})
            elif isinstance(where, (int, np.integer)):
                markers.append({"name": name, "vertex": int(where)})
            else:
                markers.append({"name": name, "position": [float(x) for x in np.ravel(where)]})
        return {"markers": markers}
    return {"markers": [dict(m) for m in layout]}


class Actors(Resource):
    """``/v1/actors``: actors, their neutral mesh and marker layout."""

    def create(self, name: str, metadata: Mapping[str, Any] | None = None) -> Actor:
        """Create an actor.

        Parameters
        ----------
        name : str                 display name
        metadata : dict, optional  free-form JSON (at most 64 KiB)

        Returns
        -------
        Actor

        Examples
        --------
        >>> actor = client.actors.create("Ada", {"session": "2025-01"})     # doctest: +SKIP
        """
        body = {"name": name, **({"metadata": dict(metadata)} if metadata is not None else {})}
        return self._run(self._core.call_json(Call("POST", "/v1/actors", json=body),
                                              Actor.from_json))

    def list(self) -> list[Actor]:
        """Every actor, oldest first."""
        return self._run(self._core.call_items(Call("GET", "/v1/actors"), Actor.from_json))

    def get(self, actor_id: str) -> Actor:
        """One actor with the counts of what was uploaded (404: :class:`NotFound`)."""
        return self._run(self._core.call_json(Call("GET", f"/v1/actors/{actor_id}"),
                                              Actor.from_json))

    def delete(self, actor_id: str, *, cascade: bool = False) -> None:
        """Delete an actor with its clips and rigs. With models, a :class:`Conflict` unless
        ``cascade=True`` (which deletes the models too)."""
        return self._run(self._core.call_empty(Call(
            "DELETE", f"/v1/actors/{actor_id}", params={"cascade": "true" if cascade else None})))

    def upload_neutral(self, actor_id: str, mesh: Any = None, *, vertices: Any = None,
                       faces: Any = None, uv: Any = None, uv_faces: Any = None,
                       **arrays: Any) -> NeutralInfo:
        """Upload the high-resolution neutral mesh with its UV layout (``PUT .../neutral``).

        Parameters
        ----------
        mesh : path, bytes, trimesh-like or mapping, optional
            an ``.obj`` / ``.npz`` file (sent as is; the OBJ's vertex order is kept), or a
            mesh object / dict of arrays (sent as NPZ)
        vertices : (V,3) float, optional   in the actor's unit (e.g. mm)
        faces : (T,3) int, optional        triangles (polygons in an OBJ are fan-split)
        uv : (V,2) float or (K,2), optional  per-vertex UVs in [0,1]², or per-corner with
                                             ``uv_faces``
        uv_faces : (T,3) int, optional
        **arrays : extra arrays, e.g. ``region_<name>`` (V,) bool

        Returns
        -------
        NeutralInfo   ``vertex_count``, ``triangle_count``, ``uv_seams``, ...

        Examples
        --------
        >>> client.actors.upload_neutral(actor.id, vertices=V, faces=F, uv=uv)  # doctest: +SKIP
        >>> client.actors.upload_neutral(actor.id, "neutral.obj")              # doctest: +SKIP
        """
        content, media_type = A.mesh_body(mesh, vertices=vertices, faces=faces, uv=uv,
                                          uv_faces=uv_faces, **arrays)
        return self._run(self._core.call_json(Call(
            "PUT", f"/v1/actors/{actor_id}/neutral", content=content,
            headers={"Content-Type": media_type}), NeutralInfo.from_json))

    def set_markers(self, actor_id: str, layout: Any) -> MarkersInfo:
        """Upload the marker layout (``PUT .../markers``); its order is the column order of
        every clip's and request's markers.

        Parameters
        ----------
        layout : mapping, list or path
            ``{name: vertex_index}``, ``{name: (x,y,z)}`` (a position, snapped to the
            surface), ``{name: {"triangle": t, "barycentric": [a,b,c]}}``; or the list of
            marker dicts of API.md; or ``{"markers": [...]}``; or a path of such a JSON file

        Returns
        -------
        MarkersInfo

        Examples
        --------
        >>> client.actors.set_markers(actor.id, {"FH1": 812, "FH2": [12.5, 80.1, 95.0]})  # doctest: +SKIP
        """
        return self._run(self._core.call_json(Call(
            "PUT", f"/v1/actors/{actor_id}/markers", json=_layout(layout)), MarkersInfo.from_json))
