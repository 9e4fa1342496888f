"""A pose-space model on disk: ``manifest.json`` + ``model.npz`` (+ ``cache.npz``).

* ``model.npz``  every array of :class:`~.model.PoseSpaceData` in the dtype the model holds
  (the rest mesh and layout, handles, rest markers, pose weights, feature nodes and graph,
  basis features, per-vertex RBF weights (n,P,3) float32, α as CSR arrays ``alpha_data``
  float32 / ``alpha_indices`` / ``alpha_indptr`` (WPSD), the polynomial term (``poly_*``,
  ``map_poly_*``: the linear parts as CSR arrays like α), the map band's texels and weights,
  the training feature range, the marker regression (``regression_*``: low-rank factors and means; a model stored with its full CSR is truncated on reading)); a load reproduces the model bit for bit;
* ``cache.npz``  the thin-shell basis (n,M) float32 and handle energy: derived (a load
  without it recomputes them), listed under ``derived`` and checksummed like the rest;
* ``manifest.json``  kind (``psd`` | ``wpsd``), format version, params, metrics, scalars
  (the regression's input: ``regression_input``, ``"handles"`` where absent), basis names and the sha256 of every file (:mod:`service.methods.model_dir`).

Every file is written atomically, the manifest last.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from service.geometry.marker_prior import MarkerPrior
from service.io.atomic import write_bytes, write_npz
from service.io.npz import npz_arrays, sparse_matrix, sparse_members
from service.methods.model_dir import ModelCorrupt, read_model_files, read_regression
from service.methods.pdm.base_surface import BaseSurface
from service.methods.pose_space.data import PoseSpaceData
from service.methods.pose_space.params import parse_params

FORMAT_VERSION = 1
CACHE = "cache.npz"
ARRAYS = ("faces", "uv", "uv_faces", "neutral", "handles", "rest_markers", "pose_weights",
          "node_triangle", "node_barycentric", "edges", "rest_length", "basis_features", "weights",
          "map_index", "map_weights", "feature_low", "feature_high")
#: CSR arrays (``NAME_data`` / ``_indices`` / ``_indptr`` / ``_shape``) and optional dense arrays
SPARSE = ("alpha", "poly_linear", "map_poly_linear")
OPTIONAL = ("poly_const", "map_poly_const", "marker_mean", "marker_modes", "marker_residual_var")
#: model.npz members of the marker regression (:meth:`.MarkerRegression.arrays`)
REGRESSION = "regression"


def write_model(d: PoseSpaceData, base: BaseSurface, path) -> dict:
    """Write a model's stored data ``d`` (and its thin shell's basis as derived data) into
    directory ``path`` (created); returns the manifest."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    arrays = {k: getattr(d, k) for k in ARRAYS}
    for name in SPARSE:
        m = getattr(d, name)
        if m is not None:
            arrays.update(sparse_members(name, m))
    for name in OPTIONAL:
        if getattr(d, name) is not None:
            arrays[name] = getattr(d, name)
    if d.regression is not None:
        arrays.update(d.regression.arrays(REGRESSION))
    if base.marker_prior is not None:
        arrays.update(base.marker_prior.arrays())
    files = {"model.npz": write_npz(path / "model.npz", arrays)}
    derived = {CACHE: write_npz(path / CACHE, {"basis": base.basis, "energy": base.energy})}
    manifest = {
        "kind": d.kind, "format_version": FORMAT_VERSION, "params": d.params.model_dump(mode="json"),
        "metrics": d.metrics, "map_resolution": d.map_resolution,
        "confidence_scale": d.confidence_scale, "basis_names": list(d.basis_names),
        "marker_prior_scale_mm": _finite_or_none(base.prior_scale_mm),
        "regression_input": d.regression_input,
        "files": files, "derived": derived,
        "size_bytes": sum((path / f).stat().st_size for f in files),
    }
    write_bytes(path / "manifest.json", json.dumps(manifest, indent=1).encode())
    return manifest


def read_model(path) -> tuple[PoseSpaceData, BaseSurface]:
    """The stored data and thin shell of a model written by :func:`write_model` (checksums
    verified first)."""
    given, path = path, Path(path)
    try:
        kind = json.loads((path / "manifest.json").read_bytes()).get("kind")
    except (OSError, ValueError) as e:
        raise ModelCorrupt(f"{path}: no readable manifest.json ({e})") from None
    if kind not in ("psd", "wpsd"):
        raise ModelCorrupt(f"{path}: not a pose-space model (kind {kind!r})")
    # the path as given: a verified directory's digests (models_store.blobs.VerifiedDir)
    manifest, data = read_model_files(given, kind, FORMAT_VERSION, required=("model.npz",))
    a = npz_arrays(data["model.npz"])
    missing = [k for k in ARRAYS if k not in a]
    if missing:
        raise ModelCorrupt(f"{path}: model.npz lacks {missing}")
    sparse = {name: sparse_matrix(a, name) for name in SPARSE}
    # a model stored before marker_noise_mm existed interpolated its markers exactly, and one
    # stored before marker_regression existed has none (WPSD's default is s = 3 since)
    params = parse_params({"marker_noise_mm": 0.0, "marker_regression": None, **manifest["params"]})
    if params.method != kind:
        raise ModelCorrupt(f"{path}: params are for {params.method}, the manifest says {kind}")
    d = PoseSpaceData(params=params, **sparse, **{k: a.get(k) for k in OPTIONAL},
                      regression=read_regression(a, REGRESSION), map_resolution=int(manifest["map_resolution"]),
                      confidence_scale=float(manifest["confidence_scale"]),
                      basis_names=tuple(manifest["basis_names"]), metrics=manifest["metrics"],
                      regression_input=manifest.get("regression_input", "handles"),
                      **{k: a[k] for k in ARRAYS})
    cache = npz_arrays(data[CACHE]) if CACHE in data else {}
    base = BaseSurface.from_smooth(d.neutral, d.faces, d.uv, d.uv_faces, d.handles, d.rest_markers,
                                   basis=cache.get("basis"), energy=cache.get("energy"))
    scale = manifest.get("marker_prior_scale_mm")
    return d, base.with_marker_noise(params.marker_noise_mm, None if scale is None else float(scale),
                                     marker_prior=MarkerPrior.from_arrays(a))


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None
