"""Write constraints.txt: the exact versions, from the working virtualenv, of every package
the project needs (its dependency closure), so `make setup` and the Docker image install
what was tested.

    python docker/freeze_constraints.py            # writes constraints.txt at the repo root
    python docker/freeze_constraints.py --check    # exit 1 if constraints.txt is out of date

The roots are the requirements of pyproject.toml (with the ``dev`` extra) and of
clients/python/pyproject.toml (with ``grpc``); each installed distribution's own
requirements are followed (environment markers evaluated for this interpreter, extras as
requested). Like ``pip freeze``, limited to that closure; the project's own packages are
left out.
"""

from __future__ import annotations

import sys
import tomllib
from importlib import metadata
from pathlib import Path

from packaging.markers import default_environment
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "constraints.txt"
#: (pyproject, extras) whose requirements are the roots of the closure
ROOTS = ((ROOT / "pyproject.toml", ("dev",)), (ROOT / "clients/python/pyproject.toml", ("grpc",)))
OWN = {"facesynth", "facesynth-client"}


def root_requirements() -> list[tuple[Requirement, frozenset[str]]]:
    """The requirements declared by the project's pyprojects, with the extras they apply to."""
    out = []
    for path, extras in ROOTS:
        project = tomllib.loads(path.read_text())["project"]
        out += [(Requirement(r), frozenset({""})) for r in project.get("dependencies", [])]
        for extra in extras:
            out += [(Requirement(r), frozenset({extra}))
                    for r in project.get("optional-dependencies", {}).get(extra, [])]
    return out


def applies(requirement: Requirement, extras: frozenset[str]) -> bool:
    """The requirement's marker holds here for one of ``extras`` ("" = no extra)."""
    if requirement.marker is None:
        return True
    return any(requirement.marker.evaluate({**default_environment(), "extra": e}) for e in extras)


def closure() -> dict[str, str]:
    """Canonical name → installed version of every package the roots need, transitively."""
    pinned: dict[str, str] = {}
    todo = [(r, e) for r, e in root_requirements() if applies(r, e)]
    seen: set[tuple[str, frozenset[str]]] = set()
    while todo:
        requirement, _ = todo.pop()
        name = canonicalize_name(requirement.name)
        key = (name, frozenset(requirement.extras))
        if key in seen or name in OWN:
            continue
        seen.add(key)
        try:
            dist = metadata.distribution(requirement.name)
        except metadata.PackageNotFoundError:
            raise SystemExit(f"{requirement.name} is required but not installed: install the "
                             "project first (make setup)") from None
        pinned[name] = dist.version
        extras = frozenset({""} | set(requirement.extras))
        for text in dist.requires or []:
            sub = Requirement(text)
            if applies(sub, extras):
                todo.append((sub, extras))
    return dict(sorted(pinned.items()))


def render(pins: dict[str, str]) -> str:
    py = ".".join(map(str, sys.version_info[:3]))
    lines = ["# Exact versions of the project's dependency closure, as tested (Python "
             f"{py}, {sys.platform}).",
             "# Used by `make setup` and docker/Dockerfile as pip constraints (-c); "
             "regenerate with",
             "#   python docker/freeze_constraints.py"]
    return "\n".join(lines + [f"{name}=={version}" for name, version in pins.items()]) + "\n"


def main(argv: list[str]) -> int:
    text = render(closure())
    if "--check" in argv:
        current = OUT.read_text() if OUT.exists() else ""
        strip = lambda t: [l for l in t.splitlines() if not l.startswith("#")]
        if strip(current) != strip(text):
            print("constraints.txt is out of date: run python docker/freeze_constraints.py",
                  file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text)
    print(f"wrote {OUT.relative_to(ROOT)}: {len(text.splitlines()) - 3} packages")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
