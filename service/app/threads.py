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

The S slots are one pool per process (:class:`SynthesisPool`, held by
:class:`service.app.services.Services`): HTTP requests take a slot for their synthesis
(:class:`service.app.synthesis.Synthesizer`, which queues them and answers 503 when the wait
runs out) and the gRPC streams' frames are synthesized on the pool's threads, each holding a
slot while it runs; so with both busy at most S syntheses run at once, not S per transport
(2 S on 2 cores before: each synthesis then had half the cores its BLAS threads were sized
for).
"""

from __future__ import annotations

import contextlib
import os
import threading
from concurrent import futures
from typing import Any, Callable, Iterator, MutableMapping

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


class SynthesisPool(futures.Executor):
    """The synthesis slots of one process: at most ``limit`` syntheses at once, over the
    HTTP requests and the gRPC stream frames together (see the module docstring).

    A slot is held as a semaphore (:meth:`acquire`, :meth:`release`, or :meth:`hold` around
    a block: the HTTP path, which decides itself how long to wait); as an executor,
    :meth:`submit` runs a call on one of the pool's ``limit`` threads while it holds a slot,
    waiting as long as it takes for one (the gRPC path: its frames' futures are taken in
    submission order, so a stream's replies stay in order). A future cancelled before its
    thread started never takes a slot.

    With ``share_cores`` each synthesis's compiled kernels (:mod:`service.geometry.ranges`)
    run on those cores divided among the syntheses running when it starts (a lone request
    takes them all; with every slot busy each has its one share, as without); BLAS stays at
    its per-slot count, which should be 1: OpenBLAS's idle workers spin and take the cores the
    kernels need (:mod:`service.geometry.ranges`). A lone level-1 maps frame then takes
    ~31 ms instead of ~43 on 2 cores (``Settings.synthesis_kernel_threads``).

    Parameters
    ----------
    limit : int or None   syntheses at once (``max_concurrent_syntheses``; None: one per
                          core, :func:`synthesis_slots`)
    share_cores : int or None   the cores the running syntheses' kernels share (None: the
                          kernels keep ``NUMBA_NUM_THREADS``, the per-slot count)

    Attributes
    ----------
    limit : int
    running : int         slots held now
    waiting : int         callers blocked in :meth:`acquire` now (either transport)
    """

    def __init__(self, limit: int | None = None, share_cores: int | None = None):
        self.limit = synthesis_slots(limit)
        self.share_cores = share_cores
        self._slots = threading.BoundedSemaphore(self.limit)
        self._lock = threading.Lock()
        self._threads: futures.ThreadPoolExecutor | None = None
        self.running = 0
        self.waiting = 0

    def acquire(self, blocking: bool = True, timeout: float | None = None) -> bool:
        """Take a slot, as ``threading.Semaphore.acquire``; True if one was taken."""
        if self._slots.acquire(blocking=False):
            got = True
        elif not blocking:
            return False
        else:
            with self._lock:
                self.waiting += 1
            try:
                got = self._slots.acquire(timeout=timeout)
            finally:
                with self._lock:
                    self.waiting -= 1
        if got:
            with self._lock:
                self.running += 1
        return got

    def release(self) -> None:
        """Give back a slot taken by :meth:`acquire`."""
        with self._lock:
            self.running -= 1
        self._slots.release()

    @contextlib.contextmanager
    def hold(self) -> Iterator[None]:
        """Hold one slot while the block runs (waiting for it as long as it takes)."""
        self.acquire()
        try:
            yield
        finally:
            self.release()

    @contextlib.contextmanager
    def kernel_share(self) -> Iterator[None]:
        """Around a synthesis holding a slot: its kernels' threads, ``share_cores`` over the
        syntheses running now (at least 1); without ``share_cores``, unchanged."""
        if not self.share_cores:
            yield
            return
        from service.geometry import ranges

        with ranges.frame_threads(self.share_cores // max(1, self.running)):
            yield

    def _run(self, fn: Callable[..., Any], args: tuple, kwargs: dict) -> Any:
        with self.hold(), self.kernel_share():
            return fn(*args, **kwargs)

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> futures.Future:
        """Run ``fn(*args, **kwargs)`` on one of the pool's threads, holding a slot."""
        with self._lock:
            if self._threads is None:
                self._threads = futures.ThreadPoolExecutor(self.limit,
                                                           thread_name_prefix="facesynth-synthesis")
            threads = self._threads
        return threads.submit(self._run, fn, args, kwargs)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Stop the pool's threads (calls not yet started are cancelled with
        ``cancel_futures``); a later :meth:`submit` starts new ones. The slots stay usable."""
        with self._lock:
            threads, self._threads = self._threads, None
        if threads is not None:
            threads.shutdown(wait=wait, cancel_futures=cancel_futures)
