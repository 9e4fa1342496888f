"""The model-kind registry: what the API and the jobs need to know about each method.

A :class:`Kind` bundles a method's name, its OpenAPI text, its parameters as a pydantic
model (bounds, defaults, ``extra="forbid"`` so a misspelt parameter is a 422), what it takes
as input, and its ``train``/``load`` functions. Routers and job tasks look a kind up here
and never import a method module themselves, so a new method is one entry in
:data:`KINDS`.

Examples
--------
>>> kind = get_kind("pdm")
>>> params = kind.parse_params({"order": "linear", "medium_resolution": 64})
>>> params.fine_resolution
1024
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Literal, Mapping, Protocol, Sequence

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from service.methods.inputs import ActorData, Clip, InvalidInput, Progress
from service.methods.pdm.model import PdmModel, PdmParams, train as pdm_train
from service.methods.shape_space.model import ShapeSpaceModel, train as shape_space_train
from service.methods.shape_space.params import REGION_SOURCES, SMOOTHING, ShapeSpaceParams


class TrainedModel(Protocol):
    """What ``Kind.train`` returns and ``Kind.load`` reads back."""

    metrics: dict

    def save(self, path: Path) -> dict: ...

    def synthesize(self, markers: np.ndarray, outputs: Sequence[str] = ...,
                   clamp: bool = ...) -> dict[str, np.ndarray]: ...


@dataclass(frozen=True)
class Kind:
    """One model kind.

    Attributes
    ----------
    name : str            the API's ``kind`` value, e.g. ``"pdm"``
    title : str           one line for listings and OpenAPI
    description : str     OpenAPI text (paper, what it learns, licensing notes)
    params : type         pydantic model of the training parameters (``extra="forbid"``)
    input : str           ``"markers"`` (``/synthesize``) or ``"meshes"`` (``/enhance``)
    train : callable      ``(ActorData, list[Clip], params, progress) -> model`` with
                          ``.save(dir)`` and ``.metrics``
    load : callable       ``(Path) -> model`` with ``.synthesize(markers, outputs, clamp)``
    """

    name: str
    title: str
    description: str
    params: type[BaseModel]
    input: Literal["markers", "meshes"]
    train: Callable[[ActorData, Sequence[Clip], BaseModel, Progress], TrainedModel]
    load: Callable[[Path], TrainedModel]

    def parse_params(self, raw: Mapping[str, Any] | BaseModel | None) -> BaseModel:
        """Validated parameters from a request's (or a stored model's) ``params``.

        ``None`` gives the defaults. Raises :class:`pydantic.ValidationError` for unknown
        names or values out of bounds (the API maps it to 422 with per-field errors).
        """
        if isinstance(raw, self.params):
            return raw
        if isinstance(raw, BaseModel):
            raw = raw.model_dump()
        return self.params.model_validate(dict(raw or {}))


# ---------------------------------------------------------------------------- pdm
PDM_PATENT_NOTICE = (
    "The PDM method is covered by US patent 8,902,232 B2 (University of Southern California, "
    "in force until about 2031); commercial users should check licensing.")


_PDM = PdmParams()          # the method's defaults, the one source of truth


class PdmParamsModel(BaseModel):
    """Training parameters of a ``pdm`` model (mirrors :class:`service.methods.pdm.model.PdmParams`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    order: Literal["linear", "biquadratic", "bicubic"] = Field(
        default=_PDM.order,
        description="Polynomial order of the displacement maps in (d1, d2): linear (3 "
                    "coefficients per channel), biquadratic (6, the paper's eq. 1) or bicubic (10).",
        examples=[_PDM.order])
    medium_resolution: int = Field(
        default=_PDM.medium_resolution, ge=16, le=8192,
        description="Texels per side of the 3D medium-band PDM (the paper uses 512).",
        examples=[_PDM.medium_resolution])
    fine_resolution: int = Field(
        default=_PDM.fine_resolution, ge=16, le=8192,
        description="Texels per side of the 1D fine-band PDM and of the synthesized "
                    "displacement/normal maps (the paper uses 1024).",
        examples=[_PDM.fine_resolution])
    gamma: float = Field(
        default=_PDM.gamma, ge=0,
        description="Regularization constant γ of the per-texel least-squares fit (§4.2); "
                    "larger values pull the coefficients towards zero.",
        examples=[_PDM.gamma])
    axis_threshold_deg: float = Field(
        default=_PDM.axis_threshold_deg, ge=0, le=90,
        description="Axis-smoothing threshold angle of §4.1, in degrees.",
        examples=[_PDM.axis_threshold_deg])
    extrapolation_margin: float | None = Field(
        default=_PDM.extrapolation_margin, ge=0,
        description="Limit the deformation parameters of each texel to (1 + margin) times "
                    "the largest radius seen in training, so expressions beyond the training "
                    "data keep the most extreme trained detail instead of growing "
                    "polynomially; null disables the limit.",
        examples=[_PDM.extrapolation_margin, None])
    fine_highpass_mm: float = Field(
        default=_PDM.fine_highpass_mm, ge=0,
        description="σ on the surface, in the actor's unit, of the Gaussian whose complement "
                    "splits the fine band off the medium residual (0: no filter).",
        examples=[_PDM.fine_highpass_mm])
    smoothing_lam_dt: float = Field(
        default=_PDM.smoothing_lam_dt, gt=0,
        description="Curvature-flow step (actor's unit squared) that makes the smooth "
                    "neutral underlying the base surface.",
        examples=[_PDM.smoothing_lam_dt])


def _pdm_train(actor: ActorData, clips: Sequence[Clip], params: BaseModel,
               progress: Progress) -> TrainedModel:
    """Train a PDM (ma2008 §4) with the pydantic parameters converted to ``PdmParams``."""
    return pdm_train(actor, list(clips), PdmParams(**PDM_KIND.parse_params(params).model_dump()),
                 progress)


def _pdm_load(path: Path) -> TrainedModel:
    """Read a PDM model directory (checksums verified)."""
    return PdmModel.load(path)


PDM_KIND = Kind(
    name="pdm",
    title="Deformation-driven polynomial displacement maps (Ma et al. 2008)",
    description=(
        "Learns per-texel polynomial displacement maps driven by the local deformation of a "
        "sparse marker mesh (Ma, Jones, Chiang, Hawkins, Frederiksen, Peers, Vukovic, "
        "Ouhyoung, Debevec: 'Facial performance synthesis using deformation-driven polynomial "
        "displacement maps', SIGGRAPH Asia 2008). Input: motion-capture markers; output: "
        "medium-scale meshes, fine-scale displacement, normal and (if trained with albedo) "
        "albedo maps. " + PDM_PATENT_NOTICE),
    params=PdmParamsModel,
    input="markers",
    train=_pdm_train,
    load=_pdm_load,
)

# ---------------------------------------------------------------------------- shape_space
_SS = ShapeSpaceParams()    # the method's defaults, the one source of truth


class ShapeSpaceParamsModel(BaseModel):
    """Training parameters of a ``shape_space`` model (mirrors
    :class:`service.methods.shape_space.params.ShapeSpaceParams`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    lam_dt: float = Field(
        default=_SS.lam_dt, gt=0,
        description="λdt of the implicit curvature-flow step of the frequency separation "
                    "(§4.2 eq. 1), actor's unit squared (the paper: 125 mm²).",
        examples=[_SS.lam_dt])
    smoothing: Literal[SMOOTHING] = Field(  # type: ignore[valid-type]
        default=_SS.smoothing,
        description="Build the curvature-flow operator once on the neutral (rest, the default: "
                    "one factorization shared by every frame, as §5.5 does for the "
                    "reconstruction; ~0.4 s per level-1 frame) or on every frame (per_frame, "
                    "eq. 1 literally: one factorization per frame, ~3x slower).",
        examples=[_SS.smoothing])
    frame_stride: int = Field(
        default=_SS.frame_stride, ge=1,
        description="Keep every k-th frame of the database clips (the detail store holds "
                    "frames × triangles × 9 float32).",
        examples=[_SS.frame_stride])
    patch_size: int = Field(
        default=_SS.patch_size, ge=3,
        description="Target vertices per compression patch (§4.2: 100).",
        examples=[_SS.patch_size])
    patch_seed: int = Field(
        default=_SS.patch_seed,
        description="Seed of the random patch seeds.", examples=[_SS.patch_seed])
    patch_relax_iterations: int = Field(
        default=_SS.patch_relax_iterations, ge=0,
        description="Lloyd relaxations of the seed-and-grow patches (0: the paper's plain "
                    "random seeds).",
        examples=[_SS.patch_relax_iterations])
    regions: Literal[REGION_SOURCES] = Field(  # type: ignore[valid-type]
        default=_SS.regions,
        description="Where the four voluntary regions of §4.3 come from: actor (the actor's "
                    "region masks), derived (clustered from the database motion), auto "
                    "(the actor's when all four are given, else derived), whole (the face "
                    "matched as one region).",
        examples=[_SS.regions])
    region_falloff: float = Field(
        default=_SS.region_falloff, gt=0,
        description="σ of the Gaussian fall-off of the region weights with geodesic "
                    "distance outside a region, actor's unit (§4.3).",
        examples=[_SS.region_falloff])
    region_motion_fraction: float = Field(
        default=_SS.region_motion_fraction, gt=0, lt=1,
        description="Region derivation: vertices whose RMS motion exceeds this fraction of "
                    "the 99th percentile take part in the clustering.",
        examples=[_SS.region_motion_fraction])
    region_seed: int = Field(
        default=_SS.region_seed,
        description="Seed of the region clustering (k-means initialization).",
        examples=[_SS.region_seed])
    up_axis: tuple[float, float, float] = Field(
        default=_SS.up_axis,
        description="The actor's up direction (region derivation names the upper cluster "
                    "'brow'); facesynth's convention is y up.",
        examples=[list(_SS.up_axis)])
    left_axis: tuple[float, float, float] = Field(
        default=_SS.left_axis,
        description="The actor's left direction (region derivation splits left/right at the "
                    "mid-plane across it); nearly orthogonal to up_axis.",
        examples=[list(_SS.left_axis)])
    boundary_weight: float = Field(
        default=_SS.boundary_weight, ge=0,
        description="Weight of the boundary 1D-Laplacian term of the Poisson reconstruction "
                    "(§5.5: 0.05).",
        examples=[_SS.boundary_weight])
    map_resolution: int = Field(
        default=_SS.map_resolution, ge=8, le=8192,
        description="Texels per side of the displacement map /enhance returns (the enhanced "
                    "surface's normal offset from the input surface, over the neutral's UVs).",
        examples=[_SS.map_resolution])
    restore_low_frequencies: bool = Field(
        default=_SS.restore_low_frequencies,
        description="After reconstruction, replace the result's low band by the input's "
                    "(a departure that lowers the drift of the Poisson solve; false: the paper).",
        examples=[_SS.restore_low_frequencies])
    marker_correction: bool = Field(
        default=_SS.marker_correction,
        description="For marker input, match the markers' thin shell against the database "
                    "frames' own shells and correct it by the database's pose-space "
                    "corrections (what the shell missed on each database frame, bickel2008 "
                    "§5) blended with the matched weights, before enhancing it (a departure; "
                    "false: the paper enhances the shell as it is). The model stores "
                    "frames x vertices x 3 float32 more.",
        examples=[_SS.marker_correction])
    sequence_seconds: float = Field(
        default=_SS.sequence_seconds, ge=0,
        description="Temporal projection (§6.1): database clips longer than this are cut "
                    "into windows of this duration with 50% overlap (0: every clip is one "
                    "sequence).",
        examples=[_SS.sequence_seconds])

    @model_validator(mode="after")
    def _check_axes(self) -> "ShapeSpaceParamsModel":
        """Cross-field checks of the method (axes finite, non-zero, nearly orthogonal)."""
        try:
            ShapeSpaceParams(**self.model_dump())
        except InvalidInput as error:
            raise ValueError(str(error)) from None
        return self


def _shape_space_train(actor: ActorData, clips: Sequence[Clip], params: BaseModel,
                       progress: Progress) -> TrainedModel:
    """Train a shape-space model (bermano2014 §4) with the pydantic parameters converted."""
    parsed = SHAPE_SPACE_KIND.parse_params(params)
    return shape_space_train(actor, list(clips), ShapeSpaceParams(**parsed.model_dump()), progress)


def _shape_space_load(path: Path) -> TrainedModel:
    """Read a shape-space model directory (checksums verified)."""
    return ShapeSpaceModel.load(path)


SHAPE_SPACE_KIND = Kind(
    name="shape_space",
    title="Shape-space performance enhancement (Bermano et al. 2014)",
    description=(
        "Adds the high-frequency detail of a high-resolution performance database to "
        "low-resolution facial animation by convex matching in a deformation-gradient shape "
        "space per voluntary region (Bermano, Bradley, Beeler, Zünd, Nowrouzezahrai, Baran, "
        "Sorkine-Hornung, Pfister, Sumner, Bickel, Gross: 'Facial performance enhancement "
        "using dynamic shape space analysis', ACM TOG 33(2), 2014). Input: meshes on the "
        "actor's topology or on a registered input rig (/enhance), or markers; output: "
        "enhanced high-resolution meshes."),
    params=ShapeSpaceParamsModel,
    input="meshes",
    train=_shape_space_train,
    load=_shape_space_load,
)

#: every model kind the service knows, by name
KINDS: dict[str, Kind] = {k.name: k for k in (PDM_KIND, SHAPE_SPACE_KIND)}


def get_kind(name: str) -> Kind:
    """The :class:`Kind` called ``name``; :class:`InvalidInput` naming the known kinds."""
    try:
        return KINDS[name]
    except KeyError:
        raise InvalidInput(f"unknown model kind '{name}'; known kinds: "
                           f"{', '.join(sorted(KINDS))}") from None
