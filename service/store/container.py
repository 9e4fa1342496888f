"""The store of one deployment: the metadata database and the blob store named by the
settings, opened once per process and shared by the API, the gRPC server and the jobs.

Engines are expensive and pool connections, so one :class:`Store` is kept per database URL
and blob directory for the life of the process (:func:`get_store`); tests that make many
data directories call :func:`close_stores` at the end.
"""

from __future__ import annotations

import contextlib
import threading
from dataclasses import dataclass
from typing import Iterator

from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from models_store.blobs import BlobStore
from models_store.db import make_engine, make_session_factory, upgrade
from service.config import Settings


@dataclass(frozen=True)
class Store:
    """Database sessions and blobs of one deployment.

    Attributes
    ----------
    sessions : sessionmaker   ``with store.sessions() as session: ...``
    blobs : BlobStore
    """

    sessions: sessionmaker[Session]
    blobs: BlobStore

    @property
    def engine(self) -> Engine:
        """The database engine the sessions are bound to."""
        return self.sessions.kw["bind"]

    @contextlib.contextmanager
    def session(self) -> Iterator[Session]:
        """A database session, closed (and any open transaction rolled back) on exit."""
        session = self.sessions()
        try:
            yield session
        finally:
            session.close()

    def dispose(self) -> None:
        """Close the engine's pooled connections (the store stays usable: a later session
        opens new ones)."""
        self.engine.dispose()


_stores: dict[tuple[str, str], Store] = {}
_lock = threading.Lock()


def get_store(settings: Settings, *, migrate: bool = False) -> Store:
    """The process-wide :class:`Store` for ``settings`` (made on first use).

    ``migrate`` upgrades the database to the current schema first (the API's start-up).
    """
    key = (settings.database_url_resolved, str(settings.blob_dir.absolute()))
    with _lock:
        store = _stores.get(key)
        if store is None:
            store = Store(make_session_factory(make_engine(key[0])), BlobStore(key[1]))
            _stores[key] = store
    if migrate:
        upgrade(store.engine)
    return store


def close_stores() -> None:
    """Dispose of every cached store (their engines' connections)."""
    with _lock:
        for store in _stores.values():
            store.dispose()
        _stores.clear()
