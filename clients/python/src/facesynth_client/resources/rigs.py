"""``client.rigs``: an actor's input rigs (``/v1/actors/{actor_id}/input-rigs``)."""

from __future__ import annotations

import json as jsonlib
from typing import Any, Sequence

import numpy as np

from .. import arrays as A
from .._core import Call
from ..types import InputRig, RigAccepted
from ._base import Resource

__all__ = ["Rigs"]


class Rigs(Resource):
    """``/v1/actors/{actor_id}/input-rigs``: low-resolution input topologies."""

    def upload(self, actor_id: str, rig: str, mesh: Any = None, *, vertices: Any = None,
               faces: Any = None, landmarks: Sequence[Sequence[int]] | None = None) -> RigAccepted:
        """Upload (or replace) input rig ``rig`` and queue its registration to the actor's
        neutral — a job (wait for ``.job_id``).

        Parameters
        ----------
        rig : str          your name for it (letters, digits, ``._-``)
        mesh : path, bytes, trimesh-like or mapping, optional   the rig's neutral
        vertices : (v,3) float, optional
        faces : (t,3) int, optional
        landmarks : (P,2) int, optional   ``[rig_vertex, neutral_vertex]`` pairs that guide
                                          the registration (sent as multipart)

        Returns
        -------
        RigAccepted   ``rig_id``, ``job_id``, counts

        Examples
        --------
        >>> accepted = client.rigs.upload(actor.id, "game-lod2", "lod2.obj")  # doctest: +SKIP
        >>> client.wait(accepted)                                             # doctest: +SKIP
        """
        content, media_type = A.mesh_body(mesh, vertices=vertices, faces=faces)
        path = f"/v1/actors/{actor_id}/input-rigs/{rig}"
        if landmarks is None:
            call = Call("PUT", path, content=content, headers={"Content-Type": media_type})
        else:
            suffix = "npz" if media_type == A.NPZ else "obj"
            pairs = [[int(a), int(b)] for a, b in np.asarray(landmarks).reshape(-1, 2)]
            call = Call("PUT", path, files=[("mesh", (f"{rig}.{suffix}", content, media_type))],
                        data={"landmarks": jsonlib.dumps(pairs)})
        return self._run(self._core.call_accepted(call, RigAccepted.from_json))

    def list(self, actor_id: str) -> list[InputRig]:
        """The actor's input rigs with their registration state."""
        return self._run(self._core.call_items(
            Call("GET", f"/v1/actors/{actor_id}/input-rigs"), InputRig.from_json))

    def get(self, actor_id: str, rig: str) -> InputRig:
        """One input rig (``registering``, ``ready`` or ``failed``)."""
        return self._run(self._core.call_json(
            Call("GET", f"/v1/actors/{actor_id}/input-rigs/{rig}"), InputRig.from_json))
