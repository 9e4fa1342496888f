"""The clients: :class:`Client` (sync) and :class:`AsyncClient` (async).

Both expose the same resources — ``client.actors``, ``client.clips``, ``client.rigs``,
``client.models``, ``client.synthesis``, ``client.jobs``, ``client.artifacts``,
``client.tracking`` — and the same shortcuts (:meth:`~_Api.wait`, :meth:`~_Api.cancel`,
:meth:`~_Api.download_artifact`, :meth:`~_Api.synthesize`, ...). The resource classes are
written once: each method builds an operation of :mod:`facesynth_client._core` and hands it
to the client, which runs it synchronously (``Client``: the method returns the result) or
asynchronously (``AsyncClient``: the method returns an awaitable of the result; iterators
are async iterators).

Examples
--------
>>> import numpy as np
>>> from facesynth_client import Client
>>> with Client("http://127.0.0.1:8000") as fs:                        # doctest: +SKIP
...     actor = fs.actors.create("Ada")
...     fs.actors.upload_neutral(actor.id, "ada_neutral.obj")
...     fs.actors.set_markers(actor.id, {"FH1": 812, "FH2": 1304, "NOSE": 77})
...     clip = fs.clips.upload(actor.id, vertices=frames, markers=markers, fps=60)
...     accepted = fs.models.train(actor.id, "pdm", [clip.clip_id])
...     fs.wait(accepted, progress=True)
...     out = fs.synthesize(accepted.model_id, markers[:2])
...     out["vertices"].shape
(2, 40962, 3)
"""

from __future__ import annotations

import asyncio
import inspect
import json as jsonlib
import os
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import httpx
import numpy as np

from . import arrays as A
from ._core import (Call, Close, Core, DEFAULT_BASE_URL, Emit, Op, Read, Send, Sleep,
                    job_id_of)
from .types import (Actor, Artifact, Clip, ClipFrame, InputRig, Job, JobAccepted, KindInfo,
                    MapInfo, MarkersInfo, Model, ModelAccepted, NeutralInfo, Readiness,
                    RigAccepted)

__all__ = ["Client", "AsyncClient"]

#: the default timeout: 60 s to read/write, 10 s to connect
DEFAULT_TIMEOUT = httpx.Timeout(60.0, connect=10.0)


def _timeout(value: float | httpx.Timeout | None) -> httpx.Timeout:
    if isinstance(value, httpx.Timeout):
        return value
    return DEFAULT_TIMEOUT if value is None else httpx.Timeout(value)


def _items(parse: Callable[[Any], Any]) -> Callable[[Any], list]:
    return lambda body: [parse(item) for item in body["items"]]


def _outputs(outputs: str | Sequence[str] | None) -> str | None:
    if outputs is None:
        return None
    return outputs if isinstance(outputs, str) else ",".join(outputs)


def _markers_json(markers: np.ndarray) -> list:
    """(F,M,3) as JSON frames, NaN (occluded) markers as null."""
    occluded = np.isnan(markers).any(axis=-1)
    return [[None if occluded[f, m] else [float(x) for x in markers[f, m]]
             for m in range(markers.shape[1])] for f in range(markers.shape[0])]


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


def _file_part(source: Any, default_name: str, media_type: str) -> tuple[str, bytes, str]:
    """A multipart file part ``(filename, bytes, media type)`` from a path or bytes."""
    if A.is_path(source):
        path = Path(source)
        return path.name, path.read_bytes(), A.MARKER_FILE_SUFFIXES.get(path.suffix.lower(),
                                                                         media_type)
    if isinstance(source, tuple):
        return source  # (filename, bytes, media type) already
    return default_name, bytes(source), media_type


def _obj_text(mesh: Any) -> bytes:
    """A mesh (trimesh-like or arrays) as minimal OBJ text (``v`` and ``f`` lines)."""
    arrays = A.mesh_arrays(mesh)
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in arrays["vertices"]]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in arrays.get("faces", [])]
    return ("\n".join(lines) + "\n").encode()


# ---------------------------------------------------------------------------- resources
class _Resource:
    def __init__(self, client: "_Api"):
        self._client = client

    @property
    def _core(self) -> Core:
        return self._client._core

    def _run(self, op: Op) -> Any:
        return self._client._run(op)


