"""A real multi-process deployment for the end-to-end tests.

``deployment`` (module scope) runs, as separate OS processes started the way an operator
starts them (``python -m service.cli ...``):

- the API, ``facesynth serve --workers 0`` (HTTP + gRPC, no embedded worker);
- two workers, ``facesynth worker`` (one job thread each);

against the real PostgreSQL and Redis of the machine (:mod:`tests.servers` starts private
ones where none answers). Every run gets its own database ``facesynth_e2e_<random>`` (dropped
afterwards) and its own queue name ``facesynth_e2e_<random>`` (its Redis keys deleted
afterwards); the processes share one data directory (one machine's disk). Each process's
stdout and stderr go to files in ``<tmp>/logs``; a failing test's report ends with their tails.
Teardown always kills every process it started.

``e2e_actor_dir`` (session scope) is the smallest level-1 sample actor the tests need: the
8 training clips and the held-out in-range performance, 256² maps, no camera renders
(~15 s, ~450 MB on disk, instead of ~90 s and ~2 GB for the full actor).
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import httpx
import pytest

from tests.e2e.commands import API_COMMAND, WORKER_COMMAND
from tests.servers import free_port, postgres_server, redis_server, temporary_database  # noqa: F401

ROOT = Path(__file__).resolve().parents[2]
#: the sample actor of the end-to-end tests
SEED, LEVEL, MAP_RESOLUTION = 1, 1, 256
HELDOUT = "heldout_in_range"
#: a job whose worker stopped renewing its lease is reaped after at most this (+ a reap round)
LEASE_SECONDS = 6
#: how long a started process may take to become ready, seconds
START_TIMEOUT = 60.0
#: lines of each process log shown when a test fails
TAIL_LINES = 40


@pytest.fixture(scope="session")
def e2e_actor_dir(tmp_path_factory) -> Iterator[Path]:
    """The level-1 sample actor (seed 1): training clips + held-out in-range, 256² maps."""
    from service.samples import performances
    from service.samples.actor import build_sample_actor

    out = tmp_path_factory.mktemp("e2e_actor")
    names = tuple(f"train_{name}" for name in performances.TRAINING_EXPRESSIONS) + (HELDOUT,)
    build_sample_actor(out, seed=SEED, level=LEVEL, with_tracking=False,
                       map_resolution=MAP_RESOLUTION, performance_names=names)
    yield out
    shutil.rmtree(out, ignore_errors=True)


#: the clips of the small actor of the fault and tenancy tests
FAULT_CLIPS = ("train_smile", "train_brow_raise")


@pytest.fixture(scope="session")
def actor_dir(tmp_path_factory) -> Iterator[Path]:
    """A small level-0 sample actor (seed 1, 64² maps): two training clips and the held-out
    in-range performance, shared by the fault, storage and tenancy tests (read only)."""
    from service.samples.actor import build_sample_actor

    out = tmp_path_factory.mktemp("fault_actor")
    build_sample_actor(out, seed=1, level=0, with_tracking=False, map_resolution=64,
                       performance_names=FAULT_CLIPS + (HELDOUT,))
    yield out
    shutil.rmtree(out, ignore_errors=True)


@dataclass
class Process:
    """One started service process, its output captured to ``<logs>/<name>.out|.err``."""

    name: str
    popen: subprocess.Popen
    stdout: Path
    stderr: Path

    @property
    def pid(self) -> int:
        return self.popen.pid

    def alive(self) -> bool:
        return self.popen.poll() is None

    def tail(self, lines: int = TAIL_LINES) -> str:
        parts = []
        for path in (self.stdout, self.stderr):
            text = path.read_text(errors="replace").splitlines() if path.exists() else []
            parts.append(f"--- {path.name} (last {min(lines, len(text))} of {len(text)} lines)\n"
                         + "\n".join(text[-lines:]))
        state = "running" if self.alive() else f"exited with {self.popen.returncode}"
        return f"=== {self.name} (pid {self.pid}, {state})\n" + "\n".join(parts)

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 30.0) -> int | None:
        """Send ``sig`` and wait up to ``timeout`` s; SIGKILL if it is still alive then."""
        if self.alive():
            self.popen.send_signal(sig)
            try:
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait()
        return self.popen.returncode


@dataclass
class Deployment:
    """The API and workers of one test run, and how to reach them."""

    env: dict[str, str]
    data_dir: Path
    logs: Path
    database_url: str
    redis_url: str
    queue_name: str
    port: int
    grpc_port: int
    processes: list[Process] = field(default_factory=list)
    api: Process | None = None
    workers: list[Process] = field(default_factory=list)

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def client(self, timeout: float = 120.0) -> httpx.Client:
        return httpx.Client(base_url=self.base_url, timeout=timeout)

    # -- processes ---------------------------------------------------------------------------
    def _start(self, name: str, *argv: str, **env: str) -> Process:
        count = sum(p.name.startswith(name) for p in self.processes)
        name = f"{name}-{count + 1}"
        stdout, stderr = self.logs / f"{name}.out", self.logs / f"{name}.err"
        with open(stdout, "wb") as out, open(stderr, "wb") as err:
            popen = subprocess.Popen([sys.executable, "-m", "service.cli", *argv],
                                     cwd=ROOT, env={**self.env, **env}, stdout=out, stderr=err,
                                     stdin=subprocess.DEVNULL)
        process = Process(name, popen, stdout, stderr)
        self.processes.append(process)
        return process

    def start_api(self) -> Process:
        """``facesynth serve --workers 0`` on the deployment's ports; returns once /readyz
        answers 200 (database, blobs and queue reachable)."""
        self.api = self._start("api", *API_COMMAND)
        deadline = time.monotonic() + START_TIMEOUT
        while True:
            try:
                response = httpx.get(f"{self.base_url}/readyz", timeout=2)
                if response.status_code == 200:
                    return self.api
            except httpx.TransportError:
                pass
            self._check_starting(self.api, deadline, "its /readyz never answered 200")
            time.sleep(0.2)

    def start_worker(self) -> Process:
        """``facesynth worker`` with one job thread; returns once it logged that it started."""
        worker = self._start("worker", *WORKER_COMMAND)
        self.workers.append(worker)
        deadline = time.monotonic() + START_TIMEOUT
        while "worker started" not in worker.stderr.read_text(errors="replace"):
            self._check_starting(worker, deadline, "it never logged 'worker started'")
            time.sleep(0.2)
        return worker

    def _check_starting(self, process: Process, deadline: float, what: str) -> None:
        if not process.alive():
            raise RuntimeError(f"{process.name} exited while starting\n{self.tails()}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"{process.name} did not start in {START_TIMEOUT} s: {what}\n"
                               f"{self.tails()}")

    def worker_by_pid(self, pid: int) -> Process:
        matches = [w for w in self.workers if w.pid == pid]
        assert matches, f"pid {pid} is none of our workers {[w.pid for w in self.workers]}"
        return matches[0]

    def tails(self) -> str:
        return "\n\n".join(p.tail() for p in self.processes)

    def kill_all(self, grace: float = 5.0) -> None:
        """Stop every process: SIGTERM, then SIGKILL what is still alive ``grace`` s later."""
        for process in self.processes:
            if process.alive():
                process.popen.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace
        for process in self.processes:
            try:
                process.popen.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.popen.kill()
                process.popen.wait()

    # -- the store, read directly (what the API does not expose) -----------------------------
    def sessions(self):
        """A session factory on the run's database (close it with ``.kw['bind'].dispose()``)."""
        from models_store.db import make_session_factory

        return make_session_factory(self.database_url)

    def blobs(self):
        from models_store.blobs import BlobStore

        return BlobStore(self.data_dir / "blobs")


