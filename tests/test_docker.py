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


def env_example() -> dict[str, str]:
    """The variables of docker/.env.example."""
    lines = (DOCKER / ".env.example").read_text().splitlines()
    return dict(l.split("=", 1) for l in lines if l.strip() and not l.startswith("#"))


#: compose's ``${VAR}``, ``${VAR:?message}`` and ``${VAR:-default}``
_INTERPOLATION = re.compile(r"\$\{(\w+)(?::([?-])([^}]*))?\}")


def interpolate(node, env: dict[str, str]):
    """``node`` with compose's variables replaced from ``env`` (a required one must be set)."""
    if isinstance(node, dict):
        return {k: interpolate(v, env) for k, v in node.items()}
    if isinstance(node, list):
        return [interpolate(v, env) for v in node]
    if isinstance(node, str):
        def value(m: re.Match) -> str:
            if m.group(1) in env:
                return env[m.group(1)]
            assert m.group(2) == "-", f"required variable {m.group(1)} is not set"
            return m.group(3)
        return _INTERPOLATION.sub(value, node)
    return node


@pytest.fixture(scope="module")
def raw_compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


@pytest.fixture(scope="module")
def compose(raw_compose) -> dict:
    """The compose file as compose reads it with the variables of docker/.env.example."""
    return interpolate(raw_compose, env_example())


def test_compose_restarts_limits_memory_and_builds_its_images(compose):
    services = compose["services"]
    for name, service in services.items():
        assert service["restart"] in ("unless-stopped", "always", "on-failure"), name
        memory = service["deploy"]["resources"]["limits"]["memory"]
        assert re.fullmatch(r"\d+[mg]", memory), (name, memory)
    gib = lambda m: int(m[:-1]) / (1024 if m.endswith("m") else 1)
    # training takes several GB; the API holds the model cache (2 GiB by default)
    assert gib(services["worker"]["deploy"]["resources"]["limits"]["memory"]) >= 8
    api_limit = gib(services["api"]["deploy"]["resources"]["limits"]["memory"])
    assert api_limit * 2**30 > Settings.model_fields["model_cache_bytes"].default
    for name in ("api", "worker"):
        assert services[name]["build"] == {"context": "..", "dockerfile": "docker/Dockerfile"}
    assert services["api"]["image"] == services["worker"]["image"]


def test_worker_healthcheck_is_a_facesynth_command_that_probes_its_dependencies(compose, tmp_path):
    check = compose["services"]["worker"]["healthcheck"]
    assert not check.get("disable") and check["test"][0] == "CMD"
    command = check["test"][1:]
    assert command[0] == "facesynth"
    args = build_parser().parse_args(command[1:])
    assert args.command == "check"
    # it answers 0 where database, blobs and queue are reachable (embedded defaults here)
    from service.cli import main

    assert main([*command[1:], "--data-dir", str(tmp_path)]) == 0


def test_secrets_come_from_the_env_file_not_trust_auth(raw_compose, compose, monkeypatch):
    text = (DOCKER / "compose.yaml").read_text()
    assert "trust" not in text and "POSTGRES_HOST_AUTH_METHOD" not in text
    example = env_example()
    required = {m.group(1) for m in _INTERPOLATION.finditer(text) if m.group(2) == "?"}
    assert required == {"POSTGRES_PASSWORD", "FACESYNTH_TOKENS"} <= set(example)
    with pytest.raises(AssertionError, match="required variable"):
        interpolate(raw_compose, {})
    postgres = compose["services"]["postgres"]["environment"]
    api = settings_from(compose["services"]["api"]["environment"], monkeypatch)
    assert api.tokens == [example["FACESYNTH_TOKENS"]]
    assert f":{postgres['POSTGRES_PASSWORD']}@postgres:" in api.database_url


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


#: an image reference pinned to an exact release, name:VERSION[-variant] with at least
#: MAJOR.MINOR (PostgreSQL's releases are MAJOR.MINOR), or a digest
PINNED = re.compile(r"^[a-z0-9./-]+:\d+\.\d+(\.\d+)?(-[a-z0-9.-]+)?(@sha256:[0-9a-f]{64})?$|@sha256:[0-9a-f]{64}$")


def base_image(from_args: str, ins: list[tuple[str, str]]) -> str:
    """The image of a FROM line, ``${ARG}`` resolved from the Dockerfile's ARG defaults."""
    defaults = dict(a.split("=", 1) for word, a in ins if word == "ARG" and "=" in a)
    image = from_args.split()[0]
    return re.sub(r"\$\{(\w+)\}", lambda m: defaults[m.group(1)], image)


def test_base_images_are_pinned_to_exact_releases(compose):
    ins = instructions(DOCKER / "Dockerfile")
    for word, args in ins:
        if word == "FROM":
            image = base_image(args, ins)
            assert PINNED.match(image) and "latest" not in image, image
            assert re.match(r"python:3\.\d+\.\d+-", image), image   # Python: the patch release
    for name, service in compose["services"].items():
        if "build" not in service:
            assert PINNED.match(service["image"]), (name, service["image"])
    assert not PINNED.match("redis:7-alpine") and not PINNED.match("postgres:16")


def test_installs_use_the_constraints_of_the_dependency_closure():
    """constraints.txt pins (==) every dependency pyproject declares, at a version its
    specifier allows; the Makefile's install step and the Dockerfile's use it."""
    import tomllib

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            name, _, version = line.partition("==")
            assert version, f"not an exact pin: {line!r}"
            pins[canonicalize_name(name)] = version
    for path in (ROOT / "pyproject.toml", ROOT / "clients/python/pyproject.toml"):
        project = tomllib.loads(path.read_text())["project"]
        declared = project["dependencies"] + [r for extra in project.get("optional-dependencies", {}).values() for r in extra]
        for text in declared:
            requirement = Requirement(text)
            name = canonicalize_name(requirement.name)
            if requirement.marker is not None and not requirement.marker.evaluate({"extra": ""}):
                continue
            assert name in pins, f"{name} ({path.name}) is not in constraints.txt"
            assert requirement.specifier.contains(pins[name], prereleases=True), (text, pins[name])
    make = (ROOT / "Makefile").read_text()
    installs = [l for l in make.splitlines() if "pip install" in l and "-e" in l]
    assert installs and all("-c constraints.txt" in l for l in installs)
    docker = " ".join(a for w, a in instructions(DOCKER / "Dockerfile") if w == "RUN")
    assert "-c constraints.txt" in docker


def test_pyproject_license_is_an_spdx_string():
    """A ``project.license`` table is deprecated (setuptools warns from 77 on)."""
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert isinstance(project["license"], str)
    assert all((ROOT / f).exists() for f in project["license-files"])


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
    assert api.database_url.startswith(f"postgresql://{postgres['POSTGRES_USER']}:")
    assert api.database_url.endswith(f"@postgres:5432/{postgres['POSTGRES_DB']}")


def test_dockerfile_is_multi_stage_slim_non_root_with_healthcheck(monkeypatch, tmp_path):
    ins = instructions(DOCKER / "Dockerfile")
    froms = [base_image(args, ins) for word, args in ins if word == "FROM"]
    assert len(froms) >= 2 and all(f.startswith("python:3.11") and "-slim" in f for f in froms)
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
