"""Exact-stamp matching of the messages that make up one RGB-D frame (message_filters is not on PyPI).

ROS-free and shared by the bag reader and the nodes: items arrive per key (topic) with a stamp; when
every key has an item for a stamp, the set is complete. Memory is bounded: beyond ``max_pending``
incomplete stamps, the oldest is given up and counted.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable
from typing import Generic, TypeVar

T = TypeVar("T")


class StampMatcher(Generic[T]):
    """Collects items by (stamp, key); returns the full ``{key: item}`` set when a stamp completes."""

    def __init__(self, keys: Iterable[Hashable], max_pending: int = 16) -> None:
        self.keys = frozenset(keys)
        if not self.keys:
            raise ValueError("StampMatcher needs at least one key")
        if max_pending < 1:
            raise ValueError(f"max_pending must be >= 1, got {max_pending}")
        self.max_pending = max_pending
        self.completed = 0
        self.dropped = 0
        """Stamps given up incomplete (overflow or :meth:`flush`)."""
        self._pending: dict[int, dict[Hashable, T]] = {}

    def add(self, stamp_ns: int, key: Hashable, item: T) -> dict[Hashable, T] | None:
        """Add one item; the complete set for ``stamp_ns`` once every key has arrived, else None.

        A second item for the same (stamp, key) replaces the first.
        """
        if key not in self.keys:
            raise KeyError(f"unknown key {key!r}; expected one of {sorted(map(str, self.keys))}")
        parts = self._pending.setdefault(stamp_ns, {})
        parts[key] = item
        if len(parts) == len(self.keys):
            del self._pending[stamp_ns]
            self.completed += 1
            return parts
        while len(self._pending) > self.max_pending:
            del self._pending[min(self._pending)]
            self.dropped += 1
        return None

    @property
    def pending(self) -> int:
        """Incomplete stamps currently held."""
        return len(self._pending)

    def flush(self) -> int:
        """Give up every incomplete stamp (end of input); return how many were dropped."""
        n = len(self._pending)
        self._pending.clear()
        self.dropped += n
        return n
