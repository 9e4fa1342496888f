"""service.app.threads: synthesis slots and BLAS threads sized together."""

from __future__ import annotations

import os
import subprocess
import sys

from service.app.threads import (BLAS_THREAD_VARIABLES, apply_blas_threads,
                                 blas_threads_per_slot, synthesis_slots)


def test_slots_times_threads_fill_the_cores_without_oversubscribing():
    for cores in (1, 2, 4, 8, 16):
        for slots in (1, 2, 3, 4, 16):
            threads = blas_threads_per_slot(slots, None, cores)
            assert threads >= 1 and (slots * threads <= cores or threads == 1)
            assert slots * (threads + 1) > cores or threads == cores
    assert blas_threads_per_slot(2, None, 2) == 1 and blas_threads_per_slot(1, None, 2) == 2
    assert blas_threads_per_slot(2, None, 8) == 4 and blas_threads_per_slot(3, 5, 8) == 5
    assert synthesis_slots(None, 6) == 6 and synthesis_slots(3, 6) == 3


def test_the_environment_is_set_where_unset_or_when_the_setting_names_a_count():
    env = {"OMP_NUM_THREADS": "7"}
    count = apply_blas_threads(1, None, env)
    assert env["OMP_NUM_THREADS"] == "7"                 # the operator's choice is kept
    assert env["OPENBLAS_NUM_THREADS"] == env["MKL_NUM_THREADS"] == str(count)
    apply_blas_threads(1, 3, env)
    assert all(env[v] == "3" for v in BLAS_THREAD_VARIABLES)


def test_serve_sets_the_threads_before_numpy_loads():
    """``facesynth serve`` imports nothing that loads NumPy before it sizes the threads."""
    code = ("import sys; import service.cli, service.config, service.app.threads; "
            "print('numpy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=os.getcwd(), check=True)
    assert out.stdout.strip() == "False"


def test_the_pool_bounds_slot_holders_and_its_threads_together():
    """Two slots: with both held by semaphore users (the HTTP path), a submitted call (the
    gRPC path) waits, counted as waiting, and runs once one is given back; a call cancelled
    before its thread started never takes a slot; a shut-down pool starts new threads."""
    import threading
    import time

    from service.app.threads import SynthesisPool

    pool = SynthesisPool(2)
    assert pool.limit == 2 and pool.acquire() and pool.acquire(blocking=False)
    assert not pool.acquire(blocking=False) and not pool.acquire(timeout=0.05)
    assert (pool.running, pool.waiting) == (2, 0)
    ran = threading.Event()
    first = pool.submit(lambda x: (ran.set(), x * 2)[1], 21)
    deadline = time.monotonic() + 2
    while pool.waiting < 1 and time.monotonic() < deadline:
        time.sleep(0.005)
    assert pool.waiting == 1 and not ran.is_set()
    second = pool.submit(lambda: "never")             # behind `first` on the pool's 2nd thread
    third = pool.submit(lambda: "never")              # queued: no thread free
    assert third.cancel()
    pool.release()
    assert first.result(2) == 42
    pool.release()
    assert second.result(2) == "never" and third.cancelled()
    assert (pool.running, pool.waiting) == (0, 0)
    pool.shutdown()
    assert pool.submit(lambda: 1).result(2) == 1     # new threads after a shutdown
    with pool.hold():
        assert pool.running == 1
    assert pool.running == 0
    pool.shutdown()


def test_shared_cores_go_to_the_syntheses_running(monkeypatch):
    """With ``share_cores`` a synthesis's kernels take the cores over the syntheses running
    when it starts, on either path (a submitted call, the HTTP slot); without, the per-slot
    count (NUMBA_NUM_THREADS) stays."""
    from service.app.metrics import Metrics
    from service.app.synthesis import Synthesizer
    from service.app.threads import SynthesisPool
    from service.geometry import ranges

    monkeypatch.setenv("NUMBA_NUM_THREADS", "1")
    pool = SynthesisPool(2, share_cores=4)
    assert pool.submit(ranges.kernel_threads).result(2) == 4          # alone: every core
    with pool.hold():                                                 # another one running
        assert pool.submit(ranges.kernel_threads).result(2) == 2
    synthesizer = Synthesizer(Metrics(), pool=pool)
    with synthesizer.slot("pdm", 1):
        assert ranges.kernel_threads() == 4
    assert ranges.kernel_threads() == 1
    pool.shutdown()
    plain = SynthesisPool(2)
    assert plain.submit(ranges.kernel_threads).result(2) == 1
    plain.shutdown()
