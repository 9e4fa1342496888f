"""service.api.thread_handoff: calls run on worker threads, in the caller's context, at most
``size`` at once, and the threads end when idle."""

from __future__ import annotations

import asyncio
import contextvars
import threading
import time

import pytest

from service.api.thread_handoff import ThreadHandoff

tenant = contextvars.ContextVar("tenant", default=None)


def test_results_errors_and_context_come_back_from_a_worker_thread():
    handoff = ThreadHandoff(2)

    def where() -> tuple[str, str | None]:
        return threading.current_thread().name, tenant.get()

    def fail() -> None:
        raise KeyError("missing")

    async def run():
        tenant.set("acme")
        name, seen = await handoff.run(where)
        assert name.startswith("facesynth-handoff") and name != threading.current_thread().name
        assert seen == "acme"
        with pytest.raises(KeyError, match="missing"):
            await handoff.run(fail)
        return await asyncio.gather(*(handoff.run(lambda k=k: k * k) for k in range(10)))

    assert asyncio.run(run()) == [k * k for k in range(10)]
    assert 1 <= handoff.threads <= 2


def test_calls_run_side_by_side_up_to_size_and_the_rest_wait():
    """Four calls of 0.2 s on three threads: three at once, the fourth after one ends."""
    handoff = ThreadHandoff(3)
    lock = threading.Lock()
    running, most = [0], [0]

    def call() -> float:
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        time.sleep(0.2)
        with lock:
            running[0] -= 1
        return time.monotonic()

    async def run():
        start = time.monotonic()
        ends = await asyncio.gather(*(handoff.run(call) for _ in range(4)))
        return sorted(end - start for end in ends)

    ends = asyncio.run(run())
    assert most[0] == 3 and handoff.threads == 3
    assert ends[2] < 0.35 and ends[3] > 0.38, ends


def test_idle_threads_end_and_new_calls_start_them_again():
    handoff = ThreadHandoff(2, idle_seconds=0.05)

    async def run(n):
        return await asyncio.gather(*(handoff.run(lambda: time.sleep(0.02)) for _ in range(n)))

    asyncio.run(run(2))
    assert handoff.threads == 2
    deadline = time.monotonic() + 5
    while handoff.threads and time.monotonic() < deadline:
        time.sleep(0.01)
    assert handoff.threads == 0
    asyncio.run(run(1))
    assert handoff.threads == 1


def test_a_cancelled_caller_leaves_the_call_to_finish_and_its_result_dropped():
    handoff = ThreadHandoff(1)
    done = threading.Event()
    errors: list[dict] = []

    def slow() -> str:
        time.sleep(0.1)
        done.set()
        return "late"

    async def run():
        asyncio.get_running_loop().set_exception_handler(lambda loop, context: errors.append(context))
        task = asyncio.ensure_future(handoff.run(slow))
        await asyncio.sleep(0.02)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        await asyncio.sleep(0.2)          # the result arrives for a cancelled future
        return await handoff.run(lambda: "next")

    assert asyncio.run(run()) == "next"
    assert done.is_set() and errors == []


def test_a_thread_that_cannot_start_is_the_caller_s_error_not_a_hang(monkeypatch):
    handoff = ThreadHandoff(2)
    start = threading.Thread.start

    def refuse(self):
        raise RuntimeError("can't start new thread")

    async def run():
        monkeypatch.setattr(threading.Thread, "start", refuse)
        with pytest.raises(RuntimeError, match="can't start new thread"):
            await asyncio.wait_for(handoff.run(lambda: 1), 5)
        assert handoff.threads == 0
        monkeypatch.setattr(threading.Thread, "start", start)
        return await asyncio.wait_for(handoff.run(lambda: 2), 5)

    assert asyncio.run(run()) == 2
