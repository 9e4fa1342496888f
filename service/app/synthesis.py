"""Synchronous synthesis and synthesis-job inputs: parsing the frames, running a loaded
model, and encoding its outputs as NPZ, OBJ or EXR (API.md "Synthesis").

A request's frames are markers (F,M,3) for marker-driven kinds (``/synthesize``) or vertices
(F,V,3) for mesh-driven kinds (``/enhance``); the model's ``synthesize(frames, outputs,
clamp)`` returns the arrays of API.md (``vertices``, ``vertices_detailed``, ``faces``, maps).
"""

from __future__ import annotations

import contextlib
import io
import threading
import time
from dataclasses import dataclass, replace
from typing import Iterator, Sequence

import numpy as np
from pydantic import ValidationError

from service.errors import NotAcceptable, PayloadTooLarge, Unavailable, invalid_fields
from service.app.limits import (RETRY_AFTER_SECONDS, SYNTHESIS_QUEUE_DEPTH,
                                SYNTHESIS_WAIT_SECONDS)
from service.app.marker_units import MarkerReference
from service.app.threads import SynthesisPool
from service.app.metrics import Metrics
from service.app.schemas import SynthesizeBody
from service.methods.kinds import takes
from service.methods.outputs import DEFAULT_OUTPUTS, MAP_OUTPUTS, check_outputs
from service.app.services import LoadedModel
from service.app.uploads import (JSON_TYPE, MARKER_FILE_TYPES, NPZ_TYPES, ArraySpec, NpzUpload,
                                 npz_limit, markers_in_layout_order,
                                 parse_json, read_marker_file)
from service.app.validation import check_finite_frames
from service.config import Settings
from service.geometry.uv_raster import resample_map
from service.io.exr import write_map
from service.io.markers import read_markers_json
from service.io.mesh import Mesh, write_obj
from service.io.npz import NpzParts, npz_bytes, npz_parts
from service.methods.inputs import InvalidInput

NPZ = "application/x-npz"
OBJ = "model/obj"
EXR = "image/x-exr"
#: response media types of /synthesize, the first the default
RESPONSE_TYPES = (NPZ, OBJ, EXR)


# ---------------------------------------------------------------------------- requests
@dataclass(frozen=True)
class SynthesisInput:
    """What to synthesize.

    Attributes
    ----------
    frames : (F,N,3) float64      markers (N = M, NaN occluded) or vertices (N = V)
    outputs : tuple of str        a subset of :data:`~service.methods.outputs.OUTPUTS`
    map_resolution : int or None  resample maps to this side (None: the model's)
    clamp : bool                  limit extrapolation beyond the training data
    fps : float or None           frame rate of the input, when it has one
    """

    frames: np.ndarray
    outputs: tuple[str, ...]
    map_resolution: int | None = None
    clamp: bool = True
    fps: float | None = None


def parse_outputs(value: str | Sequence[str] | None) -> tuple[str, ...] | None:
    """``outputs`` from a query (comma-separated and/or repeated), validated; None if absent."""
    if value is None:
        return None
    items = [value] if isinstance(value, str) else list(value)
    names = [part.strip() for item in items for part in item.split(",") if part.strip()]
    if not names:
        return None
    return check_outputs(names)


@dataclass(frozen=True)
class Expected:
    """What a model takes as frames, for checking a request before any work.

    Attributes
    ----------
    model_id : str
    kind : str           the model's kind
    key : str            ``"markers"`` (marker-driven kinds) or ``"vertices"`` (mesh-driven)
    count : int or None  markers (or vertices) per frame, None if unknown
    owner : str or None  whose topology the frames are on when it is not the model's, for
                         messages (e.g. ``"input rig 'lod2'"``)
    """

    model_id: str
    kind: str
    key: str
    count: int | None
    owner: str | None = None
    markers: int | None = None
    #: the actor's layout on its neutral: marker frames are refused in the wrong unit
    reference: MarkerReference | None = None

    @classmethod
    def of(cls, loaded: LoadedModel) -> "Expected":
        """From a loaded model (its ``n_markers`` / ``n_vertices``)."""
        key = "markers" if loaded.kind.input == "markers" else "vertices"
        count = getattr(loaded.model, "n_markers" if key == "markers" else "n_vertices", None)
        markers = getattr(loaded.model, "n_markers", 0) if key == "vertices" else 0
        return cls(loaded.id, loaded.kind.name, key, count, markers=markers or None)

    def as_markers(self) -> "Expected":
        """What a mesh-driven model that also takes markers expects of marker frames."""
        return replace(self, key="markers", count=self.markers, owner=None)

    def check(self, frames: np.ndarray) -> None:
        """422 ``"model expects 150 markers, got 149"`` (or ``"input rig 'lod2' has 4012
        vertices, the frames have 4000"``) unless frames is (F, count, 3); for markers, 422
        naming the likely unit when they are in another unit than the actor's layout
        (:mod:`service.app.marker_units`)."""
        if self.count is None or frames.shape[1] == self.count:
            if self.key == "markers" and self.reference is not None:
                self.reference.check(frames)
            return
        if self.owner is None:
            raise InvalidInput(f"model expects {self.count} {self.key}, got {frames.shape[1]}")
        raise InvalidInput(f"{self.owner} has {self.count} {self.key}, the frames have "
                           f"{frames.shape[1]} (send {self.key} (F,{self.count},3) on its "
                           "topology)")

    def element(self) -> str:
        """One of the frames' elements, for messages: "marker" or "vertex"."""
        return "marker" if self.key == "markers" else "vertex"


