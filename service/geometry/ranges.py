"""Run a compiled per-element kernel over contiguous index ranges on a few threads.

The per-frame kernels of the methods (e.g. :mod:`service.geometry.shell_frames`)
are Numba functions compiled with ``nogil=True`` whose first two arguments are a half-open
range ``[lo, hi)`` of the elements they process. :func:`run` splits ``[0, n)`` into
``threads`` contiguous ranges and runs them on a shared thread pool, so one frame can use
the cores a synthesis slot owns without Numba's own threading layers (its default
``workqueue`` layer must not be entered from two Python threads at once, and a service runs
one synthesis per slot thread). With one thread the kernel is called directly.

The thread count of a kernel call is :func:`kernel_threads`: ``NUMBA_NUM_THREADS`` (set by
``facesynth serve`` with the BLAS threads, :mod:`service.app.threads`), else 1.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np

_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def kernel_threads() -> int:
    """Threads a per-frame kernel call may use: ``NUMBA_NUM_THREADS`` or 1."""
    try:
        return max(1, int(os.environ.get("NUMBA_NUM_THREADS", "1")))
    except ValueError:
        return 1


def split(n: int, parts: int) -> np.ndarray:
    """Bounds (parts+1,) int64 of ``parts`` contiguous ranges covering [0, n), sizes within 1."""
    parts = max(1, min(int(parts), max(int(n), 1)))
    return np.linspace(0, n, parts + 1).round().astype(np.int64)


def _pool(workers: int) -> ThreadPoolExecutor:
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL._max_workers < workers:
            _POOL = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="kernel")
        return _POOL


def run(kernel: Callable, n: int, *args, threads: int | None = None) -> None:
    """``kernel(lo, hi, *args)`` over [0, n) in ``threads`` ranges (default
    :func:`kernel_threads`); returns when every range is done, re-raising the first error."""
    threads = kernel_threads() if threads is None else max(1, int(threads))
    if threads == 1 or n < 2:
        kernel(0, n, *args)
        return
    b = split(n, threads)
    futures = [_pool(threads).submit(kernel, int(lo), int(hi), *args) for lo, hi in zip(b[:-1], b[1:])]
    for fut in futures:
        fut.result()