@contextlib.contextmanager
def running_deployment(root: Path, postgres_server: str, redis_server: str, *,  # noqa: F811
                       data_dir: Path | None = None, workers: int = 2,
                       env: dict[str, str] | None = None) -> Iterator[Deployment]:
    """The API (no embedded worker) and ``workers`` workers on a fresh database and queue
    name, with ``env`` added to their environment; everything is killed and removed at the
    end (``data_dir``, default ``root/data``, is emptied, not removed, when given)."""
    import redis

    logs = root / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    own_data = data_dir is None
    data_dir = root / "data" if data_dir is None else data_dir
    data_dir.mkdir(parents=True, exist_ok=True)
    queue_name = f"facesynth_e2e_{secrets.token_hex(6)}"
    with temporary_database(postgres_server, prefix="facesynth_e2e_") as database_url:
        port, grpc_port = free_port(), free_port()
        full_env = {k: v for k, v in os.environ.items() if not k.startswith("FACESYNTH_")}
        full_env.update({
            "FACESYNTH_DATA_DIR": str(data_dir),
            "FACESYNTH_DATABASE_URL": database_url,
            "FACESYNTH_QUEUE_URL": redis_server,
            "FACESYNTH_QUEUE_NAME": queue_name,
            "FACESYNTH_JOB_LEASE_SECONDS": str(LEASE_SECONDS),
            "FACESYNTH_HOST": "127.0.0.1",
            "FACESYNTH_PORT": str(port),
            "FACESYNTH_GRPC_PORT": str(grpc_port),
            "PYTHONUNBUFFERED": "1",
            **(env or {}),
        })
        deployment = Deployment(full_env, data_dir, logs, database_url, redis_server,
                                queue_name, port, grpc_port)
        connection = redis.Redis.from_url(redis_server)
        try:
            deployment.start_api()
            for _ in range(workers):
                deployment.start_worker()
            yield deployment
        finally:
            deployment.kill_all()
            try:
                for key in connection.scan_iter(f"*{queue_name}*"):
                    connection.delete(key)
                assert not list(connection.scan_iter(f"*{queue_name}*"))
            finally:
                connection.close()
                if own_data:
                    shutil.rmtree(data_dir, ignore_errors=True)
                else:
                    for child in data_dir.iterdir():
                        if child.is_dir():
                            shutil.rmtree(child, ignore_errors=True)
                        else:
                            child.unlink(missing_ok=True)
        # leaving the block drops the database (WITH (FORCE))


@pytest.fixture(scope="module")
def deployment(tmp_path_factory, postgres_server, redis_server) -> Iterator[Deployment]:  # noqa: F811
    """The API (no embedded worker) and two workers on a fresh database and queue name."""
    with running_deployment(tmp_path_factory.mktemp("e2e_deployment"), postgres_server,
                            redis_server) as deployment:
        yield deployment


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """A failing test's report ends with the tails of every process's output."""
    outcome = yield
    report = outcome.get_result()
    deployment = item.funcargs.get("deployment") if hasattr(item, "funcargs") else None
    if report.failed and isinstance(deployment, Deployment):
        report.sections.append(("facesynth process logs", deployment.tails()))
