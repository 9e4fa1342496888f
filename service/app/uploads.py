"""Uploads: bounded NPZ reading, and the parsing and validation of every upload (bytes of a
declared media type) into the canonical forms of :mod:`service.store.actors`.

Operations call one function here per upload and get back what to store (canonical bytes and
the counts to report), or an error by meaning (:mod:`service.errors`):
:class:`UnsupportedFormat` (415), :class:`MalformedInput` (400),
:class:`~service.io.errors.SizeLimitError` / :class:`PayloadTooLarge` (413),
:class:`InvalidInput` and the
readers' :class:`~service.io.errors.FormatError` (422), each naming the problem, e.g.
``"clip frame 12 has 40000 vertices, the neutral has 40962"``.

Accepted media types:

- NPZ: ``application/x-npz`` (``application/zip`` too: an NPZ is a zip archive);
- OBJ: ``model/obj`` (``text/plain`` is a 415: any text would otherwise be parsed as OBJ);
- JSON: ``application/json``;
- marker files: ``application/x-c3d`` (.c3d), ``text/x-trc`` (.trc), ``text/csv`` (.csv);
- ``multipart/form-data`` where a route says so (files named by their part's filename).

NPZ archives are read without unpickling (object arrays are refused), and their array
headers are checked (names, shapes, dtypes, total decompressed size at most
``NPZ_EXPANSION`` × ``max_body_bytes``) before any array data is decompressed, with the one
array dialect of :mod:`service.io.arrays` (:class:`~service.io.arrays.ArraySpec`). An
archive is read from bytes or from the spool file of a large body; a clip's arrays are then
read a block of frames at a time while they are checked and written to their canonical
blob, so a clip upload never holds its arrays whole in memory (issue 16, defect 11).
"""

from __future__ import annotations

import io
import json
import os
import re
import zipfile
from dataclasses import dataclass, field
from typing import Any, BinaryIO, Mapping, Sequence

import numpy as np

from service.store import actors as actor_store
from service.app.limits import (FACES_PER_VERTEX, NPZ_EXPANSION, NPZ_MAX_MEMBERS)
from service.app.validation import check_triangles, check_uv_tile
from service.config import Settings
from service.geometry.closest_point import resolve_marker_layout, surface_points
from service.io.errors import FormatError, MeshFormatError, SizeLimitError
from service.io.markers import MarkerSequence, read_marker_layout, read_markers
from service.io.mesh import Mesh, read_obj, write_npz
from service.io.arrays import ArraySpec, Axes
from service.io.npz import ZIP_ERRORS, NpyMember, buffer_members
from service.errors import InvalidInput, MalformedInput

NPZ_TYPES = ("application/x-npz", "application/zip")
OBJ_TYPES = ("model/obj",)
JSON_TYPE = "application/json"
MULTIPART = "multipart/form-data"
#: media type of a marker file → the reader's suffix
MARKER_FILE_TYPES = {"application/x-c3d": ".c3d", "application/vnd.c3d": ".c3d",
                     "text/x-trc": ".trc", "application/x-trc": ".trc", "text/csv": ".csv"}
MESH_TYPES = NPZ_TYPES + OBJ_TYPES
_SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")


# ---------------------------------------------------------------------------- bodies
def is_safe_name(name: str) -> bool:
    """Whether ``name`` can be a file-name component (letters, digits, ``._-``, no leading
    dot): what path names of maps and rigs must be."""
    return _SAFE_NAME.fullmatch(name) is not None and ".." not in name


def parse_json(data: bytes) -> Any:
    """``data`` parsed as JSON, or 400 naming the syntax error."""
    try:
        return json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as error:
        raise MalformedInput(f"the body is not valid JSON: {error}") from None


