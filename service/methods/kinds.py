"""The model-kind registry: what the API and the jobs need to know about each method.

A :class:`Kind` bundles a method's name, its OpenAPI text, its parameters (the method's own
pydantic model: bounds, defaults, ``extra="forbid"`` so a misspelt parameter is a 422), what
it takes as input, what it outputs, and its ``train``/``load`` functions. Routers and job
tasks look a kind up here and never import a method module themselves, so a new method is
one entry in :data:`KINDS` (docs/architecture.md, "Adding a model kind"). The registry
imports only each method's light modules (its ``params`` and ``outputs``); ``train`` and
``load`` are :class:`~service.methods.lazy.LazyFunction` s named ``"module:attr"``, whose
model module is imported at their first call: a server imports the model modules of the
kinds it loads and no others (issue 23's cold start).

Examples
--------
>>> kind = get_kind("pdm")
>>> params = kind.parse_params({"order": "linear", "medium_resolution": 64})
>>> params.medium_resolution
64
"""

from __future__ import annotations

import functools
import inspect
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Literal, Mapping, Protocol, Sequence

import numpy as np
from pydantic import BaseModel

from service.errors import InvalidInput
from service.methods.inputs import ActorData, Clip, Progress
from service.methods.lazy import LazyFunction
from service.methods.outputs import OUTPUTS
from service.methods.pdm.params import PdmParams
from service.methods.pose_space.outputs import OUTPUTS as POSE_SPACE_OUTPUTS
from service.methods.pose_space.params import PsdParams, WpsdParams
from service.methods.shape_space.outputs import OUTPUTS as SHAPE_SPACE_OUTPUTS
from service.methods.shape_space.params import ShapeSpaceParams
from service.methods.stress_blend.outputs import OUTPUTS as STRESS_BLEND_OUTPUTS
from service.methods.stress_blend.params import StressBlendParams


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
    params : type         the method's parameter model (a :class:`~service.methods.params.MethodParams`)
    input : str           ``"markers"`` (``/synthesize``) or ``"meshes"`` (``/enhance``)
    outputs : tuple       the outputs of :data:`~service.methods.outputs.OUTPUTS` it produces
    train : callable      ``(ActorData, list[Clip], params, progress) -> model`` with
                          ``.save(dir)`` and ``.metrics`` (a :class:`LazyFunction`: the
                          method's model module is imported at the first call)
    load : callable       ``(Path) -> model`` with ``.synthesize(frames, outputs, clamp)``
                          (a :class:`LazyFunction` too)
    weighs_mapped : bool  whether the model cache counts the loaded model's memory-mapped
                          arrays (:func:`~service.methods.footprint.nbytes`): true for a
                          kind that reads all of them per frame
    """

    name: str
    title: str
    description: str
    params: type[BaseModel]
    input: Literal["markers", "meshes"]
    outputs: tuple[str, ...]
    train: Callable[[ActorData, Sequence[Clip], Any, Progress], TrainedModel]
    load: Callable[[Path], TrainedModel]
    weighs_mapped: bool = True

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


PDM_PATENT_NOTICE = (
    "The PDM method is covered by US patent 8,902,232 B2 (University of Southern California, "
    "in force until about 2031); commercial users should check licensing.")

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
    params=PdmParams,
    input="markers",
    outputs=OUTPUTS,
    train=LazyFunction("service.methods.pdm.model:train"),
    load=LazyFunction("service.methods.pdm.model:PdmModel.load"),
)

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
        "enhanced high-resolution meshes (with the database's fine maps baked in for "
        "mesh_detailed), the detail over the input as displacement and normal maps, and the "
        "database's blended albedo."),
    params=ShapeSpaceParams,
    input="meshes",
    outputs=tuple(o for o in SHAPE_SPACE_OUTPUTS if o in OUTPUTS),
    train=LazyFunction("service.methods.shape_space.model:train"),
    load=LazyFunction("service.methods.shape_space.model:ShapeSpaceModel.load"),
    # the database (detail, colours, maps, marker corrections) is mapped and a request reads
    # only its active frames: a level-1 model's 4.4 GB would overflow the cache's budget and
    # reload on every request if it counted
    weighs_mapped=False,
)

_BICKEL2008 = ("(Bickel, Lang, Botsch, Otaduy, Gross: 'Pose-space animation and transfer of "
               "facial details', SCA 2008). Input: motion-capture markers; a linear thin shell "
               "gives the large scale and radial basis functions over marker-edge strains "
               "add each example's fine-scale correction in local tangent frames; with "
               "training maps the detail below the mesh is learned per texel the same way. "
               "Output: meshes, displacement and normal maps, a per-frame confidence.")

#: both pose-space kinds train and load with the one pose-space model
POSE_SPACE_TRAIN = LazyFunction("service.methods.pose_space.model:train")
POSE_SPACE_LOAD = LazyFunction("service.methods.pose_space.model:PoseSpaceModel.load")

PSD_KIND = Kind(
    name="psd",
    title="Pose-space deformation of facial details (Bickel et al. 2008, §5.2)",
    description="Global pose-space deformation: one feature distance per example pose "
                + _BICKEL2008,
    params=PsdParams,
    input="markers",
    outputs=POSE_SPACE_OUTPUTS,
    train=POSE_SPACE_TRAIN,
    load=POSE_SPACE_LOAD,
)

WPSD_KIND = Kind(
    name="wpsd",
    title="Weighted pose-space deformation of facial details (Bickel et al. 2008, §5.3)",
    description="Weighted pose-space deformation: per-vertex weighted feature distances, "
                "local control with the examples' full detail " + _BICKEL2008,
    params=WpsdParams,
    input="markers",
    outputs=POSE_SPACE_OUTPUTS,
    train=POSE_SPACE_TRAIN,
    load=POSE_SPACE_LOAD,
)

STRESS_BLEND_KIND = Kind(
    name="stress_blend",
    title="Stress-driven blending of expression maps (Digital Ira, real-time rendering)",
    description=(
        "Blends the maps of the actor's expression scans per texel with weights from the "
        "similarity of each vertex's surface stress (Green strain of the deformation "
        "gradients) to each scan's, as the real-time renderer of Digital Ira blends its "
        "scans' maps by surface stress ('Digital Ira and Beyond: Creating Photoreal Real-Time "
        "Digital Characters', SIGGRAPH 2014 course, 'Real-Time Rendering'). Input: meshes on the "
        "actor's topology (/enhance); output: blended displacement, albedo and normal maps "
        "and the per-region wrinkle-map weights an engine plays back."),
    params=StressBlendParams,
    input="meshes",
    outputs=tuple(o for o in STRESS_BLEND_OUTPUTS if o in OUTPUTS),
    train=LazyFunction("service.methods.stress_blend.model:train"),
    load=LazyFunction("service.methods.stress_blend.model:StressBlendModel.load"),
)

#: every model kind the service knows, by name
KINDS: dict[str, Kind] = {k.name: k for k in (PDM_KIND, PSD_KIND, WPSD_KIND, SHAPE_SPACE_KIND,
                                              STRESS_BLEND_KIND)}


def get_kind(name: str) -> Kind:
    """The :class:`Kind` called ``name``; :class:`InvalidInput` naming the known kinds."""
    try:
        return KINDS[name]
    except KeyError:
        raise InvalidInput(f"unknown model kind '{name}'; known kinds: "
                           f"{', '.join(sorted(KINDS))}") from None


def takes(model: Any, option: str) -> bool:
    """Whether ``model.synthesize`` has the keyword parameter ``option`` (issue 23: ``half``,
    maps written as float16 by the model, not in float32 and converted; ``confidence``;
    ``captured``, the markers before a synthesis job's filter); for
    a wrapper whose ``synthesize`` passes keyword options on (``**options``) to the model it
    holds as ``model.model`` (e.g. a unit check in front of it), whether that model's does."""
    synthesize = getattr(model, "synthesize", None)
    try:      # a method's signature is its class's function's: read once (a frame's path asks)
        names, passes_on = _keywords(getattr(synthesize, "__func__", synthesize))
    except (TypeError, ValueError):       # unhashable, or no signature to read: the plain call
        return False
    if option in names:
        return True
    inner = getattr(model, "model", None)
    return passes_on and inner is not None and inner is not model and takes(inner, option)


@functools.lru_cache(maxsize=256)
def _keywords(function: Callable) -> tuple[frozenset[str], bool]:
    """The parameter names of ``function`` and whether it takes ``**options``."""
    parameters = inspect.signature(function).parameters
    return (frozenset(parameters),
            any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()))
