"""Engines, sessions and migrations for the metadata database.

Two backends, chosen by URL:

- SQLite (the default, ``sqlite:////abs/path/facesynth.db``): WAL journal (readers never
  block the writer), foreign keys enforced, a 30 s busy timeout, so several processes (the API
  and its workers) share one file. The driver's own transaction handling is kept: a
  transaction starts at the first INSERT/UPDATE/DELETE, so plain reads take no lock and
  every state change in :mod:`models_store.registry` is one conditional UPDATE.
- PostgreSQL through psycopg 3 (``postgresql+psycopg://user@host/db``; ``postgresql://``
  and ``postgres://`` are rewritten to it).

The schema is created and upgraded only by the Alembic migrations shipped in
``models_store/migrations``; :func:`upgrade` runs them programmatically (no ``alembic.ini``)
under a lock (``pg_advisory_xact_lock`` on PostgreSQL, a file lock next to a SQLite file), so
processes starting at once migrate exactly once.
"""

from __future__ import annotations

import contextlib
import fcntl
import sqlite3
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

from sqlalchemy import Connection, Engine, create_engine, event, make_url, text
from sqlalchemy.engine import URL
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session, sessionmaker

if TYPE_CHECKING:  # alembic is imported only when migrating
    from alembic.config import Config

MIGRATIONS_DIR = Path(__file__).parent / "migrations"
#: busy timeout of SQLite connections, seconds
SQLITE_BUSY_TIMEOUT = 30.0
#: key of the PostgreSQL advisory lock held while migrating ("facesynt" in ASCII)
MIGRATION_LOCK_KEY = 0x6661636573796E74
#: the newest shipped migration (tests check it against Alembic's head): a database already
#: there is not migrated, so a server's start does not import Alembic (~0.27 s CPU)
HEAD_REVISION = "0003"


def normalize_url(url: str | URL) -> URL:
    """Parse a database URL, choosing psycopg 3 for PostgreSQL.

    ``postgres://`` and ``postgresql://`` (no driver, or ``+psycopg2``) become
    ``postgresql+psycopg://``; other URLs are returned parsed and unchanged.

    Raises
    ------
    ValueError   for a backend other than SQLite or PostgreSQL
    """
    if isinstance(url, str) and url.startswith("postgres://"):
        url = "postgresql://" + url[len("postgres://"):]
    parsed = make_url(url)
    backend = parsed.get_backend_name()
    if backend == "postgresql":
        return parsed.set(drivername="postgresql+psycopg")
    if backend != "sqlite":
        shown = parsed.render_as_string(hide_password=True)
        raise ValueError(f"unsupported database URL {shown!r}: expected sqlite:///... or "
                         "postgresql://...")
    return parsed


def sqlite_path(url: str | URL) -> Path | None:
    """The file of a SQLite URL (``None`` for in-memory SQLite and other backends)."""
    parsed = normalize_url(url)
    if parsed.get_backend_name() != "sqlite" or parsed.database in (None, "", ":memory:"):
        return None
    return Path(parsed.database)


def make_engine(url: str | URL, **kwargs: Any) -> Engine:
    """Create an engine for ``url`` configured for concurrent use by several processes.

    Parameters
    ----------
    url : str | URL      SQLite or PostgreSQL URL (see :func:`normalize_url`)
    **kwargs             passed on to :func:`sqlalchemy.create_engine`

    Notes
    -----
    The parent directory of a SQLite file is created if missing.
    """
    parsed = normalize_url(url)
    if parsed.get_backend_name() == "postgresql":
        kwargs.setdefault("pool_pre_ping", True)
        return create_engine(parsed, **kwargs)

    path = sqlite_path(parsed)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
    connect_args = {"timeout": SQLITE_BUSY_TIMEOUT, "check_same_thread": False}
    connect_args.update(kwargs.pop("connect_args", {}))
    engine = create_engine(parsed, connect_args=connect_args, **kwargs)
    event.listen(engine, "connect", _configure_sqlite_connection(in_memory=path is None))
    return engine


def _configure_sqlite_connection(in_memory: bool):
    """A ``connect`` listener setting the pragmas every SQLite connection needs."""

    def on_connect(dbapi_connection: Any, connection_record: Any) -> None:
        cursor = dbapi_connection.cursor()
        try:
            cursor.execute("PRAGMA foreign_keys = ON")
            cursor.execute(f"PRAGMA busy_timeout = {int(SQLITE_BUSY_TIMEOUT * 1000)}")
            if not in_memory:
                _enable_wal(cursor)
        finally:
            cursor.close()

    return on_connect


