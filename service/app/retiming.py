"""Keyframe retiming over HTTP (``POST /v1/models/{model_id}/retime``): bermano2014 §6.2
through the model's :meth:`~service.methods.shape_space.model.ShapeSpaceModel.retime`.

A request names two or more keyframes — vertices on the actor's topology, on a registered
input rig's (``rig``, carried to the actor's by its registration), or frames of the actor's
clips — and the output length m; :func:`service.methods.shape_space.temporal.retime_keyframes`
places and retimes them.
"""

from __future__ import annotations

from dataclasses import dataclass
import numpy as np
from pydantic import ValidationError

from models_store import registry
from service.store import actors as actor_store
from service.errors import PayloadTooLarge, invalid_fields
from service.app.input_rigs import LoadedRig, load_rig
from service.app.schemas import ClipFrameRef, RetimeBody
from service.app.services import LoadedModel, Services
from service.app.synthesis import Expected
from service.app.uploads import NPZ_TYPES, ArraySpec, NpzUpload, npz_limit, parse_json
from service.app.validation import check_finite_frames
from service.config import Settings
from service.methods.inputs import InvalidInput

#: model kinds whose models retime keyframes (they have ``retime(keyframes, length, extend)``)
RETIME_KINDS = ("shape_space",)
#: arrays of an NPZ retime request
KEYFRAME_SPECS = {"keyframes": ArraySpec(("K", "V", 3), "fiu")}


@dataclass(frozen=True)
class ClipFrame:
    """A keyframe given as frame ``frame`` (0-based) of the actor's clip ``clip_id``."""

    clip_id: str
    frame: int


@dataclass(frozen=True)
class RetimeRequest:
    """A parsed retime request.

    Attributes
    ----------
    keyframes : tuple of (v,3) float64 arrays or ClipFrame
                        vertices (on the rig's topology if ``rig``, else the actor's) or
                        clip frames (always on the actor's topology)
    length : int        m, output frames (keyframes included)
    extend : bool       extend each matched database subsequence to the full motion
    rig : str or None   the input rig the vertex keyframes are on
    """

    keyframes: tuple[np.ndarray | ClipFrame, ...]
    length: int
    extend: bool
    rig: str | None


def check_retime_kind(loaded: LoadedModel) -> None:
    """422 naming the kinds that retime unless ``loaded`` is one of them."""
    if loaded.kind.name not in RETIME_KINDS:
        raise InvalidInput(f"a {loaded.kind.name} model cannot retime keyframes; retiming is "
                           f"supported by the kinds {', '.join(RETIME_KINDS)}")


def check_retime_size(keyframes: int, length: int, settings: Settings) -> None:
    """413 when the keyframes K or the output length m exceed ``max_frames_per_request``;
    422 unless 2 ≤ K ≤ m."""
    limit = settings.max_frames_per_request
    for count, what in ((keyframes, "keyframes"), (length, "output frames (length)")):
        if count > limit:
            raise PayloadTooLarge(f"{count} {what} in one retime request, more than the limit "
                                  f"of {limit} frames (max_frames_per_request)")
    if keyframes < 2:
        raise InvalidInput(f"retiming needs two or more keyframes, got {keyframes}")
    if length < keyframes:
        raise InvalidInput(f"length {length} is less than the {keyframes} keyframes; the "
                           "output holds every keyframe, so length must be at least that")


