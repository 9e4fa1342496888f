"""The package layers of docs/architecture.md, checked from the source: every import of
``service`` and ``models_store`` (module level or inside a function) goes down the layers or
stays within its own package, and no modules import each other in a cycle."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: top to bottom; a package may import its own modules and those of any lower row, never a
#: package of its own row or a higher one (``models_store`` imports nothing of ``service``)
LAYERS: list[set[str]] = [
    {"service.cli"},                                          # the `facesynth` command
    {"service.client_cli", "service.demo"},                   # its SDK-side subcommands
    {"service.progress_bar"},                                 # the commands' progress output
    {"service.api", "service.grpc"},                          # transports
    {"service.app"},                                          # operations
    {"service.jobs"},                                         # queue, runner, one task per kind
    {"service.samples"},                                      # the sample actor families
    {"service.store"},                                        # database + blobs, actor store
    {"service.methods"},                                      # the papers' methods
    {"service.io"},                                           # file formats
    {"service.geometry"},                                     # the numerical core
    {"service.config", "service.logs", "service.errors"},     # settings, logs, error meanings
    {"models_store"},                                         # registry, blobs (beside service)
]


def _package_of(module: str) -> str | None:
    """The layer package ``module`` belongs to (``service.api.routes.x`` → ``service.api``;
    the ``service`` package's own ``__init__`` is in the bottom row of ``service``)."""
    if module == "service":
        return "service.errors"
    for row in LAYERS:
        for package in row:
            if module == package or module.startswith(package + "."):
                return package
    return None


def _rank(package: str) -> int:
    return next(i for i, row in enumerate(LAYERS) if package in row)


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, module: str, modules: set[str]) -> set[str]:
    """Every module of ``modules`` that ``path`` imports: ``from x import y`` counts ``x.y``
    when that is a module, else ``x``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            submodules = {f"{target}.{alias.name}" for alias in node.names} & modules
            found.update(submodules)
            if len(submodules) < len(node.names):
                found.add(target)
    return found & modules


def _graph() -> dict[str, set[str]]:
    files = [p for top in ("service", "models_store") for p in (ROOT / top).rglob("*.py")]
    modules = {_module_name(p): p for p in files}
    return {name: _imports(path, name, set(modules)) - {name} for name, path in modules.items()}


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    """``"source -> target"`` for each import of a package of the same or a higher row."""
    violations = []
    for source, targets in graph.items():
        mine = _package_of(source)
        for target in targets:
            theirs = _package_of(target)
            if theirs != mine and _rank(theirs) <= _rank(mine):
                violations.append(f"{source} -> {target}")
    return sorted(violations)


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(cycles)


GRAPH = _graph()


def test_the_graph_sees_the_tree():
    assert len(GRAPH) > 100
    assert "service.methods.kinds" in GRAPH["service.jobs.tasks.train"]


def test_every_module_belongs_to_a_layer():
    assert [m for m in GRAPH if _package_of(m) is None] == []


def test_imports_go_down_the_layers():
    assert layer_violations(GRAPH) == []


def test_no_import_cycles():
    assert import_cycles(GRAPH) == []


def test_the_checks_on_a_hand_made_graph():
    graph = {
        "service.geometry.a": {"service.io.b"},            # geometry below io: refused
        "service.methods.c": {"service.app.d"},            # upward: refused
        "service.api.e": {"service.app.d", "service.api.f"},  # down, own package: fine
        "models_store.g": {"service.errors"},              # models_store imports no service
        "service.app.d": {"service.app.h"}, "service.app.h": {"service.app.d"},  # a cycle
    }
    assert layer_violations(graph) == ["models_store.g -> service.errors",
                                       "service.geometry.a -> service.io.b",
                                       "service.methods.c -> service.app.d"]
    assert import_cycles(graph) == [["service.app.d", "service.app.h"]]


#: benchmark scripts still importing another script than the harness (to be moved into it)
BENCHMARK_IMPORTS_PENDING: dict[str, set[str]] = {}


def test_benchmarks_share_code_only_through_the_harness():
    """A benchmark script imports another one only as ``harness`` (benchmarks/harness.py:
    what the reports share), never another report (except the pending ones listed)."""
    scripts = {p.stem: p for p in (ROOT / "benchmarks").glob("*.py")}
    assert "harness" in scripts and "pose_space_l2_speed_model" in scripts
    found = {name: _imports(path, name, set(scripts)) - {name, "harness"} for name, path in scripts.items()}
    assert {k: v for k, v in found.items() if v} == BENCHMARK_IMPORTS_PENDING


#: modules ``facesynth serve`` imports before its first frame must not pull in (issue 23):
#: the tasks' methods, imported where a job runs (the runner's ``TASKS``), and the parts of
#: SciPy only training and jobs use (triangulations, trees, k-means, image filters), and
#: Numba (the compiled kernels of a model kind, imported when such a model loads)
SERVE_NEVER_IMPORTS = ("service.jobs.tasks.synthesize", "service.jobs.tasks.track",
                       "service.jobs.tasks.register", "service.jobs.tasks.correspond",
                       "service.jobs.frame_usd", "service.io.usd", "scipy.spatial",
                       "scipy.cluster", "scipy.ndimage", "numba")


def test_serve_imports_no_task_methods_until_a_job_runs():
    """What ``cmd_serve`` imports (services, gRPC server, HTTP app, maintenance thread) leaves
    the task modules above unimported; the runner's table, read once, imports every task."""
    code = ("import sys, service.app.services, service.grpc.server, service.api.app, "
            "service.jobs.worker\n"
            f"print(sorted(m for m in {SERVE_NEVER_IMPORTS!r} if m in sys.modules))\n"
            "from service.jobs import tasks\n"
            "print(sorted(tasks.TASKS), tasks.TASKS is tasks.TASKS, "
            f"all(m in sys.modules for m in {SERVE_NEVER_IMPORTS[:4]!r}))")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True,
                         text=True, check=True).stdout.splitlines()
    assert out == ["[]", "['bone_rig', 'correspond', 'register', 'synthesize', 'track', "
                   "'track_span', 'train', 'transfer'] True True"]
