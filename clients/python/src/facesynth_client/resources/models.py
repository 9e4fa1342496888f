"""``client.models``: training and trained models, their maps and kinds (``/v1/models``,
``/v1/actors/{actor_id}/models``, ``/v1/kinds``)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Sequence

from .._core import Call
from ..types import KindInfo, MapInfo, Model, ModelAccepted
from ._base import Resource

__all__ = ["Models"]


class Models(Resource):
    """``/v1/models`` and ``/v1/actors/{actor_id}/models``: training and trained models."""

    def train(self, actor_id: str, kind: str, clips: Sequence[Any],
              params: Mapping[str, Any] | None = None) -> ModelAccepted:
        """Create a model of ``kind`` from clips and queue its training (a job).

        Parameters
        ----------
        kind : str   ``pdm``, ``psd``, ``wpsd`` or ``shape_space`` (see :meth:`kinds`)
        clips : sequence of clip ids or :class:`Clip`
        params : dict, optional   the kind's training parameters (e.g. pdm: ``order``,
                                  ``medium_resolution``, ``fine_resolution``, ``gamma``);
                                  a misspelt name is an :class:`Unprocessable`

        Returns
        -------
        ModelAccepted   ``model_id`` and ``job_id``

        Examples
        --------
        >>> accepted = client.models.train(actor.id, "pdm", [clip.clip_id],
        ...                                {"medium_resolution": 256})       # doctest: +SKIP
        >>> client.wait(accepted, progress=True)                            # doctest: +SKIP
        """
        body: dict[str, Any] = {"kind": kind, "clips": [getattr(c, "clip_id", c) for c in clips]}
        if params is not None:
            body["params"] = dict(params)
        return self._run(self._core.call_accepted(
            Call("POST", f"/v1/actors/{actor_id}/models", json=body), ModelAccepted.from_json))

    def transfer(self, model_id: str, target_actor_id: str, landmarks: Sequence[Sequence[int]],
                 params: Mapping[str, Any] | None = None) -> ModelAccepted:
        """Transfer a ready ``psd``/``wpsd`` model's details to another actor (Bickel et al.
        2008 §5.4; a job).

        Parameters
        ----------
        target_actor_id : str        the actor the details go to (neutral and markers uploaded)
        landmarks : (L,2) ints       corresponding [source_vertex, target_vertex] pairs on the
                                     two neutrals (at least 4; ~40 spread over the face)
        params : dict, optional      ``pose_weights``: one head-alignment weight per target
                                     marker

        Returns
        -------
        ModelAccepted   ``model_id`` (the target's new model, ``training`` until the job
                        ends) and ``job_id``

        Examples
        --------
        >>> accepted = client.models.transfer(model_id, other.id, pairs)    # doctest: +SKIP
        >>> client.wait(accepted, progress=True)                            # doctest: +SKIP
        >>> client.synthesize(accepted.model_id, other_markers)             # doctest: +SKIP
        """
        body: dict[str, Any] = {"target_actor_id": target_actor_id,
                                "landmarks": [[int(a), int(b)] for a, b in landmarks]}
        if params is not None:
            body["params"] = dict(params)
        return self._run(self._core.call_accepted(
            Call("POST", f"/v1/models/{model_id}/transfer", json=body), ModelAccepted.from_json))

    def get(self, model_id: str) -> Model:
        """A model: kind, status (``training``, ``ready``, ``failed``), params, metrics."""
        return self._run(self._core.call_json(Call("GET", f"/v1/models/{model_id}"),
                                              Model.from_json))

    def list(self, actor_id: str, *, status: str | None = None) -> list[Model]:
        """The actor's models, oldest first, optionally of one status."""
        return self._run(self._core.call_items(
            Call("GET", f"/v1/actors/{actor_id}/models", params={"status": status}),
            Model.from_json))

    def delete(self, model_id: str) -> None:
        """Delete a model and its files (its queued or running jobs are cancelled)."""
        return self._run(self._core.call_empty(Call("DELETE", f"/v1/models/{model_id}")))

    def maps(self, model_id: str) -> list[MapInfo]:
        """The model's UV-space maps (EXR files; e.g. a PDM's coefficient maps)."""
        return self._run(self._core.call_items(
            Call("GET", f"/v1/models/{model_id}/maps"), MapInfo.from_json))

    def download_map(self, model_id: str, name: str, path: str | os.PathLike, *,
                     half: bool = False) -> Path:
        """Download map ``name`` as an OpenEXR file to ``path`` (atomically; 32-bit float
        unless ``half``). Returns the path."""
        return self._run(self._core.download(
            f"/v1/models/{model_id}/maps/{name}.exr", path,
            params={"half": "true"} if half else None))

    def kinds(self) -> list[KindInfo]:
        """The model kinds the server trains, with their parameters' JSON Schema."""
        return self._run(self._core.call_items(Call("GET", "/v1/kinds"), KindInfo.from_json))

    def kind(self, name: str) -> KindInfo:
        """One model kind (404 for an unknown one)."""
        return self._run(self._core.call_json(Call("GET", f"/v1/kinds/{name}"),
                                              KindInfo.from_json))
