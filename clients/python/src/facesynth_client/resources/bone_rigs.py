"""``client.bone_rigs``: performances compressed to bone rigs
(``/v1/actors/{actor_id}/bone-rig-jobs``)."""

from __future__ import annotations

from typing import Any, Mapping

from .._core import Call
from ..types import JobAccepted
from ._base import Resource

__all__ = ["BoneRigs"]


class BoneRigs(Resource):
    """``/v1/actors/{actor_id}/bone-rig-jobs``: smooth-skinning decomposition of a
    performance into a linear-blend-skinned bone rig (Le & Deng 2012; a job)."""

    def submit(self, actor_id: str, *, clip: Any = None, artifact: Any = None,
               params: Mapping[str, Any] | None = None, fps: float | None = None,
               usd: bool = False) -> JobAccepted:
        """Queue a bone-rig job for one of the actor's performances.

        Parameters
        ----------
        clip : clip id or :class:`Clip`       one of the actor's clips (its ``vertices``) …
        artifact : artifact id                … or a synthesis job's ``.npz`` result
        params : dict, optional   ``bones`` (default 70), ``max_influences`` (4),
                                  ``iterations``, ``seed``, ... (``GET /openapi.json``)
        fps : float, optional     the exported animation's frame rate (default: the clip's)
        usd : bool                also store the rig as a UsdSkel stage (a third artifact)

        Returns
        -------
        JobAccepted   wait for it; its ``artifact_ids`` are the rig ``.npz`` and the ``.glb``
                      (and the ``.usd`` with ``usd=True``)

        Examples
        --------
        >>> accepted = client.bone_rigs.submit(actor.id, clip=clip.clip_id,
        ...                                    params={"bones": 40})       # doctest: +SKIP
        >>> rig_npz, rig_glb = client.wait(accepted, progress=True).artifact_ids  # doctest: +SKIP
        """
        if (clip is None) == (artifact is None):
            raise ValueError("give exactly one of clip and artifact")
        body: dict[str, Any] = ({"clip_id": getattr(clip, "clip_id", clip)} if clip is not None
                                else {"artifact_id": getattr(artifact, "id", artifact)})
        if params is not None:
            body["params"] = dict(params)
        if fps is not None:
            body["fps"] = float(fps)
        if usd:
            body["usd"] = True
        return self._run(self._core.call_accepted(
            Call("POST", f"/v1/actors/{actor_id}/bone-rig-jobs", json=body),
            JobAccepted.from_json))
