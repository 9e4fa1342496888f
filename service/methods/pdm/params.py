"""Training parameters of a PDM (ma2008 §4), declared once for the library, the API and
OpenAPI (:class:`~service.methods.params.MarkerParams`)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from service.geometry.curvature_flow import LAMBDA_DT
from service.methods.params import MarkerParams


class PdmParams(MarkerParams):
    """Training parameters of a ``pdm`` model (API.md: ``POST /models`` with ``kind: pdm``).

    Notes
    -----
    Two ridges for the per-texel fit (:mod:`.polynomial`), one used: ``gamma`` given → the
    paper's rows γ/(σ1^i σ2^j) (ma2008 §4.2), exactly as before ``ridge`` existed (models
    stored with ``gamma: 30`` load and mean what they meant); ``gamma`` null (the default) →
    ``ridge``, dimensionless (issue 17): ridge² is the ridge / data energy of every
    non-constant term at every texel, whatever the units of d1, d2, the number of frames or
    the actor (the paper's γ/σ rows were not: γ = 30 shrank family b's d2 terms 35–60× and
    family a's 3×). ``ridge`` chosen on family a (level 0, fine band 512², held-out in
    range / combinations / out of range, fine detail r): ridge = 0, 0.03, 0.1, 0.3, 1 gave
    0.694/0.423/0.580, 0.689/0.419/0.578, 0.686/0.420/0.579, 0.682/0.421/0.575,
    0.676/0.417/0.545 (flat up to 0.3): 0.1 keeps a little shrinkage for texels whose
    parameters barely varied. Confirmed on family b: fine r 0.708/0.340/0.531 (old γ = 30)
    → 0.717/0.362/0.594, training fine fit / signal 0.555 → 0.456.

    The paper's γ (old default 30): its strength depends on the units of d1, d2 (mm here,
    strains scaled by √|N2|): the γ rows weigh γ/σ² against data of size σ². Chosen then on
    the sample actor's held-out in-range performance (level 1, biquadratic): γ = 1e-3, 30,
    100 gave fine-detail r 0.706, 0.745, 0.745 and medium mean error 0.197, 0.194, 0.204 mm;
    at level 0, 30 was best of 1e-3…3000.
    """

    order: Literal["linear", "biquadratic", "bicubic"] = Field(
        default="biquadratic",
        description="Polynomial order of the displacement maps in (d1, d2): linear (3 "
                    "coefficients per channel), biquadratic (6, the paper's eq. 1) or bicubic (10).",
        examples=["biquadratic"])
    medium_resolution: int = Field(
        default=512, ge=16, le=8192, strict=True,
        description="Texels per side of the 3D medium-band PDM (the paper uses 512).",
        examples=[512])
    fine_resolution: int | None = Field(
        default=None, ge=16, le=8192, strict=True,
        description="Texels per side of the 1D fine-band PDM and of the synthesized "
                    "displacement/normal maps (the paper uses 1024). Null (the default): the "
                    "training clips' map resolution, or 1024 when they have no maps (issue 17: "
                    "a band finer than its data learns only the data's interpolation, and "
                    "brought back to the data's resolution it loses that much detail: level-0 "
                    "sample actors, 512² maps, fine band 1024² → 512², held-out map part of the "
                    "detail error 0.50 → 0.21 on family a, see README).",
        examples=[None, 1024])
    gamma: float | None = Field(
        default=None, ge=0, allow_inf_nan=False,
        description="The paper's regularization constant γ of the per-texel least-squares fit "
                    "(§4.2): rows γ/(σ1^i σ2^j), σ the standard deviations of the deformation "
                    "parameters at the texel (units-dependent; the former default was 30). "
                    "When given, `ridge` is ignored; null (the default) uses `ridge`.",
        examples=[30.0])
    ridge: float = Field(
        default=0.1, ge=0, allow_inf_nan=False,
        description="Dimensionless ridge of the per-texel least-squares fit, used when `gamma` "
                    "is null (ignored when `gamma` is given): ridge² is each non-constant "
                    "term's ridge relative to its data energy at the texel (0: plain least "
                    "squares); larger values pull the coefficients towards zero.",
        examples=[0.1])
    neutral_anchor: bool = Field(
        default=False,
        description="Fix each texel's constant term to the neutral's detail (issue 17): the "
                    "polynomial at zero deformation reproduces the neutral exactly (the thin "
                    "shell's medium band, the rest frames' fine and albedo maps) and the other "
                    "terms are fitted to the rest. Off by default (the paper's free constant): "
                    "on family a it raised the held-out in-range mean error 0.272 → 0.291 mm "
                    "and left the combinations' max error unchanged (see model.py).",
        examples=[False, True])
    axis_threshold_deg: float = Field(
        default=30.0, ge=0, le=90,
        description="Axis-smoothing threshold angle of §4.1, in degrees.",
        examples=[30.0])
    extrapolation_margin: float | None = Field(
        default=0.25, ge=0,
        description="Limit the deformation parameters of each texel to (1 + margin) times "
                    "the largest radius seen in training, so expressions beyond the training "
                    "data keep the most extreme trained detail instead of growing "
                    "polynomially; null disables the limit.",
        examples=[0.25, None])
    validity_width: float | None = Field(
        default=3.0, ge=0, allow_inf_nan=False,
        description="Validity of the polynomial (issue 17): outside the hull of the (d1, d2) "
                    "each point was trained on, the detail is continued from the hull's "
                    "boundary and faded to the neutral's (the thin shell and the static "
                    "neutral map), reaching it at this relative distance beyond the hull "
                    "(3: four times the training range; chosen on family a's held-out "
                    "combinations and out-of-range performances, see validity.py). It "
                    "replaces the extrapolation_margin limit; null uses that limit instead.",
        examples=[3.0, None])
    validity_slope: float = Field(
        default=1.0, ge=0, le=1, allow_inf_nan=False,
        description="Order of the continuation outside the hull: 1 continues the polynomial "
                    "linearly along the expression's direction, 0 holds the boundary's detail.",
        examples=[1.0])
    fit_skill_floor: float | None = Field(
        default=None, lt=1, allow_inf_nan=False,
        description="Cross-validated fit skill s0 of the medium band (issue 17): each UV "
                    "point's detail is scaled towards the thin shell by clip((skill - s0) / "
                    "(1 - s0), 0, 1), skill = 1 - (leave-one-frame-out error) / (the thin "
                    "shell's error) over the training frames (fit_skill.py); null (the "
                    "default): no scaling. 0 lowered family a's frames above the thin shell's "
                    "max 56 -> 47 of 243 but family b's in-range detail corr 0.55 -> 0.52.",
        examples=[None, 0.0])
    medium_regression: float | None = Field(
        default=4.0, gt=0.0, le=20.0, allow_inf_nan=False,
        description="The mesh's medium-scale offsets from a locally weighted linear regression "
                    "on the markers' displacement vectors instead of the medium polynomial "
                    "(issue 17; service/geometry/marker_regression.py: per vertex a ridge "
                    "regression weighted by exp(-d^2/s^2) of the markers' rest distance d, "
                    "through the neutral, kept in low-rank form). The value is s in median "
                    "nearest-marker spacings (default 4: chosen on one sample actor family, "
                    "confirmed on the other; see model.py); null: the medium PDM of ma2008. "
                    "The maps, the confidence and the fine band are unchanged.",
        examples=[4.0, None])
    medium_regression_ridge: float = Field(
        default=0.1, gt=0.0, le=10.0, allow_inf_nan=False,
        description="Relative ridge of medium_regression (x the mean diagonal of each "
                    "vertex's kernel).",
        examples=[0.1])
    fine_driver: Literal["deformation", "strain"] = Field(
        default="strain",
        description="What drives the fine band at synthesis: 'deformation', ma2008's polynomial "
                    "in the texel's d1, d2; 'strain', a polynomial of the same order (linear: "
                    "4 terms, biquadratic or bicubic: the 10 of a quadratic) in the Green "
                    "strain of the synthesized mesh at the texel (issue 17; strain_band.py). "
                    "fine.exr holds ma2008's fine PDM either way.",
        examples=["strain", "deformation"])
    fine_highpass_mm: float = Field(
        default=2.0, ge=0, allow_inf_nan=False,
        description="σ on the surface, in the actor's unit, of the Gaussian whose complement "
                    "splits the fine band off the medium residual (0: no filter).",
        examples=[2.0])
    smoothing_lam_dt: float = Field(
        default=LAMBDA_DT, gt=0, allow_inf_nan=False,
        description="Curvature-flow step (actor's unit squared) that makes the smooth "
                    "neutral underlying the base surface.",
        examples=[LAMBDA_DT])
