"""The canonical stored forms of an actor's neutral, marker layout and clips, and their loaders.

The API parses whatever a user uploads (OBJ, NPZ, marker files, per-frame OBJs), validates
it and stores one canonical blob per resource, written by the functions here; the jobs read
those blobs back into the method inputs :class:`~service.methods.inputs.ActorData` and
:class:`~service.methods.inputs.Clip`. The formats:

neutral (NPZ)
    ``vertices`` (n,3) float64 · ``faces`` (m,3) int64 · ``uv`` (K,2) float64 ·
    ``uv_faces`` (m,3) int64 (per-corner UV indices; ``faces`` when the UVs are per vertex) ·
    optional ``region_<name>`` (n,) bool named vertex sets (per-region training metrics)
marker layout (JSON)
    ``{"names": [M str], "triangle": [M int], "barycentric": [[b0, b1, b2], ...]}``: every
    marker already resolved to a surface point of the neutral (the API snaps vertex and
    position placements before storing)
clip (NPZ)
    ``vertices`` (F,n,3) float32 · ``markers`` (F,M,3) float32, NaN where occluded ·
    optional ``displacement`` (F,H,H) float32 · optional ``albedo`` (F,Ha,Ha,3) float32
    linear RGB · ``fps`` () float64

The clip's ``displacement`` is the fine detail along the normal **relative to the clip's
own** ``vertices`` (a scan delivered as mesh + displacement map, :class:`Clip`'s meaning),
so the loader passes it through. The sample actor's files hold it relative to their medium
surface instead; :func:`service.samples.uploads.sample_actor_uploads` converts them with
:func:`service.samples.dataset.load_clip`, the one place that conversion lives.

Writers validate what they are given with the one array dialect of :mod:`service.io.arrays`
and raise :class:`InvalidInput` naming the problem;
loaders raise :class:`InvalidInput` for a missing neutral or layout, a blob that is not in
the canonical form, or a clip that does not match the actor.
"""

from __future__ import annotations

import io
import json
import re
from typing import Any, BinaryIO, Mapping, Sequence

import numpy as np
from sqlalchemy.orm import Session

from models_store import registry
from models_store.blobs import BlobStore
from models_store.errors import NotFound
from service.geometry.marker_layout import BARYCENTRIC_TOLERANCE  # the layout readers' (1e-4)
from service.io.arrays import OCCLUDED_NOTE, Axes, as_array, check_finite, check_indices, checked
from service.io.npz import npz_arrays, npz_bytes, write_npz
from service.methods.inputs import ActorData, Clip, InvalidInput, check_clips

#: prefix of the neutral NPZ's region keys (``region_<name>``)
REGION_PREFIX = "region_"
#: allowed region names
_REGION_NAME = re.compile(r"[A-Za-z0-9_]{1,64}")
#: media types of the canonical blobs
NPZ_MEDIA_TYPE = "application/x-npz"
LAYOUT_MEDIA_TYPE = "application/json"


# ---------------------------------------------------------------------------- helpers
def open_npz(data: bytes, what: str) -> Mapping[str, np.ndarray]:
    """The arrays of an NPZ blob (no pickles), or InvalidInput."""
    try:
        return npz_arrays(data)
    except (ValueError, OSError, EOFError) as error:
        raise InvalidInput(f"{what} is not a readable .npz: {error}") from None


