"""Run a compiled per-element kernel over contiguous index ranges on a few threads.

The per-frame kernels of the methods (e.g. :mod:`service.geometry.shell_frames`)
are Numba functions compiled with ``nogil=True`` whose first two arguments are a half-open
range ``[lo, hi)`` of the elements they process. :func:`run` splits ``[0, n)`` into
``threads`` contiguous ranges and runs them on a shared thread pool, so one frame can use
the cores a synthesis slot owns without Numba's own threading layers (its default
``workqueue`` layer must not be entered from two Python threads at once, and a service runs
one synthesis per slot thread). With one thread the kernel is called directly.

The kernels are compiled with ``error_model="numpy"``: a float division by zero gives inf or
NaN, as NumPy's would, instead of Numba's default check and ZeroDivisionError, and the loops
lose those checks (level 1, interleaved in one process with the default model: a maps
frame 39.7–45.8 → 33.6–41.1 ms CPU, every output bit for bit; the vertex strain pass alone
3.3 → 1.7 ms). Their inner loops index arrays element by element: a row view taken per
element (``a = coeffs[p]``) cost the strain band's texel pass ~40 %.

The thread count of a kernel call is :func:`kernel_threads`: the calling thread's
:func:`frame_threads` setting, else ``NUMBA_NUM_THREADS`` (set by ``facesynth serve`` with the
BLAS threads, :mod:`service.app.threads`), else 1. A caller computing one frame at a time
in-process (a DCC plug-in, ``benchmarks/realtime.py``'s second in-process rows) runs its
kernels on every core with ``with frame_threads(cores):`` — and one BLAS thread: OpenBLAS's
idle workers spin after each product and take the cores the kernels need. Measured, level 1,
2 vCPUs, medians of 55 frames, runs alternating: a maps frame (mesh + displacement + normal
map) 42.9–43.7 ms wall on one kernel thread, 31.0–31.6 ms on two with one BLAS thread, 44.0–
45.3 ms on two with two BLAS threads (what an earlier measurement took for the two vCPUs
sharing one core); a mesh frame 13.8–14.0 → 11.8–12.1 ms.

:func:`scratch` hands a calling thread the same work array for the same key on every call, so
a per-frame kernel's temporaries are not fresh allocations (at level 2 a frame's temporaries
are ~15 MB; freshly mapped pages fault on first touch: measured 2–3 ms of a 10–16 ms step).
"""

from __future__ import annotations

import contextlib
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterator

import numpy as np

_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()
_SCRATCH = threading.local()
_LOCAL = threading.local()          # the calling thread's frame_threads setting


def kernel_threads() -> int:
    """Threads a per-frame kernel call may use: the calling thread's :func:`frame_threads`,
    else ``NUMBA_NUM_THREADS``, else 1."""
    count = getattr(_LOCAL, "threads", None)
    if count is not None:
        return count
    try:
        return max(1, int(os.environ.get("NUMBA_NUM_THREADS", "1")))
    except ValueError:
        return 1


@contextlib.contextmanager
def frame_threads(count: int) -> Iterator[None]:
    """Within the block, the calling thread's kernel calls (:func:`run` without ``threads``)
    use ``count`` threads (at least 1); other threads keep theirs, and the previous setting
    comes back after the block (module docstring: with one BLAS thread)."""
    previous = getattr(_LOCAL, "threads", None)
    _LOCAL.threads = max(1, int(count))
    try:
        yield
    finally:
        _LOCAL.threads = previous


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


def scratch(key: str, shape: tuple[int, ...], dtype=np.float32) -> np.ndarray:
    """A work array of ``shape`` and ``dtype`` owned by the calling thread, the same one for
    the same ``key`` (contents undefined): for temporaries that do not outlive the call that
    takes them. One array per key and thread; a new shape replaces it."""
    arrays = getattr(_SCRATCH, "arrays", None)
    if arrays is None:
        arrays = _SCRATCH.arrays = {}
    a = arrays.get(key)
    if a is None or a.shape != tuple(shape) or a.dtype != np.dtype(dtype):
        a = arrays[key] = np.empty(shape, dtype)
    return a
