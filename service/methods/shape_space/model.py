"""Shape-space performance enhancement (bermano2014 §4–6): training and the model.

Training (:func:`train`, §4) from the actor's high-resolution neutral d0 and database
clips (frames in vertex correspondence):

1. rigid head motion removed from every frame (weighted Horn, :mod:`.alignment`);
2. frequency separation f(·) of every frame and of the neutral (§4.2 eq. 1);
3. per frame the high-frequency detail (gradients f(d) → d) and the low-frequency shape
   (gradients f(d0) → f(d)), both as rotation log + stretch (:mod:`.encoding`);
4. the low-frequency shape compressed to patch means over ~100-vertex seed-and-grow
   patches (:mod:`.patches`): the columns of D̃;
5. the four voluntary regions with their soft per-triangle weights (§4.3, :mod:`.regions`)
   and the Gram matrices ``D̃ᵀ diag(ω_r) D̃`` per region (§5.3).

Enhancement (:meth:`ShapeSpaceModel.enhance`, §5), per frame on the neutral's topology
(or markers, carried to it by the linear thin shell): align, separate, encode and
compress (§5.1–5.2); convex weights per region (§5.3, :mod:`.simplex_qp`); detail blended
per triangle (§5.4 eq. 4, :mod:`.blending`) and composed with the input's low-frequency
gradients; the prefactored Poisson solve on f(d0) with the boundary term (§5.5); the
result aligned to the input and put back in its pose; colours blended likewise.

Temporal retiming (:meth:`ShapeSpaceModel.retime`, §6) lives in :mod:`.temporal`.

The model is its stored data (:class:`~.data.ShapeSpaceData`, frozen, what :mod:`.store`
round-trips) and a :class:`ShapeSpaceEvaluator` derived from it once (the frequency filter,
the prefactored Poisson solve, the patch averager, the normalized region weights, the map
operators and blenders, the marker shell); enhancement reads both and changes neither.

Departures and choices (beyond those of the modules):

* the Poisson solve's boundary term targets the 1D Laplacian of the *input* frame's
  boundary (aligned, unsmoothed), where the paper writes only "the 1D Laplacian term along
  the mesh boundaries": the input's boundary curve (lip line, eyelids, the neck cut) is
  the shape the detail should not move, and with this reference an input equal to a
  database frame is reproduced exactly (the smoothed frame as reference moved boundary
  vertices of such a frame by up to 0.17 mm on the sample actor);
* after reconstruction the result is aligned (Horn, uniform weights) to the aligned input
  before the input's transform is undone: the Poisson solution is defined up to a
  translation, and the paper's "align it to the database" needs a target — the input's
  own aligned frame is the one that keeps the low frequencies where the input put them;
* the input's low frequencies are restored after the reconstruction (parameter
  ``restore_low_frequencies``, default on): ``x ← x + f(ā) − f(x)``. The composed
  gradients carry the input's low band only approximately — small errors of the blended
  detail integrate over the whole head in the Poisson solve into a smooth drift the rigid
  alignment cannot remove. One correction step puts the low band back where the input has
  it (exactly for the linear ``smoothing="rest"`` filter, to first order for the
  per-frame one) and leaves the transferred detail untouched; an input equal to a
  database frame is unchanged by it. On the level-0 sample actor (held-out in-range
  frames, 126 database frames) it lowered the face RMS error from 0.095 to 0.044 mm and the
  error where the ground truth has detail from 0.105 to 0.080 mm;
* database frames and colours are kept as float32 (the stored precision; the detail store
  is frames × triangles × 9 values), everything else float64, so that a saved and reloaded
  model enhances bit-identically.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import scipy.sparse as sp

from service.geometry.deformation_gradient import (
    PoissonReconstruction, deformation_gradients, rest_frames_inverse,
)
from service.geometry.geodesic import HeatGeodesics
from service.geometry.laplacian import triangle_areas
from service.geometry.marker_filter import MarkerModes
from service.geometry.normal_map import NormalMapper
from service.geometry.normals import vertex_normals
from service.geometry.rigid import rigid_align
from service.geometry.tangent_frames import FrameField
from service.geometry.uv_raster import interpolation_matrix, map_to_vertices, rasterize_uv
from service.methods.inputs import ActorData, Clip, InvalidInput, Progress, check_clips, no_progress
from service.methods.shape_space.alignment import align_frames, stability_weights
from service.methods.shape_space.blending import blend
from service.methods.shape_space.encoding import (
    FrequencySeparator, compose, detail_encoding, encode_gradients, shape_encoding,
)
from service.methods.shape_space.data import ShapeSpaceData
from service.methods.shape_space.maps import DatabaseMaps, MapBlender
from service.methods.shape_space.markers import (
    MIN_VISIBLE_MARKERS, MarkerDatabase, MarkerShell, corrected_input,
)
from service.methods.shape_space.outputs import OUTPUTS
from service.methods.shape_space.params import (
    COMPONENTS, ENHANCE_BATCH_TRIANGLES, VOLUNTARY_REGIONS, WEIGHT_EPS, WHOLE_FACE,
    ShapeSpaceParams,
)
from service.methods.shape_space.patches import PatchAverager, seed_and_grow_patches, triangle_patches
from service.methods.shape_space.regions import (
    actor_regions, derive_regions, normalize_region_weights, region_triangle_weights,
    vertex_region_weights,
)
from service.methods.outputs import check_outputs
from service.methods.shape_space import store
from service.methods.shape_space.simplex_qp import solve_simplex_qp
from service.methods.shape_space.temporal import retime as retime_sequence


#: the stored fields the evaluator is derived from (a change of any other field, e.g. the
#: colours or the marker database, keeps the evaluator; :meth:`ShapeSpaceModel.replace`)
DERIVED_FROM = frozenset({"params", "faces", "neutral", "smooth_neutral", "patches", "tri_patch",
                          "region_weights", "marker_triangle", "marker_barycentric",
                          "marker_weights", "uv", "uv_faces", "marker_prior"})
#: the stored maps and their blenders (:class:`ShapeSpaceEvaluator` attributes of the same name)
MAP_FIELDS = ("fine_maps", "albedo_maps")


@dataclass(frozen=True)
class ShapeSpaceEvaluator:
    """What enhancement reuses, derived once from :class:`~.data.ShapeSpaceData` (bermano2014 §5).

    Attributes (n vertices, m triangles, R regions)
    ----------
    separator : FrequencySeparator        the frequency filter f(·) (§4.2 eq. 1)
    poisson : PoissonReconstruction       prefactored on f(d0), with the boundary term (§5.5)
    averager : PatchAverager              triangle values → patch means (§4.2)
    rest_inverse : (m,3,3) float64        inverse rest frames of f(d0)
    omega_hat : (R,m) float64             normalized region weights per triangle (§5.4 eq. 4)
    vertex_omega_hat : (R,n) float64      the same per vertex (colours, corrections, maps, timing)
    map_operator : (H²,n) CSR             vertex values → the ``map_resolution`` UV map
    normal_mapper : NormalMapper          tangent-space normal maps at ``map_resolution``
    shell : MarkerShell | None            the linear thin shell of marker input (None: no markers)
    frame_field : FrameField              tangent frames of deformed poses (marker corrections,
                                          normal maps)
    fine_maps, albedo_maps : MapBlender | None   the database's maps, ready to blend (the fine
                                          maps also sampled at the vertices: ``mesh_detailed``)
    """

    separator: FrequencySeparator
    poisson: PoissonReconstruction
    averager: PatchAverager
    rest_inverse: np.ndarray
    omega_hat: np.ndarray
    vertex_omega_hat: np.ndarray
    map_operator: sp.csr_matrix
    normal_mapper: NormalMapper
    shell: MarkerShell | None
    frame_field: FrameField
    fine_maps: MapBlender | None
    albedo_maps: MapBlender | None

    @classmethod
    def build(cls, d: ShapeSpaceData) -> "ShapeSpaceEvaluator":
        """Precompute everything of the class docstring from the stored data ``d``."""
        p = d.params
        vertex_omega_hat = normalize_region_weights(
            vertex_region_weights(d.faces, d.region_weights, d.n_vertices))
        H = p.map_resolution
        raster = rasterize_uv(d.uv, d.uv_faces, H, H)
        shell = None
        if d.n_markers:
            shell = MarkerShell.build(d.neutral, d.faces, d.marker_triangle, d.marker_barycentric,
                                      d.marker_weights).with_marker_noise(
                p.marker_noise_mm, d.metrics.get("marker_prior_scale_mm"), d.marker_prior)
        return cls(
            separator=FrequencySeparator(d.faces, p.lam_dt, p.smoothing, rest=d.neutral),
            poisson=PoissonReconstruction(d.smooth_neutral, d.faces, boundary_weight=p.boundary_weight),
            averager=PatchAverager(d.tri_patch, triangle_areas(d.smooth_neutral, d.faces),
                                   int(d.patches.max()) + 1),
            rest_inverse=rest_frames_inverse(d.smooth_neutral, d.faces),
            omega_hat=normalize_region_weights(d.region_weights),
            vertex_omega_hat=vertex_omega_hat,
            map_operator=interpolation_matrix(raster, d.faces, d.n_vertices),
            normal_mapper=NormalMapper(raster, d.faces, d.uv, d.uv_faces, d.n_vertices),
            shell=shell, frame_field=FrameField.build(d.neutral, d.faces, d.uv, d.uv_faces),
            **cls.map_blenders(d, vertex_omega_hat, raster.mask))

    @staticmethod
    def map_blenders(d: ShapeSpaceData, vertex_omega_hat: np.ndarray,
                     covered: np.ndarray | None = None) -> dict[str, MapBlender | None]:
        """The :class:`~.maps.MapBlender` of each of ``d``'s maps (None where it has none); the
        fine maps resample to ``map_resolution`` (they are added to the displacement;
        ``covered`` the layout's texels at that size, if rasterized already)."""
        resolution = {"fine_maps": d.params.map_resolution, "albedo_maps": None}
        return {name: None if getattr(d, name) is None else
                MapBlender.build(getattr(d, name), d.uv, d.uv_faces, d.faces, vertex_omega_hat,
                                 resolution[name], covered if resolution[name] else None,
                                 vertex_sampler=name == "fine_maps")
                for name in MAP_FIELDS}


class ShapeSpaceModel:
    """A trained shape-space model (bermano2014): the stored :class:`~.data.ShapeSpaceData` and
    its :class:`ShapeSpaceEvaluator`. Build with :func:`train` or :meth:`load`.

    The stored fields read through: ``model.detail`` is ``model.data.detail`` (the
    attributes of :class:`~.data.ShapeSpaceData`). Neither part changes after construction;
    :meth:`replace` gives a model with other stored fields.
    """

    def __init__(self, data: ShapeSpaceData, evaluator: ShapeSpaceEvaluator | None = None):
        self.data = data
        self.evaluator = evaluator or ShapeSpaceEvaluator.build(data)

    def __getattr__(self, name: str):
        # only reached for names that are not the model's own: the stored fields
        if name in _DATA_FIELDS and "data" in self.__dict__:
            return getattr(self.data, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def replace(self, **changes) -> "ShapeSpaceModel":
        """A model with some stored fields changed (e.g. ``marker_database=None``). The
        evaluator is kept when no field it is derived from changes (:data:`DERIVED_FROM`;
        changed maps rebuild only their blenders)."""
        data = dataclasses.replace(self.data, **changes)
        if changes.keys() & DERIVED_FROM:
            return ShapeSpaceModel(data)
        evaluator = self.evaluator
        if changes.keys() & set(MAP_FIELDS):
            blenders = ShapeSpaceEvaluator.map_blenders(data, evaluator.vertex_omega_hat)
            evaluator = dataclasses.replace(evaluator, **{k: blenders[k] for k in changes.keys() & set(MAP_FIELDS)})
        return ShapeSpaceModel(data, evaluator)

    # ------------------------------------------------------------------ sizes
    @property
    def n_vertices(self) -> int:
        return self.data.n_vertices

    @property
    def n_frames(self) -> int:
        return self.data.n_frames

    @property
    def n_patches(self) -> int:
        return self.data.n_patches

    @property
    def n_markers(self) -> int:
        return self.data.n_markers

    @property
    def marker_modes(self) -> MarkerModes | None:
        """The modes of the learned marker prior, in which a synthesis job's
        ``marker_filter_frames: "auto"`` filters the take
        (:func:`~service.geometry.marker_filter.filter_performance`); None without a prior."""
        shell = self.evaluator.shell
        return None if shell is None else MarkerModes.of(shell.rest, self.data.marker_prior, shell.weights)

    def component_weights(self, region: int | None) -> np.ndarray:
        """Ω_r (9P,): region r's patch weights repeated over the 9 components (None: all 1)."""
        if region is None:
            return np.ones(self.data.shapes.shape[1])
        return np.repeat(self.data.patch_weights[region], COMPONENTS)

    # ------------------------------------------------------------------ encoding
    def encode(self, frames: np.ndarray, shape: bool = True) -> dict[str, np.ndarray | list]:
        """Align, separate, encode and compress frames on the neutral's topology (§5.1–5.2).

        Parameters
        ----------
        frames : (F,n,3) float   world-space vertices, mm
        shape : bool             also the compressed shape vectors (the polar decomposition
                                 and logarithm of every gradient: most of the cost); not
                                 needed to compose detail with the gradients

        Returns
        -------
        dict with ``aligned`` (F,n,3) float64, ``transforms`` (list of F RigidTransform,
        world → database frame), ``low`` (F,n,3) f(aligned), ``G_low`` (F,m,3,3) gradients
        f(d0) → f(ā) and ``shape`` (F,9P) the compressed vectors ã (None without ``shape``)
        """
        frames = self._check_vertices(frames)
        aligned, transforms = align_frames(frames, self.data.neutral, self.data.align_weights)
        low = self.low_frequencies(aligned)
        G_low = deformation_gradients(self.data.smooth_neutral, low, self.data.faces, self.evaluator.rest_inverse)
        if not shape:
            return {"aligned": aligned, "transforms": transforms, "low": low, "G_low": G_low,
                    "shape": None}
        x = encode_gradients(G_low)                                              # (F,m,9)
        vectors = self.evaluator.averager(x).reshape(len(frames), -1)
        return {"aligned": aligned, "transforms": transforms, "low": low, "G_low": G_low,
                "shape": vectors}

    def low_frequencies(self, frames: np.ndarray) -> np.ndarray:
        """f(frames) (F,n,3) float64 (§4.2 eq. 1), frame by frame: the frequency filter's
        solve of one frame's three columns, so that a frame's result does not depend on the
        batch it came in (a solve of more columns rounds differently)."""
        return np.stack([self.evaluator.separator(x) for x in frames])

    def match(self, shape: np.ndarray, markers: bool = False) -> dict[str, np.ndarray]:
        """Convex weights per region for one compressed vector ã (9P,) (§5.3 eq. 3).

        ``markers``: ã is a marker shell's, matched against the database frames' shells
        (``marker_database``, :mod:`.markers`) where the model has them.

        Returns
        -------
        dict with ``weights`` (R,N) float64 (rows on the simplex), ``nonzero`` (R,) int
        (weights above :data:`~.params.WEIGHT_EPS`) and ``error`` (R,) float, the
        Ω_r-weighted RMS of ``D̃ w_r − ã`` per component (rad / dimensionless)
        """
        R, N = len(self.data.region_names), self.n_frames
        space = self.data.marker_database if markers and self.data.marker_database is not None else self.data
        W = np.empty((R, N))
        err = np.empty(R)
        for r in range(R):
            Om = self.component_weights(r)
            res = solve_simplex_qp(space.gram[r], space.shapes @ (Om * shape))
            W[r] = res.w
            sq = res.objective + float(shape @ (Om * shape))
            err[r] = np.sqrt(max(sq, 0.0) / max(Om.sum(), 1e-300))
        return {"weights": W, "nonzero": np.count_nonzero(W > WEIGHT_EPS, axis=1), "error": err}

    # ------------------------------------------------------------------ enhancement
    def enhance(self, frames: np.ndarray, outputs: Sequence[str] = ("mesh",),
                input_kind: str = "auto") -> dict[str, np.ndarray]:
        """Enhanced meshes for frames without detail (bermano2014 §5).

        Parameters
        ----------
        frames : (F,n,3) float   vertices on the neutral's topology (e.g. a rig propagated to
                 it, or a medium-resolution surface), world pose, mm; or (F,M,3) markers
                 (NaN when occluded), carried to the neutral by the linear thin shell
        outputs : subset of :data:`OUTPUTS`: ``mesh`` (always computed), ``mesh_detailed``,
                  ``displacement``, ``albedo``, ``normal_map``, ``colors``
        input_kind : "auto" | "vertices" | "markers"   how to read ``frames`` (auto: by count)

        Returns
        -------
        dict with
        ``vertices`` (F,n,3) float32   enhanced meshes in the input's world pose, mm;
        ``vertices_detailed`` (F,n,3) float32  (``mesh_detailed``) ``vertices`` with the
                                        blended fine maps (below) sampled at the vertices and
                                        added along the vertex normals; ``vertices`` itself
                                        for a model without fine maps (its detail is all in
                                        the mesh);
        ``faces`` (m,3) int32;
        ``weights`` (F,R,N) float32    the convex weights per region (§5.3);
        ``nonzero`` (F,R) int32        weights above :data:`~.params.WEIGHT_EPS` per region;
        ``match_error`` (F,R) float32  weighted RMS shape-space distance of the projection;
        ``displacement`` (F,H,H) float32  (if asked) the detail over the input surface, mm,
                                        as a map over the neutral's UVs (H =
                                        ``map_resolution``; 0 where no triangle covers a
                                        texel): the enhanced surface's offset from the input
                                        along the input's vertex normals, plus the blended
                                        ``fine_displacement`` if the model has maps;
        ``fine_displacement`` (F,Hf,Wf) float32  (with ``displacement``, for a model with
                                        ``fine_maps``) the database's fine maps blended with
                                        the same weights, relative to ``vertices``, at the
                                        database maps' resolution (:mod:`.maps`);
        ``vertex_displacement`` (F,n) float32  (with ``displacement``) the same per vertex,
                                        ``(x − a) · n_a``;
        ``albedo`` (F,Ha,Wa,3) float32  (if asked; the model needs albedo maps) the
                                        database's albedo maps blended with the same weights;
        ``normal_map`` (F,H,H,3) float32  (if asked) the tangent-space normal map of
                                        ``displacement`` on the input surface (what renders
                                        the input mesh with the enhanced detail);
        ``colors`` (F,n,C) float32     (if asked; the model needs colours) blended colours;
        ``input_vertices`` (F,n,3) float32  for marker input: the thin-shell surface;
        ``corrected_input`` (F,n,3) float32  for marker input to a model with
                                        ``marker_database``: the shell plus its blended
                                        pose-space correction (:mod:`.markers`), the
                                        surface that was enhanced;
        ``region_names`` (R,) str

        Raises
        ------
        InvalidInput   wrong shapes, unknown outputs, colours asked of a model without them
        """
        check_outputs(outputs, OUTPUTS)
        if "colors" in outputs and self.data.colors is None:
            raise InvalidInput("this model was trained without colours; 'colors' is not available")
        if "albedo" in outputs and self.data.albedo_maps is None:
            raise InvalidInput("this model's database had no albedo maps; 'albedo' is not available")
        frames = np.asarray(frames, dtype=np.float64)
        if frames.ndim == 2:
            frames = frames[None]
        kind = self._input_kind(frames, input_kind)
        out: dict[str, np.ndarray] = {}
        correct = kind == "markers" and self.data.marker_database is not None
        if kind == "markers":
            frames = self.markers_to_vertices(frames)
            out["input_vertices"] = frames.astype(np.float32)
            if correct:
                out["corrected_input"] = np.empty(frames.shape, np.float32)
        nf, n, R, N = len(frames), self.n_vertices, len(self.data.region_names), self.n_frames
        out.update({
            "vertices": np.empty((nf, n, 3), np.float32),
            "faces": self.data.faces.astype(np.int32),
            "weights": np.empty((nf, R, N), np.float32),
            "nonzero": np.empty((nf, R), np.int32),
            "match_error": np.empty((nf, R), np.float32),
            "region_names": np.array(self.data.region_names),
        })
        want = set(outputs)
        disp = bool(want & {"displacement", "normal_map"})          # the displacement is computed
        fine = bool(want & {"displacement", "normal_map", "mesh_detailed"}) and self.data.fine_maps is not None
        if disp:
            H = self.data.params.map_resolution
            out["vertex_displacement"] = np.empty((nf, n), np.float32)
            out["displacement"] = np.empty((nf, H, H), np.float32)
        if "mesh_detailed" in want:
            out["vertices_detailed"] = np.empty((nf, n, 3), np.float32)
        ev = self.evaluator
        batch = max(1, ENHANCE_BATCH_TRIANGLES // max(len(self.data.faces), 1))
        # the blended maps at the covered texels: one batch's at a time, in work arrays reused
        # by every batch (a whole request's (F,P,C) values were fresh memory: 86 MB of first
        # touches for 30 level-1 frames), made into images straight into the outputs
        texel_maps = {"fine_displacement": ev.fine_maps if fine else None,
                      "albedo": ev.albedo_maps if "albedo" in outputs else None}
        texel_maps = {k: (m, np.empty((min(batch, nf),) + m.maps.shape[1:], np.float32))
                      for k, m in texel_maps.items() if m is not None}
        if "albedo" in texel_maps:
            C = ev.albedo_maps.maps.shape[2]
            out["albedo"] = np.zeros((nf,) + ev.albedo_maps.shape + ((C,) if C > 1 else ()), np.float32)
        # the fine maps' images at their stored size (the ``fine_displacement`` output), none
        # when only the normal map or the detailed mesh needed the displacement; when that
        # is the displacement's size too, they are the images added to it (not made twice)
        if fine and "displacement" in want:
            out["fine_displacement"] = np.zeros((nf,) + ev.fine_maps.shape, np.float32)
        same_size = ev.fine_maps is not None and ev.fine_maps.shape == (self.data.params.map_resolution,) * 2
        if "colors" in outputs:
            out["colors"] = np.empty((nf, n, self.data.colors.shape[2]), np.float32)
        for a in range(0, nf, batch):
            b = min(nf, a + batch)
            inputs = frames[a:b]
            enc = self.encode(inputs)
            W = np.empty((b - a, R, N))
            for f, shape in enumerate(enc["shape"]):
                m = self.match(shape, markers=kind == "markers")
                W[f] = out["weights"][a + f] = m["weights"]
                out["nonzero"][a + f] = m["nonzero"]
                out["match_error"][a + f] = m["error"]
            if correct:
                enc = self._pose_space_correction(enc, W)
                out["corrected_input"][a:b] = np.stack([
                    T.inverse().apply(x) for T, x in zip(enc["transforms"], enc["aligned"])])
            world = self._reconstruct(enc, W)
            out["vertices"][a:b] = world
            if disp:
                normals = vertex_normals(inputs, self.data.faces)
                out["vertex_displacement"][a:b] = np.einsum("fnd,fnd->fn", world - inputs, normals)
            values = {}
            for key, (maps, work) in texel_maps.items():
                values[key] = work[:b - a]
                for f in range(b - a):
                    maps.blend(W[f], out=values[key][f])
            if "albedo" in values:
                ev.albedo_maps.database.image(values["albedo"], out=out["albedo"][a:b])
            if disp:      # per batch: a whole request's (F,H²) float64 maps are GBs at 1024²
                self.vertex_map(out["vertex_displacement"][a:b], out=out["displacement"][a:b])
                if fine:
                    if "fine_displacement" in out:
                        image = ev.fine_maps.database.image(values["fine_displacement"], out=out["fine_displacement"][a:b])
                    if "fine_displacement" not in out or not same_size:
                        image = ev.fine_maps.image(values["fine_displacement"], self.data.params.map_resolution)
                    out["displacement"][a:b] += image
            if "mesh_detailed" in want:
                detailed = world
                if fine:
                    h = np.stack([ev.fine_maps.vertex_sampler @ values["fine_displacement"][f][:, 0]
                                  for f in range(b - a)])
                    detailed = world + h[..., None] * vertex_normals(world, self.data.faces)
                out["vertices_detailed"][a:b] = detailed
            if "colors" in outputs:
                for f in range(b - a):
                    out["colors"][a + f] = blend(self.data.colors, self.evaluator.vertex_omega_hat, W[f])
        if "normal_map" in want:
            H = self.data.params.map_resolution
            out["normal_map"] = np.empty((nf, H, H, 3), np.float32)
            for f, (h, V) in enumerate(zip(out["displacement"], frames)):
                ev.normal_mapper.normal_map(h, V, ev.frame_field.frames(V), out=out["normal_map"][f])
        if "displacement" not in want:        # computed for the normal map or the detailed mesh
            for key in ("displacement", "vertex_displacement", "fine_displacement"):
                out.pop(key, None)
        return out

    def _reconstruct(self, enc: dict, weights: np.ndarray) -> np.ndarray:
        """The enhanced frames (B,n,3) float64 in the inputs' world pose from their encoding
        (:meth:`encode`) and convex weights (B,R,N) (bermano2014 §5.4–5.5): detail blended
        per triangle (eq. 4) and composed with the input's low-frequency gradients, the
        prefactored Poisson solve on f(d0) with the input's boundary, the result aligned to
        the aligned input, its low frequencies restored, and the input's pose put back.

        The frames of a batch go through the per-triangle arithmetic together (one
        (B,m,3,3) array) and through each solve one at a time (its three columns), so a
        frame's result is bit for bit the one it gets alone."""
        aligned = enc["aligned"]
        bh = np.stack([blend(self.data.detail, self.evaluator.omega_hat, w) for w in weights])  # (B,m,9)
        G = compose(bh, enc["G_low"])
        X = self.evaluator.poisson.solve(G, boundary_reference=aligned)
        X = np.stack([rigid_align(x, y).apply(x) for x, y in zip(X, aligned)])
        if self.data.params.restore_low_frequencies:
            X = X + enc["low"] - self.low_frequencies(X)
        return np.stack([T.inverse().apply(x) for T, x in zip(enc["transforms"], X)])

    def vertex_map(self, values: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Per-vertex values (F,n) as UV maps (F,H,H) float32 over the neutral's layout
        (written into ``out`` (F,H,H) float32 if given, and returned).

        Barycentric interpolation into every texel a triangle covers (0 elsewhere), at
        ``params.map_resolution`` texels per side (the evaluator's sparse (H², n) operator),
        in float64, rounded to float32 once.
        """
        H = self.data.params.map_resolution
        values = np.asarray(values, dtype=np.float64)
        maps = (self.evaluator.map_operator @ values.T).T                   # (F,H²)
        if out is None:
            return maps.reshape(len(values), H, H).astype(np.float32)
        out[...] = maps.reshape(len(values), H, H)
        return out

    def synthesize(self, frames: np.ndarray, outputs: Sequence[str] = ("mesh",),
                   clamp: bool = True) -> dict[str, np.ndarray]:
        """:meth:`enhance` under the method-uniform name of DESIGN.md (``clamp`` is unused:
        convex weights never extrapolate the database)."""
        return self.enhance(frames, outputs)

    def _check_vertices(self, frames: np.ndarray) -> np.ndarray:
        """Finite (F,n,3) float64 frames on the neutral's topology, or :class:`InvalidInput`."""
        frames = np.asarray(frames, dtype=np.float64)
        if frames.ndim == 2:
            frames = frames[None]
        if frames.ndim != 3 or frames.shape[1:] != (self.n_vertices, 3):
            raise InvalidInput(f"frames must be (F,{self.n_vertices},3) vertices on the neutral's "
                               f"topology, got {frames.shape}")
        if not np.isfinite(frames).all():
            bad = np.flatnonzero(~np.isfinite(frames).all(axis=(1, 2)))
            raise InvalidInput(f"frame {bad[0]} has non-finite vertices")
        return frames

    def _input_kind(self, frames: np.ndarray, input_kind: str) -> str:
        """``"vertices"`` or ``"markers"`` for (F,k,3) frames (auto: by k), or :class:`InvalidInput`."""
        if input_kind not in ("auto", "vertices", "markers"):
            raise InvalidInput(f"input_kind must be 'auto', 'vertices' or 'markers', got {input_kind!r}")
        if frames.ndim != 3 or frames.shape[2] != 3:
            raise InvalidInput(f"frames must be (F,k,3), got {frames.shape}")
        if input_kind != "auto":
            return input_kind
        if frames.shape[1] == self.n_vertices:
            return "vertices"
        if self.n_markers and frames.shape[1] == self.n_markers:
            return "markers"
        raise InvalidInput(f"frames must be (F,{self.n_vertices},3) vertices"
                           + (f" or (F,{self.n_markers},3) markers" if self.n_markers else "")
                           + f", got {frames.shape}")

    # ------------------------------------------------------------------ markers
    def markers_to_vertices(self, markers: np.ndarray) -> np.ndarray:
        """The neutral deformed to markers (F,M,3) by the linear thin shell, (F,n,3) world
        vertices (bickel2008 §4; bermano2014 §5.1 "marker" input; :class:`.markers.MarkerShell`)."""
        if self.evaluator.shell is None:
            raise InvalidInput("this model has no marker layout; give vertices")
        return self.evaluator.shell(markers)

    def _pose_space_correction(self, enc: dict, weights: np.ndarray) -> dict:
        """The encoding (:meth:`encode`) of shell inputs' corrected surfaces
        ā' = ā + Frameᵀ(ā) · c, c the database corrections blended with each frame's
        ``weights`` (B,R,N) (:mod:`.markers`), in the shells' world pose.

        The weights stay those of the shell's match against the database's shells (like
        with like); ā' is encoded again (gradients only, no shape vector) because its
        low-frequency gradients orient the blended detail. (Keeping the shell's gradients
        and adding the correction to the restored low band instead saves that encoding, but
        leaves a database frame's own markers 0.028 mm RMS, 0.36 mm at worst, off the frame
        on the level-0 actor.)
        """
        frame_field = self.frame_field()
        corrected = np.stack([
            T.inverse().apply(corrected_input(frame_field, a, blend(
                self.data.marker_database.corrections, self.evaluator.vertex_omega_hat, w)))  # (n,3)
            for T, a, w in zip(enc["transforms"], enc["aligned"], weights)])
        return self.encode(corrected, shape=False)

    def frame_field(self) -> FrameField:
        """Per-vertex tangent frames of deformed poses (:mod:`.markers`, normal maps)."""
        return self.evaluator.frame_field

    # ------------------------------------------------------------------ temporal
    def sequences(self) -> list[np.ndarray]:
        """Database sequences of §6.1 as index arrays into the database frames: one per clip,
        cut into windows of ``sequence_seconds`` with 50 % overlap when set (at least 3 kept
        frames a window)."""
        out = []
        for c in range(len(self.data.clip_names)):
            idx = np.flatnonzero(self.data.frame_clip == c)
            if len(idx) < 2:
                continue
            win = 0
            if self.data.params.sequence_seconds > 0:
                win = max(3, int(round(self.data.params.sequence_seconds * self.data.clip_fps[c]
                                       / self.data.params.frame_stride)) + 1)
            if win and len(idx) > win:
                step = max(1, win // 2)
                starts = list(range(0, len(idx) - win + 1, step))
                if starts[-1] + win < len(idx):
                    starts.append(len(idx) - win)
                out.extend(idx[s:s + win] for s in starts)
            else:
                out.append(idx)
        if not out:
            raise InvalidInput("the database has no sequence of two or more frames to retime with")
        return out

    def retime(self, keyframes: np.ndarray, length: int, extend: bool = False) -> dict[str, np.ndarray]:
        """Data-driven timing between two keyframes (bermano2014 §6.2), per region.

        Parameters
        ----------
        keyframes : (2,n,3) float   the two keyframes on the neutral's topology, world pose, mm
        length : int                frames of the result m ≥ 2, keyframes included
        extend : bool               extend the matched subsequence to the full database motion

        Returns
        -------
        dict with ``vertices`` (m,n,3) float32 (the keyframes interpolated per vertex with the
        region-blended timing; frame 0 and m−1 are the keyframes), ``timestamps`` (m,) and
        ``progress`` (m,) of the whole face (:class:`~.temporal.Retiming`),
        ``region_timestamps`` / ``region_progress`` (R,m), ``region_sequences`` (R,) int (the
        chosen sequence, an index into :meth:`sequences`), ``region_spans`` (R,2) (the matched,
        possibly extended, subsequence as positions along that sequence: 0-based, in its
        kept frames, fractional between them)
        """
        keyframes = self._check_vertices(keyframes)
        if len(keyframes) != 2:
            raise InvalidInput(f"retime takes exactly two keyframes, got {len(keyframes)}")
        if not isinstance(length, (int, np.integer)) or length < 2:
            raise InvalidInput(f"length must be an integer >= 2, got {length!r}")
        shape = self.encode(keyframes)["shape"]
        seqs = [self.data.shapes[idx] for idx in self.sequences()]
        R = len(self.data.region_names)
        whole = retime_sequence(shape[0], shape[1], seqs, int(length), None, extend)
        per = [retime_sequence(shape[0], shape[1], seqs, int(length), self.component_weights(r), extend)
               for r in range(R)]
        S = np.stack([p.progress for p in per])                               # (R,m)
        s_v = S.T @ self.evaluator.vertex_omega_hat                                    # (m,n)
        V = keyframes[0] + s_v[..., None] * (keyframes[1] - keyframes[0])
        return {
            "vertices": V.astype(np.float32),
            "timestamps": whole.timestamps, "progress": whole.progress,
            "region_timestamps": np.stack([p.timestamps for p in per]),
            "region_progress": S,
            "region_sequences": np.array([p.sequence for p in per]),
            "region_spans": np.array([p.span for p in per]),
            "region_names": np.array(self.data.region_names),
        }

    # ------------------------------------------------------------------ storage
    def save(self, path) -> dict:
        """Write the model directory (manifest.json + npz files); see :mod:`.store`."""
        return store.write_model(self.data, path)

    @classmethod
    def load(cls, path) -> "ShapeSpaceModel":
        """Read a model directory written by :meth:`save`, verifying checksums."""
        return cls(store.read_model(path))


# ---------------------------------------------------------------------- training
def _database_frames(clips: Sequence[Clip], stride: int):
    """(clip index, frame index) of the kept frames and their vertices (N,n,3) float64."""
    which = [(c, f) for c, clip in enumerate(clips) for f in range(0, clip.frames, stride)]
    frame_clip = np.array([c for c, _ in which], dtype=np.int64)
    frame_index = np.array([f for _, f in which], dtype=np.int64)
    V = np.concatenate([np.asarray(clip.vertices[::stride], dtype=np.float64) for clip in clips])
    return frame_clip, frame_index, V


def _vertex_colors(actor: ActorData, clips: Sequence[Clip], stride: int,
                   vertex_colors: Sequence[np.ndarray] | None) -> np.ndarray | None:
    """Per-vertex colours (N,n,C) float32 of the kept frames: given, or sampled from albedo maps."""
    n = actor.n_vertices
    if vertex_colors is not None:
        if len(vertex_colors) != len(clips):
            raise InvalidInput(f"vertex_colors: one array per clip expected, got {len(vertex_colors)} "
                               f"for {len(clips)} clips")
        out = []
        for clip, col in zip(clips, vertex_colors):
            col = np.asarray(col)
            if col.ndim != 3 or col.shape[:2] != (clip.frames, n):
                raise InvalidInput(f"vertex_colors of clip '{clip.name}' must be ({clip.frames},{n},C), "
                                   f"got {col.shape}")
            out.append(col[::stride])
        if len({c.shape[2] for c in out}) > 1:
            raise InvalidInput("vertex_colors differ in channel count between clips")
        return np.concatenate(out).astype(np.float32)
    if all(c.albedo is not None for c in clips):
        cols = [map_to_vertices(np.asarray(a, dtype=np.float64), actor.uv, actor.uv_faces, actor.faces, n)
                for clip in clips for a in clip.albedo[::stride]]
        return np.nan_to_num(np.stack(cols)).astype(np.float32)
    return None


def train(actor: ActorData, clips: Sequence[Clip], params: ShapeSpaceParams = ShapeSpaceParams(),
          progress: Progress = no_progress, vertex_colors: Sequence[np.ndarray] | None = None
          ) -> ShapeSpaceModel:
    """Build a shape-space model from database clips (bermano2014 §4; steps in the module docstring).

    Parameters
    ----------
    actor : ActorData            the high-resolution neutral d0 (and markers, regions if any)
    clips : sequence of Clip     database performances in vertex correspondence with d0
    params : ShapeSpaceParams
    progress : Progress
    vertex_colors : list of (F_c,n,C) float | None   per-vertex colours per clip (e.g.
                                 albedo); by default sampled from the clips' albedo maps
                                 when every clip has them, else the model has no colours

    Clips may differ in which maps they carry: the fine displacement and albedo maps of the
    clips that have them are kept and blended over those frames (:mod:`.maps`, "Clips
    without maps"), and ``metrics["maps_partial"]`` names the clips without and the rule.
    Per-vertex colours sampled from albedo need albedo in every clip.

    Raises
    ------
    InvalidInput   clips that do not match the actor, a database of fewer than 2 frames,
                   missing actor regions with ``regions="actor"``, regions that cannot be derived
    """
    clips = list(clips)
    check_clips(actor, clips, mixed_maps=True)
    p = params
    F = np.asarray(actor.faces, dtype=np.int64)
    d0 = np.asarray(actor.vertices, dtype=np.float64)
    n, m = len(d0), len(F)
    frame_clip, frame_index, frames = _database_frames(clips, p.frame_stride)
    N = len(frames)
    if N < 2:
        raise InvalidInput(f"the database needs at least 2 frames, got {N}")

    progress(0.0, "alignment")
    align_w = stability_weights(frames, d0)
    aligned, _ = align_frames(frames, d0, align_w, inplace=True)     # frames: our own copy
    del frames

    progress(0.1, "patches")
    labels = seed_and_grow_patches(d0, F, p.patch_size, p.patch_seed, p.patch_relax_iterations)
    tri_patch = triangle_patches(F, labels)
    P = int(labels.max()) + 1
    separator = FrequencySeparator(F, p.lam_dt, p.smoothing, rest=d0)
    smooth0 = separator(d0)
    averager = PatchAverager(tri_patch, triangle_areas(smooth0, F), P)

    progress(0.15, "encoding")
    shapes = np.empty((N, P * COMPONENTS))
    detail = np.empty((N, m, COMPONENTS), np.float32)
    chunk = 16 if p.smoothing == "rest" else 1
    rest_inverse = rest_frames_inverse(smooth0, F)
    for s in range(0, N, chunk):
        low = separator(aligned[s:s + chunk])
        for k in range(len(low)):
            _, x = shape_encoding(smooth0, low[k], F, rest_inverse)
            shapes[s + k] = averager(x).ravel()
            detail[s + k] = detail_encoding(low[k], aligned[s + k], F)
        progress(0.15 + 0.65 * min(s + chunk, N) / N, "encoding")

    progress(0.8, "regions")
    region_info: dict = {"source": p.regions}
    if p.regions == "whole":
        names, region_vertices = WHOLE_FACE, np.ones((1, n), dtype=bool)
    elif p.regions == "actor" or (p.regions == "auto" and all(k in actor.regions for k in VOLUNTARY_REGIONS)):
        names, region_vertices = VOLUNTARY_REGIONS, actor_regions(dict(actor.regions), n)
        region_info["source"] = "actor"
    else:
        names = VOLUNTARY_REGIONS
        aligned -= d0                                                 # the motion, in place
        region_vertices, info = derive_regions(d0, F, aligned, np.array(p.up_axis),
                                               np.array(p.left_axis), p.region_motion_fraction,
                                               p.region_seed)
        region_info.update(source="derived", **info)
    del aligned
    if len(names) == 1:
        omega = np.ones((1, m))
    else:
        omega = region_triangle_weights(d0, F, region_vertices, p.region_falloff, HeatGeodesics(d0, F))
    patch_w = averager(omega[..., None])[..., 0]                          # (R,P)

    progress(0.85, "gram matrices")
    gram = _gram_matrices(shapes, patch_w)

    colors = _vertex_colors(actor, clips, p.frame_stride, vertex_colors)
    marker_weights = _marker_weights(actor, clips, frame_clip, frame_index)
    fine_maps = DatabaseMaps.from_clips(actor, clips, p.frame_stride, "displacement")
    albedo_maps = DatabaseMaps.from_clips(actor, clips, p.frame_stride, "albedo")
    sizes = np.bincount(labels, minlength=P)
    prior, marker_prior = {}, None
    if actor.n_markers:                # the priors of marker_noise_mm, from the database
        shell = MarkerShell.build(d0, F, np.asarray(actor.marker_triangle, np.int64),
                                  np.asarray(actor.marker_barycentric, np.float64), marker_weights)
        db_markers = np.stack([clips[c].markers[f] for c, f in zip(frame_clip, frame_index)])
        prior["marker_prior_scale_mm"] = shell.prior_scale(db_markers)
        marker_prior = shell.learned_prior(db_markers)
    data = ShapeSpaceData(
        params=p, faces=F, neutral=d0, smooth_neutral=smooth0, align_weights=align_w,
        patches=labels, tri_patch=tri_patch, shapes=shapes, detail=detail,
        region_names=tuple(names), region_vertices=region_vertices, region_weights=omega,
        patch_weights=patch_w, gram=gram, frame_clip=frame_clip, frame_index=frame_index,
        clip_names=tuple(c.name for c in clips), clip_fps=tuple(float(c.fps) for c in clips),
        colors=colors,
        marker_triangle=np.asarray(actor.marker_triangle, np.int64),
        marker_barycentric=np.asarray(actor.marker_barycentric, np.float64),
        marker_weights=marker_weights, marker_prior=marker_prior,
        uv=np.asarray(actor.uv, np.float64), uv_faces=np.asarray(actor.uv_faces, np.int64),
        metrics={
            "database_frames": N, "clips": [c.name for c in clips],
            "patches": P, "patch_vertices": {"mean": float(sizes.mean()), "min": int(sizes.min()),
                                             "max": int(sizes.max())},
            "regions": {**region_info, "names": list(names),
                        "vertices": [int(x) for x in region_vertices.sum(axis=1)]},
            "detail_bytes": int(detail.nbytes),
            "colors": colors is not None,
            "marker_database": bool(p.marker_correction and actor.n_markers),
            "maps": {k: list(m.shape) for k, m in (("displacement", fine_maps), ("albedo", albedo_maps))
                     if m is not None},
            **_partial_maps(clips, p.frame_stride, N), **prior,
            "params": p.model_dump(mode="json"),
        },
        fine_maps=fine_maps, albedo_maps=albedo_maps,
    )
    progress(0.9, "prepare")
    model = ShapeSpaceModel(data)
    if p.marker_correction and actor.n_markers:
        model = model.replace(marker_database=_marker_database(
            model, clips, frame_clip, frame_index,
            lambda x: progress(0.9 + 0.1 * x, "marker shells and corrections")))
    progress(1.0, "done")
    return model


def _partial_maps(clips: Sequence[Clip], stride: int, N: int) -> dict:
    """``{"maps_partial": {kind: {...}}}`` for the map kinds only some clips carry (else
    ``{}``): how many database frames have them, the clips without, and the rule used."""
    out = {}
    for kind in ("displacement", "albedo"):
        without = [c.name for c in clips if getattr(c, kind) is None]
        if without and len(without) < len(clips):
            frames = sum(len(range(0, c.frames, stride)) for c in clips if getattr(c, kind) is not None)
            out[kind] = {
                "database_frames_with_maps": frames, "database_frames": N, "clips_without": without,
                "rule": "maps are blended over the frames that have them; a region's weight on "
                        "frames without maps goes to the mean map of those that have them"}
    return {"maps_partial": out} if out else {}


def _gram_matrices(shapes: np.ndarray, patch_weights: np.ndarray) -> np.ndarray:
    """``D̃ᵀ Ω_r D̃`` (R,N,N), symmetric, for shapes (N,9P) and patch weights (R,P) (§5.3)."""
    gram = np.stack([(shapes * np.repeat(w, COMPONENTS)) @ shapes.T for w in patch_weights])
    return 0.5 * (gram + gram.transpose(0, 2, 1))


def _marker_database(model: ShapeSpaceModel, clips: Sequence[Clip], frame_clip: np.ndarray,
                     frame_index: np.ndarray, progress: Callable[[float], None],
                     chunk: int = 16) -> MarkerDatabase:
    """The database frames' marker shells encoded as inputs are, and what they miss (:mod:`.markers`).

    A frame with too few visible markers stands in for its own shell (its shape is its
    captured one, its correction zero).
    """
    frames = model.frame_field()
    N = len(frame_clip)
    shapes = np.empty((N, model.shapes.shape[1]))
    corrections = np.empty((N, model.n_vertices, 3), np.float32)
    for s in range(0, N, chunk):
        ks = range(s, min(s + chunk, N))
        truth = np.stack([clips[frame_clip[k]].vertices[frame_index[k]] for k in ks]).astype(np.float64)
        markers = np.stack([clips[frame_clip[k]].markers[frame_index[k]] for k in ks]).astype(np.float64)
        usable = np.isfinite(markers).all(axis=2).sum(axis=1) >= MIN_VISIBLE_MARKERS
        shells = truth.copy()
        if usable.any():
            shells[usable] = model.markers_to_vertices(markers[usable])
        enc = model.encode(shells)
        shapes[s:s + len(ks)] = enc["shape"]
        for j, T in enumerate(enc["transforms"]):
            a = enc["aligned"][j]
            corrections[s + j] = np.einsum("nij,nj->ni", frames.frames(a), T.apply(truth[j]) - a)
        progress(min(s + chunk, N) / N)
    return MarkerDatabase(shapes, _gram_matrices(shapes, model.patch_weights), corrections)


def _marker_weights(actor: ActorData, clips: Sequence[Clip], frame_clip: np.ndarray,
                    frame_index: np.ndarray) -> np.ndarray:
    """Head-alignment weights (M,) of the markers from their motion in the database clips."""
    from service.methods.pdm.base_surface import stability_weights as marker_stability

    M = actor.n_markers
    if M == 0:
        return np.zeros(0)
    rest = actor.marker_positions()
    markers = np.stack([clips[c].markers[f] for c, f in zip(frame_clip, frame_index)]).astype(np.float64)
    aligned = np.empty_like(markers)
    for k, P in enumerate(markers):
        try:
            aligned[k] = rigid_align(P, rest).apply(P)
        except ValueError:                           # too few visible markers: ignore the frame
            aligned[k] = np.nan
    return marker_stability(aligned, rest)


#: the stored fields a model reads through to its data
_DATA_FIELDS = frozenset(f.name for f in dataclasses.fields(ShapeSpaceData))

__all__ = ["OUTPUTS", "ShapeSpaceData", "ShapeSpaceEvaluator", "ShapeSpaceModel", "ShapeSpaceParams",
           "train"]
