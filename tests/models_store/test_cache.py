"""ByteLRUCache: eviction by bytes in least-recently-used order, thread safety."""

from __future__ import annotations

import threading
import time

import pytest

from models_store.cache import ByteLRUCache


def load(cache, key, size, calls=None):
    """get_or_load of an object (key, size) that weighs ``size`` bytes."""
    def loader():
        if calls is not None:
            calls.append(key)
        return (key, size)
    return cache.get_or_load(key, loader, size_of=lambda obj: obj[1])


def test_evicts_least_recently_used_first():
    cache = ByteLRUCache(100)
    load(cache, "a", 40)
    load(cache, "b", 40)
    load(cache, "a", 40)          # a is now more recent than b
    load(cache, "c", 40)          # 120 > 100: evict b
    assert cache.keys() == ["a", "c"]
    assert cache.total_bytes == 80


def test_evicts_as_many_entries_as_the_new_bytes_need():
    cache = ByteLRUCache(100)
    for key in "abc":
        load(cache, key, 30)
    load(cache, "d", 80)          # 170: a (140), b (110), c (80) must go
    assert cache.keys() == ["d"]
    assert cache.total_bytes == 80


def test_entry_exactly_at_budget_is_kept():
    cache = ByteLRUCache(100)
    load(cache, "a", 100)
    assert cache.keys() == ["a"] and cache.total_bytes == 100


def test_object_larger_than_budget_is_returned_but_not_kept():
    cache = ByteLRUCache(100)
    load(cache, "small", 10)
    assert load(cache, "huge", 101) == ("huge", 101)
    assert "huge" not in cache
    assert cache.keys() == ["small"] and cache.total_bytes == 10


def test_hit_does_not_call_the_loader():
    cache = ByteLRUCache(100)
    calls = []
    load(cache, "a", 1, calls)
    load(cache, "a", 1, calls)
    assert calls == ["a"]
    assert (cache.hits, cache.misses) == (1, 1)


def test_loader_error_reaches_the_caller_and_caches_nothing():
    cache = ByteLRUCache(100)

    def broken():
        raise OSError("disk on fire")

    with pytest.raises(OSError, match="disk on fire"):
        cache.get_or_load("a", broken, size_of=len)
    assert len(cache) == 0
    assert load(cache, "a", 5) == ("a", 5)   # a later load is tried afresh


def test_negative_size_is_refused():
    cache = ByteLRUCache(100)
    with pytest.raises(ValueError, match="sizes are >= 0"):
        cache.get_or_load("a", lambda: 1, size_of=lambda obj: -1)
    assert len(cache) == 0


def test_concurrent_misses_of_one_key_load_once():
    cache = ByteLRUCache(100)
    calls = []
    start = threading.Barrier(8)

    def slow_loader():
        calls.append(1)
        time.sleep(0.1)
        return object()

    results = []

    def worker():
        start.wait()
        results.append(cache.get_or_load("model", slow_loader, size_of=lambda _: 10))

    threads = [threading.Thread(target=worker) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1
    assert len(results) == 8 and all(r is results[0] for r in results)


def test_concurrent_loads_of_many_keys_stay_within_budget():
    cache = ByteLRUCache(1000)

    def worker(offset):
        for i in range(200):
            load(cache, (offset + i) % 50, 10 + (i % 7) * 10)

    threads = [threading.Thread(target=worker, args=(k * 13,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert cache.total_bytes <= 1000
    assert cache.total_bytes == sum(obj[1] for obj in
                                    (cache.get_or_load(k, lambda: None, len) for k in cache.keys()))


def test_invalidate_and_clear():
    cache = ByteLRUCache(100)
    load(cache, "a", 10)
    load(cache, "b", 20)
    assert cache.invalidate("a") and not cache.invalidate("a")
    assert cache.keys() == ["b"] and cache.total_bytes == 20
    cache.clear()
    assert len(cache) == 0 and cache.total_bytes == 0


def test_negative_budget_is_refused():
    with pytest.raises(ValueError, match="budget_bytes must be >= 0"):
        ByteLRUCache(-1)
