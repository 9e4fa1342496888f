"""Tests for service.geometry.ranges: contiguous ranges and the threaded kernel runner."""

import numpy as np
import pytest

from service.geometry import ranges


@pytest.mark.parametrize("n, parts", [(10, 3), (7, 7), (3, 8), (0, 2), (100_003, 2)])
def test_split_covers_the_range_in_near_equal_contiguous_parts(n, parts):
    b = ranges.split(n, parts)
    assert b[0] == 0 and b[-1] == n and (np.diff(b) >= 0).all()
    sizes = np.diff(b)
    assert sizes.max() - sizes.min() <= 1 and len(sizes) == max(1, min(parts, max(n, 1)))


def test_run_fills_every_element_once_on_any_thread_count():
    def kernel(lo, hi, out):
        out[lo:hi] += np.arange(lo, hi)

    for threads in (1, 2, 3):
        out = np.zeros(1001, np.int64)
        ranges.run(kernel, len(out), out, threads=threads)
        np.testing.assert_array_equal(out, np.arange(1001))


def test_run_reraises_a_kernel_error():
    def kernel(lo, hi):
        if lo > 0:
            raise ValueError("second range")

    with pytest.raises(ValueError, match="second range"):
        ranges.run(kernel, 10, threads=2)


def test_kernel_threads_reads_numba_num_threads(monkeypatch):
    monkeypatch.setenv("NUMBA_NUM_THREADS", "2")
    assert ranges.kernel_threads() == 2
    monkeypatch.delenv("NUMBA_NUM_THREADS")
    assert ranges.kernel_threads() == 1
    monkeypatch.setenv("NUMBA_NUM_THREADS", "x")
    assert ranges.kernel_threads() == 1


def test_scratch_is_one_array_per_key_and_thread():
    a = ranges.scratch("t.a", (4, 3))
    assert ranges.scratch("t.a", (4, 3)) is a and a.dtype == np.float32
    assert ranges.scratch("t.b", (4, 3)) is not a
    assert ranges.scratch("t.a", (5, 3)).shape == (5, 3)              # a new shape replaces it
    assert ranges.scratch("t.a", (5, 3), np.float64).dtype == np.float64
    from concurrent.futures import ThreadPoolExecutor

    mine = ranges.scratch("t.c", (2,))
    with ThreadPoolExecutor(1) as ex:
        theirs = ex.submit(ranges.scratch, "t.c", (2,)).result()
    assert theirs is not mine


def test_frame_threads_sets_the_calling_threads_kernel_calls_only(monkeypatch):
    import threading

    monkeypatch.setenv("NUMBA_NUM_THREADS", "1")
    calls: list[tuple[int, int]] = []

    def kernel(lo, hi):
        calls.append((lo, hi))

    with ranges.frame_threads(3):
        assert ranges.kernel_threads() == 3
        ranges.run(kernel, 9)
        other: list[int] = []
        worker = threading.Thread(target=lambda: other.append(ranges.kernel_threads()))
        worker.start()
        worker.join()
        with ranges.frame_threads(0):                  # at least one, and nested blocks restore
            assert ranges.kernel_threads() == 1
        assert ranges.kernel_threads() == 3
    assert sorted(calls) == [(0, 3), (3, 6), (6, 9)] and other == [1]
    assert ranges.kernel_threads() == 1
