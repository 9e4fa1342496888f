"""A shape-space model on disk: ``manifest.json`` + ``model.npz`` + ``detail.npz`` (+ ``colors.npz``).

Layout (DESIGN.md "Data and storage"):

* ``model.npz``   the neutral and its smoothed version, faces, UV layout, alignment weights, patches,
  compressed shape vectors D̃ᵀ, regions (vertex sets, triangle and patch weights), the Gram
  matrices of §5.3, the database frame index and the marker layout;
* ``detail.npz``  ``detail`` (N,m,9) float32: the high-frequency detail of every database
  frame (rotation log + stretch per triangle) — the bulk of the model;
* ``colors.npz``  ``colors`` (N,n,C) float32, only for a model trained with colours;
* ``maps.npz``    per map kind (``displacement``, ``albedo``) the maps (N,P,C) int16 at the
  covered texels with their per-frame steps ``<kind>_scale`` (N,) float32 (float16 values and
  no scale in models stored before), ``<kind>_texels`` (P,) and ``<kind>_shape`` (2,) (:mod:`.maps`), only
  if the database had maps; when only some of its clips had them, the maps are (K,P,C) and
  ``<kind>_frames`` (K,) names their database frames;
* ``markers.npz`` the :class:`~.markers.MarkerDatabase`: ``shapes`` (N,9P) and ``gram``
  (R,N,N) of the database frames' marker shells, ``corrections`` (N,n,3) float32
  (:mod:`.markers`), only for a model trained with ``marker_correction`` and markers;
* ``manifest.json`` kind, format version, params, metrics, region and clip names, and the
  sha256 of every file.

Every array is stored in the dtype the model holds in memory, so a load reproduces the
:class:`~.data.ShapeSpaceData` bit for bit (the database files :data:`MAPPED_FILES`
memory-mapped, read-only); the evaluator (prefactored solvers, operators)
is rebuilt from it. Every file
is written atomically, the manifest last; a load verifies every checksum before it parses
a byte.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from service.geometry.marker_prior import MarkerPrior
from service.io.atomic import write_bytes, write_npz
from service.io.npz import npz_arrays, npz_mapped
from service.methods.model_dir import ModelCorrupt, read_model_files
from service.methods.shape_space.data import ShapeSpaceData
from service.methods.shape_space.maps import DatabaseMaps
from service.methods.shape_space.markers import MarkerDatabase
from service.methods.shape_space.params import ShapeSpaceParams

KIND = "shape_space"
FORMAT_VERSION = 2
#: maps.npz names → ShapeSpaceData attributes (:mod:`.maps`)
MAP_FIELDS = {"displacement": "fine_maps", "albedo": "albedo_maps"}
MODEL_ARRAYS = ("faces", "neutral", "smooth_neutral", "align_weights", "patches", "tri_patch",
                "shapes", "region_vertices", "region_weights", "patch_weights", "gram",
                "frame_clip", "frame_index", "marker_triangle", "marker_barycentric",
                "marker_weights", "uv", "uv_faces")
"""arrays of model.npz (attribute names of :class:`~.data.ShapeSpaceData`)"""
#: the database files, memory-mapped at load (read-only): a request reads only the active
#: frames' detail (:mod:`.blending`), so their pages come in as they are needed
MAPPED_FILES = frozenset({"detail.npz", "colors.npz", "markers.npz", "maps.npz"})


def write_model(model: ShapeSpaceData, path) -> dict:
    """Write a model's stored data ``model`` into directory ``path`` (created); returns the
    manifest."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    files = {
        "model.npz": write_npz(path / "model.npz", {k: getattr(model, k) for k in MODEL_ARRAYS} | (
            {} if model.marker_prior is None else model.marker_prior.arrays())),
        "detail.npz": write_npz(path / "detail.npz", {"detail": model.detail}),
    }
    if model.colors is not None:
        files["colors.npz"] = write_npz(path / "colors.npz", {"colors": model.colors})
    if model.marker_database is not None:
        md = model.marker_database
        files["markers.npz"] = write_npz(path / "markers.npz", {"shapes": md.shapes, "gram": md.gram,
                                                                "corrections": md.corrections})
    maps = {}
    for name, dm in ((n, getattr(model, a)) for n, a in MAP_FIELDS.items()):
        if dm is not None:
            maps.update({name: dm.maps, f"{name}_texels": dm.texels,
                         f"{name}_shape": np.array(dm.shape, np.int64)})
            if dm.scale is not None:
                maps[f"{name}_scale"] = dm.scale
            if dm.frames is not None:
                maps[f"{name}_frames"] = dm.frames
    if maps:
        files["maps.npz"] = write_npz(path / "maps.npz", maps)
    manifest = {
        "kind": KIND, "format_version": FORMAT_VERSION, "params": model.params.model_dump(mode="json"),
        "region_names": list(model.region_names), "clip_names": list(model.clip_names),
        "clip_fps": list(model.clip_fps),
        "metrics": model.metrics, "files": files,
        "size_bytes": sum((path / f).stat().st_size for f in files),
    }
    write_bytes(path / "manifest.json", json.dumps(manifest, indent=1).encode())
    return manifest


