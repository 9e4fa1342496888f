"""service.methods.kinds: the model-kind registry and the pdm parameters' schema."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from service.methods import kinds
from service.methods.inputs import InvalidInput
from service.methods.outputs import OUTPUTS
from service.methods.pdm.params import PdmParams
from service.methods.shape_space.params import ShapeSpaceParams


def test_pdm_parameter_defaults_mirror_the_method():
    kind = kinds.get_kind("pdm")
    assert kind.parse_params(None).model_dump() == PdmParams().model_dump()
    assert PdmParams(**kind.parse_params({"order": "bicubic"}).model_dump()).order == "bicubic"


@pytest.mark.parametrize("params, field", [
    ({"medium_resolution": 8}, "medium_resolution"),
    ({"fine_resolution": 9000}, "fine_resolution"),
    ({"gamma": -1}, "gamma"),
    ({"ridge": -1}, "ridge"),
    ({"ridge": "inf"}, "ridge"),
    ({"order": "quartic"}, "order"),
    ({"extrapolation_margin": -0.1}, "extrapolation_margin"),
    ({"gama": 3}, "gama"),  # misspelt: refused, not ignored
])
def test_pdm_parameters_out_of_bounds_or_unknown_are_refused(params, field):
    with pytest.raises(ValidationError) as info:
        kinds.get_kind("pdm").parse_params(params)
    assert [e["loc"] for e in info.value.errors()] == [(field,)]


#: the params a model trained on main before ``ridge`` existed stored in its manifest.json
_STORED_BEFORE_RIDGE = {
    "marker_noise_mm": 0.0, "order": "biquadratic", "medium_resolution": 512,
    "fine_resolution": 1024, "gamma": 30.0, "axis_threshold_deg": 30.0,
    "extrapolation_margin": 0.25, "validity_width": 3.0, "validity_slope": 1.0,
    "fine_highpass_mm": 2.0, "smoothing_lam_dt": 125.0,
}


def test_pdm_gamma_keeps_the_paper_meaning_and_ridge_is_the_default():
    """``gamma`` null → the dimensionless ``ridge`` 0.1; a request or a stored model with
    ``gamma: 30`` (no ``ridge``) validates unchanged and keeps the paper's γ rows
    (``polynomial.fit`` ignores ``ridge`` when ``gamma`` is given)."""
    default = kinds.get_kind("pdm").parse_params(None)
    assert (default.gamma, default.ridge) == (None, 0.1)
    sent = kinds.get_kind("pdm").parse_params({"gamma": 30})
    assert (sent.gamma, sent.ridge) == (30.0, 0.1)
    stored = PdmParams(**{"marker_noise_mm": 0.0, **_STORED_BEFORE_RIDGE})   # as store.load
    assert stored.gamma == 30.0
    assert PdmParams(**stored.model_dump(mode="json")) == stored              # re-saves too


def test_pdm_extrapolation_limit_can_be_disabled():
    assert kinds.get_kind("pdm").parse_params({"extrapolation_margin": None}).extrapolation_margin is None


def test_pdm_schema_documents_every_parameter_and_the_patent():
    kind = kinds.get_kind("pdm")
    schema = kind.params.model_json_schema()
    assert schema["additionalProperties"] is False
    for name, prop in schema["properties"].items():
        assert prop.get("description") and prop.get("examples"), name
    assert schema["properties"]["medium_resolution"]["minimum"] == 16
    assert "US patent 8,902,232 B2" in kind.description and kind.input == "markers"


def test_unknown_kind_names_the_known_ones():
    with pytest.raises(InvalidInput, match="unknown model kind 'tracking'; known kinds: pdm, psd, shape_space, stress_blend, wpsd"):
        kinds.get_kind("tracking")


def test_shape_space_parameter_defaults_mirror_the_method():
    kind = kinds.get_kind("shape_space")
    assert kind.input == "meshes"
    assert kind.parse_params(None).model_dump() == ShapeSpaceParams().model_dump()
    parsed = kind.parse_params({"frame_stride": 5, "regions": "whole", "up_axis": [0, 0, 1]})
    method = ShapeSpaceParams(**parsed.model_dump())
    assert (method.frame_stride, method.regions, method.up_axis) == (5, "whole", (0.0, 0.0, 1.0))


@pytest.mark.parametrize("params, field", [
    ({"lam_dt": 0}, "lam_dt"),
    ({"smoothing": "never"}, "smoothing"),
    ({"frame_stride": 0}, "frame_stride"),
    ({"patch_size": 2}, "patch_size"),
    ({"regions": "cheeks"}, "regions"),
    ({"region_motion_fraction": 1.0}, "region_motion_fraction"),
    ({"boundary_weight": -0.1}, "boundary_weight"),
    ({"sequence_seconds": -1}, "sequence_seconds"),
    ({"up_axis": [0, 1]}, "up_axis"),
    ({"patch_sise": 50}, "patch_sise"),  # misspelt: refused, not ignored
])
def test_shape_space_parameters_out_of_bounds_or_unknown_are_refused(params, field):
    with pytest.raises(ValidationError) as info:
        kinds.get_kind("shape_space").parse_params(params)
    assert [e["loc"][0] for e in info.value.errors()] == [field]


def test_shape_space_axes_must_be_orthogonal_and_non_zero():
    kind = kinds.get_kind("shape_space")
    for params in ({"up_axis": [1, 0, 0]}, {"left_axis": [0, 0, 0]}):
        with pytest.raises(ValidationError, match="up_axis|left_axis"):
            kind.parse_params(params)


def test_shape_space_schema_documents_every_parameter():
    schema = kinds.get_kind("shape_space").params.model_json_schema()
    assert schema["additionalProperties"] is False
    for name, prop in schema["properties"].items():
        assert prop.get("description") and "examples" in prop, name
    assert schema["properties"]["patch_size"]["minimum"] == 3
    assert set(schema["properties"]) == set(ShapeSpaceParams().model_dump())


@pytest.mark.parametrize("name", sorted(kinds.KINDS))
def test_every_kind_documents_its_parameters_and_outputs(name):
    kind = kinds.get_kind(name)
    schema = kind.params.model_json_schema()
    assert schema["additionalProperties"] is False
    assert all(prop.get("description") for prop in schema["properties"].values())
    assert set(kind.outputs) <= set(OUTPUTS) and "mesh" in kind.outputs
    assert kind.parse_params(None) == kind.params()


def test_pose_space_kinds_train_their_own_method():
    assert kinds.get_kind("psd").parse_params({"fit": "exact"}).method == "psd"
    assert kinds.get_kind("wpsd").parse_params(None).method == "wpsd"
    with pytest.raises(ValidationError):
        kinds.get_kind("psd").parse_params({"alpha_threshold": 0.1})   # a WPSD parameter


def test_marker_noise_is_a_number_or_auto_with_one_error_at_the_field():
    """marker_noise_mm (declared once on MarkerParams): a number in [0, 5] mm or "auto";
    anything else is one error located at the field; pose space's posterior refuses auto."""
    for name in ("pdm", "shape_space"):
        kind = kinds.get_kind(name)
        assert kind.parse_params({"marker_noise_mm": "auto"}).marker_noise_mm == "auto"
        assert kind.parse_params({"marker_noise_mm": 0.3}).marker_noise_mm == 0.3
        for bad in ("x", 6, -1, "nan"):
            with pytest.raises(ValidationError) as info:
                kind.parse_params({"marker_noise_mm": bad})
            assert [e["loc"] for e in info.value.errors()] == [("marker_noise_mm",)]
        prop = kind.params.model_json_schema()["properties"]["marker_noise_mm"]
        assert {"maximum": 5.0, "minimum": 0.0, "type": "number"} in prop["anyOf"]
        assert {"const": "auto", "type": "string"} in prop["anyOf"]
    wpsd = kinds.get_kind("wpsd")
    assert wpsd.parse_params({"marker_noise_mm": "auto", "marker_prior": "none"}).marker_noise_mm == "auto"
    with pytest.raises(ValidationError, match="marker_prior"):
        wpsd.parse_params({"marker_noise_mm": "auto"})
