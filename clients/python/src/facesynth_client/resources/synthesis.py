"""``client.synthesis``: synchronous synthesis, enhancement and retiming, and synthesis
jobs (``/v1/models/{model_id}/...``)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Mapping, Sequence

import numpy as np

from .. import arrays as A
from .._core import Call, Op
from ..types import ClipFrame, JobAccepted
from ._base import Resource, file_part, outputs_param

__all__ = ["Synthesis"]


def _markers_json(markers: np.ndarray) -> list:
    """(F,M,3) as JSON frames, NaN (occluded) markers as null."""
    occluded = np.isnan(markers).any(axis=-1)
    return [[None if occluded[f, m] else [float(x) for x in markers[f, m]]
             for m in range(markers.shape[1])] for f in range(markers.shape[0])]


class Synthesis(Resource):
    """``/v1/models/{model_id}/...``: synchronous synthesis and synthesis jobs.

    Repeated calls send the triangles once: a model's first ``synthesize``/``enhance``
    answer carries ``faces``, which this resource keeps per model id (a model's topology
    never changes), and later calls ask with ``topology=false`` and put the kept ``faces``
    back into the result, so every result still has them. :meth:`topology` fetches the
    model's topology resource itself (``faces``, ``uv``, ``uv_faces``), revalidated with its
    ``ETag`` (a 304 costs no body).
    """

    def __init__(self, client: Any):
        super().__init__(client)
        #: model id → ``faces`` (T,3) int32, from a first answer or the topology resource
        self._faces: dict[str, np.ndarray] = {}
        #: model id → (ETag, the topology resource's arrays)
        self._topology: dict[str, tuple[str, dict[str, np.ndarray]]] = {}

    def _arrays(self, call: Call, copy: bool = True) -> Op:
        content = yield from self._core.call_bytes(call)
        return A.load_npz(content, views=not copy)

    def _frames(self, model_id: str, call: Call, reuse_topology: bool, copy: bool = True) -> Op:
        """Send a synthesis ``call``: ``topology=false`` when this model's ``faces`` are
        kept (then put back into the result), else kept from the answer; ``copy=False``
        decodes the answer as views of its body (:func:`~facesynth_client.arrays.load_npz`)."""
        faces = self._faces.get(model_id) if reuse_topology else None
        if faces is not None:
            call = replace(call, params={**(call.params or {}), "topology": "false"})
        out = yield from self._arrays(call, copy)
        if faces is not None:
            out["faces"] = faces
        elif reuse_topology and "faces" in out:
            self._faces[model_id] = out["faces"]
        return out

    def topology(self, model_id: str) -> dict[str, np.ndarray]:
        """The model's topology (``GET /v1/models/{model_id}/topology``): ``faces`` (T,3)
        int32 and, where the model has them, ``uv`` (K,2) and ``uv_faces`` (T,3). Kept by
        its ``ETag``: a later call revalidates with ``If-None-Match`` (the server answers
        304 without a body while it is unchanged)."""
        return self._run(self._topology_op(model_id))

    def _topology_op(self, model_id: str) -> Op:
        kept = self._topology.get(model_id)
        headers = {"Accept": A.NPZ, **({"If-None-Match": kept[0]} if kept else {})}
        response = yield from self._core.send(Call("GET", f"/v1/models/{model_id}/topology",
                                                   headers=headers))
        if response.status_code == 304 and kept is not None:
            arrays = kept[1]
        else:
            arrays = A.load_npz(response.content)
            etag = response.headers.get("etag")
            if etag:
                self._topology[model_id] = (etag, arrays)
        self._faces[model_id] = arrays["faces"]
        return dict(arrays)

    def _frames_call(self, route: str, model_id: str, arrays: dict[str, Any], *,
                     params: dict[str, Any], accept: str = A.NPZ) -> Call:
        return Call("POST", f"/v1/models/{model_id}/{route}", params=params,
                    content=A.npz_bytes(**arrays), idempotent=True,
                    headers={"Content-Type": A.NPZ, "Accept": accept})

    def synthesize(self, model_id: str, markers: Any, *,
                   outputs: str | Sequence[str] | None = None, map_resolution: int | None = None,
                   clamp: bool = True, half: bool = False,
                   reuse_topology: bool = True, copy: bool = True) -> dict[str, np.ndarray]:
        """Detailed meshes and maps from markers, for a marker-driven model (e.g. ``pdm``).

        Parameters
        ----------
        markers : (F,M,3) or (M,3) float   world-space, layout order, NaN: occluded
        outputs : subset of ``mesh``, ``mesh_detailed``, ``displacement``, ``albedo``,
                  ``normal_map`` (default ``mesh``, ``displacement``)
        map_resolution : int, optional     side of the returned maps in texels
        clamp : bool                       limit extrapolation beyond the training data
        half : bool                        maps as float16 (half the bytes; within 2^-11
                                           relative of float32); meshes stay float32
        reuse_topology : bool              send the triangles once per model (see the class)
        copy : bool                        False: the arrays are read-only views of the
                                           response body, decoded without copying them and
                                           without the zip's CRC-32 check (the same values;
                                           for per-frame loops: a 9 MB maps answer decodes in
                                           ~0.1 ms instead of several)

        Returns
        -------
        dict of ndarray
            ``vertices`` (F,V,3) in the input's world pose, ``faces`` (T,3),
            ``vertices_detailed`` (F,V,3) with ``mesh_detailed``, ``displacement`` (F,H,W) in
            the actor's unit, ``albedo``/``normal_map`` (F,H,W,3), ``clamped`` (F,)

        Raises
        ------
        Conflict        the model is not ready
        Unprocessable   e.g. "model expects 150 markers, got 149"
        PayloadTooLarge more frames than ``max_frames_per_request`` (use :meth:`submit_job`)

        Examples
        --------
        >>> out = client.synthesis.synthesize(model_id, markers[:4],
        ...                                   outputs=["mesh_detailed"])    # doctest: +SKIP
        >>> out["vertices_detailed"].shape                                  # doctest: +SKIP
        (4, 40962, 3)
        """
        frames = A.frames_array(markers, "markers")
        if map_resolution is None:
            call = self._frames_call("synthesize", model_id, {"markers": frames},
                                     params={"outputs": outputs_param(outputs),
                                             "clamp": None if clamp else "false",
                                             "half": "true" if half else None})
        else:
            body: dict[str, Any] = {"markers": _markers_json(frames),
                                    "map_resolution": int(map_resolution), "clamp": clamp}
            if outputs is not None:
                body["outputs"] = (outputs.split(",") if isinstance(outputs, str)
                                   else list(outputs))
            call = Call("POST", f"/v1/models/{model_id}/synthesize", json=body,
                        params={"half": "true" if half else None},
                        idempotent=True, headers={"Accept": A.NPZ})
        return self._run(self._frames(model_id, call, reuse_topology, copy))

    def synthesize_obj(self, model_id: str, markers: Any, *, detailed: bool = False,
                       clamp: bool = True) -> str:
        """One frame's mesh as OBJ text (with UVs); ``detailed`` bakes the fine scale onto
        the vertices. ``markers`` is (M,3) or (1,M,3)."""
        call = self._frames_call(
            "synthesize", model_id, {"markers": A.frames_array(markers, "markers")},
            params={"outputs": "mesh_detailed" if detailed else "mesh",
                    "clamp": None if clamp else "false"}, accept=A.OBJ)
        return self._run(self._core.call_text(call))

    def synthesize_exr(self, model_id: str, markers: Any, output: str = "displacement", *,
                       half: bool = False, clamp: bool = True) -> bytes:
        """One frame's map ``output`` (``displacement``, ``albedo`` or ``normal_map``) as
        an OpenEXR file's bytes (32-bit float unless ``half``)."""
        call = self._frames_call(
            "synthesize", model_id, {"markers": A.frames_array(markers, "markers")},
            params={"outputs": output, "half": "true" if half else None,
                    "clamp": None if clamp else "false"}, accept=A.EXR)
        return self._run(self._core.call_bytes(call))

    def enhance(self, model_id: str, vertices: Any = None, *, markers: Any = None,
                rig: str | None = None, outputs: str | Sequence[str] | None = None,
                clamp: bool = True, half: bool = False,
                reuse_topology: bool = True, copy: bool = True) -> dict[str, np.ndarray]:
        """Detailed meshes from low-resolution meshes, for mesh-driven kinds
        (``shape_space``).

        Parameters
        ----------
        vertices : (F,n,3) or (n,3) float, or meshes
            frames on the actor's topology, or on the registered input rig ``rig``
        markers : (F,M,3) float, optional   instead of vertices, for kinds that take them
        rig : str, optional                 name of a ready input rig of the actor
        outputs, clamp, half, reuse_topology, copy : as for :meth:`synthesize`

        Returns
        -------
        dict of ndarray
            as for :meth:`synthesize`; a ``shape_space`` model gives ``displacement`` per
            vertex (F,V) and ``weights`` (F,R,N)

        Examples
        --------
        >>> out = client.enhance(model_id, low_res_frames, rig="game-lod2")  # doctest: +SKIP
        """
        arrays = {}
        if vertices is not None:
            arrays["vertices"] = A.frames_array(vertices)
        if markers is not None:
            arrays["markers"] = A.frames_array(markers, "markers")
        if not arrays:
            raise TypeError("enhance needs vertices (or markers)")
        call = self._frames_call("enhance", model_id, arrays,
                                 params={"outputs": outputs_param(outputs), "rig": rig,
                                         "clamp": None if clamp else "false",
                                         "half": "true" if half else None})
        return self._run(self._frames(model_id, call, reuse_topology, copy))

    def retime(self, model_id: str, keyframes: Any, length: int, *,
               extend_to_full_motion: bool = False, rig: str | None = None) -> dict[str, np.ndarray]:
        """Temporal enhancement (``shape_space``): ``length`` frames between two or more
        keyframes, timed like the database's motion.

        Parameters
        ----------
        keyframes : (K,v,3) float, or a sequence of (v,3) arrays / :class:`ClipFrame` /
            ``(clip_id, frame)`` pairs / ``{"clip_id", "frame"}`` dicts
        length : int    output frames m (keyframes included, m >= K)
        extend_to_full_motion : bool   extend the matched database motion
        rig : str, optional   the input rig the vertex keyframes are on

        Returns
        -------
        dict of ndarray
            ``vertices`` (m,V,3), ``timestamps`` (m,), ``keyframe_indices`` (K,), ``faces``, ...

        Examples
        --------
        >>> out = client.retime(model_id, [ClipFrame(clip_id, 0), ClipFrame(clip_id, 11)],
        ...                     length=24)                                   # doctest: +SKIP
        """
        if isinstance(keyframes, np.ndarray):
            call = self._frames_call(
                "retime", model_id, {"keyframes": A.frames_array(keyframes)},
                params={"length": int(length), "rig": rig,
                        "extend_to_full_motion": "true" if extend_to_full_motion else None})
        else:
            items = []
            for key in keyframes:
                if isinstance(key, ClipFrame):
                    items.append(key.to_json())
                elif isinstance(key, Mapping):
                    items.append({"clip_id": key["clip_id"], "frame": int(key["frame"])})
                elif isinstance(key, tuple) and len(key) == 2 and isinstance(key[0], str):
                    items.append({"clip_id": key[0], "frame": int(key[1])})
                else:
                    items.append(np.asarray(getattr(key, "vertices", key), float).tolist())
            body = {"keyframes": items, "length": int(length),
                    "extend_to_full_motion": bool(extend_to_full_motion)}
            if rig is not None:
                body["rig"] = rig
            call = Call("POST", f"/v1/models/{model_id}/retime", json=body, idempotent=True,
                        headers={"Accept": A.NPZ})
        return self._run(self._arrays(call))

    def submit_job(self, model_id: str, performance: Any = None, *, markers: Any = None,
                   vertices: Any = None, fps: float | None = None,
                   outputs: str | Sequence[str] | None = None, format: str = "npz",
                   clamp: bool = True, rig: str | None = None,
                   marker_filter_frames: float | str = 0.0) -> JobAccepted:
        """Queue the synthesis of a whole performance (a job; its result is an artifact).

        Parameters
        ----------
        performance : path, optional
            an ``.npz`` (``markers`` or ``vertices``), ``.json``, ``.c3d``, ``.trc`` or
            ``.csv`` file; marker files go as multipart and are read by the server
        markers : (F,M,3) float, optional    for marker-driven kinds, NaN: occluded
        vertices : (F,n,3) float, optional   for mesh-driven kinds (on ``rig``'s topology
                                             if given)
        fps : float, optional
        outputs : as for :meth:`synthesize`
        format : str    ``npz``, ``obj-exr-zip`` (per-frame OBJ + EXR) or ``usd`` (one USD
                        point cache, time code k = frame k, at ``fps``; a zip of the cache
                        and the EXR maps it references when maps are among the outputs;
                        needs ``mesh`` or ``mesh_detailed``)
        rig : str, optional
        marker_filter_frames : float or "auto"   σ in frames of the server's temporal
                                       marker filter (marker-driven kinds; 0: off, 3 at 30
                                       fps for ordinary mocap noise; ``"auto"``: the take's
                                       noise estimated, the window chosen per frame in the
                                       modes of the model's marker prior)

        Returns
        -------
        JobAccepted   ``job_id``; then ``client.wait(...)`` and
                      ``client.download_artifact(job.artifact_ids[0], path)``

        Examples
        --------
        >>> accepted = client.synthesis.submit_job(model_id, "take7.c3d")     # doctest: +SKIP
        >>> job = client.wait(accepted, progress=True)                       # doctest: +SKIP
        >>> client.download_artifact(job.artifact_ids[0], "take7.npz")       # doctest: +SKIP
        """
        params = {"outputs": outputs_param(outputs), "format": format, "rig": rig,
                  "clamp": None if clamp else "false",
                  "marker_filter_frames": marker_filter_frames or None}
        path = f"/v1/models/{model_id}/synthesis-jobs"
        if performance is not None:
            if isinstance(performance, (bytes, bytearray)):
                call = Call("POST", path, params=params, content=bytes(performance),
                            headers={"Content-Type": A.NPZ})
            else:
                call = Call("POST", path, params=params,
                            files=[("file", file_part(performance, "performance",
                                                       "application/octet-stream"))])
        else:
            arrays: dict[str, Any] = {"fps": None if fps is None else np.float64(fps)}
            if markers is not None:
                arrays["markers"] = A.frames_array(markers, "markers")
            if vertices is not None:
                arrays["vertices"] = A.frames_array(vertices)
            if len(arrays) == 1:
                raise TypeError("submit_job needs a performance file, markers or vertices")
            call = Call("POST", path, params=params, content=A.npz_bytes(**arrays),
                        headers={"Content-Type": A.NPZ})
        return self._run(self._core.call_accepted(call, JobAccepted.from_json))
