"""The base of every method's training parameters: one pydantic model per method.

A method declares its parameters once, as a subclass of :class:`MethodParams` with bounds,
defaults and descriptions in ``Field(...)``. The library, the model registry
(:mod:`service.methods.kinds`), job payloads, stored manifests and OpenAPI all use that one
class, so a bound cannot exist in one copy and not in another.

Two ways in, one set of rules:

* ``Params(**values)`` (library code) raises :class:`~service.errors.InvalidInput`
  (with per-field ``errors``) whose message names the field, what was expected
  and what was given;
* ``Params.model_validate(mapping)`` (the API, through ``Kind.parse_params``) raises
  pydantic's ``ValidationError`` with per-field ``errors`` for the 422 body.

Numeric and boolean fields are declared ``strict`` where a string or a bool must not pass
for a number (``"125"`` is not 125, ``1`` is not ``true``).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, PlainValidator, TypeAdapter, ValidationError

from service.errors import InvalidInput, field_errors


def describe(error: dict[str, Any]) -> str:
    """One readable line for a pydantic error: ``"order must be one of [...], got 'x'"``."""
    where = ".".join(str(part) for part in error.get("loc", ())) or "parameters"
    given = error.get("input")
    if error.get("type") == "literal_error":
        expected = error.get("ctx", {}).get("expected", "")
        return f"{where} must be one of {expected}, got {given!r}"
    if error.get("type") == "extra_forbidden":
        return f"{where} is not a parameter of this method"
    return f"{where}: {error.get('msg', 'invalid')}, got {given!r}"


class MethodParams(BaseModel):
    """Frozen, hashable parameters that refuse unknown names."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    def __init__(self, **values: Any):
        try:
            super().__init__(**values)
        except ValidationError as error:
            errors = error.errors(include_url=False)
            raise InvalidInput("; ".join(describe(e) for e in errors),
                               field_errors(errors)) from None

    # pydantic calls a custom __init__ from model_validate too; marked as the base one, it is
    # used for construction only, so model_validate keeps raising ValidationError per field
    __init__.__pydantic_base_init__ = True  # type: ignore[attr-defined]


#: default ``marker_noise_mm`` (see :class:`MarkerParams`)
MARKER_NOISE_MM = 0.0
#: the ``marker_noise_mm`` value that estimates σ per request
#: (:data:`service.geometry.marker_prior.AUTO`)
MARKER_NOISE_AUTO = "auto"
#: bounds of a numeric ``marker_noise_mm``, mm
MARKER_NOISE_RANGE = (0.0, 5.0)
_NOISE_NUMBER = TypeAdapter(Annotated[float, Field(ge=MARKER_NOISE_RANGE[0], le=MARKER_NOISE_RANGE[1],
                                                   allow_inf_nan=False)])


def _marker_noise(value: Any) -> float | str:
    """``marker_noise_mm``: "auto" or a finite number in :data:`MARKER_NOISE_RANGE` (one error,
    located at the field, for anything else)."""
    if value == MARKER_NOISE_AUTO:
        return MARKER_NOISE_AUTO
    try:
        return _NOISE_NUMBER.validate_python(value)
    except ValidationError:
        raise ValueError(f'must be "{MARKER_NOISE_AUTO}" or a finite number from {MARKER_NOISE_RANGE[0]:g} '
                         f'to {MARKER_NOISE_RANGE[1]:g} (mm)') from None


class MarkerParams(MethodParams):
    """Parameters of every method driven by markers: the base of their params models, so the
    marker-noise field is declared once (issue 17)."""

    marker_noise_mm: Annotated[float | str, PlainValidator(
        _marker_noise, json_schema_input_type=Annotated[float, Field(ge=MARKER_NOISE_RANGE[0], le=MARKER_NOISE_RANGE[1])]
        | Literal["auto"])] = Field(
        default=MARKER_NOISE_MM,
        description="Assumed noise of the input markers, σ per coordinate in the actor's unit "
                    "(mm). 0 (default) interpolates the markers exactly, as the papers do "
                    "(occluded, NaN, markers are completed from the visible ones by the "
                    "learned prior below); "
                    "σ > 0 makes them soft constraints: the handles are the MAP estimate "
                    "under Gaussian marker noise σ and a Gaussian prior over the head-aligned "
                    "marker displacements learned from the training frames (a tapered "
                    "covariance, stored with the model; models trained before it use the "
                    "thin-shell energy as the prior), and every feature is computed from the "
                    "denoised markers. Used in training and synthesis alike. Set it to the "
                    "capture's noise level (e.g. 0.3 for ordinary optical mocap). \"auto\" "
                    "estimates σ per request (each frame's residual against the learned prior "
                    "in the directions the training never moved in, the request's median) "
                    "and denoises with it. Whatever the setting, each frame's reported "
                    "confidence is lowered by its own noise estimate (not the detail's "
                    "fade). For whole performances, see also the synthesis job's "
                    "`marker_filter_frames`.",
        examples=[0.0, 0.3, "auto"])
