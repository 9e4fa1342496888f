"""``facesynth worker``: flags and environment variables become the worker's settings."""

from __future__ import annotations

from pathlib import Path

from service import cli
from service.jobs import worker


def test_worker_flags_override_the_environment(monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(worker, "run_worker", lambda settings: calls.append(settings))
    monkeypatch.setenv("FACESYNTH_QUEUE_NAME", "from_env")
    monkeypatch.setenv("FACESYNTH_WORKERS", "2")
    monkeypatch.setenv("FACESYNTH_DATA_DIR", "/nonexistent")
    assert cli.main(["worker", "--data-dir", str(tmp_path), "--workers", "3"]) == 0
    (settings,) = calls
    assert (settings.data_dir, settings.workers, settings.queue_name) == (Path(tmp_path), 3, "from_env")
    cli.main(["worker"])
    assert (calls[1].data_dir, calls[1].workers) == (Path("/nonexistent"), 2)
