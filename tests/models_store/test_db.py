"""Engines and migrations: URL handling, SQLite pragmas, the migrated schema equals the ORM,
upgrades are idempotent and safe when processes start at once, timestamps are aware UTC."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
from datetime import datetime, timedelta, timezone
from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import inspect, select, text

from models_store.db import (HEAD_REVISION, alembic_config, current_revision, make_engine,
                             make_session_factory, normalize_url, sqlite_path, upgrade)
from models_store.schema import Actor, Base

REPO = Path(__file__).resolve().parents[2]
HEAD = ScriptDirectory.from_config(alembic_config()).get_current_head()


def schema_diff(url):
    """Alembic autogenerate's differences between the database and the ORM metadata."""
    engine = make_engine(url)
    try:
        with engine.connect() as connection:
            context = MigrationContext.configure(connection, opts={"compare_type": True})
            return compare_metadata(context, Base.metadata)
    finally:
        engine.dispose()


def revision_of(url):
    engine = make_engine(url)
    try:
        with engine.connect() as connection:
            return MigrationContext.configure(connection).get_current_revision()
    finally:
        engine.dispose()


@pytest.mark.parametrize("given, driver", [
    ("postgresql://u:p@db:5432/fs", "postgresql+psycopg"),
    ("postgres://u@db/fs", "postgresql+psycopg"),
    ("postgresql+psycopg2://u@db/fs", "postgresql+psycopg"),
    ("postgresql+psycopg://u@db/fs", "postgresql+psycopg"),
    ("sqlite:////data/facesynth.db", "sqlite"),
])
def test_normalize_url_uses_psycopg3_for_postgres(given, driver):
    url = normalize_url(given)
    assert url.drivername == driver
    assert url.database in ("fs", "/data/facesynth.db")


def test_normalize_url_rejects_other_backends():
    with pytest.raises(ValueError, match="unsupported database URL 'mysql://u:\\*\\*\\*@db/fs'"):
        normalize_url("mysql://u:secret@db/fs")


def test_sqlite_path_of_file_and_memory_urls(tmp_path):
    assert sqlite_path(f"sqlite:///{tmp_path}/x.db") == tmp_path / "x.db"
    assert sqlite_path("sqlite://") is None
    assert sqlite_path("postgresql://db/x") is None


def test_migrated_schema_equals_the_orm_metadata(fresh_db_url):
    upgrade(fresh_db_url)
    assert schema_diff(fresh_db_url) == []
    assert revision_of(fresh_db_url) == HEAD
    engine = make_engine(fresh_db_url)
    tables = set(inspect(engine).get_table_names())
    engine.dispose()
    assert tables == set(Base.metadata.tables) | {"alembic_version"}


def test_an_empty_database_differs_from_the_orm(fresh_db_url):
    """The comparison above has teeth: it sees every missing table."""
    diff = schema_diff(fresh_db_url)
    assert {d[1].name for d in diff if d[0] == "add_table"} == set(Base.metadata.tables)


def test_upgrade_is_idempotent(fresh_db_url):
    upgrade(fresh_db_url)
    sessions = make_session_factory(fresh_db_url)
    with sessions() as session:
        session.add(Actor(id="act_" + "0" * 26, name="kept"))
        session.commit()
    upgrade(fresh_db_url)
    with sessions() as session:
        assert session.scalars(select(Actor.name)).all() == ["kept"]
    sessions.kw["bind"].dispose()
    assert revision_of(fresh_db_url) == HEAD


def test_head_revision_is_alembics_head():
    assert HEAD_REVISION == HEAD


def test_a_database_at_head_is_not_migrated_and_alembic_not_imported(fresh_db_url):
    engine = make_engine(fresh_db_url)
    assert current_revision(engine) is None
    upgrade(fresh_db_url, "0002")
    assert current_revision(engine) == "0002"
    upgrade(fresh_db_url)
    assert current_revision(engine) == HEAD_REVISION
    engine.dispose()
    code = ("import sys; from models_store.db import upgrade; upgrade(sys.argv[1]); "
            "print('alembic' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code, str(fresh_db_url)], capture_output=True,
                         text=True, check=True, timeout=60).stdout
    assert out.strip() == "False"