def read_model(path) -> ShapeSpaceData:
    """The stored data written by :func:`write_model` in ``path`` (checksums verified first,
    shapes checked)."""
    # the path as given: a verified directory's digests (models_store.blobs.VerifiedDir)
    manifest, data = read_model_files(path, KIND, FORMAT_VERSION, ("model.npz", "detail.npz"),
                                      mapped=MAPPED_FILES.__contains__)
    path = Path(path)
    a = npz_arrays(data["model.npz"])
    missing = [k for k in MODEL_ARRAYS if k not in a]
    if missing:
        raise ModelCorrupt(f"{path}: model.npz lacks {missing}")
    detail = npz_mapped(data["detail.npz"])["detail"]
    colors = npz_mapped(data["colors.npz"])["colors"] if "colors.npz" in data else None
    marker_database = MarkerDatabase(**npz_mapped(data["markers.npz"])) if "markers.npz" in data else None
    m = npz_mapped(data["maps.npz"]) if "maps.npz" in data else {}
    # models stored before the maps were frame-major hold them texel-major: copied at load
    # (then held in memory, and weighed by the cache), since a request reads whole frames
    maps = {attr: DatabaseMaps(np.ascontiguousarray(m[name]), m[f"{name}_texels"], tuple(int(x) for x in m[f"{name}_shape"]),
                               m.get(f"{name}_frames"), m.get(f"{name}_scale"))
            for name, attr in MAP_FIELDS.items() if name in m}
    fields = dict(params=ShapeSpaceParams(**manifest["params"]), detail=detail, colors=colors,
                  marker_database=marker_database, **maps,
                  region_names=tuple(manifest["region_names"]),
                  clip_names=tuple(manifest["clip_names"]),
                  clip_fps=tuple(float(x) for x in manifest["clip_fps"]),
                  metrics=manifest["metrics"], marker_prior=MarkerPrior.from_arrays(a),
                  **{k: a[k] for k in MODEL_ARRAYS})
    frames, triangles, vertices = len(a["shapes"]), len(a["faces"]), len(a["neutral"])
    if detail.shape != (frames, triangles, 9):
        raise ModelCorrupt(f"{path}: detail.npz has shape {detail.shape}, expected "
                           f"({frames},{triangles},9)")
    for attr, dm in maps.items():
        count = frames if dm.frames is None else len(dm.frames)
        if dm.maps.shape[:2] != (count, len(dm.texels)) or (
                dm.frames is not None and len(dm.frames) and not (
                    np.all(np.diff(dm.frames) > 0) and 0 <= dm.frames[0] and dm.frames[-1] < frames)):
            raise ModelCorrupt(f"{path}: maps.npz has {attr} {dm.maps.shape} for "
                               f"{count} of {frames} frames and {len(dm.texels)} texels")
        if dm.scale is not None and (dm.scale.shape != (count,) or dm.maps.dtype != np.int16):
            raise ModelCorrupt(f"{path}: maps.npz has {attr} {dm.maps.dtype} with steps of shape "
                               f"{dm.scale.shape}, expected int16 and ({count},)")
    md = marker_database
    if md is not None and (md.corrections.shape != (frames, vertices, 3)
                           or md.shapes.shape != a["shapes"].shape or md.gram.shape != a["gram"].shape):
        raise ModelCorrupt(f"{path}: markers.npz has shapes {md.shapes.shape}, gram {md.gram.shape}, "
                           f"corrections {md.corrections.shape} for a model of shapes "
                           f"{a['shapes'].shape} and {vertices} vertices")
    return ShapeSpaceData(**fields)
