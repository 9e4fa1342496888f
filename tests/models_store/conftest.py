"""Fixtures of the model-store tests: a migrated database on each backend, sessions, blobs.

``db_url`` is parametrized over SQLite (a fresh file per test) and PostgreSQL (one database
``facesynth_test_<random>`` per test session, migrated once and emptied before each test);
PostgreSQL is the machine's own server or one the fixtures start (``tests/servers.py``).
"""

from __future__ import annotations

from typing import Iterator

import pytest
from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from models_store.blobs import BlobStore
from models_store.db import make_engine, make_session_factory, upgrade
from models_store.schema import Base
from tests.servers import postgres_database, postgres_server, temporary_database  # noqa: F401

BACKENDS = ("sqlite", "postgresql")


def sqlite_url(directory) -> str:
    """URL of a SQLite file in ``directory``."""
    return f"sqlite:///{directory / 'facesynth.db'}"


@pytest.fixture(scope="session")
def migrated_postgres(request: pytest.FixtureRequest) -> str:
    """The session's PostgreSQL test database, migrated to head."""
    url = request.getfixturevalue("postgres_database")
    upgrade(url)
    return url


@pytest.fixture(params=BACKENDS)
def db_url(request: pytest.FixtureRequest, tmp_path) -> str:
    """URL of an empty, migrated database on each backend."""
    if request.param == "sqlite":
        url = sqlite_url(tmp_path)
        upgrade(url)
        return url
    url = request.getfixturevalue("migrated_postgres")
    engine = make_engine(url)
    with engine.begin() as connection:
        for table in reversed(Base.metadata.sorted_tables):
            connection.execute(table.delete())
    engine.dispose()
    return url


@pytest.fixture(params=BACKENDS)
def fresh_db_url(request: pytest.FixtureRequest, tmp_path) -> Iterator[str]:
    """URL of a new database on each backend with no schema at all."""
    if request.param == "sqlite":
        yield sqlite_url(tmp_path)
    else:
        with temporary_database(request.getfixturevalue("postgres_server")) as url:
            yield url


@pytest.fixture
def engine(db_url: str) -> Iterator[Engine]:
    engine = make_engine(db_url)
    yield engine
    engine.dispose()


@pytest.fixture
def sessions(engine: Engine) -> sessionmaker[Session]:
    """A session factory; threads each open their own session from it."""
    return make_session_factory(engine)


@pytest.fixture
def session(sessions: sessionmaker[Session]) -> Iterator[Session]:
    with sessions() as session:
        yield session


@pytest.fixture
def blobs(tmp_path) -> BlobStore:
    return BlobStore(tmp_path / "blobs")
