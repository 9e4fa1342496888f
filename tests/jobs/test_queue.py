"""service.jobs.queue: storage chosen by URL, JSON messages (never pickles), immediate mode."""

from __future__ import annotations

import datetime as dt
import json
import pickle

import numpy as np
import pytest
from huey import MemoryHuey, RedisHuey, SqliteHuey

from service.config import Settings
from service.jobs import queue as queue_module
from service.jobs.queue import JsonSerializer, get_queue, make_queue, submit
from service.jobs.worker import Worker


def test_messages_are_json_and_round_trip(tmp_path):
    queue = make_queue(Settings(data_dir=tmp_path))
    task = queue.run_job.s("job_01m84g72zv56qgast3a85c8cy8")
    task.eta = dt.datetime(2030, 1, 2, 3, 4, 5, tzinfo=dt.timezone.utc)
    data = queue.huey.serialize_task(task)
    body = json.loads(data)  # plain JSON on the wire ...
    assert body["__huey_message__"]["args"] == ["job_01m84g72zv56qgast3a85c8cy8"]
    with pytest.raises(pickle.UnpicklingError):  # ... and no pickle
        pickle.loads(data)
    back = queue.huey.deserialize_task(data)
    assert (back.id, back.args, back.eta, back.retries) == (task.id, task.args, task.eta, 3)
    assert back.name == task.name


def test_serializer_refuses_objects():
    with pytest.raises(TypeError, match="pass ids, not objects"):
        JsonSerializer().serialize({"job": object()})
    with pytest.raises(TypeError, match="string keys"):
        JsonSerializer().serialize({1: "a"})
    assert JsonSerializer().deserialize(JsonSerializer().serialize((None, True))) == [None, True]


def test_storage_is_chosen_by_the_queue_url(tmp_path, redis_server):
    sqlite = make_queue(Settings(data_dir=tmp_path, queue_name="q1"))
    assert isinstance(sqlite.huey, SqliteHuey) and sqlite.huey.name == "q1"
    assert sqlite.huey.storage.filename == str((tmp_path / "queue.db").absolute())
    redis = make_queue(Settings(data_dir=tmp_path, queue_url=redis_server, queue_name="q2"))
    assert isinstance(redis.huey, RedisHuey) and redis.huey.storage.queue_key == "huey.redis.q2"
    memory = make_queue(Settings(data_dir=tmp_path, queue_url="memory://"))
    assert isinstance(memory.huey, MemoryHuey) and memory.immediate
    with pytest.raises(ValueError, match="unsupported queue URL 'amqp://x'"):
        make_queue(Settings(data_dir=tmp_path, queue_url="amqp://x"))
    for q in (sqlite, redis):
        q.huey.storage.close()


def test_queues_are_cached_per_settings(tmp_path):
    a = Settings(data_dir=tmp_path)
    assert get_queue(a) is get_queue(Settings(data_dir=tmp_path))
    assert get_queue(a) is not get_queue(Settings(data_dir=tmp_path, queue_name="other"))
    queue_module.close_queues()


def test_a_memory_queue_runs_the_job_on_submit_and_has_no_workers(deployment, trained):
    settings = deployment.settings.model_copy(update={"queue_url": "memory://"})
    model_id, _ = trained
    markers = np.zeros((1, 150, 3))  # well-formed, but no visible marker can be aligned
    job_id = deployment.create_synthesis_job(model_id, markers * np.nan)
    submit(settings, job_id)  # returns when the job has ended
    job = deployment.job(job_id)
    assert job.status == "failed" and job.error["code"] == "invalid_input"
    assert "visible markers" in job.error["message"]
    with pytest.raises(ValueError, match="no workers"):
        Worker(settings)


@pytest.mark.parametrize("name", ["", "a-b", "a b", "x" * 101])
def test_queue_names_are_plain_identifiers(tmp_path, name):
    """Redis keys are built from the name (Huey would silently strip other characters)."""
    with pytest.raises(ValueError):
        Settings(data_dir=tmp_path, queue_name=name)
