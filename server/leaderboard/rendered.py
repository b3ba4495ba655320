"""Rendered leaderboard page contents, kept by what they show (server/leaderboard/pages.py)."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable

BUDGET = 16_000_000
"""Characters of rendered content kept per process at most (a page of 200 rows is ~0.5 MB)."""


class BoardPages:
    """Rendered leaderboard contents by what they show; an LRU bounded by count and by size,
    shared by the threads."""

    def __init__(self, size: int = 512, budget: int = BUDGET) -> None:
        self._pages: OrderedDict[Hashable, str] = OrderedDict()
        self._size = size
        self._budget = budget
        self._used = 0
        self._lock = threading.Lock()

    def get(self, key: Hashable, render: Callable[[], str]) -> str:
        """The content kept under `key`, or rendered now and kept."""
        with self._lock:
            if (hit := self._pages.get(key)) is not None:
                self._pages.move_to_end(key)
                return hit
        made = render()
        with self._lock:
            if (old := self._pages.pop(key, None)) is not None:
                self._used -= len(old)  # rendered meanwhile by another thread
            self._pages[key] = made
            self._used += len(made)
            while self._pages and (len(self._pages) > self._size or self._used > self._budget):
                self._used -= len(self._pages.popitem(last=False)[1])
        return made