# ---------------------------------------------------------------------------- NPZ
@dataclass
class NpzUpload:
    """An uploaded NPZ whose headers passed their :class:`~service.io.arrays.ArraySpec`
    (nothing decompressed yet): ``shapes`` and ``dims`` (symbol → length) are known,
    :meth:`load` reads the data into memory, :meth:`members` gives it as
    :class:`~service.io.npz.NpyMember` arrays read in blocks (so a spooled body of hundreds
    of MiB is checked and rewritten holding a few MiB of it: issue 16, defect 11). A body in
    memory that is a plain archive of stored members is read from its zip records directly
    (:func:`~service.io.npz.buffer_members`); any other goes through :mod:`zipfile`, whose
    errors it reports.

    Parameters
    ----------
    data : bytes or path             the archive, in memory or in a (spool) file
    specs : name → ArraySpec         the arrays it may hold
    max_bytes : int                  bound on the summed decompressed size of its arrays
    prefixes : prefix → ArraySpec    specs for families of names (``region_<name>``)
    what : str                       the upload's name in messages, e.g. ``"clip"``
    """

    data: bytes | os.PathLike
    specs: Mapping[str, ArraySpec]
    max_bytes: int
    prefixes: Mapping[str, ArraySpec] = field(default_factory=dict)
    what: str = "upload"
    shapes: dict[str, tuple[int, ...]] = field(init=False)
    dims: dict[str, int] = field(init=False)

    def __post_init__(self) -> None:
        in_memory = isinstance(self.data, (bytes, bytearray))
        members = buffer_members(self.data) if in_memory else None
        self._zip = None
        if members is None:                 # not a plain stored archive: zipfile reads it
            source = io.BytesIO(self.data) if in_memory else self.data
            try:
                self._zip = zipfile.ZipFile(source)
                members = self._zip.infolist()
            except ZIP_ERRORS as error:
                raise FormatError(f"the {self.what} is not a readable .npz archive: {error}") from None
        if len(members) > NPZ_MAX_MEMBERS:
            raise SizeLimitError("arrays", len(members), NPZ_MAX_MEMBERS)
        self.shapes, self._members = {}, {}
        axes = Axes()
        total = 0
        for info in members:
            read = isinstance(info, zipfile.ZipInfo)       # else a BufferMember, read already
            if read and not info.filename.endswith(".npy"):
                raise FormatError(f"the {self.what} .npz holds '{info.filename}', which is not "
                                  "an array (.npy)")
            key = info.filename[:-4] if read else info.name
            spec = self._spec(key)
            member = self._header(info) if read else info
            shape = spec.check(f"'{key}'", member.shape, member.dtype, axes, FormatError)
            total += member.nbytes
            if total > self.max_bytes:
                raise SizeLimitError("bytes of decompressed array data", total, self.max_bytes)
            self.shapes[key], self._members[key] = shape, member
        self.dims = axes.lengths
        missing = [k for k, s in self.specs.items() if s.required and k not in self.shapes]
        if missing:
            raise FormatError(f"the {self.what} .npz lacks {', '.join(repr(k) for k in missing)}; "
                              f"it holds {sorted(self.shapes) or 'nothing'}")

    def _spec(self, key: str) -> ArraySpec:
        if key in self.specs:
            return self.specs[key]
        for prefix, spec in self.prefixes.items():
            if key.startswith(prefix):
                return spec
        allowed = [f"{k} {s.describe()}" for k, s in self.specs.items()]
        allowed += [f"{p}<name> {s.describe()}" for p, s in self.prefixes.items()]
        raise FormatError(f"unexpected array '{key}' in the {self.what} .npz; allowed: "
                          f"{', '.join(allowed)}")

    def _header(self, info: zipfile.ZipInfo) -> NpyMember:
        key = info.filename[:-4]
        try:
            member = NpyMember(self._zip, info)
        except ZIP_ERRORS as error:
            raise FormatError(f"cannot read the header of '{key}' in the {self.what} .npz: "
                              f"{error}") from None
        if member.dtype.hasobject:
            raise FormatError(f"'{key}' holds Python objects; only numeric arrays are accepted "
                              "(pickles are never loaded)")
        return member

    def load(self) -> dict[str, np.ndarray]:
        """Every array, read into memory without unpickling."""
        arrays = {}
        for key, member in self._members.items():
            try:
                arrays[key] = member.read()
            except ZIP_ERRORS as error:
                raise FormatError(f"cannot read '{key}' in the {self.what} .npz: {error}") from None
        return arrays

    def members(self) -> dict[str, "_UploadedArray"]:
        """Every array as an array still in the archive, read in blocks along axis 0 by
        :func:`service.io.arrays.blocks` (a read error is this format's error)."""
        return {key: _UploadedArray(member, self.what) for key, member in self._members.items()}

    def close(self) -> None:
        """Close the archive (and the spool file it reads)."""
        if self._zip is not None:
            self._zip.close()


