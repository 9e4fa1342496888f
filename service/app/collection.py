"""Python's cyclic garbage collector paused while ``facesynth serve`` starts (issue 23's cold start).

A start imports FastAPI, pydantic, SQLAlchemy, gRPC and Numba and declares the app's routes
and models: hundreds of thousands of container objects, almost none of them garbage, so the
collector's generation-0 and generation-1 passes triggered by those allocations (and the
full passes they escalate to) scan live objects for nothing. With the collector off until
the server is ready, the imports of ``serve`` cost 8–10 % less CPU (the same imports
1.20–1.31 s → 1.06–1.16 s, four runs each, 2 cores at load 2), and the model preload, which
runs beside them on the same interpreter lock, finishes earlier: ``benchmarks/cold_start.py
--against`` (level-1 PDM preloaded, 3 rounds alternating, load 1.9–2.5) took the server's
CPU until ready 2.4–2.5 → 2.0 s and the first frame after spawn 2.8–3.0 → 2.4 s.

Reference counting still frees everything that is not in a cycle; the cycles made while
starting are collected by the first passes after the collector is resumed. The collector's
thresholds are untouched, so steady-state behaviour is that of any Python process.
"""

from __future__ import annotations

import gc
import threading
from typing import Callable


def pause_collection() -> Callable[[], None]:
    """Turn the cyclic collector off; return the function that turns it back on.

    The returned ``resume()`` is idempotent and thread-safe, and it re-enables the collector
    only if this call was what disabled it (an embedding program that had it off keeps it
    off).
    """
    was_enabled = gc.isenabled()
    gc.disable()
    lock = threading.Lock()
    resumed = False

    def resume() -> None:
        nonlocal resumed
        with lock:
            if not resumed:
                resumed = True
                if was_enabled:
                    gc.enable()

    return resume


def resume_when(resume: Callable[[], None], done: threading.Event | None) -> None:
    """Call ``resume`` once ``done`` is set (at once if ``done`` is None), from a daemon
    thread so that the caller does not wait."""
    if done is None or done.is_set():
        resume()
        return
    threading.Thread(target=lambda: (done.wait(), resume()), name="facesynth-gc-resume",
                     daemon=True).start()