class Actors(_Resource):
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
        return self._run(self._core.call_json(Call("GET", "/v1/actors"), _items(Actor.from_json)))

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


class Clips(_Resource):
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
                part = _file_part(frame, f"frame{k:05d}.obj", A.OBJ)
            else:
                part = (f"frame{k:05d}.obj", _obj_text(frame), A.OBJ)
            files.append(("frames", (part[0], part[1], A.OBJ)))
        files.append(("markers", _file_part(markers, "markers.csv", "text/csv")))
        data = {"fps": str(float(fps))} if fps is not None else None
        return self._post(actor_id, name, files=files, data=data)

    def _post(self, actor_id: str, name: str | None, **body: Any) -> Clip:
        return self._run(self._core.call_json(Call(
            "POST", f"/v1/actors/{actor_id}/clips", params={"name": name}, **body),
            Clip.from_json))

    def list(self, actor_id: str) -> list[Clip]:
        """The actor's clips, oldest first."""
        return self._run(self._core.call_json(Call("GET", f"/v1/actors/{actor_id}/clips"),
                                              _items(Clip.from_json)))

    def get(self, actor_id: str, clip_id: str) -> Clip:
        """One clip of the actor."""
        return self._run(self._core.call_json(
            Call("GET", f"/v1/actors/{actor_id}/clips/{clip_id}"), Clip.from_json))

    def delete(self, actor_id: str, clip_id: str) -> None:
        """Delete a clip (models trained on it keep what they learnt)."""
        return self._run(self._core.call_empty(
            Call("DELETE", f"/v1/actors/{actor_id}/clips/{clip_id}")))


class Rigs(_Resource):
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
        return self._run(self._core.call_json(Call("GET", f"/v1/actors/{actor_id}/input-rigs"),
                                              _items(InputRig.from_json)))

    def get(self, actor_id: str, rig: str) -> InputRig:
        """One input rig (``registering``, ``ready`` or ``failed``)."""
        return self._run(self._core.call_json(
            Call("GET", f"/v1/actors/{actor_id}/input-rigs/{rig}"), InputRig.from_json))


class Models(_Resource):
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

    def get(self, model_id: str) -> Model:
        """A model: kind, status (``training``, ``ready``, ``failed``), params, metrics."""
        return self._run(self._core.call_json(Call("GET", f"/v1/models/{model_id}"),
                                              Model.from_json))

    def list(self, actor_id: str, *, status: str | None = None) -> list[Model]:
        """The actor's models, oldest first, optionally of one status."""
        return self._run(self._core.call_json(
            Call("GET", f"/v1/actors/{actor_id}/models", params={"status": status}),
            _items(Model.from_json)))

    def delete(self, model_id: str) -> None:
        """Delete a model and its files (its queued or running jobs are cancelled)."""
        return self._run(self._core.call_empty(Call("DELETE", f"/v1/models/{model_id}")))

    def maps(self, model_id: str) -> list[MapInfo]:
        """The model's UV-space maps (EXR files; e.g. a PDM's coefficient maps)."""
        return self._run(self._core.call_json(Call("GET", f"/v1/models/{model_id}/maps"),
                                              _items(MapInfo.from_json)))

    def download_map(self, model_id: str, name: str, path: str | os.PathLike, *,
                     half: bool = False) -> Path:
        """Download map ``name`` as an OpenEXR file to ``path`` (atomically; 32-bit float
        unless ``half``). Returns the path."""
        return self._run(self._core.download(
            f"/v1/models/{model_id}/maps/{name}.exr", path,
            params={"half": "true"} if half else None))

    def kinds(self) -> list[KindInfo]:
        """The model kinds the server trains, with their parameters' JSON Schema."""
        return self._run(self._core.call_json(Call("GET", "/v1/kinds"), _items(KindInfo.from_json)))

    def kind(self, name: str) -> KindInfo:
        """One model kind (404 for an unknown one)."""
        return self._run(self._core.call_json(Call("GET", f"/v1/kinds/{name}"),
                                              KindInfo.from_json))


