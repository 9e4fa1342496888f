"""The app's construction (service/api/app.py): FastAPI's native OpenTelemetry follows
``Settings.opentelemetry``."""

from __future__ import annotations

import inspect

import pytest
from fastapi import FastAPI

from service.api import create_app
from service.api.app import TELEMETRY_OFF, telemetry_argument
from service.config import Settings

native = pytest.mark.skipif("telemetry" not in inspect.signature(FastAPI.__init__).parameters,
                            reason="this FastAPI has no native telemetry")


@native
def test_fastapi_telemetry_is_off_unless_asked(tmp_path):
    off = create_app(Settings(data_dir=tmp_path / "off"))
    assert all(off._telemetry[k] is False for k in TELEMETRY_OFF)
    assert off._native_telemetry.enabled() is False
    on = create_app(Settings(data_dir=tmp_path / "on", opentelemetry=True))
    assert all(on._telemetry[k] is True for k in TELEMETRY_OFF)      # FastAPI's defaults


def test_telemetry_argument():
    assert telemetry_argument(True) == {}
    assert telemetry_argument(False) in ({}, {"telemetry": TELEMETRY_OFF})