def neutral_arrays(neutral: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n,3) and faces (m,3) of a stored canonical neutral (:func:`neutral_npz`)."""
    arrays = npz_arrays(neutral)
    return arrays["vertices"], arrays["faces"]


# ---------------------------------------------------------------------------- writers
def neutral_npz(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray,
                uv_faces: np.ndarray | None = None,
                regions: Mapping[str, np.ndarray] | None = None) -> bytes:
    """The canonical neutral blob.

    Parameters
    ----------
    vertices : (n,3) float      the high-resolution neutral, actor's unit
    faces : (m,3) int           triangles
    uv : (K,2) float            UVs in the unit tile (per vertex, K = n, if uv_faces is None)
    uv_faces : (m,3) int        per-corner UV indices (default: ``faces``)
    regions : name → (n,) bool  optional named vertex sets

    Returns
    -------
    bytes   NPZ (see the module docstring)
    """
    axes = Axes()
    V = as_array(vertices, "neutral vertices", ("V", 3), "fiu", np.float64, axes=axes)
    check_finite(V, "neutral", ("vertex",))
    n = len(V)
    F = as_array(faces, "neutral faces", ("T", 3), "iu", np.int64, axes=axes)
    check_indices(F, n, "face", "vertex", "neutral", "vertices")
    UV = as_array(uv, "neutral uv", ("K", 2), "fiu", np.float64)
    check_finite(UV, "neutral", ("uv",))
    if uv_faces is None:
        if len(UV) != n:
            raise InvalidInput(f"per-vertex uv must have one row per vertex ({n}), got {len(UV)}; "
                               "give uv_faces for per-corner UVs")
        uv_faces = F
    UVF = as_array(uv_faces, "neutral uv_faces", ("T", 3), "iu", np.int64, axes=axes)
    check_indices(UVF, len(UV), "uv face", "uv", "neutral", "uv coordinates")
    arrays = {"vertices": V, "faces": F, "uv": UV, "uv_faces": UVF}
    for name, mask in (regions or {}).items():
        if not _REGION_NAME.fullmatch(name):
            raise InvalidInput(f"region name {name!r} must be 1-64 characters of [A-Za-z0-9_]")
        arrays[REGION_PREFIX + name] = as_array(mask, f"region '{name}'", ("V",), "biu", bool,
                                                axes=axes)
    return npz_bytes(**arrays)


def layout_json(names: Sequence[str], triangle: np.ndarray, barycentric: np.ndarray) -> bytes:
    """The canonical marker-layout blob: markers as surface points of the neutral.

    Parameters
    ----------
    names : M str               unique marker names, in layout (and clip column) order
    triangle : (M,) int         triangle of the neutral each marker lies in
    barycentric : (M,3) float   barycentric coordinates (non-negative, summing to 1)
    """
    names = [str(name) for name in names]
    M = len(names)
    if M == 0:
        raise InvalidInput("a marker layout needs at least one marker")
    seen: set[str] = set()
    for name in names:
        if name in seen:
            raise InvalidInput(f"marker name '{name}' appears more than once")
        seen.add(name)
    tri = as_array(triangle, "marker triangles", ("M",), "iu", np.int64, axes=Axes(M=M))
    bary = as_array(barycentric, "marker barycentric coordinates", ("M", 3), "fiu", np.float64,
                    axes=Axes(M=M))
    check_finite(bary, "the layout", ("marker",))
    bad = np.flatnonzero((bary < -BARYCENTRIC_TOLERANCE).any(axis=1)
                         | (np.abs(bary.sum(axis=1) - 1) > BARYCENTRIC_TOLERANCE))
    if len(bad):
        raise InvalidInput(f"marker '{names[bad[0]]}' has barycentric {bary[bad[0]].tolist()}; "
                           "they must be non-negative and sum to 1")
    return json.dumps({"names": names, "triangle": tri.astype(np.int64).tolist(),
                       "barycentric": bary.tolist()}).encode()


def clip_npz(vertices: np.ndarray, markers: np.ndarray, *, displacement: np.ndarray | None = None,
             albedo: np.ndarray | None = None, fps: float = 30.0) -> bytes:
    """The canonical clip blob, in memory: :func:`write_clip` into bytes."""
    buffer = io.BytesIO()
    write_clip(buffer, vertices, markers, displacement=displacement, albedo=albedo, fps=fps)
    return buffer.getvalue()


def write_clip(target: BinaryIO, vertices: Any, markers: Any, *, displacement: Any = None,
               albedo: Any = None, fps: float = 30.0) -> None:
    """Validate a clip and write its canonical blob to ``target``, a block of frames at a time.

    The arrays may be in memory or still in the uploaded archive (anything
    :func:`service.io.arrays.blocks` reads, e.g. :class:`service.io.npz.NpyMember`): they
    are checked and cast to float32 block by block, so a clip of hundreds of MiB is written
    holding a few MiB of it (issue 16, defect 11).

    Parameters
    ----------
    target : seekable binary file
    vertices : (F,n,3) float        high-resolution frames, in vertex correspondence with
                                    the neutral
    markers : (F,M,3) float         markers in layout order, NaN where occluded
    displacement : (F,H,W) float    fine detail along the normal relative to ``vertices``
    albedo : (F,H,W,3) float        linear RGB
    fps : float                     frame rate (> 0)

    Raises
    ------
    InvalidInput   naming the array, what is wrong and what was expected
    """
    V = checked(vertices, "clip vertices", ("F", "V", 3))
    frames = len(V)
    if frames == 0:
        raise InvalidInput("a clip needs at least one frame")
    P = checked(markers, "clip markers", ("F", "M", 3), axes=Axes(F=frames))
    if not np.isfinite(fps) or fps <= 0:
        raise InvalidInput(f"fps must be a positive number, got {fps}")
    arrays = {"vertices": V, "markers": P}
    if displacement is not None:
        arrays["displacement"] = checked(displacement, "clip displacement", ("F", "H", "W"),
                                         axes=Axes(F=frames))
    if albedo is not None:
        arrays["albedo"] = checked(albedo, "clip albedo", ("F", "H", "W", 3), axes=Axes(F=frames))
    check_finite(V, "clip", ("frame", "vertex"))
    check_finite(P, "clip", ("frame", "marker"), allow_nan=True, note=OCCLUDED_NOTE)
    for key in ("displacement", "albedo"):
        if key in arrays:
            check_finite(arrays[key], f"clip {key}", ("frame",))
    arrays["fps"] = np.float64(fps)
    write_npz(target, arrays, dtypes={key: np.float32 for key in arrays if key != "fps"})


# ---------------------------------------------------------------------------- readers
def actor_from_blobs(neutral: bytes, layout: bytes) -> ActorData:
    """:class:`ActorData` from a canonical neutral and marker-layout blob."""
    arrays = open_npz(neutral, "the stored neutral")
    missing = {"vertices", "faces", "uv", "uv_faces"} - set(arrays)
    if missing:
        raise InvalidInput(f"the stored neutral lacks {sorted(missing)}")
    try:
        body = json.loads(layout)
        names, triangle, barycentric = body["names"], body["triangle"], body["barycentric"]
    except (ValueError, TypeError, KeyError) as error:
        raise InvalidInput(f"the stored marker layout is not in the canonical form: {error!r}") from None
    tri = as_array(np.asarray(triangle, dtype=np.int64), "marker triangles", ("M",), "iu",
                   np.int64, axes=Axes(M=len(names)))
    check_indices(tri, len(arrays["faces"]), "marker", "triangle", "neutral", "triangles")
    regions = {key[len(REGION_PREFIX):]: value.astype(bool) for key, value in arrays.items()
               if key.startswith(REGION_PREFIX)}
    return ActorData(arrays["vertices"].astype(np.float64), arrays["faces"].astype(np.int64),
                     arrays["uv"].astype(np.float64), arrays["uv_faces"].astype(np.int64),
                     tri, np.asarray(barycentric, np.float64).reshape(len(names), 3),
                     tuple(names), regions)


def clip_from_blob(data: bytes, name: str) -> Clip:
    """A :class:`Clip` called ``name`` from a canonical clip blob (vertices and markers
    in float64, maps in float32)."""
    arrays = open_npz(data, f"clip '{name}'")
    missing = {"vertices", "markers"} - set(arrays)
    if missing:
        raise InvalidInput(f"clip '{name}' lacks {sorted(missing)}")
    fps = float(arrays["fps"]) if "fps" in arrays else 30.0
    maps = {key: arrays[key].astype(np.float32) if key in arrays else None
            for key in ("displacement", "albedo")}
    return Clip(name, arrays["vertices"].astype(np.float64), arrays["markers"].astype(np.float64),
                maps["displacement"], maps["albedo"], fps)


# ---------------------------------------------------------------------------- the store
def load_neutral_arrays(session: Session, blobs: BlobStore, actor_id: str,
                        needed_for: str = "") -> Mapping[str, np.ndarray]:
    """The arrays of the actor's stored neutral (:func:`neutral_npz`).

    Raises
    ------
    NotFound       unknown actor
    InvalidInput   the actor has no neutral yet (``needed_for`` says what wanted it)
    """
    try:
        return open_npz(registry.read_neutral(session, blobs, actor_id), "the stored neutral")
    except NotFound as error:
        if error.kind == "actor":
            raise
        why = f" ({needed_for} needs it)" if needed_for else ""
        raise InvalidInput(f"actor {actor_id!r} has no neutral yet{why}; upload it "
                           "first") from None


def load_actor_data(session: Session, blobs: BlobStore, actor_id: str) -> ActorData:
    """The stored actor as :class:`ActorData`.

    Raises
    ------
    NotFound       unknown actor
    InvalidInput   the actor has no neutral or no marker layout yet
    """
    try:
        neutral = registry.read_neutral(session, blobs, actor_id)
        layout = registry.read_markers(session, blobs, actor_id)
    except NotFound as error:
        if error.kind == "actor":
            raise
        raise InvalidInput(f"actor {actor_id!r} has no {error.kind} yet; upload it first") from None
    return actor_from_blobs(neutral, layout)


def load_clips(session: Session, blobs: BlobStore, clip_ids: Sequence[str],
               actor: ActorData) -> list[Clip]:
    """The stored clips, in the given order, checked against ``actor``.

    A clip is named by its ``name`` (its id when it has none), so error messages and
    training metrics say which clip they mean.

    Raises
    ------
    NotFound       unknown clip
    InvalidInput   a clip that does not match the actor or the others
                   (:func:`~service.methods.inputs.check_clips`; whether every clip must
                   carry maps when some do is the method's rule, checked when it trains)
    """
    clips = []
    for clip_id in clip_ids:
        row = registry.get_clip(session, clip_id)
        data = registry.read_clip(session, blobs, clip_id)
        clips.append(clip_from_blob(data, row.name or row.id))
    check_clips(actor, clips, mixed_maps=True)
    return clips
