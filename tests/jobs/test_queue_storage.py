"""service.jobs.queue_storage: the queue URL's form and a probe of its storage, without Huey."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from service.config import Settings
from service.jobs.queue_storage import (
    QUEUE_FILE, QueueStorage, probe, queue_storage, worker_storage,
)
from tests.servers import free_port

ROOT = Path(__file__).resolve().parents[2]


def test_the_storage_is_read_from_the_url_form(tmp_path):
    assert queue_storage(Settings(data_dir=tmp_path)) == QueueStorage(
        "sqlite", str((tmp_path / QUEUE_FILE).absolute()))
    for url in ("redis://q:6379/0", "rediss://q:6380/1", "unix:///run/redis.sock"):
        assert queue_storage(Settings(data_dir=tmp_path, queue_url=url)) == QueueStorage("redis", url)
    memory = Settings(data_dir=tmp_path, queue_url="memory://")
    assert queue_storage(memory).kind == "memory"
    with pytest.raises(ValueError, match="runs jobs when they are submitted; it has no workers"):
        worker_storage(memory)
    with pytest.raises(ValueError, match="unsupported queue URL 'amqp://x'"):
        queue_storage(Settings(data_dir=tmp_path, queue_url="amqp://x"))


def test_the_probe_opens_the_sqlite_queue_and_pings_redis(tmp_path, redis_server):
    probe(Settings(data_dir=tmp_path))          # creates the file, as Huey would
    assert (tmp_path / QUEUE_FILE).is_file()
    probe(Settings(data_dir=tmp_path, queue_url=redis_server))
    probe(Settings(data_dir=tmp_path, queue_url="memory://"))


def test_the_probe_raises_what_an_unreachable_storage_raises(tmp_path):
    import redis

    with pytest.raises(redis.ConnectionError):
        probe(Settings(data_dir=tmp_path, queue_url=f"redis://127.0.0.1:{free_port()}/0"),
              timeout=1)
    with pytest.raises(Exception, match="unable to open database file"):
        probe(Settings(data_dir=tmp_path / "no" / "such" / "dir"))


def test_readiness_probes_the_queue_without_importing_huey(tmp_path):
    """``Services.check`` (``/readyz``, ``facesynth check``) answers the queue check with
    the probe: Huey (and the redis and psycopg it imports, ~0.18 s) stays unimported."""
    code = ("import sys; from pathlib import Path\n"
            "from service.config import Settings\n"
            "from service.app.services import Services\n"
            f"services = Services.open(Settings(data_dir=Path({str(tmp_path)!r})))\n"
            "print(services.check(), sorted(m for m in ('huey', 'redis', 'psycopg') if m in sys.modules))\n"
            "services.close()")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, check=True).stdout
    assert out.strip() == "{'database': 'ok', 'blobs': 'ok', 'queue': 'ok'} []"
