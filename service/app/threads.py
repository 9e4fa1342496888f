"""Synthesis slots and BLAS threads sized together (issue 23).

A synchronous synthesis is CPU-bound NumPy/SciPy work; ``max_concurrent_syntheses`` of them
run at once (:class:`service.app.synthesis.Synthesizer`), and each dense BLAS call inside one
may start OpenBLAS's (or OpenMP's, MKL's) own threads — by default one per core — and the
compiled per-frame kernels split their vertices over as many threads. With S
slots on C cores that is up to S·C busy threads: on 2 cores, 2 slots × 2 BLAS threads
oversubscribe the machine twice over and every synthesis slows down (the threads preempt
each other and OpenBLAS's spin-waits burn the cycles). Sized together, S slots get
``max(1, C // S)`` BLAS threads each, so S · threads <= C.

The thread count is read by the BLAS library when it loads, so :func:`apply_blas_threads`
sets the environment variables before NumPy is imported (``facesynth serve`` calls it first
thing); a variable already in the environment is the operator's choice and is kept unless
the ``blas_threads`` setting names a count.
"""

from __future__ import annotations

import os
from typing import MutableMapping

#: the thread-count variables of the BLAS / OpenMP runtimes NumPy and SciPy may load, and
#: of the compiled per-frame kernels (:func:`service.geometry.ranges.kernel_threads`)
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


def cores() -> int:
    """The CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:                     # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def synthesis_slots(max_concurrent: int | None, n_cores: int | None = None) -> int:
    """Synchronous syntheses at once: ``max_concurrent``, or one per core when None."""
    return int(max_concurrent) if max_concurrent else (n_cores or cores())


def blas_threads_per_slot(slots: int, threads: int | None, n_cores: int | None = None) -> int:
    """BLAS threads per synthesis: ``threads`` if given, else ``max(1, cores // slots)``."""
    if threads:
        return int(threads)
    return max(1, (n_cores or cores()) // max(1, int(slots)))


def apply_blas_threads(max_concurrent: int | None, threads: int | None,
                       environ: MutableMapping[str, str] | None = None) -> int:
    """Set :data:`BLAS_THREAD_VARIABLES` in ``environ`` (default ``os.environ``) to
    :func:`blas_threads_per_slot` and return that count: overriding what is there when
    ``threads`` is given, else only where unset. Call it before NumPy is imported."""
    environ = os.environ if environ is None else environ
    count = blas_threads_per_slot(synthesis_slots(max_concurrent), threads)
    for name in BLAS_THREAD_VARIABLES:
        if threads or name not in environ:
            environ[name] = str(count)
    return count
