"""Training parameters of the shape-space model and the method's named constants.

bermano2014 fixes few numbers (λdt = 125, patches of ~100 vertices, boundary weight 0.05);
everything else the paper leaves open is a named, validated parameter here, so a model's
``manifest.json`` records every choice that shaped it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.geometry.curvature_flow import LAMBDA_DT
from service.geometry.deformation_gradient import BOUNDARY_WEIGHT
from service.methods.inputs import InvalidInput

#: the four voluntary regions of bermano2014 §4.3 (Figure 4), in this order everywhere
VOLUNTARY_REGIONS = ("mouth_left", "mouth_right", "brow_left", "brow_right")
#: the single region of ``regions="whole"`` (holistic matching, no region split)
WHOLE_FACE = ("face",)
#: how the regions are obtained (see :class:`ShapeSpaceParams`)
REGION_SOURCES = ("auto", "actor", "derived", "whole")
#: frequency-separation operator: per frame (the paper) or the neutral's, prefactored once
SMOOTHING = ("per_frame", "rest")
#: components per triangle of the shape-space encoding: rotation log (3) + stretch (6)
COMPONENTS = 9

#: relative ridge added to the Gram matrices of the convex matching (x mean diagonal):
#: makes the simplex QP strictly convex, so its solution is unique (database frames are
#: often nearly affinely dependent); changes the objective by ~1e-12 relative
QP_RIDGE = 1e-12
#: relative tolerance of the active-set solver's optimality and feasibility tests
QP_TOL = 1e-12
#: a convex weight counts as non-zero (reports) above this value
WEIGHT_EPS = 1e-9
#: sum of the region weights of a triangle below which it takes equal weights (eq. 4's
#: normalization would divide by ~0 far from every region)
REGION_WEIGHT_FLOOR = 1e-12


@dataclass(frozen=True)
class ShapeSpaceParams:
    """Parameters of :func:`service.methods.shape_space.model.train` (bermano2014 §4).

    Attributes
    ----------
    lam_dt : float                 λdt of the implicit curvature-flow step of the frequency
                                   separation f(·), actor unit² (§4.2 eq. 1: 125 mm²)
    smoothing : "rest" | "per_frame"   build the curvature-flow operator once on the neutral
                                   (the default: one factorization for all frames, the
                                   approximation §5.5 makes for the reconstruction "in the
                                   interest of runtime performance") or on every frame (eq. 1
                                   literally; one factorization per database and input frame,
                                   which alone costs ~1 s per frame at 45k vertices, twice
                                   the per-frame budget). On the level-0 sample actor the two
                                   differ by < 0.004 mm in held-out error (see
                                   :func:`~service.geometry.curvature_flow.implicit_curvature_flow`)
    frame_stride : int             keep every k-th frame of the database clips (memory: the
                                   detail store is frames × triangles × 9 float32)
    patch_size : int               target vertices per compression patch (§4.2: 100)
    patch_seed : int               seed of the random patch seeds
    patch_relax_iterations : int   Lloyd relaxations of the seed-and-grow patches (0: the
                                   plain random seeds of the paper)
    regions : "auto" | "actor" | "derived" | "whole"   where the four voluntary regions of
                                   §4.3 come from: ``actor`` reads ``ActorData.regions``
                                   (keys :data:`VOLUNTARY_REGIONS`), ``derived`` clusters the
                                   database motion (:func:`~.regions.derive_regions`),
                                   ``auto`` takes the actor's when all four are given and
                                   derives them otherwise, ``whole`` matches the face as one
                                   region (no region split)
    region_falloff : float         σ of the Gaussian fall-off of the region weights with
                                   geodesic distance outside a region, actor unit (§4.3)
    region_motion_fraction : float  region derivation: vertices whose RMS motion exceeds this
                                   fraction of the 99th percentile take part in the clustering
    region_seed : int              seed of the region clustering (k-means initialization)
    up_axis, left_axis : (3,) float  the actor's up and left directions (region derivation
                                   names the upper cluster "brow" and splits at the
                                   mid-plane across ``left_axis``); facesynth's convention is
                                   y up, x to the actor's left
    boundary_weight : float        weight of the boundary 1D-Laplacian term of the Poisson
                                   reconstruction (§5.5: 0.05)
    restore_low_frequencies : bool  after reconstruction, replace the result's low band by the
                                   input's: ``x ← x + f(ā) − f(x)`` (departure, see
                                   :mod:`~service.methods.shape_space.model`; False: the paper)
    marker_correction : bool       for marker input, match the markers' thin shell against the
                                   database frames' own shells and correct it by their
                                   pose-space corrections blended with the matched weights
                                   before enhancing it (departure, see
                                   :mod:`~service.methods.shape_space.markers`; False: the
                                   paper, the shell is matched against the frames and
                                   enhanced as it is). Stores (N,n,3) float32 and the shells'
                                   shape vectors and Gram matrices more in the model
    map_resolution : int           texels per side of the displacement map of
                                   :meth:`~.model.ShapeSpaceModel.enhance` (the enhanced
                                   surface's offset from the input, rasterized over the
                                   neutral's UV layout)
    sequence_seconds : float       temporal projection (§6.1): database clips longer than this
                                   (seconds) are cut into windows of this duration with 50 %
                                   overlap, each one sequence (0: every clip is one sequence).
                                   The paper's database holds short single-expression
                                   sequences; a long captured performance (the sample actor's
                                   630-frame database) would otherwise match a keyframe pair
                                   with a "subsequence" spanning several expressions
    """

    lam_dt: float = LAMBDA_DT
    smoothing: str = "rest"
    frame_stride: int = 1
    patch_size: int = 100
    patch_seed: int = 0
    patch_relax_iterations: int = 10
    regions: str = "auto"
    region_falloff: float = 15.0
    region_motion_fraction: float = 0.2
    region_seed: int = 0
    up_axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    left_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    boundary_weight: float = BOUNDARY_WEIGHT
    restore_low_frequencies: bool = True
    marker_correction: bool = True
    sequence_seconds: float = 1.0
    map_resolution: int = 1024

    def __post_init__(self):
        for name in ("up_axis", "left_axis"):
            value = getattr(self, name)
            try:
                axis = tuple(float(x) for x in value)
            except (TypeError, ValueError):
                raise InvalidInput(f"{name} must be three numbers, got {value!r}") from None
            if len(axis) != 3 or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) == 0:
                raise InvalidInput(f"{name} must be a finite non-zero 3-vector, got {value!r}")
            object.__setattr__(self, name, axis)
        up, left = (np.array(a) / np.linalg.norm(a) for a in (self.up_axis, self.left_axis))
        if abs(float(up @ left)) > 0.1:
            raise InvalidInput(f"up_axis and left_axis must be (nearly) orthogonal, got "
                               f"{self.up_axis} and {self.left_axis}")
        for name in ("lam_dt", "region_falloff", "region_motion_fraction", "boundary_weight",
                     "sequence_seconds"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise InvalidInput(f"{name} must be a number, got {value!r}")
        if not (self.lam_dt > 0 and np.isfinite(self.lam_dt)):
            raise InvalidInput(f"lam_dt must be > 0, got {self.lam_dt}")
        if self.smoothing not in SMOOTHING:
            raise InvalidInput(f"smoothing must be one of {list(SMOOTHING)}, got {self.smoothing!r}")
        if self.regions not in REGION_SOURCES:
            raise InvalidInput(f"regions must be one of {list(REGION_SOURCES)}, got {self.regions!r}")
        for name, lo in (("frame_stride", 1), ("patch_size", 3), ("patch_relax_iterations", 0),
                         ("map_resolution", 8)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lo:
                raise InvalidInput(f"{name} must be an integer >= {lo}, got {value!r}")
        if not (self.sequence_seconds >= 0 and np.isfinite(self.sequence_seconds)):
            raise InvalidInput(f"sequence_seconds must be >= 0, got {self.sequence_seconds}")
        for name in ("patch_seed", "region_seed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise InvalidInput(f"{name} must be an integer, got {getattr(self, name)!r}")
        if not (self.region_falloff > 0 and np.isfinite(self.region_falloff)):
            raise InvalidInput(f"region_falloff must be > 0, got {self.region_falloff}")
        if not 0 < self.region_motion_fraction < 1:
            raise InvalidInput(f"region_motion_fraction must be in (0, 1), got {self.region_motion_fraction}")
        for name in ("restore_low_frequencies", "marker_correction"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise InvalidInput(f"{name} must be true or false, got {getattr(self, name)!r}")
        if not (self.boundary_weight >= 0 and np.isfinite(self.boundary_weight)):
            raise InvalidInput(f"boundary_weight must be >= 0, got {self.boundary_weight}")