def check_frames(frames: int, settings: Settings, model_id: str) -> None:
    """413 naming the limit when a synchronous request carries too many frames."""
    limit = settings.max_frames_per_request
    if frames > limit:
        raise PayloadTooLarge(
            f"{frames} frames in one request, more than the limit of {limit} frames "
            f"(max_frames_per_request); submit a synthesis job for longer performances "
            f"(POST /v1/models/{model_id}/synthesis-jobs)")


def _frame_array(key: str) -> dict[str, ArraySpec]:
    other = "vertices" if key == "markers" else "markers"
    return {key: ArraySpec(("F", "N", 3), "fiu"), other: ArraySpec(("F", "O", 3), "fiu", False),
            "fps": ArraySpec((), "fiu", False)}


def _json_markers(markers: list) -> np.ndarray:
    """(F,M,3) float64 from JSON frames of ``[x,y,z]`` or null (NaN: occluded)."""
    count = len(markers[0])
    for f, frame in enumerate(markers):
        if len(frame) != count:
            raise InvalidInput(f"frame {f} has {len(frame)} markers, frame 0 has {count}")
        for m, marker in enumerate(frame):
            if marker is not None and len(marker) != 3:
                raise InvalidInput(f"frame {f} marker {m} has {len(marker)} coordinates, "
                                   "expected [x, y, z] or null")
    rows = [[(None, None, None) if m is None else m for m in frame] for frame in markers]
    array = np.array(rows, dtype=np.float64).reshape(len(markers), count, 3)
    return np.where(np.isnan(array).any(axis=2, keepdims=True), np.nan, array)


def parse_synthesis_request(kind: str, data: bytes, expected: Expected, settings: Settings,
                            query_outputs: tuple[str, ...] | None, clamp: bool) -> SynthesisInput:
    """A synchronous request's frames and options (``kind`` is the body's media type).

    NPZ: the frames under ``markers`` (or ``vertices`` for a mesh-driven model). JSON
    (marker-driven models): :class:`~service.app.schemas.SynthesizeBody`. The frame count
    is checked against ``max_frames_per_request`` before the arrays are read.
    """
    key = expected.key
    map_resolution = None
    outputs = query_outputs
    if kind in NPZ_TYPES:
        spec = _frame_array(key)
        if key == "vertices" and expected.markers:          # /enhance: vertices, or markers instead
            spec["vertices"] = replace(spec["vertices"], required=False)
        upload = NpzUpload(data, spec, npz_limit(settings), what="request")
        if "F" not in upload.dims:
            raise InvalidInput(f"the request has neither 'vertices' (F,{expected.count},3) nor "
                               f"'markers' (F,{expected.markers},3)")
        check_frames(upload.dims["F"], settings, expected.model_id)
        arrays = upload.load()
        if key not in arrays:
            expected, key = expected.as_markers(), "markers"
        frames, fps = arrays[key].astype(np.float64), arrays.get("fps")
    else:
        if key != "markers":
            raise InvalidInput(f"a {expected.kind} model takes vertices: send an .npz "
                               "with 'vertices' (F,V,3)")
        body = parse_json(data)
        try:
            request = SynthesizeBody.model_validate(body)
        except ValidationError as error:
            raise invalid_fields(error) from None
        check_frames(len(request.markers), settings, expected.model_id)
        frames, fps = _json_markers(request.markers), None
        outputs = tuple(dict.fromkeys(request.outputs)) if request.outputs else outputs
        map_resolution, clamp = request.map_resolution, request.clamp
    if len(frames) == 0:
        raise InvalidInput(f"the request has no frames ('{key}' is empty)")
    if map_resolution is not None and map_resolution > settings.max_map_resolution:
        raise PayloadTooLarge(f"map_resolution {map_resolution} is more than the limit of "
                              f"{settings.max_map_resolution} (max_map_resolution)")
    check_finite_frames(frames, "request", expected.element(), allow_nan=key == "markers")
    expected.check(frames)
    return SynthesisInput(frames, outputs or DEFAULT_OUTPUTS, map_resolution, clamp,
                          None if fps is None else float(fps))


