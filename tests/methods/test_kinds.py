"""service.methods.kinds: the model-kind registry and the pdm parameters' schema."""

from __future__ import annotations

from dataclasses import asdict

import pytest
from pydantic import ValidationError

from service.methods import kinds
from service.methods.inputs import InvalidInput
from service.methods.pdm.model import PdmParams


def test_pdm_parameter_defaults_mirror_the_method():
    kind = kinds.get_kind("pdm")
    assert kind.parse_params(None).model_dump() == asdict(PdmParams())
    assert PdmParams(**kind.parse_params({"order": "bicubic"}).model_dump()).order == "bicubic"


@pytest.mark.parametrize("params, field", [
    ({"medium_resolution": 8}, "medium_resolution"),
    ({"fine_resolution": 9000}, "fine_resolution"),
    ({"gamma": -1}, "gamma"),
    ({"order": "quartic"}, "order"),
    ({"extrapolation_margin": -0.1}, "extrapolation_margin"),
    ({"gama": 3}, "gama"),  # misspelt: refused, not ignored
])
def test_pdm_parameters_out_of_bounds_or_unknown_are_refused(params, field):
    with pytest.raises(ValidationError) as info:
        kinds.get_kind("pdm").parse_params(params)
    assert [e["loc"] for e in info.value.errors()] == [(field,)]


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
    with pytest.raises(InvalidInput, match="unknown model kind 'psd'; known kinds: pdm"):
        kinds.get_kind("psd")
