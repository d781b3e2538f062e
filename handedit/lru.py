"""One least-recently-used cache for the per-process caches of derived data (a clip's
scenes, dilated holes, features, matches, homographies): thread-safe (a worker's task
threads share them) and bounded by entries, by bytes, or both."""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any, Callable, Hashable

MISSING = object()


class Lru:
    def __init__(self, max_items: int | None = None, max_bytes: int | None = None,
                 size: Callable[[Any], int] = lambda value: 0):
        self.max_items, self.max_bytes, self._size = max_items, max_bytes, size
        self._items: OrderedDict = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key: Hashable, default: Any = MISSING) -> Any:
        """The value (now the most recent), or ``default`` (``MISSING``: a value may be None)."""
        with self._lock:
            if key not in self._items:
                return default
            self._items.move_to_end(key)
            return self._items[key]

    def __contains__(self, key: Hashable) -> bool:
        with self._lock:
            return key in self._items

    def __len__(self) -> int:
        return len(self._items)

    def put(self, key: Hashable, value: Any) -> Any:
        """Keep ``value`` (a value another thread put first wins, and is returned), dropping
        the least recent entries beyond the bounds (never the one just put)."""
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
            self._items[key] = value
            self._bytes += self._size(value)
            while len(self._items) > 1 and ((self.max_items is not None and len(self._items) > self.max_items)
                                            or (self.max_bytes is not None and self._bytes > self.max_bytes)):
                self._bytes -= self._size(self._items.popitem(last=False)[1])
            return value

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0