# ---------------------------------------------------------------------------- running
class Synthesizer:
    """Runs synchronous syntheses in the process's synthesis slots (``pool``, shared with the
    gRPC streams: :class:`~service.app.threads.SynthesisPool`); a request finding every slot
    busy waits for one up to ``wait_seconds`` (at most ``max_queue`` requests wait; beyond
    that, or when the wait runs out, a 503 with ``Retry-After``), and records frames, rate,
    the running count (HTTP and gRPC) and the queue depth (HTTP) in the metrics.

    Parameters
    ----------
    metrics : Metrics
    limit : int            syntheses at once when no ``pool`` is given
                           (``max_concurrent_syntheses``; default: one per CPU core — a
                           synthesis is CPU-bound)
    wait_seconds : float   longest wait for a slot (``synthesis_queue_seconds``)
    max_queue : int        most requests waiting at once (``synthesis_queue_depth``)
    pool : SynthesisPool or None   the process's slots (None: a pool of ``limit`` of its own)
    """

    def __init__(self, metrics: Metrics, limit: int | None = None,
                 wait_seconds: float = SYNTHESIS_WAIT_SECONDS,
                 max_queue: int = SYNTHESIS_QUEUE_DEPTH, pool: SynthesisPool | None = None):
        #: the synthesis slots this synthesizer takes from
        self.pool = pool if pool is not None else SynthesisPool(limit)
        self.limit = self.pool.limit
        self.wait_seconds, self.max_queue = float(wait_seconds), int(max_queue)
        self._metrics = metrics
        metrics.synthesis_running.set_function(lambda: self.pool.running)
        self._lock = threading.Lock()
        self.waiting = 0

    @property
    def running(self) -> int:
        """Syntheses running now in the pool (this one's and any other user's)."""
        return self.pool.running

    def _count(self, waiting: int) -> None:
        with self._lock:
            self.waiting += waiting
            self._metrics.synthesis_queue_depth.set(self.waiting)

    @contextlib.contextmanager
    def slot(self, kind: str, frames: int) -> Iterator[None]:
        """Hold one synthesis slot while the block runs (waiting for one as the class
        docstring says) and record ``frames`` output frames of a ``kind`` model and the
        time taken."""
        if not self.pool.acquire(blocking=False):
            with self._lock:
                full = self.waiting >= self.max_queue
            if full:
                raise Unavailable(f"every synthesis slot is busy and {self.waiting} requests "
                                  f"are waiting (at most {self.max_queue}); retry shortly, or "
                                  "submit a synthesis job", retry_after=RETRY_AFTER_SECONDS)
            self._count(waiting=1)
            try:
                got = self.pool.acquire(timeout=self.wait_seconds)
            finally:
                self._count(waiting=-1)
            if not got:
                raise Unavailable(f"every synthesis slot stayed busy (waited "
                                  f"{self.wait_seconds:g} s); retry shortly, or submit a "
                                  "synthesis job", retry_after=RETRY_AFTER_SECONDS)
        try:
            start = time.perf_counter()
            with self.pool.kernel_share():
                yield
            seconds = time.perf_counter() - start
        finally:
            self.pool.release()
        self._metrics.observe_synthesis(kind, frames, seconds)

    def run(self, loaded: LoadedModel, request: SynthesisInput, half: bool = False) -> dict[str, np.ndarray]:
        """The model's outputs for ``request``, maps resampled to ``map_resolution``. With
        ``half`` (an NPZ answer of ``half=true``) a model whose ``synthesize`` takes ``half``
        writes its maps as float16 itself (issue 23: NumPy's rounding of its float32 maps bit
        for bit, without the float32 maps and the conversion); others, and resampled maps,
        stay float32 and are converted by :func:`encode`."""
        options = {"half": True} if half and request.map_resolution is None and takes(loaded.model, "half") else {}
        with self.slot(loaded.kind.name, len(request.frames)):
            result = loaded.model.synthesize(request.frames, outputs=list(request.outputs),
                                             clamp=request.clamp, **options)
        if request.map_resolution is not None:
            result = resample_maps(result, request.map_resolution)
        return result


