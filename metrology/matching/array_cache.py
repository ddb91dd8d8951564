"""A least-recently-used store of arrays within a byte budget, shared by a diagnosis's threads.

Written here because ``functools.lru_cache`` bounds a count, not bytes, and keys on the call's
arguments (arrays are not hashable); the models key their renders on what made them.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Hashable

import numpy as np

__all__ = ["ArrayCache"]


class ArrayCache:
    """Least-recently-used store of arrays within a byte budget (always keeps the newest).

    Safe to share between threads (a diagnosis's workers): each call holds the store's lock.
    Two threads that miss the same key both compute it; the later one's array is kept.
    """

    def __init__(self, max_bytes: int, max_items: int | None = None) -> None:
        self.max_bytes = int(max_bytes)
        self.max_items = max_items
        self._items: OrderedDict = OrderedDict()
        self._bytes = 0  # of the arrays held: a put is then not a sum over them
        self._lock = threading.Lock()

    def get(self, key: Hashable) -> np.ndarray | None:
        with self._lock:
            value = self._items.get(key)
            if value is not None:
                self._items.move_to_end(key)
            return value

    def put(self, key: Hashable, value: np.ndarray) -> None:
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self._bytes -= old.nbytes
            self._items[key] = value
            self._bytes += value.nbytes
            while len(self._items) > 1 and (self._bytes > self.max_bytes
                                            or (self.max_items and len(self._items) > self.max_items)):
                self._bytes -= self._items.popitem(last=False)[1].nbytes

    def __contains__(self, key: Hashable) -> bool:
        with self._lock:
            return key in self._items

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0