class _UploadedArray:
    """An :class:`NpyMember` whose read errors are :class:`FormatError` naming the upload."""

    def __init__(self, member: NpyMember, what: str):
        self.member, self.what = member, what
        self.shape, self.dtype, self.ndim = member.shape, member.dtype, member.ndim

    def __len__(self) -> int:
        return self.shape[0]

    def read(self) -> np.ndarray:
        try:
            return self.member.read()
        except ZIP_ERRORS as error:
            raise self._error(error) from None

    def blocks(self, max_bytes: int):
        try:
            yield from self.member.blocks(max_bytes)
        except ZIP_ERRORS as error:
            raise self._error(error) from None

    def _error(self, error: BaseException) -> FormatError:
        return FormatError(f"cannot read '{self.member.name}' in the {self.what} .npz: {error}")


def npz_limit(settings: Settings) -> int:
    """Bound on the decompressed array bytes of an uploaded NPZ."""
    return NPZ_EXPANSION * settings.max_body_bytes


# ---------------------------------------------------------------------------- meshes
MESH_SPECS = {
    "vertices": ArraySpec(("V", 3), "f"), "faces": ArraySpec(("T", 3), "iu"),
    "uv": ArraySpec(("K", 2), "f", False), "uv_faces": ArraySpec(("T", 3), "iu", False),
    "quad_split": ArraySpec(("T",), "iu", False),
}
REGION_SPEC = ArraySpec(("V",), "biu", False)


@dataclass(frozen=True)
class MeshUpload:
    """A parsed, validated mesh upload.

    Attributes
    ----------
    mesh : Mesh                      as the file gave it (vertex order kept)
    regions : name → (V,) bool       ``region_<name>`` arrays of an NPZ neutral
    polygons_split : int             polygons with more than three corners, fan-split
    """

    mesh: Mesh
    regions: dict[str, np.ndarray]
    polygons_split: int

    @property
    def uv_seam_vertices(self) -> int:
        """Vertices with more than one UV (on a seam)."""
        return len(self.mesh.seam_vertices())


def parse_mesh(kind: str, data: bytes | os.PathLike, settings: Settings, what: str,
               regions: bool = False) -> MeshUpload:
    """Read an uploaded mesh (.npz or .obj, per ``kind``) and check its triangles.

    Parameters
    ----------
    kind : str        the media type (one of :data:`MESH_TYPES`)
    data : bytes or path   the body, in memory or its spool file
    settings : the limits (``max_vertices``; triangles up to ``FACES_PER_VERTEX`` × that)
    what : str        the mesh's name in messages (``"neutral"``, ``"input rig"``)
    regions : bool    accept ``region_<name>`` (V,) arrays in an NPZ

    Raises
    ------
    FormatError, SizeLimitError, InvalidInput
    """
    max_faces = FACES_PER_VERTEX * settings.max_vertices
    found: dict[str, np.ndarray] = {}
    if kind in NPZ_TYPES:
        upload = NpzUpload(data, MESH_SPECS, npz_limit(settings),
                           {actor_store.REGION_PREFIX: REGION_SPEC} if regions else {}, what)
        for symbol, limit, name in (("V", settings.max_vertices, "vertices"),
                                    ("T", max_faces, "triangles")):
            if upload.dims.get(symbol, 0) > limit:
                raise SizeLimitError(name, upload.dims[symbol], limit)
        try:
            arrays = upload.load()
        finally:
            upload.close()
        found = {k[len(actor_store.REGION_PREFIX):]: v.astype(bool) for k, v in arrays.items()
                 if k.startswith(actor_store.REGION_PREFIX)}
        try:
            mesh = Mesh(**{k: v for k, v in arrays.items() if k in MESH_SPECS})
        except MeshFormatError as error:
            raise MeshFormatError(f"the {what}: {error}") from None
    else:
        mesh = read_obj(data, max_vertices=settings.max_vertices, max_faces=max_faces)
    check_triangles(mesh.vertices, mesh.faces, what)
    split = 0 if mesh.quad_split is None else int(np.count_nonzero(np.bincount(mesh.quad_split) > 1))
    return MeshUpload(mesh, found, split)