def _enable_wal(cursor: Any, timeout: float = SQLITE_BUSY_TIMEOUT) -> None:
    """Put the database file in WAL mode (a no-op where it already is), retrying while it is
    locked, for up to ``timeout`` seconds.

    The switch needs the file's exclusive lock. When two connections that each hold a shared
    lock both ask for it (two processes opening a new database at once), SQLite answers one
    of them SQLITE_BUSY at once instead of calling its busy handler (that wait would be a
    deadlock), so ``busy_timeout`` does not cover it: the loser retries once the winner's
    switch is done, and then finds the file in WAL mode already.
    """
    deadline = time.monotonic() + timeout
    delay = 0.005
    while True:
        try:
            if cursor.execute("PRAGMA journal_mode").fetchone()[0].lower() != "wal":
                cursor.execute("PRAGMA journal_mode = WAL")
            return
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or time.monotonic() + delay > deadline:
                raise
            time.sleep(delay)
            delay = min(2 * delay, 0.1)


def make_session_factory(bind: Engine | str | URL) -> sessionmaker[Session]:
    """A session factory for an engine (or a URL, for which an engine is made).

    Sessions keep their objects' attributes after commit (``expire_on_commit=False``), so
    the rows that :mod:`models_store.registry` returns stay readable after its commit.
    """
    engine = bind if isinstance(bind, Engine) else make_engine(bind)
    return sessionmaker(engine, expire_on_commit=False)


def alembic_config(url: str | URL | None = None) -> Config:
    """An Alembic configuration for the shipped migrations, built without an ini file.

    Use it for maintenance too, e.g. a new revision after changing :mod:`models_store.schema`::

        from alembic import command
        command.revision(alembic_config("sqlite:////tmp/x.db"), autogenerate=True,
                         message="add ...")

    (run :func:`upgrade` on that database first, so autogenerate diffs against head).
    """
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    if url is not None:
        rendered = normalize_url(url).render_as_string(hide_password=False)
        config.set_main_option("sqlalchemy.url", rendered.replace("%", "%%"))
    return config


def upgrade(url: str | URL | Engine, revision: str = "head") -> None:
    """Migrate the database at ``url`` to ``revision``; a no-op when it is already there.

    Safe when several processes call it at once: they serialize on a lock and all but the
    first find nothing to do.
    """
    engine = url if isinstance(url, Engine) else make_engine(url)
    try:
        if revision in ("head", HEAD_REVISION) and current_revision(engine) == HEAD_REVISION:
            return
        with _migration_lock(engine), engine.begin() as connection:
            if connection.dialect.name == "postgresql":
                connection.execute(text("SELECT pg_advisory_xact_lock(:key)"),
                                   {"key": MIGRATION_LOCK_KEY})
            _run_alembic(connection, revision)
    finally:
        if engine is not url:
            engine.dispose()


def current_revision(engine: Engine) -> str | None:
    """The migration the database at ``engine`` is at (Alembic's ``alembic_version`` row),
    or None before the first one (no table, or no row)."""
    with engine.connect() as connection:
        try:
            return connection.execute(text("SELECT version_num FROM alembic_version")).scalar()
        except DBAPIError:  # no version table yet: a new database
            return None


def _run_alembic(connection: Connection, revision: str) -> None:
    """Run ``alembic upgrade`` on an open connection, inside its transaction."""
    from alembic import command

    config = alembic_config()
    config.attributes["connection"] = connection
    command.upgrade(config, revision)


@contextlib.contextmanager
def _migration_lock(engine: Engine) -> Iterator[None]:
    """Hold an exclusive file lock next to a SQLite database file while migrating.

    SQLite runs DDL outside the migration's transaction, so two processes could otherwise
    both find the schema missing and both create it. PostgreSQL uses an advisory lock inside
    the migration's transaction instead (see :func:`upgrade`); this is then a no-op.
    """
    path = sqlite_path(engine.url) if engine.dialect.name == "sqlite" else None
    if path is None:
        yield
        return
    with open(path.with_name(path.name + ".migrate-lock"), "a+b") as lock:
        fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock.fileno(), fcntl.LOCK_UN)
