"""Static checks of the container files (issue 6): docker/Dockerfile and docker/compose.yaml.

No Docker daemon is needed: the compose file is parsed and every service's command is run
through the ``facesynth`` CLI parser, every ``FACESYNTH_*`` variable through the settings;
the Dockerfile is read instruction by instruction. The api and worker commands must be the
ones the multi-process end-to-end test runs (:mod:`tests.e2e.commands`), which is what
makes that test the proof of the compose topology.
"""

from __future__ import annotations

import os
import re
import shlex
from pathlib import Path

import pytest
import yaml

from service.cli import build_parser
from service.config import Settings
from tests.e2e.commands import API_COMMAND, WORKER_COMMAND

ROOT = Path(__file__).resolve().parents[1]
DOCKER = ROOT / "docker"


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


def instructions(path: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of a Dockerfile, continuation lines joined, comments dropped."""
    text = re.sub(r"\\\n", " ", path.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def settings_from(env: dict[str, str], monkeypatch) -> Settings:
    """Settings read from exactly these FACESYNTH_* variables (raises on a bad value)."""
    unknown = {k for k in env if k.startswith("FACESYNTH_")} - {
        f"FACESYNTH_{name.upper()}" for name in Settings.model_fields}
    assert not unknown, f"not settings of service/config.py: {sorted(unknown)}"
    for key in list(os.environ):
        if key.startswith("FACESYNTH_"):
            monkeypatch.delenv(key)
    for key, value in env.items():
        monkeypatch.setenv(key, str(value))
    return Settings()


def test_compose_has_the_deployment_topology(compose):
    services = compose["services"]
    assert set(services) == {"api", "worker", "redis", "postgres"}
    assert "blobs" in compose["volumes"]
    for name in ("api", "worker"):
        assert "blobs:/data" in services[name]["volumes"]
        assert "deploy" not in services[name] or "replicas" not in services[name]["deploy"]
        # --scale worker=N needs no fixed container name or host port on the worker
        assert "container_name" not in services[name]
    assert "ports" not in services["worker"]
    assert all(p.startswith("127.0.0.1:") for p in services["api"]["ports"])


def test_compose_commands_are_the_e2e_commands_and_parse(compose):
    services = compose["services"]
    assert tuple(services["api"]["command"]) == API_COMMAND
    assert tuple(services["worker"]["command"]) == WORKER_COMMAND
    parser = build_parser()
    assert parser.parse_args(services["api"]["command"]).command == "serve"
    assert parser.parse_args(services["worker"]["command"]).command == "worker"


def test_compose_environment_is_valid_settings(compose, monkeypatch):
    for name in ("api", "worker"):
        env = compose["services"][name]["environment"]
        s = settings_from(env, monkeypatch)
        assert s.data_dir == Path("/data")
        assert s.database_url.startswith("postgresql://") and "@postgres:" in s.database_url
        assert s.queue_url == "redis://redis:6379/0"
    api = settings_from(compose["services"]["api"]["environment"], monkeypatch)
    assert (api.host, api.port, api.grpc_port) == ("0.0.0.0", 8000, 50051)
    published = {p.rsplit(":", 1)[1] for p in compose["services"]["api"]["ports"]}
    assert published == {str(api.port), str(api.grpc_port)}
    postgres = compose["services"]["postgres"]["environment"]
    assert api.database_url.endswith(f"{postgres['POSTGRES_USER']}@postgres:5432/{postgres['POSTGRES_DB']}")


def test_dockerfile_is_multi_stage_slim_non_root_with_healthcheck(monkeypatch, tmp_path):
    ins = instructions(DOCKER / "Dockerfile")
    froms = [args for word, args in ins if word == "FROM"]
    assert len(froms) >= 2 and all(f.startswith("python:3.11-slim") for f in froms)
    runtime = max(i for i, (word, _) in enumerate(ins) if word == "FROM")
    final = ins[runtime:]
    users = [args for word, args in final if word == "USER"]
    assert users and users[-1] not in ("root", "0")
    health = " ".join(args for word, args in final if word == "HEALTHCHECK")
    assert "/healthz" in health
    from service.api.app import create_app

    assert "/healthz" in create_app(Settings(data_dir=tmp_path)).openapi()["paths"]
    entry = [args for word, args in final if word == "ENTRYPOINT"][-1]
    assert entry == '["facesynth"]'
    cmd = yaml.safe_load([args for word, args in final if word == "CMD"][-1])
    assert build_parser().parse_args(cmd).command == "serve"
    env = {}
    for word, args in final:
        if word == "ENV":
            for item in shlex.split(args):
                key, _, value = item.partition("=")
                env[key] = value
    s = settings_from({k: v for k, v in env.items() if k.startswith("FACESYNTH_")}, monkeypatch)
    assert s.host == "0.0.0.0" and s.data_dir == Path("/data")
    # every COPY source from the build context exists
    for word, args in ins:
        if word == "COPY" and not args.startswith("--from"):
            for src in shlex.split(args)[:-1]:
                assert (ROOT / src).exists(), f"COPY source {src} is not in the repository"