def parse_neutral(kind: str, data: bytes | os.PathLike, settings: Settings) -> tuple[MeshUpload, bytes]:
    """The neutral upload and its canonical blob (:func:`service.store.actors.neutral_npz`);
    the neutral needs UVs in the unit tile."""
    upload = parse_mesh(kind, data, settings, "neutral", regions=True)
    mesh = upload.mesh
    check_uv_tile(mesh, "neutral")
    return upload, actor_store.neutral_npz(mesh.vertices, mesh.faces, mesh.uv, mesh.uv_faces,
                                           upload.regions)


def parse_rig_mesh(kind: str, data: bytes | os.PathLike, settings: Settings) -> tuple[MeshUpload, bytes]:
    """An input rig's mesh and the NPZ to store (:func:`service.io.mesh.write_npz`, readable
    by :func:`service.io.mesh.read_npz`)."""
    upload = parse_mesh(kind, data, settings, "input rig")
    buffer = io.BytesIO()
    write_npz(buffer, upload.mesh)
    return upload, buffer.getvalue()


# ---------------------------------------------------------------------------- layouts
@dataclass(frozen=True)
class LayoutUpload:
    """A marker layout resolved onto the neutral.

    Attributes
    ----------
    blob : bytes             canonical layout (:func:`service.store.actors.layout_json`)
    marker_count : int
    snapped : int            markers given as free positions and snapped to the surface
    max_snap_distance : float   the farthest of those snaps, actor's unit (0 if none)
    """

    blob: bytes
    marker_count: int
    snapped: int
    max_snap_distance: float
    renormalized: int = 0


def parse_layout(data: bytes, neutral: bytes) -> LayoutUpload:
    """Read API.md's layout JSON and resolve every marker to a surface point of the stored
    neutral (vertex and position placements become triangle + barycentric)."""
    parse_json(data)
    V, F = actor_store.neutral_arrays(neutral)
    layout = read_marker_layout(data, vertex_count=len(V), triangle_count=len(F))
    try:
        triangle, barycentric = resolve_marker_layout(layout, V, F)
    except ValueError as error:
        raise InvalidInput(str(error)) from None
    free = np.asarray(layout.kinds) == "position"
    distance = 0.0
    if free.any():
        snapped = surface_points(V, F, triangle[free], barycentric[free])
        distance = float(np.linalg.norm(snapped - layout.position[free], axis=1).max())
    given = np.asarray(layout.kinds) == "triangle"
    renormalized = int((given & ~np.all(barycentric == np.asarray(
        layout.barycentric, np.float64).reshape(-1, 3), axis=1)).sum())
    blob = actor_store.layout_json(layout.names, triangle, barycentric)
    return LayoutUpload(blob, len(layout.names), int(free.sum()), distance, renormalized)


def layout_names(layout: bytes) -> list[str]:
    """Marker names of a stored canonical layout, in layout order."""
    return list(json.loads(layout)["names"])