def parse_retime_request(kind: str, data: bytes, settings: Settings, *, length: int | None,
                         extend: bool | None, rig: str | None) -> RetimeRequest:
    """A retime request from its body (``kind`` is the media type) and query parameters.

    JSON: :class:`~service.app.schemas.RetimeBody` (its ``length`` and
    ``extend_to_full_motion`` are the body's; ``rig`` may be given in the body or the query,
    not differently in both). NPZ: ``keyframes`` (K,v,3) with ``length``,
    ``extend_to_full_motion`` and ``rig`` from the query; K and m are checked against the
    limits before the array is read.
    """
    if kind in NPZ_TYPES:
        upload = NpzUpload(data, KEYFRAME_SPECS, npz_limit(settings), what="retime request")
        if length is None:
            raise InvalidInput("an .npz retime request needs the query parameter 'length' "
                               "(the number of output frames)")
        check_retime_size(upload.dims["K"], length, settings)
        keyframes = upload.load()["keyframes"].astype(np.float64)
        return RetimeRequest(tuple(keyframes), int(length), bool(extend), rig)
    try:
        body = RetimeBody.model_validate(parse_json(data))
    except ValidationError as error:
        raise invalid_fields(error) from None
    if rig is not None and body.rig is not None and rig != body.rig:
        raise InvalidInput(f"rig is {body.rig!r} in the body but {rig!r} in the query; give "
                           "it once")
    check_retime_size(len(body.keyframes), body.length, settings)
    keyframes = tuple(ClipFrame(k.clip_id, k.frame) if isinstance(k, ClipFrameRef)
                      else np.asarray(k, dtype=np.float64).reshape(-1, 3)
                      for k in body.keyframes)
    return RetimeRequest(keyframes, body.length, body.extend_to_full_motion, body.rig or rig)


def resolve_keyframes(services: Services, loaded: LoadedModel,
                      request: RetimeRequest) -> np.ndarray:
    """The request's keyframes as (K,n,3) float64 on the model's topology (n vertices).

    Vertex keyframes are checked (count, finite) and, with a rig, propagated through its
    registration; clip frames are read from the actor's clips.

    Raises
    ------
    NotFound       an unknown clip (or one of another actor), an unknown rig
    Conflict       a rig that is not ready
    InvalidInput   a wrong vertex count, a non-finite vertex, a frame out of range
    """
    n = loaded.model.n_vertices
    expected = Expected(loaded.id, loaded.kind.name, "vertices", n)
    rig: LoadedRig | None = None
    if request.rig is not None:
        rig = load_rig(services, loaded.actor_id, request.rig, n)
        expected = rig.expected(expected)
    out = np.empty((len(request.keyframes), n, 3))
    given = [k for k, key in enumerate(request.keyframes) if not isinstance(key, ClipFrame)]
    for k in given:
        frame = request.keyframes[k][None]
        try:
            expected.check(frame)
        except InvalidInput as error:
            raise InvalidInput(f"keyframe {k}: {error}") from None
        check_finite_frames(frame, f"keyframe {k}", "vertex")
    if given:
        stack = np.stack([request.keyframes[k] for k in given])
        out[given] = rig.propagate(stack) if rig is not None else stack
    refs = {k: key for k, key in enumerate(request.keyframes) if isinstance(key, ClipFrame)}
    for clip_id in dict.fromkeys(ref.clip_id for ref in refs.values()):
        wanted = {k: ref.frame for k, ref in refs.items() if ref.clip_id == clip_id}
        out[list(wanted)] = _clip_frames(services, loaded.actor_id, clip_id, wanted)
    return out


def _clip_frames(services: Services, actor_id: str, clip_id: str,
                 wanted: dict[int, int]) -> np.ndarray:
    """Vertices (len(wanted),n,3) float64 of frames ``wanted`` (keyframe → frame) of the
    actor's clip ``clip_id``; NotFound for another actor's clip, 422 for a frame out of
    range."""
    with services.session() as session:
        row = registry.get_clip(session, clip_id, actor_id)
        for k, frame in wanted.items():
            if not 0 <= frame < row.frames:
                raise InvalidInput(f"keyframe {k} refers to frame {frame} of clip {clip_id!r}, "
                                   f"which has {row.frames} frames (0 to {row.frames - 1})")
        data = registry.read_clip(session, services.blobs, clip_id)
    vertices = actor_store.clip_from_blob(data, row.name or row.id).vertices
    return vertices[list(wanted.values())]


__all__ = ["RETIME_KINDS", "ClipFrame", "RetimeRequest", "check_retime_kind",
           "parse_retime_request", "resolve_keyframes"]