def resample_maps(result: dict[str, np.ndarray], side: int) -> dict[str, np.ndarray]:
    """The maps of ``result`` resampled to ``side``² texels
    (:func:`~service.geometry.uv_raster.resample_map`; normal maps kept unit length)."""
    out = dict(result)
    for name in MAP_OUTPUTS:
        maps = result.get(name)
        if maps is not None and maps.ndim < 3:
            raise InvalidInput(_per_vertex(name, maps, "map_resolution does not apply"))
        if maps is not None and maps.shape[1] != side:
            out[name] = resample_map(maps, side, unit=name == "normal_map")
    return out


# ---------------------------------------------------------------------------- responses
def negotiate(accept: str | None) -> str:
    """The response media type for an ``Accept`` header: the acceptable type of highest
    quality among :data:`RESPONSE_TYPES` (``*/*`` and ``application/*`` give NPZ)."""
    if not accept or not accept.strip():
        return NPZ
    ranked = []
    for order, item in enumerate(accept.split(",")):
        kind, *params = [p.strip() for p in item.split(";")]
        q = 1.0
        for param in params:
            name, _, value = param.partition("=")
            if name.strip().lower() == "q":
                try:
                    q = float(value)
                except ValueError:
                    q = 0.0
        ranked.append((-q, order, kind.lower()))
    for negative_q, _, kind in sorted(ranked):
        if negative_q >= 0:
            continue
        if kind in RESPONSE_TYPES:
            return kind
        if kind in ("*/*", "application/*", "application/octet-stream"):
            return NPZ
        if kind == "model/*":
            return OBJ
        if kind == "image/*":
            return EXR
    raise NotAcceptable(f"cannot answer with any of '{accept[:200]}'; this route returns "
                        f"{', '.join(RESPONSE_TYPES)}")


def check_response_request(media: str, request: SynthesisInput) -> None:
    """422 unless the request can be answered as ``media`` (OBJ and EXR hold one frame; EXR
    one map)."""
    if media == NPZ:
        return
    if len(request.frames) != 1:
        raise InvalidInput(f"Accept: {media} returns one frame; the request has "
                           f"{len(request.frames)} (use application/x-npz for several)")
    if media == OBJ and not {"mesh", "mesh_detailed"} & set(request.outputs):
        raise InvalidInput("Accept: model/obj needs outputs 'mesh' or 'mesh_detailed'")
    if media == EXR:
        maps = [o for o in request.outputs if o in MAP_OUTPUTS]
        if len(maps) != 1 or len(request.outputs) != 1:
            raise InvalidInput(f"Accept: image/x-exr needs outputs=<one map of "
                               f"{list(MAP_OUTPUTS)}>, got {list(request.outputs)}")


#: the arrays of a model's topology (``GET /v1/models/{id}/topology``), which a synthesis
#: response leaves out with ``topology=false``
TOPOLOGY_KEYS = ("faces", "uv", "uv_faces")
#: the bound on a map value sent in half precision (``half=true``), relative and absolute:
#: IEEE 754 binary16 rounds to nearest with an 11-bit significand, so a normal value v comes
#: back as v(1 + e), |e| <= 2**-11; below 2**-14 (subnormals) the spacing is 2**-24, so the
#: error is at most 2**-25. Beyond 65504 a value overflows to +-inf.
HALF_RELATIVE_ERROR = 2.0 ** -11
HALF_ABSOLUTE_ERROR = 2.0 ** -25


def npz_arrays(result: dict[str, np.ndarray], *, topology: bool = True) -> dict[str, np.ndarray]:
    """The arrays of an NPZ synthesis response: ``topology=False`` leaves out
    :data:`TOPOLOGY_KEYS` (the client has them from the topology resource); ``half=true``
    then stores :func:`half_maps` of them as float16 (:func:`encode`)."""
    return {k: v for k, v in result.items() if topology or k not in TOPOLOGY_KEYS}


