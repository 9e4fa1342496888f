"""The fallback servers of tests/servers.py start, answer and go away (on a free port, so
this runs even where the machine's own servers answer on the standard ports)."""

from __future__ import annotations

import psycopg

from tests.servers import (embedded_postgres, embedded_redis, free_port, port_open, redis_ping,
                           temporary_database)


def test_embedded_postgres_serves_on_loopback_and_stops():
    port = free_port()
    with embedded_postgres(port) as url:
        assert url == f"postgresql://postgres@127.0.0.1:{port}/postgres"
        with temporary_database(url) as db_url:
            assert db_url.rsplit("/", 1)[1].startswith("facesynth_test_")
            with psycopg.connect(db_url) as conn:
                assert conn.execute("SELECT 1 + 1").fetchone() == (2,)
    assert not port_open("127.0.0.1", port)


def test_embedded_redis_serves_on_loopback_and_stops():
    port = free_port()
    with embedded_redis(port) as url:
        assert url == f"redis://127.0.0.1:{port}/0"
        assert redis_ping(port)
    assert not port_open("127.0.0.1", port)
