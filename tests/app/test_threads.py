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
