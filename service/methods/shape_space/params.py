"""Training parameters of the shape-space model and the method's named constants.

bermano2014 fixes few numbers (λdt = 125, patches of ~100 vertices, boundary weight 0.05);
everything else the paper leaves open is a named, validated parameter here, so a model's
``manifest.json`` records every choice that shaped it.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from service.geometry.curvature_flow import LAMBDA_DT
from service.geometry.deformation_gradient import BOUNDARY_WEIGHT
from service.methods.params import MarkerParams

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
#: most triangles × frames :meth:`~.model.ShapeSpaceModel.enhance` processes as one batch:
#: a batch's (B,m,3,3) float64 temporaries are B·m·72 bytes, and they should stay within the
#: last-level cache (32 MiB here) — at 1 << 20 (11 frames of a level-1 actor, 75 MB per
#: array) a 30-frame request took 0.31 s of CPU per frame against 0.21 s frame by frame;
#: at this size a level-1 frame is its own batch and level-0 frames go 5 at a time
ENHANCE_BATCH_TRIANGLES = 1 << 17
#: sum of the region weights of a triangle below which it takes equal weights (eq. 4's
#: normalization would divide by ~0 far from every region)
REGION_WEIGHT_FLOOR = 1e-12


class ShapeSpaceParams(MarkerParams):
    """Parameters of :func:`service.methods.shape_space.model.train` (bermano2014 §4).

    Notes
    -----
    ``smoothing="rest"`` is the approximation §5.5 makes for the reconstruction "in the
    interest of runtime performance"; on the level-0 sample actor the two settings differ by
    < 0.004 mm in held-out error (see
    :func:`~service.geometry.curvature_flow.implicit_curvature_flow`), while ``per_frame``
    costs ~1 s per frame at 45k vertices. ``restore_low_frequencies`` and
    ``marker_correction`` are departures (see :mod:`~service.methods.shape_space.model` and
    :mod:`~service.methods.shape_space.markers`). ``sequence_seconds`` exists because the
    paper's database holds short single-expression sequences; a long captured performance
    (the sample actor's 630-frame database) would otherwise match a keyframe pair with a
    "subsequence" spanning several expressions.
    """

    lam_dt: float = Field(
        default=LAMBDA_DT, gt=0, allow_inf_nan=False, strict=True,
        description="λdt of the implicit curvature-flow step of the frequency separation "
                    "(§4.2 eq. 1), actor's unit squared (the paper: 125 mm²).",
        examples=[LAMBDA_DT])
    smoothing: Literal[SMOOTHING] = Field(  # type: ignore[valid-type]
        default="rest",
        description="Build the curvature-flow operator once on the neutral (rest, the default: "
                    "one factorization shared by every frame, as §5.5 does for the "
                    "reconstruction; ~0.4 s per level-1 frame) or on every frame (per_frame, "
                    "eq. 1 literally: one factorization per frame, ~3x slower).",
        examples=["rest"])
    frame_stride: int = Field(
        default=1, ge=1, strict=True,
        description="Keep every k-th frame of the database clips (the detail store holds "
                    "frames × triangles × 9 float32).",
        examples=[1])
    patch_size: int = Field(
        default=100, ge=3, strict=True,
        description="Target vertices per compression patch (§4.2: 100).", examples=[100])
    patch_seed: int = Field(
        default=0, strict=True, description="Seed of the random patch seeds.", examples=[0])
    patch_relax_iterations: int = Field(
        default=10, ge=0, strict=True,
        description="Lloyd relaxations of the seed-and-grow patches (0: the paper's plain "
                    "random seeds).",
        examples=[10])
    regions: Literal[REGION_SOURCES] = Field(  # type: ignore[valid-type]
        default="auto",
        description="Where the four voluntary regions of §4.3 come from: actor (the actor's "
                    "region masks), derived (clustered from the database motion), auto "
                    "(the actor's when all four are given, else derived), whole (the face "
                    "matched as one region).",
        examples=["auto"])
    region_falloff: float = Field(
        default=15.0, gt=0, allow_inf_nan=False, strict=True,
        description="σ of the Gaussian fall-off of the region weights with geodesic "
                    "distance outside a region, actor's unit (§4.3).",
        examples=[15.0])
    region_motion_fraction: float = Field(
        default=0.2, gt=0, lt=1, strict=True,
        description="Region derivation: vertices whose RMS motion exceeds this fraction of "
                    "the 99th percentile take part in the clustering.",
        examples=[0.2])
    region_seed: int = Field(
        default=0, strict=True,
        description="Seed of the region clustering (k-means initialization).", examples=[0])
    up_axis: tuple[float, float, float] = Field(
        default=(0.0, 1.0, 0.0),
        description="The actor's up direction (region derivation names the upper cluster "
                    "'brow'); facesynth's convention is y up.",
        examples=[[0.0, 1.0, 0.0]])
    left_axis: tuple[float, float, float] = Field(
        default=(1.0, 0.0, 0.0),
        description="The actor's left direction (region derivation splits left/right at the "
                    "mid-plane across it); nearly orthogonal to up_axis.",
        examples=[[1.0, 0.0, 0.0]])
    boundary_weight: float = Field(
        default=BOUNDARY_WEIGHT, ge=0, allow_inf_nan=False, strict=True,
        description="Weight of the boundary 1D-Laplacian term of the Poisson reconstruction "
                    "(§5.5: 0.05).",
        examples=[BOUNDARY_WEIGHT])
    restore_low_frequencies: bool = Field(
        default=True, strict=True,
        description="After reconstruction, replace the result's low band by the input's "
                    "(a departure that lowers the drift of the Poisson solve; false: the paper).",
        examples=[True])
    marker_correction: bool = Field(
        default=True, strict=True,
        description="For marker input, match the markers' thin shell against the database "
                    "frames' own shells and correct it by the database's pose-space "
                    "corrections (what the shell missed on each database frame, bickel2008 "
                    "§5) blended with the matched weights, before enhancing it (a departure; "
                    "false: the paper enhances the shell as it is). The model stores "
                    "frames x vertices x 3 float32 more.",
        examples=[True])
    sequence_seconds: float = Field(
        default=1.0, ge=0, allow_inf_nan=False, strict=True,
        description="Temporal projection (§6.1): database clips longer than this are cut "
                    "into windows of this duration with 50% overlap (0: every clip is one "
                    "sequence).",
        examples=[1.0])
    map_resolution: int = Field(
        default=1024, ge=8, le=8192, strict=True,
        description="Texels per side of the displacement map /enhance returns (the enhanced "
                    "surface's normal offset from the input surface, over the neutral's UVs).",
        examples=[1024])

    @model_validator(mode="after")
    def _check_axes(self) -> "ShapeSpaceParams":
        """The axes are finite, non-zero and (nearly) orthogonal."""
        for name in ("up_axis", "left_axis"):
            axis = np.asarray(getattr(self, name))
            if not np.all(np.isfinite(axis)) or np.linalg.norm(axis) == 0:
                raise ValueError(f"{name} must be a finite non-zero 3-vector, got "
                                 f"{getattr(self, name)}")
        up, left = (np.array(a) / np.linalg.norm(a) for a in (self.up_axis, self.left_axis))
        if abs(float(up @ left)) > 0.1:
            raise ValueError(f"up_axis and left_axis must be (nearly) orthogonal, got "
                             f"{self.up_axis} and {self.left_axis}")
        return self