class Synthesis(_Resource):
    """``/v1/models/{model_id}/...``: synchronous synthesis and synthesis jobs."""

    def _arrays(self, call: Call) -> Op:
        content = yield from self._core.call_bytes(call)
        return A.load_npz(content)

    def _frames_call(self, route: str, model_id: str, arrays: dict[str, Any], *,
                     params: dict[str, Any], accept: str = A.NPZ) -> Call:
        return Call("POST", f"/v1/models/{model_id}/{route}", params=params,
                    content=A.npz_bytes(**arrays), idempotent=True,
                    headers={"Content-Type": A.NPZ, "Accept": accept})

    def synthesize(self, model_id: str, markers: Any, *,
                   outputs: str | Sequence[str] | None = None, map_resolution: int | None = None,
                   clamp: bool = True) -> dict[str, np.ndarray]:
        """Detailed meshes and maps from markers, for a marker-driven model (e.g. ``pdm``).

        Parameters
        ----------
        markers : (F,M,3) or (M,3) float   world-space, layout order, NaN: occluded
        outputs : subset of ``mesh``, ``mesh_detailed``, ``displacement``, ``albedo``,
                  ``normal_map`` (default ``mesh``, ``displacement``)
        map_resolution : int, optional     side of the returned maps in texels
        clamp : bool                       limit extrapolation beyond the training data

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
                                     params={"outputs": _outputs(outputs),
                                             "clamp": None if clamp else "false"})
        else:
            body: dict[str, Any] = {"markers": _markers_json(frames),
                                    "map_resolution": int(map_resolution), "clamp": clamp}
            if outputs is not None:
                body["outputs"] = (outputs.split(",") if isinstance(outputs, str)
                                   else list(outputs))
            call = Call("POST", f"/v1/models/{model_id}/synthesize", json=body,
                        idempotent=True, headers={"Accept": A.NPZ})
        return self._run(self._arrays(call))

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
                clamp: bool = True) -> dict[str, np.ndarray]:
        """Detailed meshes from low-resolution meshes, for mesh-driven kinds
        (``shape_space``).

        Parameters
        ----------
        vertices : (F,n,3) or (n,3) float, or meshes
            frames on the actor's topology, or on the registered input rig ``rig``
        markers : (F,M,3) float, optional   instead of vertices, for kinds that take them
        rig : str, optional                 name of a ready input rig of the actor
        outputs, clamp : as for :meth:`synthesize`

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
                                 params={"outputs": _outputs(outputs), "rig": rig,
                                         "clamp": None if clamp else "false"})
        return self._run(self._arrays(call))

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
                   clamp: bool = True, rig: str | None = None) -> JobAccepted:
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
        format : str    ``npz``, ``obj-exr-zip`` (per-frame OBJ + EXR) or ``usd``
        rig : str, optional

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
        params = {"outputs": _outputs(outputs), "format": format, "rig": rig,
                  "clamp": None if clamp else "false"}
        path = f"/v1/models/{model_id}/synthesis-jobs"
        if performance is not None:
            if isinstance(performance, (bytes, bytearray)):
                call = Call("POST", path, params=params, content=bytes(performance),
                            headers={"Content-Type": A.NPZ})
            else:
                call = Call("POST", path, params=params,
                            files=[("file", _file_part(performance, "performance",
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


class Tracking(_Resource):
    """``/v1/actors/{actor_id}/tracking-jobs``: performance-flow tracking (a job).

    Provisional: API.md names the inputs (static scans, cameras, per-view video frames,
    params) but not their encoding yet; this sends them as multipart file parts plus a
    ``params`` JSON field.
    """

    def submit(self, actor_id: str, files: Mapping[str, Any] | Sequence[tuple[str, Any]],
               params: Mapping[str, Any] | None = None) -> JobAccepted:
        """Queue a tracking job.

        Parameters
        ----------
        files : mapping or sequence of (part name, value)
            a value is a path, bytes, a ``(filename, bytes, media type)`` tuple, or a list
            of them (several parts of that name, in order)
        params : dict, optional   sent as the JSON field ``params``
        """
        pairs = files.items() if isinstance(files, Mapping) else files
        parts = []
        for name, value in pairs:
            for item in (value if isinstance(value, list) else [value]):
                parts.append((name, _file_part(item, name, "application/octet-stream")))
        data = {"params": jsonlib.dumps(dict(params))} if params is not None else None
        return self._run(self._core.call_accepted(
            Call("POST", f"/v1/actors/{actor_id}/tracking-jobs", files=parts, data=data),
            JobAccepted.from_json))


class Jobs(_Resource):
    """``/v1/jobs``: state, progress events, cancellation, artifacts."""

    def get(self, job: Any) -> Job:
        """A job's state (``job``: an id, a :class:`Job` or an accepted job)."""
        return self._run(self._core.get_job(job_id_of(job)))

    def list(self, *, status: str | None = None, actor_id: str | None = None,
             kind: str | None = None, model_id: str | None = None) -> list[Job]:
        """Jobs, oldest first, filtered by any of ``status``, ``actor_id``, ``kind``,
        ``model_id``."""
        return self._run(self._core.call_json(Call("GET", "/v1/jobs", params={
            "status": status, "actor_id": actor_id, "kind": kind, "model_id": model_id}),
            _items(Job.from_json)))

    def cancel(self, job: Any) -> Job:
        """Cancel a job: a queued one is ``cancelled`` at once, a running one stops at its
        next progress point (the returned state may still say ``running``); a finished one
        is returned unchanged."""
        return self._run(self._core.call_json(Call("DELETE", f"/v1/jobs/{job_id_of(job)}"),
                                              Job.from_json))

    def artifacts(self, job: Any) -> list[Artifact]:
        """The downloadable results of a job."""
        return self._run(self._core.call_json(
            Call("GET", f"/v1/jobs/{job_id_of(job)}/artifacts"), _items(Artifact.from_json)))

    def events(self, job: Any) -> Any:
        """The job's states from its event stream (``GET /v1/jobs/{id}/events``) until it
        ends: an iterator of :class:`Job` (an async iterator on :class:`AsyncClient`).

        Examples
        --------
        >>> for state in client.jobs.events(job_id):                         # doctest: +SKIP
        ...     print(f"{state.progress:.0%} {state.stage}")
        """
        return self._client._iterate(self._core.follow_events(job_id_of(job), None))

    def wait(self, job: Any, timeout: float | None = None, progress: Any = False, *,
             poll_interval: float | None = None, events: bool = True) -> Job:
        """See :meth:`Client.wait`."""
        return self._run(self._core.wait(job, timeout, progress, poll_interval, events))


class Artifacts(_Resource):
    """``/v1/artifacts/{artifact_id}``: job results."""

    def download(self, artifact_id: str, path: str | os.PathLike, *, resume: bool = True,
                 sha256: str | None = None) -> Path:
        """Stream an artifact to ``path`` (see :meth:`Client.download_artifact`)."""
        return self._run(self._core.download(f"/v1/artifacts/{artifact_id}", path,
                                              expected_sha256=sha256, resume=resume))

    def read(self, artifact_id: str) -> bytes:
        """An artifact's bytes, in memory."""
        return self._run(self._core.call_bytes(Call("GET", f"/v1/artifacts/{artifact_id}",
                                                    headers={"Accept": "*/*"})))

    def arrays(self, artifact_id: str) -> dict[str, np.ndarray]:
        """An ``.npz`` artifact's arrays (read with ``allow_pickle=False``)."""
        return self._run(self._load(artifact_id))

    def _load(self, artifact_id: str) -> Op:
        content = yield from self._core.call_bytes(
            Call("GET", f"/v1/artifacts/{artifact_id}", headers={"Accept": "*/*"}))
        return A.load_npz(content)


# ---------------------------------------------------------------------------- the clients
class _Api:
    """What :class:`Client` and :class:`AsyncClient` share: configuration, resources and
    shortcuts. Subclasses supply ``_run`` (and ``_iterate``)."""

    def __init__(self, base_url: str | None, token: str | None, *, timeout: Any,
                 max_retries: int, backoff: float, backoff_max: float, poll_interval: float,
                 headers: Mapping[str, str] | None, http: Any, random: Callable[[], float] | None):
        client_base = str(getattr(http, "base_url", "") or "").rstrip("/")
        self.base_url: str = (base_url or client_base or os.environ.get("FACESYNTH_URL")
                              or DEFAULT_BASE_URL).rstrip("/")
        token = token if token is not None else os.environ.get("FACESYNTH_TOKEN") or None
        from . import __version__
        core_args: dict[str, Any] = {}
        if random is not None:
            core_args["random"] = random
        self._core = Core(
            base_url=self.base_url, token=token, timeout=_timeout(timeout),
            max_retries=int(max_retries), backoff=float(backoff), backoff_max=float(backoff_max),
            poll_interval=float(poll_interval), build_request=http.build_request,
            headers={"User-Agent": f"facesynth-client/{__version__}", **(headers or {})},
            **core_args)
        self.actors = Actors(self)
        self.clips = Clips(self)
        self.rigs = Rigs(self)
        self.models = Models(self)
        self.synthesis = Synthesis(self)
        self.tracking = Tracking(self)
        self.jobs = Jobs(self)
        self.artifacts = Artifacts(self)

    def _run(self, op: Op) -> Any:  # pragma: no cover - supplied by subclasses
        raise NotImplementedError

    def _iterate(self, op: Op) -> Any:  # pragma: no cover - supplied by subclasses
        raise NotImplementedError

    @property
    def max_retries(self) -> int:
        return self._core.max_retries

    # ------------------------------------------------------------------ operations
    def health(self) -> dict[str, Any]:
        """``GET /healthz``: ``{"status": "ok"}`` while the process serves requests."""
        return self._run(self._core.call_json(Call("GET", "/healthz")))

    def ready(self) -> Readiness:
        """``GET /readyz``: whether the database, the blob store and the queue are
        reachable (``.ready``), with each check; a 503 answer is returned, not raised."""
        return self._run(self._core.call_json(Call("GET", "/readyz", accept_statuses=(503,)),
                                              Readiness.from_json))

    def metrics(self) -> str:
        """``GET /metrics``: the Prometheus text exposition."""
        return self._run(self._core.call_text(Call("GET", "/metrics",
                                                   headers={"Accept": "text/plain"})))

    def wait(self, job: Any, timeout: float | None = None, progress: Any = False, *,
             poll_interval: float | None = None, events: bool = True) -> Job:
        """Wait until a job ends.

        Follows the job's event stream (``GET /v1/jobs/{id}/events``); if the stream
        cannot be opened or breaks, polls ``GET /v1/jobs/{id}`` every ``poll_interval``
        seconds instead.

        Parameters
        ----------
        job : str, Job, ModelAccepted, RigAccepted or JobAccepted
        timeout : float, optional   seconds; None waits as long as it takes
        progress : bool or callable
            True: a text progress bar on stderr (tqdm's if it is installed); a callable
            ``(job) -> None`` is called with every new state
        poll_interval : float, optional   seconds between polls (default: the client's)
        events : bool   False: poll only

        Returns
        -------
        Job   the succeeded job (``.result.model_id``, ``.artifact_ids``)

        Raises
        ------
        JobFailed      the job failed (``.code``, ``.message``, ``.job``)
        JobCancelled   the job was cancelled
        WaitTimeout    ``timeout`` passed first (the job goes on)

        Examples
        --------
        >>> job = client.wait(client.models.train(actor_id, "pdm", clip_ids),
        ...                   timeout=3600, progress=True)                     # doctest: +SKIP
        >>> client.wait(job_id, progress=lambda j: print(j.progress, j.stage))  # doctest: +SKIP
        """
        return self.jobs.wait(job, timeout, progress, poll_interval=poll_interval, events=events)

    def cancel(self, job: Any) -> Job:
        """Cancel a job (see :meth:`Jobs.cancel`)."""
        return self.jobs.cancel(job)

    def download_artifact(self, artifact_id: str, path: str | os.PathLike, *,
                          resume: bool = True, sha256: str | None = None) -> Path:
        """Stream an artifact to ``path``.

        Written to ``<path>.part`` and renamed once complete, so ``path`` never holds a
        partial file; checked against ``Content-Length`` and its sha256 (the server's ETag,
        or ``sha256``). An interrupted download is resumed with a range request (also on
        the next call, from the ``.part`` file, while the ETag is unchanged).

        Returns
        -------
        pathlib.Path

        Raises
        ------
        IntegrityError   the content does not match its sha256

        Examples
        --------
        >>> client.download_artifact(job.artifact_ids[0], "out/take7.npz")   # doctest: +SKIP
        """
        return self.artifacts.download(artifact_id, path, resume=resume, sha256=sha256)

    def synthesize(self, model_id: str, markers: Any, **options: Any) -> dict[str, np.ndarray]:
        """Shortcut of :meth:`Synthesis.synthesize`."""
        return self.synthesis.synthesize(model_id, markers, **options)

    def enhance(self, model_id: str, vertices: Any = None, **options: Any) -> dict[str, np.ndarray]:
        """Shortcut of :meth:`Synthesis.enhance`."""
        return self.synthesis.enhance(model_id, vertices, **options)

    def retime(self, model_id: str, keyframes: Any, length: int, **options: Any) -> dict[str, np.ndarray]:
        """Shortcut of :meth:`Synthesis.retime`."""
        return self.synthesis.retime(model_id, keyframes, length, **options)


class Client(_Api):
    """The synchronous client.

    Parameters
    ----------
    base_url : str, optional    default ``$FACESYNTH_URL``, else ``http://127.0.0.1:8000``
                                (or the injected ``http_client``'s base URL)
    token : str, optional       bearer token, default ``$FACESYNTH_TOKEN``
    timeout : float or httpx.Timeout   per request (default 60 s, 10 s to connect)
    max_retries : int           retries of connection errors, timeouts and 503s (default 3);
                                other errors are never retried
    backoff : float             base of the exponential backoff with full jitter, seconds
    backoff_max : float         cap of one backoff sleep, seconds
    poll_interval : float       seconds between polls when waiting without events
    http_client : httpx.Client, optional   use this client (not closed by :meth:`close`)
    transport : httpx.BaseTransport, optional   transport of the client made here (e.g.
                                ``httpx.MockTransport`` in tests)
    sleep : callable, optional  ``sleep(seconds)`` for backoff and polling (default
                                ``time.sleep``; tests inject a recorder)
    headers : dict, optional    extra headers on every request

    Examples
    --------
    >>> with Client(token="s3cret") as fs:                                   # doctest: +SKIP
    ...     print(fs.health())
    {'status': 'ok'}
    """

    def __init__(self, base_url: str | None = None, token: str | None = None, *,
                 timeout: float | httpx.Timeout | None = None, max_retries: int = 3,
                 backoff: float = 0.5, backoff_max: float = 30.0, poll_interval: float = 1.0,
                 http_client: httpx.Client | None = None,
                 transport: httpx.BaseTransport | None = None,
                 sleep: Callable[[float], Any] | None = None,
                 headers: Mapping[str, str] | None = None,
                 random: Callable[[], float] | None = None):
        self._own = http_client is None
        self._http = http_client if http_client is not None else httpx.Client(
            transport=transport, timeout=_timeout(timeout))
        self._sleep = sleep if sleep is not None else time.sleep
        super().__init__(base_url, token, timeout=timeout, max_retries=max_retries,
                         backoff=backoff, backoff_max=backoff_max, poll_interval=poll_interval,
                         headers=headers, http=self._http, random=random)

    def close(self) -> None:
        """Close the HTTP client made by this client (an injected one stays open)."""
        if self._own:
            self._http.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ------------------------------------------------------------------ the driver
    def _perform(self, effect: Any, streams: dict) -> Any:
        if isinstance(effect, Send):
            response = self._http.send(effect.request, stream=True)
            if effect.stream and response.status_code < 400:
                streams[id(response)] = (response, response.iter_bytes())
            else:
                try:
                    response.read()
                finally:
                    response.close()
            return response
        if isinstance(effect, Read):
            entry = streams.get(id(effect.response))
            if entry is not None:
                for chunk in entry[1]:
                    if chunk:
                        return chunk
            return b""
        if isinstance(effect, Close):
            entry = streams.pop(id(effect.response), None)
            if entry is not None:
                entry[0].close()
            return None
        if isinstance(effect, Sleep):
            self._sleep(effect.seconds)
            return None
        raise TypeError(f"unknown effect {effect!r}")

    def _steps(self, op: Op, result: list):
        """Run ``op``, yielding what it emits; its value is appended to ``result``."""
        streams: dict = {}
        value: Any = None
        error: BaseException | None = None
        try:
            while True:
                try:
                    effect = op.throw(error) if error is not None else op.send(value)
                except StopIteration as stop:
                    result.append(stop.value)
                    return
                value, error = None, None
                try:
                    if isinstance(effect, Emit):
                        yield effect.value
                    else:
                        value = self._perform(effect, streams)
                except Exception as exc:  # handed to the operation, which may handle it
                    error = exc
        finally:
            op.close()
            for response, _ in streams.values():
                response.close()

    def _run(self, op: Op) -> Any:
        result: list = []
        for _ in self._steps(op, result):
            pass
        return result[0]

    def _iterate(self, op: Op) -> Any:
        yield from self._steps(op, [])


class AsyncClient(_Api):
    """The asynchronous client: the same resources and methods as :class:`Client`, each
    returning an awaitable (:meth:`Jobs.events` an async iterator).

    Parameters are those of :class:`Client`, with an ``httpx.AsyncClient`` /
    ``httpx.AsyncBaseTransport`` and ``sleep`` an async (or plain) function.

    Examples
    --------
    >>> async with AsyncClient() as fs:                                    # doctest: +SKIP
    ...     actor = await fs.actors.create("Ada")
    ...     async for state in fs.jobs.events(job_id):
    ...         print(state.progress)
    """

    def __init__(self, base_url: str | None = None, token: str | None = None, *,
                 timeout: float | httpx.Timeout | None = None, max_retries: int = 3,
                 backoff: float = 0.5, backoff_max: float = 30.0, poll_interval: float = 1.0,
                 http_client: httpx.AsyncClient | None = None,
                 transport: httpx.AsyncBaseTransport | None = None,
                 sleep: Callable[[float], Any] | None = None,
                 headers: Mapping[str, str] | None = None,
                 random: Callable[[], float] | None = None):
        self._own = http_client is None
        self._http = http_client if http_client is not None else httpx.AsyncClient(
            transport=transport, timeout=_timeout(timeout))
        self._sleep = sleep if sleep is not None else asyncio.sleep
        super().__init__(base_url, token, timeout=timeout, max_retries=max_retries,
                         backoff=backoff, backoff_max=backoff_max, poll_interval=poll_interval,
                         headers=headers, http=self._http, random=random)

    async def aclose(self) -> None:
        """Close the HTTP client made by this client (an injected one stays open)."""
        if self._own:
            await self._http.aclose()

    async def __aenter__(self) -> "AsyncClient":
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.aclose()

    # ------------------------------------------------------------------ the driver
    async def _perform(self, effect: Any, streams: dict) -> Any:
        if isinstance(effect, Send):
            response = await self._http.send(effect.request, stream=True)
            if effect.stream and response.status_code < 400:
                streams[id(response)] = (response, response.aiter_bytes())
            else:
                try:
                    await response.aread()
                finally:
                    await response.aclose()
            return response
        if isinstance(effect, Read):
            entry = streams.get(id(effect.response))
            if entry is not None:
                while True:
                    try:
                        chunk = await entry[1].__anext__()
                    except StopAsyncIteration:
                        break
                    if chunk:
                        return chunk
            return b""
        if isinstance(effect, Close):
            entry = streams.pop(id(effect.response), None)
            if entry is not None:
                await entry[0].aclose()
            return None
        if isinstance(effect, Sleep):
            result = self._sleep(effect.seconds)
            if inspect.isawaitable(result):
                await result
            return None
        raise TypeError(f"unknown effect {effect!r}")

    async def _steps(self, op: Op, result: list):
        """Run ``op``, yielding what it emits; its value is appended to ``result``."""
        streams: dict = {}
        value: Any = None
        error: BaseException | None = None
        try:
            while True:
                try:
                    effect = op.throw(error) if error is not None else op.send(value)
                except StopIteration as stop:
                    result.append(stop.value)
                    return
                value, error = None, None
                try:
                    if isinstance(effect, Emit):
                        yield effect.value
                    else:
                        value = await self._perform(effect, streams)
                except Exception as exc:  # handed to the operation, which may handle it
                    error = exc
        finally:
            op.close()
            for response, _ in streams.values():
                await response.aclose()

    async def _run(self, op: Op) -> Any:
        result: list = []
        async for _ in self._steps(op, result):
            pass
        return result[0]

    async def _iterate(self, op: Op) -> Any:
        async for item in self._steps(op, []):
            yield item