def test_processes_starting_at_once_migrate_once(fresh_db_url):
    code = "import sys; from models_store.db import upgrade; upgrade(sys.argv[1])"
    procs = [subprocess.Popen([sys.executable, "-c", code, fresh_db_url], cwd=REPO,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
             for _ in range(2)]
    outputs = [p.communicate(timeout=120)[0].decode() for p in procs]
    assert [p.returncode for p in procs] == [0, 0], "\n".join(outputs)
    assert revision_of(fresh_db_url) == HEAD
    assert schema_diff(fresh_db_url) == []


def test_sqlite_connections_use_wal_foreign_keys_and_a_busy_timeout(tmp_path):
    engine = make_engine(f"sqlite:///{tmp_path}/sub/dir/x.db")     # parent made on demand
    with engine.connect() as connection:
        assert connection.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert connection.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
        assert connection.exec_driver_sql("PRAGMA busy_timeout").scalar() >= 10_000
    engine.dispose()


def test_sqlite_enforces_foreign_keys(tmp_path):
    url = f"sqlite:///{tmp_path}/x.db"
    upgrade(url)
    engine = make_engine(url)
    with pytest.raises(Exception, match="FOREIGN KEY"):
        with engine.begin() as connection:
            connection.execute(text(
                "INSERT INTO clips (id, actor_id, frames, blob, sha256, size_bytes, created_at)"
                " VALUES ('clp_x', 'act_missing', 1, 'k', 's', 1, '2024-01-01 00:00:00')"))
    engine.dispose()


def test_timestamps_round_trip_as_aware_utc(db_url):
    sessions = make_session_factory(db_url)
    eastern = timezone(timedelta(hours=-5))
    moment = datetime(2024, 3, 1, 7, 30, 15, 123456, tzinfo=eastern)
    with sessions() as session:
        session.add(Actor(id="act_" + "1" * 26, name="t", created_at=moment))
        session.commit()
    with sessions() as session:
        stored = session.scalars(select(Actor.created_at)).one()
    assert stored == moment and stored.utcoffset() == timedelta(0)
    assert stored.hour == 12
    sessions.kw["bind"].dispose()


def test_naive_timestamps_are_refused(db_url):
    sessions = make_session_factory(db_url)
    with sessions() as session:
        session.add(Actor(id="act_" + "2" * 26, name="t", created_at=datetime(2024, 1, 1)))
        with pytest.raises(Exception, match="naive datetime"):
            session.commit()
    sessions.kw["bind"].dispose()


def test_the_tenant_migration_gives_existing_rows_the_default_tenant(fresh_db_url):
    upgrade(fresh_db_url, "0001")
    engine = make_engine(fresh_db_url)
    with engine.begin() as connection:
        connection.execute(text("INSERT INTO actors (id, name, metadata, created_at) VALUES "
                                "(:id, 'old', '{}', CURRENT_TIMESTAMP)"), {"id": "act_" + "1" * 26})
    upgrade(fresh_db_url)
    with engine.connect() as connection:
        assert connection.execute(text("SELECT tenant FROM actors")).scalars().all() == ["default"]
    engine.dispose()
    assert schema_diff(fresh_db_url) == []


class _LockedCursor:
    """A DB-API cursor whose first ``locked`` executes fail as SQLite's immediate
    SQLITE_BUSY does (the deadlock case the busy handler does not cover)."""

    def __init__(self, locked: int, mode: str = "delete", error: str = "database is locked"):
        self.locked, self.mode, self.error, self.calls = locked, mode, error, []

    def execute(self, sql):
        self.calls.append(sql)
        if self.locked:
            self.locked -= 1
            raise sqlite3.OperationalError(self.error)
        if sql.endswith("= WAL"):
            self.mode = "wal"
        self.row = (self.mode,)
        return self

    def fetchone(self):
        return self.row


def test_wal_switch_retries_while_locked_and_skips_a_file_already_in_wal():
    from models_store.db import _enable_wal

    cursor = _LockedCursor(locked=3)
    _enable_wal(cursor, timeout=5.0)
    assert cursor.mode == "wal" and cursor.calls[-2:] == ["PRAGMA journal_mode", "PRAGMA journal_mode = WAL"]
    assert len(cursor.calls) == 3 + 2
    done = _LockedCursor(locked=0, mode="wal")
    _enable_wal(done)
    assert done.calls == ["PRAGMA journal_mode"]


def test_wal_switch_gives_up_after_its_timeout_and_raises_other_errors_at_once():
    from models_store.db import _enable_wal

    with pytest.raises(sqlite3.OperationalError, match="locked"):
        _enable_wal(_LockedCursor(locked=10**6), timeout=0.05)
    other = _LockedCursor(locked=1, error="disk I/O error")
    with pytest.raises(sqlite3.OperationalError, match="disk I/O"):
        _enable_wal(other, timeout=5.0)
    assert len(other.calls) == 1
