"""service.config.Settings: defaults, environment variables, derived paths."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from pydantic import ValidationError

from service.config import Settings, get_settings


@pytest.fixture
def clean_env(monkeypatch):
    for name in list(os.environ):
        if name.upper().startswith("FACESYNTH_"):
            monkeypatch.delenv(name)
    get_settings.cache_clear()
    yield monkeypatch
    get_settings.cache_clear()


def test_defaults(clean_env):
    s = Settings()
    assert s.data_dir == Path("./facesynth-data")
    assert (s.host, s.port, s.grpc_port, s.workers) == ("127.0.0.1", 8000, 50051, 1)
    assert s.tokens == [] and s.database_url is None and s.queue_url is None
    assert s.max_body_bytes == 256 * 2**20 and s.model_cache_bytes == 2 * 2**30
    assert (s.max_frames_per_request, s.max_map_resolution, s.max_vertices) == (64, 4096,
                                                                                 2_000_000)
    assert (s.job_max_retries, s.job_lease_seconds) == (2, 60)


def test_every_field_is_documented():
    assert all(field.description for field in Settings.model_fields.values())


def test_database_defaults_to_sqlite_in_the_data_dir(tmp_path):
    s = Settings(data_dir=tmp_path)
    assert s.database_url_resolved == f"sqlite:///{tmp_path}/facesynth.db"
    assert s.blob_dir == tmp_path / "blobs"
    relative = Settings(data_dir="rel")
    assert relative.database_url_resolved == f"sqlite:///{Path('rel').absolute()}/facesynth.db"
    pg = Settings(database_url="postgresql://db/fs")
    assert pg.database_url_resolved == "postgresql://db/fs"


def test_environment_variables_with_prefix(clean_env, tmp_path):
    clean_env.setenv("FACESYNTH_DATA_DIR", str(tmp_path))
    clean_env.setenv("FACESYNTH_PORT", "9000")
    clean_env.setenv("FACESYNTH_TOKENS", " alpha, beta ,,")
    clean_env.setenv("FACESYNTH_JOB_LEASE_SECONDS", "2.5")
    s = get_settings()
    assert (s.data_dir, s.port, s.tokens, s.job_lease_seconds) == (tmp_path, 9000,
                                                                   ["alpha", "beta"], 2.5)
    assert get_settings() is s                        # cached
    clean_env.setenv("FACESYNTH_TOKENS", '["x,y", "z"]')
    assert Settings().tokens == ["x,y", "z"]          # a JSON list works too


def test_tokens_are_kept_out_of_the_repr():
    assert "secret" not in repr(Settings(tokens=["secret"]))


def test_out_of_range_values_are_refused(clean_env):
    clean_env.setenv("FACESYNTH_PORT", "70000")
    with pytest.raises(ValidationError, match="port"):
        Settings()