# ---------------------------------------------------------------------------- markers
def markers_in_layout_order(sequence: MarkerSequence, names: Sequence[str],
                            what: str = "the marker file") -> np.ndarray:
    """Positions (F,M,3) of a marker file in layout order.

    A file with marker names is matched by name (extra markers are ignored); one without
    must have exactly the layout's markers, in its order.
    """
    positions = sequence.positions
    if sequence.names is None:
        if positions.shape[1] != len(names):
            raise InvalidInput(f"{what} has {positions.shape[1]} markers per frame, the marker "
                               f"layout has {len(names)} (unnamed markers must be in layout order)")
        return positions
    column = {name: k for k, name in enumerate(sequence.names)}
    missing = [name for name in names if name not in column]
    if missing:
        shown = ", ".join(missing[:8]) + (", ..." if len(missing) > 8 else "")
        raise InvalidInput(f"{what} lacks {len(missing)} of the layout's {len(names)} markers: "
                           f"{shown}")
    return positions[:, [column[name] for name in names]]


def read_marker_file(data: bytes, suffix: str, names: Sequence[str]) -> tuple[np.ndarray, float | None]:
    """A .c3d/.trc/.csv/.json marker file as (F,M,3) in layout order, and its fps."""
    sequence = read_markers(data, suffix)
    return markers_in_layout_order(sequence, names), sequence.fps


# ---------------------------------------------------------------------------- clips
CLIP_SPECS = {
    "vertices": ArraySpec(("F", "V", 3), "f"), "markers": ArraySpec(("F", "M", 3), "fiu"),
    "displacement": ArraySpec(("F", "H", "H"), "fiu", False),
    "albedo": ArraySpec(("F", "A", "A", 3), "fiu", False),
    "fps": ArraySpec((), "fiu", False),
}


@dataclass(frozen=True)
class ClipUpload:
    """A validated clip: its canonical blob (bytes, or the file it was written to), frame
    count, and the marker reader's notes
    (:attr:`~service.io.marker_sequence.MarkerSequence.notes`: what it accepted that the
    user should hear of, e.g. a TRC ``NumFrames`` that disagrees with its rows)."""

    blob: bytes | os.PathLike
    frames: int
    notes: tuple[str, ...] = ()


def _check_clip(frames: int, marker_frames: int, markers: int, n_markers: int) -> None:
    """The counts of a clip against each other and the layout (from the headers; the
    values are checked by :func:`service.store.actors.write_clip` as it writes them)."""
    if markers != n_markers:
        raise InvalidInput(f"the clip has {markers} markers per frame, the marker "
                           f"layout has {n_markers}")
    if marker_frames != frames:
        raise InvalidInput(f"the clip has {frames} mesh frames but {marker_frames} "
                           "marker frames")


def _write_clip(target: os.PathLike | None, vertices, markers, **maps) -> bytes | os.PathLike:
    """The canonical clip written to the file ``target`` (returned), or as bytes without one."""
    if target is None:
        return actor_store.clip_npz(vertices, markers, **maps)
    with open(target, "wb") as out:
        actor_store.write_clip(out, vertices, markers, **maps)
    return target


def parse_clip_npz(data: bytes | os.PathLike, settings: Settings, n_vertices: int, n_markers: int,
                   target: os.PathLike | None = None) -> ClipUpload:
    """A clip NPZ (``vertices`` (F,V,3), ``markers`` (F,M,3), optional ``displacement``
    (F,H,H), ``albedo`` (F,A,A,3), ``fps``) checked against the actor.

    ``data`` is the body in memory or its spool file. The arrays are checked from their
    headers, then read a block of frames at a time while their values are checked and the
    canonical blob is written to ``target`` (a new file, e.g. in a scratch directory of the
    blob store: ``blob`` is then that path), so no array of the body is held whole in
    memory; without ``target`` the blob is returned as bytes.
    """
    upload = NpzUpload(data, CLIP_SPECS, npz_limit(settings), what="clip")
    try:
        if upload.dims["F"] == 0:
            raise InvalidInput("the clip has no frames")
        if upload.dims["V"] != n_vertices:
            raise InvalidInput(f"the clip's frames have {upload.dims['V']} vertices, the neutral "
                               f"has {n_vertices} (frames must be in vertex correspondence with it)")
        arrays = upload.members()
        _check_clip(upload.dims["F"], upload.shapes["markers"][0], upload.dims["M"], n_markers)
        fps = float(arrays["fps"].read()) if "fps" in arrays else 30.0
        blob = _write_clip(target, arrays["vertices"], arrays["markers"],
                           displacement=arrays.get("displacement"), albedo=arrays.get("albedo"),
                           fps=fps)
    finally:
        upload.close()
    return ClipUpload(blob, upload.dims["F"])


