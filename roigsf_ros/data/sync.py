"""Exact-stamp matching of the messages that make up one RGB-D frame (message_filters is not on PyPI).

ROS-free and shared by the bag reader and the nodes: items arrive per key (topic) with a stamp; when
every key has an item for a stamp, the set is complete. Memory is bounded: beyond ``max_pending``
incomplete stamps, the oldest is given up and counted. :class:`StampGapCounter` estimates the
messages a stream lost before they reached us (the middleware does not report them).
"""

from __future__ import annotations

from collections import deque
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


class StampGapCounter:
    """Estimates the messages one stream lost from gaps in its stamps.

    A subscriber's keep-last queue overwrites the oldest sample when it is full, and Fast DDS does not
    report it (its ``message_lost`` event stays silent; checked), so only the gap in the stamps shows.
    For a regular stream a gap of k periods means k - 1 lost messages; the period is the median of the
    last ``window`` intervals, and nothing is counted before ``min_intervals`` were seen. A stamp that
    goes back starts a new sequence (a bag looped or restarted; one publisher's samples arrive in
    order); a repeated one is ignored. An estimate: exact for a regular rate that loses in fewer than
    half of the intervals (the median then ignores the gaps), low when losses are the rule (the median
    adapts to a rate change and to sustained loss alike), rough for an irregular rate.
    """

    def __init__(self, window: int = 16, min_intervals: int = 4, gap_factor: float = 1.5) -> None:
        if window < 1 or min_intervals < 1 or gap_factor <= 1.0:
            raise ValueError(
                f"need window >= 1, min_intervals >= 1, gap_factor > 1; got {window}, {min_intervals}, {gap_factor}"
            )
        self.min_intervals = min_intervals
        self.gap_factor = gap_factor
        self.missed = 0
        """Messages estimated lost so far."""
        self.restarts = 0
        """Times the stamps went back (a new sequence)."""
        self._intervals: deque[int] = deque(maxlen=window)
        self._last: int | None = None

    @property
    def period_ns(self) -> float | None:
        """The stream's period estimate (median interval), None until ``min_intervals`` were seen."""
        if len(self._intervals) < self.min_intervals:
            return None
        ordered = sorted(self._intervals)
        n = len(ordered)
        return float(ordered[n // 2]) if n % 2 else 0.5 * (ordered[n // 2 - 1] + ordered[n // 2])

    def add(self, stamp_ns: int) -> int:
        """Record the next stamp of the stream; returns the messages estimated lost just before it."""
        last, self._last = self._last, stamp_ns
        if last is None:
            return 0
        if stamp_ns <= last:
            if stamp_ns < last:
                self.restarts += 1
            return 0
        gap = stamp_ns - last
        period = self.period_ns
        lost = 0
        if period is not None and gap > self.gap_factor * period:
            lost = max(0, round(gap / period) - 1)
            self.missed += lost
        self._intervals.append(gap)
        return lost


__all__ = [
    "StampGapCounter",
    "StampMatcher",
    "T",
]
