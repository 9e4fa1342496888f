"""The SDK is its own distribution: installing it pulls httpx and numpy (and their own
dependencies) only, never the server's packages; importing it imports no server code."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

CLIENT_DIR = Path(__file__).resolve().parents[1]
#: what ``pip install facesynth-client`` may bring: httpx's and numpy's dependency trees
ALLOWED = {"facesynth-client", "httpx", "httpcore", "h11", "anyio", "sniffio", "idna", "certifi",
           "typing-extensions", "exceptiongroup", "numpy"}
#: the server's dependencies (root pyproject.toml), none of which the SDK may pull
SERVER = {"facesynth", "fastapi", "starlette", "uvicorn", "pydantic", "pydantic-settings",
          "scipy", "trimesh", "openexr", "c3d", "pillow", "tqdm", "grpcio", "protobuf",
          "sqlalchemy", "alembic", "psycopg", "huey", "redis", "prometheus-client",
          "python-multipart"}


def normalize(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def requirement_name(requirement: str) -> str:
    return normalize(re.split(r"[\s<>=!~;\[(]", requirement, maxsplit=1)[0])


def base_requirements(requires: list[str]) -> list[str]:
    """The requirements of a plain install: those of optional extras (``; extra == ...``,
    e.g. ``facesynth-client[grpc]``) left out."""
    return [r for r in requires if not re.search(r";.*\bextra\s*==", r)]


def metadata_requires() -> list[str]:
    """``Requires-Dist`` of the installed SDK's metadata (what pip wrote from its wheel) for a
    plain install (no extras), or the static ``[project] dependencies`` they are made from if
    it is not installed."""
    from importlib import metadata

    try:
        return base_requirements(list(metadata.requires("facesynth-client") or []))
    except metadata.PackageNotFoundError:
        import tomllib

        project = tomllib.loads((CLIENT_DIR / "pyproject.toml").read_text())["project"]
        assert "dependencies" not in project.get("dynamic", [])
        return list(project["dependencies"])


@pytest.mark.slow
def test_pip_install_in_a_fresh_venv_pulls_no_server_dependencies(tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    report = tmp_path / "report.json"
    result = subprocess.run(
        [str(venv / "bin" / "python"), "-m", "pip", "install", "--dry-run", "--quiet",
         "--disable-pip-version-check", "--report", str(report), str(CLIENT_DIR)],
        capture_output=True, text=True, timeout=300)
    if result.returncode != 0 or not report.exists():
        # no package index reachable: the declared requirements are what pip would resolve
        requires = metadata_requires()
        assert sorted(map(requirement_name, requires)) == ["httpx", "numpy"], requires
        return
    installs = json.loads(report.read_text())["install"]
    names = {normalize(item["metadata"]["name"]) for item in installs}
    sdk = next(item for item in installs
               if normalize(item["metadata"]["name"]) == "facesynth-client")
    assert sorted(map(requirement_name, base_requirements(
        sdk["metadata"].get("requires_dist", [])))) == ["httpx", "numpy"]
    assert not names & SERVER, names & SERVER
    assert names <= ALLOWED, names - ALLOWED


def test_declared_requirements_are_exactly_httpx_and_numpy():
    requires = metadata_requires()
    assert sorted(map(requirement_name, requires)) == ["httpx", "numpy"], requires


def test_importing_the_sdk_imports_no_server_code():
    code = ("import sys, facesynth_client; "
            "bad = sorted({m.split('.')[0] for m in sys.modules} & {'service', 'models_store', "
            "'fastapi', 'starlette', 'pydantic', 'trimesh', 'scipy', 'sqlalchemy', 'huey', "
            "'uvicorn', 'tqdm'}); print(','.join(bad))")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                         text=True, timeout=60).stdout.strip()
    assert out == ""


def test_the_grpc_extra_is_grpcio_and_protobuf_only():
    import tomllib

    project = tomllib.loads((CLIENT_DIR / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    assert sorted(extras) == ["grpc"]
    assert sorted(map(requirement_name, extras["grpc"])) == ["grpcio", "protobuf"]
