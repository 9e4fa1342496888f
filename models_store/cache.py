"""A thread-safe LRU cache of loaded objects (models), bounded by their size in bytes.

The API keeps loaded models here, keyed by model id, so a synthesis request does not
reload a model from disk; the budget is ``Settings.model_cache_bytes``.

Examples
--------
>>> cache = ByteLRUCache(budget_bytes=2 << 30)
>>> model = cache.get_or_load("mdl_…", lambda: load(path), size_of=lambda m: m.nbytes)
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from concurrent.futures import Future
from typing import Callable, Generic, Hashable, TypeVar

T = TypeVar("T")


class ByteLRUCache(Generic[T]):
    """Least-recently-used cache whose entries are weighed in bytes.

    After an insertion, least-recently-used entries are evicted until the total is within
    the budget. An object larger than the whole budget is returned to its caller but not
    kept (and evicts nothing). Concurrent callers asking for the same missing key wait for
    one load instead of loading it twice; loads of different keys run in parallel (the
    loader runs outside the lock).

    Parameters
    ----------
    budget_bytes : int   the most bytes the kept entries may weigh together (>= 0)
    """

    def __init__(self, budget_bytes: int):
        if budget_bytes < 0:
            raise ValueError(f"budget_bytes must be >= 0, got {budget_bytes}")
        self.budget_bytes = budget_bytes
        self._entries: OrderedDict[Hashable, tuple[T, int]] = OrderedDict()
        self._loading: dict[Hashable, Future[T]] = {}
        self._total = 0
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    @property
    def total_bytes(self) -> int:
        """The summed size of the kept entries."""
        return self._total

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._entries

    def keys(self) -> list[Hashable]:
        """The kept keys, least recently used first."""
        with self._lock:
            return list(self._entries)

    def get_or_load(self, key: Hashable, loader: Callable[[], T],
                    size_of: Callable[[T], int]) -> T:
        """The object cached under ``key``, loading (and caching) it on a miss.

        Parameters
        ----------
        key : hashable              e.g. a model id
        loader : () -> T            loads the object; its exceptions reach every caller
                                    waiting for this load, and nothing is cached
        size_of : T -> int          the object's size in bytes

        Returns
        -------
        T   the cached or freshly loaded object
        """
        with self._lock:
            entry = self._entries.get(key)
            if entry is not None:
                self._entries.move_to_end(key)
                self.hits += 1
                return entry[0]
            self.misses += 1
            pending = self._loading.get(key)
            owner = pending is None
            if owner:
                pending = self._loading[key] = Future()
        if not owner:
            return pending.result()

        try:
            value = loader()
            size = int(size_of(value))
            if size < 0:
                raise ValueError(f"size_of returned {size} bytes for {key!r}; sizes are >= 0")
        except BaseException as exc:
            with self._lock:
                del self._loading[key]
            pending.set_exception(exc)
            raise
        with self._lock:
            del self._loading[key]
            self._insert(key, value, size)
        pending.set_result(value)
        return value

    def invalidate(self, key: Hashable) -> bool:
        """Drop ``key`` (e.g. a deleted model); return whether it was cached."""
        with self._lock:
            entry = self._entries.pop(key, None)
            if entry is None:
                return False
            self._total -= entry[1]
            return True

    def clear(self) -> None:
        """Drop every entry."""
        with self._lock:
            self._entries.clear()
            self._total = 0

    def _insert(self, key: Hashable, value: T, size: int) -> None:
        """Keep ``value`` and evict down to the budget (the caller holds the lock)."""
        if size > self.budget_bytes:
            return
        self._entries[key] = (value, size)
        self._total += size
        while self._total > self.budget_bytes:
            _, (_, evicted) = self._entries.popitem(last=False)
            self._total -= evicted
