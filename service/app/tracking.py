"""Performance-flow tracking as an operation: ``POST /v1/actors/{actor_id}/tracking-jobs``
(fyffe, digital_ira_course2014, "Driving High-Resolution Facial Scans with Video Performance
Capture", §3 inputs).

:func:`submit_tracking` reads and checks everything the job needs — the actor's neutral (the
artist mesh, 409 without one), the camera calibration (:class:`Calibration`), the static
scans (raw OBJ/PLY meshes, not in correspondence, with one image per view), the
performance's frames per view (a zip of PNG/EXR sequences or one video file per view, decoded
with OpenCV) and the tracking parameters — and answers 4xx naming what is wrong: view counts,
frame counts and image sizes that disagree, an unreadable image or video, a bad calibration.
It then writes one canonical input NPZ under the actor's blob prefix (deleted with the
actor) and queues a ``track`` job (:mod:`service.jobs.tasks.track`).

Upload (``multipart/form-data``):

- ``cameras``: JSON ``{"views": [{"name", "K", "R", "t", "width", "height"}, ...]}`` —
  OpenCV pinhole convention (``x_cam = R X + t``, pixel ``(K x)[:2] / x_z``, pixel centres at
  integer + 0.5; :class:`service.geometry.camera.Camera`), lengths in the actor's unit;
- ``scans``: one ``.obj`` or ``.ply`` file per static scan, in order; the first is the
  neutral expression (it anchors the artist mesh, eq. 12). A scan's name is its file stem;
- ``scan_images``: a zip with one image per scan and view, ``<scan>/<view>.png`` (or
  ``.exr``); with one view also ``<scan>.png``;
- ``frames``: a zip of image sequences ``<view>/<any name>.png`` (natural name order; with
  one view also flat), or one video file per view in the calibration's order;
- ``params`` (optional): JSON of :class:`~service.methods.tracking.params.TrackingParams`;
- ``scan_maps`` (optional): ``.npz`` of maps in the neutral's UV layout, one per scan, each
  array (S,h,w) or (S,h,w,C) float (e.g. ``albedo``, ``displacement``), blended per frame.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path, PurePosixPath

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from models_store import registry
from models_store.ids import new_token
from models_store.schema import JOB_FINAL_STATUSES
from service.app.operations import submit
from service.app.services import Services, Submit
from service.app.uploads import TrackingForm
from service.errors import Conflict, InvalidInput, invalid_fields
from service.geometry.camera import Camera
from service.io.frames import (VIDEO_SUFFIXES, decode_image, decode_sequence,
                               image_zip, read_video)
from service.io.mesh import read_mesh
from service.io.npz import npz_arrays
from service.jobs.formats import RESULT_FORMATS
from service.store.actors import load_neutral_arrays
from service.jobs.track_jobs import SPAN_JOB, TRACK_JOB, span_jobs
from service.methods.tracking.params import TrackingParams

#: the neutral's region (``region_<name>``) whose vertices the facial regions are drawn on
#: (§4.1); without it every vertex
FACE_REGION = "region_face"
#: mesh suffixes of a static scan
SCAN_SUFFIXES = (".obj", ".ply")
#: most views, scans
MAX_VIEWS, MAX_SCANS = 16, 64
#: default and largest side of the blended maps, texels
MAP_RESOLUTION, MAX_MAP_RESOLUTION = 256, 2048
#: tolerance of ‖RᵀR − I‖ and |det R − 1| of a calibration's rotation
ROTATION_TOLERANCE = 1e-4

Matrix3 = list[list[float]]


class CameraView(BaseModel):
    """One calibrated view (OpenCV pinhole convention, see the module docstring)."""

    model_config = ConfigDict(extra="forbid")

    name: str | None = Field(None, min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$",
                             description="the view's name (default its index): the folder of "
                                         "its images in the zips")
    K: Matrix3 = Field(description="intrinsics (3,3) in pixels: [[fx, s, cx], [0, fy, cy], "
                                   "[0, 0, 1]], fx, fy > 0")
    R: Matrix3 = Field(description="rotation (3,3) world → camera (orthonormal, det +1)")
    t: list[float] = Field(min_length=3, max_length=3,
                           description="translation (3,) world → camera, the actor's unit")
    width: int = Field(ge=8, le=8192, description="image width, pixels")
    height: int = Field(ge=8, le=8192, description="image height, pixels")

    @field_validator("K", "R")
    @classmethod
    def _three_by_three(cls, value: Matrix3) -> Matrix3:
        if len(value) != 3 or any(len(row) != 3 for row in value):
            raise ValueError("must be a 3×3 matrix (three rows of three numbers)")
        if not np.isfinite(np.asarray(value, float)).all():
            raise ValueError("must be finite")
        return value

    @field_validator("t")
    @classmethod
    def _finite(cls, value: list[float]) -> list[float]:
        if not np.isfinite(np.asarray(value, float)).all():
            raise ValueError("must be finite")
        return value

    def camera(self, where: str) -> Camera:
        K, R = np.asarray(self.K, float), np.asarray(self.R, float)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise InvalidInput(f"{where}.K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with "
                               f"fx, fy > 0; got {self.K}")
        if (np.abs(R.T @ R - np.eye(3)).max() > ROTATION_TOLERANCE
                or abs(np.linalg.det(R) - 1) > ROTATION_TOLERANCE):
            raise InvalidInput(f"{where}.R is not a rotation (orthonormal with determinant +1 "
                               f"within {ROTATION_TOLERANCE}); got {self.R}")
        return Camera(K, R, np.asarray(self.t, float), self.width, self.height)


class Calibration(BaseModel):
    """The ``cameras`` part: the calibrated views, the same for the scans and the performance."""

    model_config = ConfigDict(extra="forbid")

    views: list[CameraView] = Field(min_length=1, max_length=MAX_VIEWS)


def parse_calibration(data: bytes) -> tuple[list[Camera], list[str]]:
    """The ``cameras`` JSON → cameras and view names (422 naming the first problem)."""
    try:
        value = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InvalidInput(f"cameras: not JSON ({error})") from None
    try:
        calibration = Calibration.model_validate(value)
    except ValidationError as error:
        raise invalid_fields(error, ("cameras",)) from None
    names = [v.name or str(k) for k, v in enumerate(calibration.views)]
    if len(set(names)) != len(names):
        raise InvalidInput(f"cameras: view names must be distinct, got {names}")
    cams = [v.camera(f"cameras.views[{k}]") for k, v in enumerate(calibration.views)]
    if len({(c.width, c.height) for c in cams}) != 1:
        raise InvalidInput("cameras: every view must have the same image size (the tracking "
                           "stacks the views); got " + ", ".join(
                               f"{n} {c.width}×{c.height}" for n, c in zip(names, cams)))
    return cams, names


def parse_params(text: str | None) -> TrackingParams:
    if not text:
        return TrackingParams()
    try:
        value = json.loads(text)
    except json.JSONDecodeError as error:
        raise InvalidInput(f"params: not JSON ({error})") from None
    if not isinstance(value, dict):
        raise InvalidInput(f"params must be a JSON object, got {type(value).__name__}")
    try:
        return TrackingParams(**value)
    except ValidationError as error:
        raise invalid_fields(error, ("params",)) from None
    except InvalidInput as error:              # MethodParams names the field itself
        raise InvalidInput(f"params: {error}", getattr(error, "errors", None)) from None


def _suffix(name: str) -> str:
    return PurePosixPath(name or "").suffix.lower()


def _read_scans(form: TrackingForm, max_vertices: int) -> tuple[list, list, list[str]]:
    if not form.scans:
        raise InvalidInput("a tracking job needs one or more 'scans' parts (.obj or .ply raw "
                           "scan meshes; the first is the neutral expression)")
    if len(form.scans) > MAX_SCANS:
        raise InvalidInput(f"{len(form.scans)} scans; at most {MAX_SCANS}")
    points, faces, names = [], [], []
    for k, (filename, file) in enumerate(form.scans):
        suffix = _suffix(filename)
        if suffix not in SCAN_SUFFIXES:
            raise InvalidInput(f"scan {k} ({filename!r}) is not .obj or .ply")
        name = PurePosixPath(filename).stem
        if name in names:
            raise InvalidInput(f"scans {names.index(name)} and {k} are both named {name!r} "
                               "(a scan's name is its file stem; its images are <name>/<view>)")
        mesh = read_mesh(file.read(), suffix, max_vertices=max_vertices)
        if len(mesh.faces) == 0:
            raise InvalidInput(f"scan {name!r} has no triangles")
        points.append(mesh.vertices)
        faces.append(mesh.faces)
        names.append(name)
    return points, faces, names


def _read_scan_images(form: TrackingForm, scans: list[str], views: list[str],
                      size: tuple[int, int]) -> np.ndarray:
    if form.scan_images is None:
        raise InvalidInput("a tracking job needs a 'scan_images' part: a zip with one image "
                           "per scan and view, <scan>/<view>.png or .exr")
    groups = image_zip(form.scan_images[1], "scan_images", MAX_SCANS * MAX_VIEWS)
    flat = {PurePosixPath(name).stem: (name, data) for name, data in groups.get("", [])}
    nested = {folder: {PurePosixPath(n).stem: (n, d) for n, d in files}
              for folder, files in groups.items() if folder}
    unknown = sorted(set(nested) - set(scans))
    if unknown:
        raise InvalidInput(f"scan_images: folder(s) {unknown} name no scan (scans: {scans})")
    out = np.zeros((len(scans), len(views), size[1], size[0]), np.uint8)
    for s, scan in enumerate(scans):
        for c, view in enumerate(views):
            found = nested.get(scan, {}).get(view)
            if found is None and len(views) == 1:
                found = flat.get(scan)
            if found is None:
                raise InvalidInput(f"scan_images: no image of scan {scan!r} in view {view!r} "
                                   f"(expected {scan}/{view}.png or .exr)")
            image = decode_image(found[1], f"scan_images/{scan}/{found[0]}")
            _check_size(image.shape, size, f"scan_images: scan {scan!r} view {view!r}")
            out[s, c] = image
    return out


def _check_size(shape: tuple, size: tuple[int, int], what: str) -> None:
    if (shape[-1], shape[-2]) != size:
        raise InvalidInput(f"{what} is {shape[-1]}×{shape[-2]} pixels; the calibration says "
                           f"{size[0]}×{size[1]}")


def _read_frames(form: TrackingForm, views: list[str], size: tuple[int, int],
                 scratch: Path) -> np.ndarray:
    if not form.frames:
        raise InvalidInput("a tracking job needs 'frames': a zip of image sequences "
                           "(<view>/<frame>.png or .exr) or one video file per view")
    suffixes = [_suffix(name) for name, _ in form.frames]
    if len(form.frames) == 1 and suffixes[0] == ".zip":
        groups = image_zip(form.frames[0][1], "frames")
        if set(groups) == {""} and len(views) == 1:
            groups = {views[0]: groups[""]}
        unknown = sorted(set(groups) - set(views))
        if unknown:
            raise InvalidInput(f"frames: folder(s) {unknown} name no view (views: {views}; "
                               "with several views each needs its folder)")
        missing = [v for v in views if v not in groups]
        if missing:
            raise InvalidInput(f"frames: no images for view(s) {missing} (expected a folder "
                               "per view: " + ", ".join(f"{v}/" for v in views) + ")")
        per_view = [decode_sequence(groups[v], f"frames/{v}") for v in views]
    else:
        bad = [name for (name, _), s in zip(form.frames, suffixes) if s not in VIDEO_SUFFIXES]
        if bad:
            raise InvalidInput(f"frames: {bad} are neither one .zip of image sequences nor "
                               f"video files ({', '.join(VIDEO_SUFFIXES)})")
        if len(form.frames) != len(views):
            raise InvalidInput(f"frames: {len(form.frames)} video file(s) for {len(views)} "
                               f"calibrated view(s) {views}; send one video per view, in order")
        per_view = []
        for (name, file), suffix, view in zip(form.frames, suffixes, views):
            path = scratch / f"view-{len(per_view)}{suffix}"
            with open(path, "wb") as out:
                shutil.copyfileobj(file, out, 1 << 20)
            per_view.append(read_video(path, f"frames: video {name!r} (view {view!r})"))
            path.unlink()
    for view, frames in zip(views, per_view):
        _check_size(frames.shape, size, f"frames of view {view!r}")
    counts = [len(f) for f in per_view]
    if len(set(counts)) != 1:
        raise InvalidInput("frames: the views have different frame counts: " + ", ".join(
            f"{v} {n}" for v, n in zip(views, counts)))
    if counts[0] < 2:
        raise InvalidInput(f"frames: a performance needs at least 2 frames, got {counts[0]}")
    return np.stack(per_view, axis=1)


def _read_scan_maps(form: TrackingForm, scans: int) -> dict[str, np.ndarray]:
    if form.scan_maps is None:
        return {}
    data = form.scan_maps[1].read()
    try:
        arrays = npz_arrays(data)
    except Exception as error:                     # noqa: BLE001 - any unreadable archive
        raise InvalidInput(f"scan_maps is not a readable .npz ({type(error).__name__}: "
                           f"{error})") from None
    out = {}
    for name, value in arrays.items():
        value = np.asarray(value)
        if value.dtype.kind not in "fiu" or value.ndim not in (3, 4) or len(value) != scans:
            raise InvalidInput(f"scan_maps[{name!r}] has shape {value.shape} ({value.dtype}); "
                               f"expected ({scans},h,w) or ({scans},h,w,C) numbers, one map per scan")
        if not np.isfinite(value).all():
            raise InvalidInput(f"scan_maps[{name!r}] has NaN or infinite values")
        out[name] = value.astype(np.float32)
    return out


def submit_tracking(services: Services, submit_job: Submit, actor_id: str, form: TrackingForm,
                    *, result_format: str = "npz", map_resolution: int = MAP_RESOLUTION) -> str:
    """Check a tracking upload, store its canonical input and queue a ``track`` job; its id.

    Raises
    ------
    NotFound       unknown actor
    Conflict       the actor has no neutral (the artist mesh)
    InvalidInput   anything wrong with the upload (named), or a bad ``format``
    """
    if result_format not in RESULT_FORMATS:
        raise InvalidInput(f"format {result_format!r} is not one of {list(RESULT_FORMATS)}")
    if not 8 <= map_resolution <= MAX_MAP_RESOLUTION:
        raise InvalidInput(f"map_resolution must be within [8, {MAX_MAP_RESOLUTION}], got "
                           f"{map_resolution}")
    with services.session() as session:
        actor = registry.get_actor(session, actor_id)
        if actor.neutral_blob is None:
            raise Conflict(f"actor {actor_id!r} has no neutral mesh yet (the artist mesh the "
                           f"performance is tracked on); PUT /v1/actors/{actor_id}/neutral first")
        neutral = dict(load_neutral_arrays(session, services.blobs, actor_id, "tracking"))
    artist = {"artist_vertices": np.asarray(neutral["vertices"], np.float64),
              "faces": np.asarray(neutral["faces"], np.int64),
              "uv": np.asarray(neutral["uv"], np.float64),
              "uv_faces": np.asarray(neutral.get("uv_faces", neutral["faces"]), np.int64),
              "face": np.asarray(neutral.get(FACE_REGION,
                                             np.ones(len(neutral["vertices"]), bool)), bool)}
    params = parse_params(form.params)
    if form.cameras is None:
        raise InvalidInput("a tracking job needs a 'cameras' part: JSON {\"views\": [{\"K\", "
                           "\"R\", \"t\", \"width\", \"height\"}, ...]}")
    cameras, views = parse_calibration(form.cameras)
    size = (cameras[0].width, cameras[0].height)
    points, faces, scans = _read_scans(form, services.settings.max_vertices)
    scan_images = _read_scan_images(form, scans, views, size)
    maps = _read_scan_maps(form, len(scans))
    prefix = f"actors/{actor_id}/tracking/{new_token()}"
    with services.blobs.scratch_dir("tracking") as scratch:
        frames = _read_frames(form, views, size, scratch)
        path = scratch / "input.npz"
        arrays = {**artist, "scan_images": scan_images,
                  "scan_vertices": np.concatenate(points).astype(np.float64),
                  "scan_vertex_counts": np.array([len(p) for p in points], np.int64),
                  "scan_faces": np.concatenate(faces).astype(np.int64),
                  "scan_face_counts": np.array([len(f) for f in faces], np.int64),
                  "cameras": np.array(json.dumps([c.to_json() for c in cameras])),
                  "scan_names": np.array(scans), "view_names": np.array(views),
                  **{f"map_{name}": value for name, value in maps.items()}}
        with open(path, "wb") as out:
            np.savez(out, **arrays)
        np.save(scratch / "frames.npy", frames)          # read a span at a time (mmap)
        info = services.blobs.put_file(f"{prefix}/input.npz", path, move=True)
        frames_info = services.blobs.put_file(f"{prefix}/frames.npy", scratch / "frames.npy",
                                              move=True)
    try:
        with services.session() as session:
            job = registry.create_job(session, TRACK_JOB, actor_id, payload={
                "input_blob": info.key, "input_sha256": info.sha256, "prefix": prefix,
                "frames_blob": frames_info.key, "frames_sha256": frames_info.sha256,
                "frames": int(frames.shape[0]), "views": views, "scans": scans,
                "maps": sorted(maps), "params": params.model_dump(mode="json"),
                "format": result_format, "map_resolution": int(map_resolution)})
            submit(session, submit_job, job)
            return job.id
    except Exception:
        services.blobs.delete(info.key)
        services.blobs.delete(frames_info.key)
        raise


def cancel_spans(session, job) -> list[str]:
    """After ``DELETE /v1/jobs/{id}`` of a ``track`` job: cancel its span jobs too (queued
    ones at once, running ones at their next progress point); their ids."""
    if job.kind != TRACK_JOB:
        return []
    ids = []
    for child in span_jobs(session, job):
        if child.status not in JOB_FINAL_STATUSES:
            registry.request_cancel(session, child.id)
            ids.append(child.id)
    return ids


__all__ = ["Calibration", "CameraView", "submit_tracking", "cancel_spans",
           "parse_calibration", "SPAN_JOB", "TRACK_JOB"]