def half_maps(arrays: dict[str, np.ndarray]) -> list[str]:
    """The names in ``arrays`` that ``half=true`` stores as float16: the UV-space maps
    (:data:`~service.methods.outputs.MAP_OUTPUTS` of ndim >= 3; meshes stay float32: a
    half-precision position of a 100 mm face would be off by up to 0.03 mm). Beyond the half
    range is ±inf, as in EXR; NumPy's rounding bit for bit (:func:`service.io.half.to_float16`)."""
    return [name for name in MAP_OUTPUTS if name in arrays and np.ndim(arrays[name]) >= 3]


def encode(media: str, result: dict[str, np.ndarray], loaded: LoadedModel,
           request: SynthesisInput, half: bool = False, topology: bool = True
           ) -> bytes | NpzParts:
    """The response body: NPZ of the arrays (:func:`npz_arrays`: ``half`` maps as float16,
    ``topology=False`` without the triangles) as the pieces it is sent in
    (:func:`service.io.npz.npz_parts`: the result's arrays not copied where they are stored
    as they are, others converted once), the frame's OBJ
    (detailed vertices if asked, with the model's UVs), or the one map as EXR (``half``:
    16-bit floats)."""
    if media == NPZ:
        arrays = npz_arrays(result, topology=topology)
        return npz_parts(arrays, {name: np.float16 for name in half_maps(arrays)} if half else None)
    if media == OBJ:
        key = "vertices_detailed" if "mesh_detailed" in request.outputs else "vertices"
        model = loaded.model
        uv, uv_faces = getattr(model, "uv", None), getattr(model, "uv_faces", None)
        mesh = Mesh(result[key][0], result["faces"], uv, uv_faces if uv is not None else None)
        buffer = io.BytesIO()
        write_obj(buffer, mesh, dtype=np.float32)
        return buffer.getvalue()
    values = result[request.outputs[0]]
    if values.ndim < 3:
        raise InvalidInput(_per_vertex(request.outputs[0], values, "ask for application/x-npz"))
    buffer = io.BytesIO()
    write_map(buffer, values[0], half=half)
    return buffer.getvalue()


def _per_vertex(name: str, values: np.ndarray, advice: str) -> str:
    """The message for a map output that a kind (e.g. shape_space) gives per vertex."""
    return (f"this model gives '{name}' per vertex, shape {tuple(values.shape)}, not as a "
            f"UV map (F,H,W); {advice}")


# ---------------------------------------------------------------------------- job inputs
#: media types a synthesis job takes as its performance
JOB_INPUT_TYPES = NPZ_TYPES + (JSON_TYPE, *MARKER_FILE_TYPES)


def parse_job_input(kind: str, data: bytes, expected: Expected, settings: Settings,
                    names: Sequence[str] | None, filename: str | None = None
                    ) -> tuple[bytes, int]:
    """A synthesis job's performance as a canonical NPZ (``markers`` (F,M,3) float32 or
    ``vertices`` (F,V,3) float32, optional ``fps``) and its frame count.

    ``kind`` is the media type, or ``multipart/form-data`` with ``filename`` naming the
    file's type by suffix (.npz, .json, .c3d, .trc, .csv). Marker files with names are
    matched to the layout's ``names``.
    """
    key = expected.key
    suffix = ("." + filename.rsplit(".", 1)[-1].lower()) if filename and "." in filename else ""
    fps = None
    if kind in NPZ_TYPES or suffix == ".npz":
        upload = NpzUpload(data, _frame_array(key), npz_limit(settings), what="performance")
        arrays = upload.load()
        frames = arrays[key]
        fps = arrays.get("fps")
    elif key != "markers":
        raise InvalidInput(f"a {expected.kind} model takes vertices: send an .npz with "
                           "'vertices' (F,V,3)")
    elif kind == JSON_TYPE or suffix == ".json":
        parse_json(data)
        sequence = read_markers_json(data)
        frames = (sequence.positions if names is None else
                  markers_in_layout_order(sequence, names, "the JSON markers"))
        fps = sequence.fps
    else:
        suffix = MARKER_FILE_TYPES.get(kind, suffix)
        if names is None:
            raise InvalidInput("the actor has no marker layout to match the file's markers to")
        frames, fps = read_marker_file(data, suffix, names)
    frames = np.asarray(frames, dtype=np.float32)
    if len(frames) == 0:
        raise InvalidInput("the performance has no frames")
    check_finite_frames(frames, "performance", expected.element(), allow_nan=key == "markers")
    expected.check(frames)
    arrays = {key: frames}
    if fps is not None:
        arrays["fps"] = np.float64(fps)
    return npz_bytes(**arrays), len(frames)