@dataclass
class ClipForm:
    """The parts of a multipart clip upload, read into memory.

    Attributes
    ----------
    frames : list of (filename, bytes)   per-frame OBJ files, in the order sent
    markers : (filename, bytes)          the marker file
    fps : float or None
    """

    frames: list[tuple[str, bytes]]
    markers: tuple[str, bytes]
    fps: float | None


@dataclass
class TrackingForm:
    """The parts of a multipart tracking upload (file parts as spooled file objects), read
    by :func:`service.app.tracking.submit_tracking`.

    Attributes
    ----------
    cameras : bytes or None;  params : str or None
    scans : list of (filename, file);  scan_images : (filename, file) or None
    frames : list of (filename, file);  scan_maps : (filename, file) or None
    """

    cameras: bytes | None
    scans: list[tuple[str, BinaryIO]] = field(default_factory=list)
    scan_images: tuple[str, BinaryIO] | None = None
    frames: list[tuple[str, BinaryIO]] = field(default_factory=list)
    params: str | None = None
    scan_maps: tuple[str, BinaryIO] | None = None


def parse_clip_form(form: ClipForm, settings: Settings, n_vertices: int,
                    names: Sequence[str], target: os.PathLike | None = None) -> ClipUpload:
    """A multipart clip (per-frame OBJ files and a marker file) checked against the actor
    (the blob written to ``target`` as :func:`parse_clip_npz` does)."""
    vertices = np.empty((len(form.frames), n_vertices, 3), np.float32)
    for k, (filename, data) in enumerate(form.frames):
        try:
            mesh = read_obj(data, max_vertices=settings.max_vertices,
                            max_faces=FACES_PER_VERTEX * settings.max_vertices)
        except FormatError as error:
            raise type(error)(f"clip frame {k} ('{filename}'): {error}") from None
        if len(mesh.vertices) != n_vertices:
            raise InvalidInput(f"clip frame {k} ('{filename}') has {len(mesh.vertices)} "
                               f"vertices, the neutral has {n_vertices}")
        vertices[k] = mesh.vertices
    filename, data = form.markers
    suffix = "." + filename.rsplit(".", 1)[-1].lower() if "." in filename else ""
    sequence = read_markers(data, suffix)
    markers, fps = markers_in_layout_order(sequence, names), sequence.fps
    _check_clip(len(vertices), len(markers), markers.shape[1], len(names))
    blob = _write_clip(target, vertices, markers, fps=form.fps or fps or 30.0)
    return ClipUpload(blob, len(vertices), sequence.notes)


# ---------------------------------------------------------------------------- landmarks
def parse_landmarks(text: str | None, rig_vertices: int, neutral_vertices: int) -> list[list[int]]:
    """Landmark pairs ``[[rig_vertex, neutral_vertex], ...]`` (JSON), indices checked."""
    if text in (None, ""):
        return []
    pairs = parse_json(text.encode() if isinstance(text, str) else text)
    if not (isinstance(pairs, list) and all(
            isinstance(p, list) and len(p) == 2 and all(type(i) is int for i in p) for p in pairs)):
        raise InvalidInput("'landmarks' must be a JSON list of [rig_vertex, neutral_vertex] "
                           "integer pairs")
    for k, (rig, neutral) in enumerate(pairs):
        if not 0 <= rig < rig_vertices:
            raise InvalidInput(f"landmark {k}: rig vertex {rig} is out of range; the rig has "
                               f"{rig_vertices} vertices")
        if not 0 <= neutral < neutral_vertices:
            raise InvalidInput(f"landmark {k}: neutral vertex {neutral} is out of range; the "
                               f"neutral has {neutral_vertices} vertices")
    return pairs


