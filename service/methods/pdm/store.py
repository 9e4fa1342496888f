"""A PDM model on disk: ``manifest.json`` + ``model.npz`` + coefficient maps as EXR.

Layout (DESIGN.md "Data and storage"):

* ``medium.exr``  channels ``x.a0 … z.a<K-1>``: the 3D medium-band PDM in the base surface's
  tangent frames (x tangent along +u, y bitangent, z normal), actor units;
* ``fine.exr``    channels ``n.a0 … n.a<K-1>``: the 1D fine-band PDM along the normal;
* ``albedo.exr``  channels ``r.a0 … b.a<K-1>``: the albedo PTM (if trained with albedo);
* ``neutral.exr`` channels ``x y z``: the neutral's static medium detail (kept per vertex in
  ``model.npz``; add it to the constant term a<K-1> to evaluate the medium map alone);
* ``model.npz``   the marker-space data: smooth neutral, mesh and layout, handles, coarse
  marker mesh, texture axes, PCA axes q̂ r̂ and scales, pose weights, and the training
  deformation vectors S (from which the extrapolation limits of d1, d2 are derived); with
  ``medium_regression``, its low-rank factors and means (``medium_regression_Pq``,
  ``_scale``, ``_Q``, ``_mean_u``, ``_mean_y``: :meth:`.MarkerRegression.arrays`; a model
  stored with the full CSR matrix is truncated on reading); with ``fine_driver`` "strain", the
  strain-driven fine band (``fine_strain_coeffs``, ``_scale``, ``_vertex_box``, ``_target_range``:
  :meth:`.strain_band.StrainBand.arrays`, row-major texel order);
* ``validity.npz`` the validity regions of the training data (:class:`~.validity.ValidityData`:
  ``hull`` at the UV points, ``<band>_envelope`` per evaluated band in row-major texel
  order, the medium band's ``sectors`` and ``sector_box`` against the thin shell of the
  detailed neutral); written when the model has them; a model directory without it (stored
  before they were kept), or without ``sector_box``, derives them from ``S_train`` at load
  (seconds);
* ``cache.npz``   derived data that loading would otherwise recompute (the thin-shell
  basis and handle energy, the extrapolation limits per texel, and each map's covered
  texels ``<band>_index`` with their coefficients ``<band>_coeffs`` (P,C,K) float32, the
  EXR's values): listed under ``derived`` in the manifest, checksummed like the rest, and
  optional (a model directory without it, or without the coefficients, loads, more
  slowly: the EXRs are decoded); ``op_<name>`` the evaluator's operators
  (:meth:`.model.PdmEvaluator.operators`: rasterization, parameter fields, sparse
  sampling matrices, the detailed neutral's shell basis less the base's
  ``op_shell_correction``; issue 23: a level-1 load 4.8 → 0.45 s of CPU; a model stored without them
  derives them at load, as before); ``op_shell_mesh_*`` the compiled mesh's vertex order and
  both bases in it (none for a PDM whose mesh is the marker regression's), mapped instead of permuted at load (level 1, +54 MB on disk: load CPU
  0.87 → 0.69 s, resident after load 438 → 336 MB and after three mesh frames 478 → 427 MB,
  peak 613 → 562 MB; permuted as before when absent) and its :class:`~service.geometry.shell_frames.ShellFrames`
  (``op_shell_mesh_frames_*``, +6.8 MB: 77 ms of a level-1 load not spent building the
  vertex order and incidence; built as before when absent); ``op_strain_texels_corner``,
  ``_weight``, the strain band's vertices → fine texels, and ``op_strain_rho_corner``,
  ``_weight``, its fade's UV points → fine texels (a cache without them rasterizes);
  ``op_strain_band_*``, the band in the evaluator's texel order, coefficients term-major,
  and ``op_strain_field_*``, the strain operators (mapped instead of permuted and built at
  load: a level-1 load −0.4 s CPU; a cache without them permutes and builds); a
  strain-driven model's cache holds none of the (d1, d2) fine band's evaluation arrays
  (``op_fine_terms``, ``op_fine_field_*``, ``op_fine_texel_rho_*``: no frame reads them, the
  band is in ``fine.exr`` for renderers);
  ``op_fine_terms`` and
  ``op_albedo_terms``, the bands' coefficients term-major in the evaluator's texel order,
  and ``op_frame_field_*``, the base surface's FrameField operators (+47 MB at level 1: a
  load maps them instead of copying the coefficients and building the field, load CPU
  0.89 → 0.67 s; copied and built as before when absent); ``op_normal_mapper_*``, the normal
  mapper's arrays (+27 MB, in place of its rasterization ``op_raster_*``, 16 MB, which a
  cache stored before holds and a load then reads to build the mapper); ``op_point_box``,
  the medium band's sector box in its kernel's (D,P,2,3) layout (+34 MB; transposed from
  ``validity.npz``'s at load when absent; none for a regression-mesh PDM, which never
  evaluates the medium band); ``size_bytes`` counts the model without it;
* ``manifest.json`` kind, format version, params, metrics, and the sha256 of every file.

Coefficient ``a<k>`` multiplies term k of ``polynomial.TERM_POWERS[order]`` (for the
biquadratic: d1², d2², d1·d2, d1, d2, 1, as ma2008 eq. 1). Maps are float32 and edge-padded
past the UV charts (so a renderer's filtering at chart borders reads plausible values);
loading reads the covered texels only. Every file is written atomically, the manifest
last; a load verifies every checksum before it trusts a byte.

Loading maps instead of reading (issue 23, cold start): each file is checksummed as it
streams past, and the ``.npz`` archives (uncompressed, as ``np.savez`` writes them) are
memory-mapped member by member (:func:`service.io.npz.npz_mapped`), so the coefficients
come from the cache's ``.npy`` members without an EXR decode, and a load never holds a
file's bytes and its arrays at once.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.geometry.marker_prior import MarkerPrior
from service.geometry.uv_raster import dilate, rasterize_uv
from service.io.atomic import sha256_file, write_bytes, write_npz
from service.io.exr import read_exr, write_exr
from service.io.npz import npz_mapped
from service.methods.model_dir import ModelCorrupt, read_model_files, read_regression
from service.methods.pdm import polynomial
from service.methods.pdm.data import PdmData, PdmDerived
from service.methods.pdm.deformation import DeformationAxes, marker_mesh
from service.methods.pdm.params import PdmParams
from service.methods.pdm.strain_band import StrainBand
from service.methods.pdm.texel_band import CoefficientMap, CoveredTexels
from service.methods.pdm.validity import ValidityData

KIND = "pdm"
FORMAT_VERSION = 1
#: texels of edge padding around the UV charts in the written maps
PAD_TEXELS = 4
COMPONENTS = {"medium": ("x", "y", "z"), "fine": ("n",), "albedo": ("r", "g", "b")}
#: what load would otherwise recompute (thin-shell basis, extrapolation limits): seconds saved
CACHE = "cache.npz"
#: the validity regions of the training data (optional: older model directories lack it)
VALIDITY = "validity.npz"
#: model.npz members of the medium marker regression (``params.medium_regression``)
REGRESSION = "medium_regression"
#: the evaluator's operators (``op_*`` members of the cache) read only while it is built —
#: the normal mapper's rasterization, the element orders, the fields' ``element`` — are read
#: into memory, not mapped: their mapped pages would stay resident with the mapping, uncounted
#: by the model cache (level 1: +29 MB resident, estimate/measured 1.03 -> 0.93)
#: the prefix of the strain-driven fine band's members in ``model.npz``
FINE_STRAIN = "fine_strain"
READ_OPERATORS = ("op_raster_", "_order", "_field_element")


@dataclass(frozen=True)
class StoredCoefficientMap:
    """A band's coefficient map left in the model directory's ``cache.npz`` (issue 23):
    what a loaded model keeps of the medium map when its medium PDM is evaluated from
    ``vertex_coeffs``. Synthesis never reads the map (only saving and the renderers' EXR do),
    so the model holds neither its arrays nor their mapping: :attr:`index` and
    :attr:`coeffs` map the file again when asked (the checksum was verified at load; the
    directory must still exist then). The model cache's weight (:func:`service.methods.footprint.nbytes`)
    then counts what the model holds in memory only.

    resolution : int;  file : Path  the ``cache.npz``;  name : str  the band (``medium``)
    """

    resolution: int
    file: Path
    name: str

    @property
    def index(self) -> np.ndarray:
        """(P,) the covered texels, flat row-major (mapped from the file)."""
        return npz_mapped(self.file)[f"{self.name}_index"]

    @property
    def coeffs(self) -> np.ndarray:
        """(P,C,K) float32 the coefficients (mapped from the file)."""
        return npz_mapped(self.file)[f"{self.name}_coeffs"]

    def mask(self) -> np.ndarray:
        """(H,W) bool: the covered texels."""
        return CoveredTexels(self.resolution, self.index).mask()


def write_model(model: PdmData, derived: PdmDerived, path) -> dict:
    """Write a model's stored data ``model`` and what a load would recompute, ``derived``
    (the cache; see the module docstring), into directory ``path`` (created); returns the
    manifest."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    files = {}
    for name, band in (("medium", model.medium), ("fine", model.fine), ("albedo", model.albedo)):
        if band is None:
            continue
        files[f"{name}.exr"] = _write_band(path / f"{name}.exr", band, COMPONENTS[name])
    m, ax = model.mesh, model.axes
    arrays = {
        "smooth": model.smooth, "faces": model.faces, "uv": model.uv, "uv_faces": model.uv_faces,
        "handles": model.handles, "rest_markers": model.rest_markers,
        "marker_uv": m.uv, "marker_faces": m.faces, "marker_axes": m.axes,
        "q": ax.q, "r": ax.r, "scale": ax.scale, "energy": ax.energy,
        "pose_weights": model.pose_weights, "S_train": model.S_train,
        "neutral_offset": model.neutral_offset,
        **({} if model.vertex_coeffs is None else {"vertex_coeffs": model.vertex_coeffs}),
        "marker_prior_scale_mm": np.float64(model.prior_scale_mm),
        **({} if model.marker_prior is None else model.marker_prior.arrays()),
        **({} if model.medium_skill is None else {"medium_skill": model.medium_skill}),
        **({} if model.medium_regression is None else model.medium_regression.arrays(REGRESSION)),
        **({} if model.fine_strain is None else model.fine_strain.arrays(FINE_STRAIN)),
        "resolutions": np.array([model.medium.resolution, model.fine.resolution,
                                 0 if model.albedo is None else model.albedo.resolution]),
    }
    files["model.npz"] = write_npz(path / "model.npz", arrays)
    files["neutral.exr"] = _write_neutral(path / "neutral.exr", model)
    if model.validity is not None:
        files[VALIDITY] = write_npz(path / VALIDITY, {"hull": model.validity.hull, **{
            f"{name}_envelope": e for name, e in model.validity.envelope.items()}, **(
            {} if model.validity.sectors is None else {"sectors": model.validity.sectors}), **(
            {} if model.validity.sector_box is None else {"sector_box": model.validity.sector_box})})
    cache = {"basis": derived.basis, "energy": derived.energy}
    for name, limit in derived.limits.items():
        cache[f"{name}_limit"] = limit
    for name, band in (("medium", model.medium), ("fine", model.fine), ("albedo", model.albedo)):
        if band is not None:        # the maps' covered texels as stored .npy members (mapped)
            cache[f"{name}_index"], cache[f"{name}_coeffs"] = band.index, band.coeffs
    cache.update({f"op_{k}": v for k, v in derived.operators.items()})
    derived_files = {CACHE: write_npz(path / CACHE, cache)}
    manifest = {
        "kind": KIND, "format_version": FORMAT_VERSION, "params": model.params.model_dump(mode="json"),
        "metrics": model.metrics, "files": files, "derived": derived_files,
        "size_bytes": sum((path / f).stat().st_size for f in files),
        "derived_bytes": sum((path / f).stat().st_size for f in derived_files),
    }
    write_bytes(path / "manifest.json", json.dumps(manifest, indent=1).encode())
    return manifest


def _write_band(file: Path, band: CoefficientMap, components) -> str:
    H = band.resolution
    P, C, K = band.coeffs.shape
    img = np.zeros((H * H, C * K), np.float32)
    img[band.index] = band.coeffs.reshape(P, C * K)
    img = dilate(img.reshape(H, H, C * K), band.mask(), PAD_TEXELS).reshape(H, H, C, K)
    write_exr(file, {f"{c}.a{k}": img[:, :, i, k] for i, c in enumerate(components) for k in range(K)})
    return sha256_file(file)


def _write_neutral(file: Path, model: PdmData) -> str:
    """The per-vertex neutral offset as an x, y, z map at the medium resolution (for renderers:
    the full constant term is ``x.a<K-1> + x``); not read back."""
    H = model.medium.resolution
    raster = rasterize_uv(model.uv, model.uv_faces, H, H)
    img = dilate(raster.interpolate(model.neutral_offset, model.faces), raster.mask, PAD_TEXELS)
    write_exr(file, {c: img[:, :, i] for i, c in enumerate("xyz")})
    return sha256_file(file)


def read_model(path) -> tuple[PdmData, PdmDerived]:
    """The stored data and the derived cache (empty where the directory has none) written
    by :func:`write_model` in ``path`` (checksums verified first)."""
    # every file is checksummed as it streams past and mapped or read only as needed; the
    # path as given, since a directory the blob store verifies (VerifiedDir, VerifyingDir)
    # carries its digests, which Path() would drop (the files were then hashed twice)
    manifest, data = read_model_files(path, KIND, FORMAT_VERSION, mapped=lambda name: True)
    path = Path(path)
    # a model stored before marker_noise_mm existed interpolated its markers exactly; one
    # stored before fine_driver existed has ma2008's fine band only
    params = PdmParams(**{"marker_noise_mm": 0.0, "fine_driver": "deformation", **manifest["params"]})
    a = npz_mapped(data["model.npz"])
    F, uv, uvf = a["faces"], a["uv"], a["uv_faces"]
    K = polynomial.ORDERS[params.order]
    cache = npz_mapped(data[CACHE], read=lambda k: k.startswith("op_") and any(
        k.startswith(p) or k.endswith(p) for p in READ_OPERATORS)) if CACHE in data else {}
    bands = {}
    for name, res in zip(("medium", "fine", "albedo"), a["resolutions"]):
        if res == 0:
            bands[name] = None
            continue
        res, comps = int(res), COMPONENTS[name]
        if f"{name}_coeffs" in cache:        # the covered texels, memory-mapped (no EXR decode)
            index, coeffs = cache[f"{name}_index"], cache[f"{name}_coeffs"]
            if coeffs.shape != (len(index), len(comps), K) or coeffs.dtype != np.float32:
                raise ModelCorrupt(f"{path}: {CACHE} holds {name} coefficients of shape "
                                   f"{coeffs.shape} {coeffs.dtype}, not ({len(index)},{len(comps)},{K}) float32")
            if name == "medium" and "vertex_coeffs" in a:    # synthesis reads vertex_coeffs
                bands[name] = StoredCoefficientMap(res, Path(data[CACHE]), name)
            else:
                bands[name] = CoefficientMap(res, index, coeffs)
            continue
        index = np.flatnonzero(rasterize_uv(uv, uvf, res, res).mask.ravel())
        ch = read_exr(data[f"{name}.exr"])
        try:
            coeffs = np.stack([np.stack([ch[f"{c}.a{k}"].ravel()[index] for k in range(K)], axis=1)
                               for c in comps], axis=1)
        except KeyError as e:
            raise ModelCorrupt(f"{path}: {name}.exr lacks channel {e}") from None
        bands[name] = CoefficientMap(res, index, coeffs)
    # the stored triangles (checksummed with the file) instead of a Delaunay again
    mesh = marker_mesh(a["marker_uv"], a["rest_markers"], a["marker_axes"], faces=a["marker_faces"])
    sm = manifest["metrics"].get("axis_smoothing", {})
    axes = DeformationAxes(a["q"], a["r"], a["scale"], a["energy"], sm.get("replaced", 0),
                           sm.get("worst_angle_deg", 0.0))
    validity = None
    if VALIDITY in data:
        v = npz_mapped(data[VALIDITY])
        validity = ValidityData(v["hull"], {k[:-9]: v[k] for k in v if k.endswith("_envelope")}, v.get("sectors"),
                                v.get("sector_box"))
    model = PdmData(params=params, faces=F, uv=uv, uv_faces=uvf, smooth=a["smooth"], handles=a["handles"],
                    rest_markers=a["rest_markers"], prior_scale_mm=float(a.get("marker_prior_scale_mm", np.nan)),
                    mesh=mesh, axes=axes, pose_weights=a["pose_weights"], S_train=a["S_train"],
                    neutral_offset=a["neutral_offset"], medium=bands["medium"], fine=bands["fine"],
                    albedo=bands["albedo"], metrics=manifest["metrics"], validity=validity,
                    vertex_coeffs=a.get("vertex_coeffs"), marker_prior=MarkerPrior.from_arrays(a),
                    medium_skill=a.get("medium_skill"),
                    medium_regression=read_regression(a, REGRESSION),
                    fine_strain=StrainBand.from_arrays(a, FINE_STRAIN))
    derived = PdmDerived(basis=cache.get("basis"), energy=cache.get("energy"),
                         limits={k[:-6]: cache[k] for k in cache if k.endswith("_limit")},
                         operators={k[3:]: cache[k] for k in cache if k.startswith("op_")})
    return model, derived
