"""Exact-stamp matching of the messages that make up one RGB-D frame (message_filters is not on PyPI).

ROS-free: items arrive per key (topic) with a stamp; when every key has an item for a stamp, the set
is complete. :class:`StampMatcher` (the bag reader) bounds memory by giving up the oldest of more than
``max_pending`` incomplete stamps. :class:`FrameLedger` (the nodes' camera input) does the same and
accounts for every frame sent exactly once, in bounded counters. :class:`StampGapCounter` estimates
the messages a stream lost before they reached us (the middleware does not report them).
"""

from __future__ import annotations

import heapq
from collections import OrderedDict, deque
from collections.abc import Hashable, Iterable
from dataclasses import dataclass, field
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
    last ``window`` intervals, and nothing is counted before ``min_intervals`` were seen. An estimate:
    exact for a regular rate that loses in fewer than half of the intervals (the median then ignores
    the gaps), low when losses are the rule (the median adapts to a rate change and to sustained loss
    alike), rough for an irregular rate.

    Implausible stamps are never losses: a repeated stamp is ignored; a stamp that goes back is set
    aside (``outliers``) and starts a new sequence (``restarts``: a bag looped or restarted) only if
    the next stamp confirms it by not returning to the old sequence, so a stray stamp of 0 changes
    nothing; a forward jump of more than ``max_gap_periods`` periods (a clock jump, a long pause)
    starts a new sequence too.
    """

    def __init__(
        self, window: int = 16, min_intervals: int = 4, gap_factor: float = 1.5, max_gap_periods: float = 1000.0
    ) -> None:
        if window < 1 or min_intervals < 1 or gap_factor <= 1.0 or max_gap_periods <= gap_factor:
            raise ValueError(
                f"need window >= 1, min_intervals >= 1, gap_factor > 1, max_gap_periods > gap_factor; got "
                f"{window}, {min_intervals}, {gap_factor}, {max_gap_periods}"
            )
        self.min_intervals = min_intervals
        self.gap_factor = gap_factor
        self.max_gap_periods = max_gap_periods
        self.missed = 0
        """Messages estimated lost so far."""
        self.restarts = 0
        """Times a new sequence started (stamps went back for good, or jumped implausibly far ahead)."""
        self.outliers = 0
        """Stamps that went back once and were ignored (the old sequence went on)."""
        self._intervals: deque[int] = deque(maxlen=window)
        self._last: int | None = None
        self._back: int | None = None  # a stamp that went back, until the next one tells stray from restart

    @property
    def period_ns(self) -> float | None:
        """The stream's period estimate (median interval), None until ``min_intervals`` were seen."""
        if len(self._intervals) < self.min_intervals:
            return None
        ordered = sorted(self._intervals)
        n = len(ordered)
        return float(ordered[n // 2]) if n % 2 else 0.5 * (ordered[n // 2 - 1] + ordered[n // 2])

    def reset(self) -> None:
        """Forget the sequence (its period too): the next stamp starts a new one."""
        self._intervals.clear()
        self._last = self._back = None

    def add(self, stamp_ns: int) -> int:
        """Record the next stamp of the stream; returns the messages estimated lost just before it."""
        if self._back is not None:
            back, self._back = self._back, None
            if self._last is not None and stamp_ns <= self._last:  # confirmed: a new sequence from ``back``
                self.restarts += 1
                self._intervals.clear()
                self._last = back
            else:  # the old sequence goes on: ``back`` was a stray stamp
                self.outliers += 1
        last = self._last
        if last is None:
            self._last = stamp_ns
            return 0
        if stamp_ns == last:
            return 0
        if stamp_ns < last:
            self._back = stamp_ns
            return 0
        self._last = stamp_ns
        gap = stamp_ns - last
        period = self.period_ns
        if period is not None and gap > self.max_gap_periods * period:
            self.restarts += 1
            self._intervals.clear()
            return 0
        lost = 0
        if period is not None and gap > self.gap_factor * period:
            lost = max(0, round(gap / period) - 1)
            self.missed += lost
        self._intervals.append(gap)
        return lost


REJECT_REASONS = ("bad_encoding", "size_mismatch", "bad_image", "bad_camera_info", "bad_pose", "no_tf", "other")
"""The categories :meth:`FrameLedger.reject` counts by (anything else is counted as "other")."""


@dataclass
class _Stamp(Generic[T]):
    """What arrived for one stamp: the items of its first copy (until complete) and messages per key."""

    items: dict[Hashable, T] = field(default_factory=dict)
    counts: dict[Hashable, int] = field(default_factory=dict)
    copies: int = 0


class FrameLedger(Generic[T]):
    """Matches the messages of frames by stamp and accounts for every frame sent exactly once.

    A frame is the set of one message per key with one stamp. Each frame sent ends in exactly one
    bounded counter: ``frames`` (complete, returned by :meth:`add` in stamp order) or ``rejected``
    [reason] (returned, then refused by the caller with :meth:`reject`), ``dropped_incomplete``
    (given up: beyond ``max_pending`` incomplete stamps, or at :meth:`flush`), ``pending`` (still
    incomplete), ``duplicate_stamp`` (one more copy of a stamp already seen: a key's message came
    again), ``out_of_order`` (first seen after newer frames were accounted: a stamp gone back, a stray
    stamp of 0, the first frame of a looped bag; never returned) or ``missed_estimate`` (none of its
    messages came: a gap in the stamps, :class:`StampGapCounter`; an estimate, exact for a regular
    rate that loses in fewer than half of the intervals). A frame that comes late inside a gap already
    counted missed (out of order, or in a block sent newest first) takes its place there, and so does a copy
    of the stamp before a gap (a frame stamped as its predecessor): neither is counted twice.

    Messages of one key are assumed to come in stamp order (one publisher per topic): a stamp is
    then settled once every key has passed it, and its gap to the previous settled stamp counted.
    A message for a stamp already given up is absorbed (``late_messages``), not counted again. When
    every key has gone back below the settled stamps and the next stamp stays back there too, the
    stream restarted (``restarts``: a looped bag, a restarted source): ordering and gaps start afresh;
    if the next stamp returns to the old sequence, the frame that went back was a stray. Memory is
    bounded: ``max_pending`` incomplete frames with their items, and the message counts of the last
    ``memory`` stamps (default: 256, or 4 ``max_pending`` if more).
    """

    def __init__(
        self,
        keys: Iterable[Hashable],
        max_pending: int = 16,
        memory: int | None = None,
        max_gap_periods: float = 1000.0,
    ) -> None:
        self.keys = frozenset(keys)
        if not self.keys:
            raise ValueError("FrameLedger needs at least one key")
        memory = max(256, 4 * max_pending) if memory is None else memory
        if max_pending < 1 or memory < max_pending:
            raise ValueError(f"need max_pending >= 1 and memory >= max_pending, got {max_pending}, {memory}")
        self.max_pending = max_pending
        self.memory = memory
        self.matched = 0
        """Frames returned complete by :meth:`add` (``frames`` plus the rejected ones)."""
        self.rejected: dict[str, int] = {}
        """Returned frames the caller refused, by reason (keys from REJECT_REASONS only)."""
        self.dropped_incomplete = 0
        self.duplicate_stamp = 0
        self.out_of_order = 0
        self.missed_estimate = 0
        self.late_messages = 0
        """Messages (not frames) of a stamp already settled or given up, absorbed."""
        self.restarts = 0
        self.gaps = StampGapCounter(max_gap_periods=max_gap_periods)
        self._pending: dict[int, _Stamp[T]] = {}
        self._done: OrderedDict[int, _Stamp[T]] = OrderedDict()
        self._latest: dict[Hashable, int] = {}
        self._unsettled: list[int] = []  # heap of stamps seen but not yet settled
        self._settled: int | None = None  # newest stamp whose gap is accounted
        self._last_returned: int | None = None
        self._recent_gaps: deque[list[int]] = deque(maxlen=32)  # [after, before, frames counted missed]
        self._back: int | None = None  # every key went back to this stamp: a restart if the next one stays back
        self._duplicates_unsettled = 0  # copies of a stamp seen since the last settled stamp

    @property
    def frames(self) -> int:
        """Frames returned and not rejected: delivered."""
        return self.matched - sum(self.rejected.values())

    @property
    def pending(self) -> int:
        """Incomplete frames currently held."""
        return len(self._pending)

    def counts(self) -> dict[str, int | dict[str, int]]:
        """Every frame counter (each frame sent is in exactly one of them)."""
        return {
            "frames": self.frames,
            "rejected": dict(self.rejected),
            "dropped_incomplete": self.dropped_incomplete,
            "pending": self.pending,
            "duplicate_stamp": self.duplicate_stamp,
            "out_of_order": self.out_of_order,
            "missed_estimate": self.missed_estimate,
        }

    def accounted(self) -> int:
        """The number of frames the counters account for (the sum over :meth:`counts`)."""
        return sum(sum(v.values()) if isinstance(v, dict) else v for v in self.counts().values())

    def reject(self, reason: str) -> None:
        """Count the frame :meth:`add` just returned as refused for ``reason`` (one of REJECT_REASONS)."""
        key = reason if reason in REJECT_REASONS else "other"
        self.rejected[key] = self.rejected.get(key, 0) + 1

    def add(self, stamp_ns: int, key: Hashable, item: T) -> dict[Hashable, T] | None:
        """Add one message; the complete ``{key: item}`` set of a new frame, else None.

        A second message of the same (stamp, key) before the frame completes replaces the first.
        """
        if key not in self.keys:
            raise KeyError(f"unknown key {key!r}; expected one of {sorted(map(str, self.keys))}")
        if self._back is not None and self._settled is not None and stamp_ns != self._back:
            if stamp_ns <= self._settled:  # a second frame back there: the source restarted
                self._restart(self._back, stamp_ns)
            else:  # the old sequence goes on: that one frame was a stray (e.g. a stamp of 0)
                self._back = None
        self._latest[key] = stamp_ns
        result = None
        entry = self._pending.get(stamp_ns)
        if entry is not None:
            self._count(entry, key)
            entry.items[key] = item
            result = self._maybe_complete(stamp_ns, entry)
        elif (entry := self._done.get(stamp_ns)) is not None:
            if not self._count(entry, key):
                self.late_messages += 1
        elif self._settled is not None and stamp_ns <= self._settled:
            self.out_of_order += 1
            self._refund_gap(stamp_ns)
            entry = _Stamp()
            self._count(entry, key)
            self._remember(stamp_ns, entry)
        else:
            self._refund_gap(stamp_ns)  # after a restart: inside a gap counted before it (a block sent newest first)
            entry = _Stamp(items={key: item})
            self._count(entry, key)
            self._pending[stamp_ns] = entry
            heapq.heappush(self._unsettled, stamp_ns)
            result = self._maybe_complete(stamp_ns, entry)
            while len(self._pending) > self.max_pending:
                oldest = min(self._pending)
                self._remember(oldest, self._pending.pop(oldest))
                self.dropped_incomplete += 1
        self._settle()
        return result

    def flush(self) -> int:
        """Give up every incomplete frame (end of input); return how many were dropped."""
        n = len(self._pending)
        for stamp in sorted(self._pending):
            self._remember(stamp, self._pending.pop(stamp))
        self.dropped_incomplete += n
        return n

    def _count(self, entry: _Stamp[T], key: Hashable) -> bool:
        """Count a message of ``entry``; True if it starts another copy of the stamp (a duplicate after the first)."""
        n = entry.counts.get(key, 0) + 1
        entry.counts[key] = n
        if n <= entry.copies:
            return False
        entry.copies = n
        if n > 1:
            self.duplicate_stamp += 1
            self._duplicates_unsettled += 1
        return True

    def _maybe_complete(self, stamp: int, entry: _Stamp[T]) -> dict[Hashable, T] | None:
        if len(entry.items) < len(self.keys):
            return None
        del self._pending[stamp]
        items, entry.items = entry.items, {}
        self._remember(stamp, entry)
        if self._last_returned is not None and stamp < self._last_returned:
            self.out_of_order += 1  # completed after a newer frame: never returned out of order
            return None
        self._last_returned = stamp
        self.matched += 1
        return items

    def _remember(self, stamp: int, entry: _Stamp[T]) -> None:
        entry.items = {}
        self._done[stamp] = entry
        while len(self._done) > self.memory:
            self._done.popitem(last=False)

    def _settle(self) -> None:
        """Account the gaps before every stamp that all keys have passed (oldest first); detect restarts."""
        if len(self._latest) < len(self.keys):
            watermark = None
        else:
            watermark = min(self._latest.values())
            if self._settled is not None and max(self._latest.values()) < self._settled:
                self._back = max(self._latest.values())
        heap = self._unsettled
        while heap and ((watermark is not None and heap[0] <= watermark) or len(heap) > self.memory):
            stamp = heapq.heappop(heap)
            if self._settled is not None and stamp <= self._settled:
                continue
            lost = self.gaps.add(stamp)
            # A copy of a stamp in place of the next frame's (a repeated stamp) leaves a gap that is that frame:
            # the copies seen since the last settled stamp fill that many of the gap's frames.
            filled = min(lost, self._duplicates_unsettled)
            lost -= filled
            self._duplicates_unsettled = 0
            if lost:
                self.missed_estimate += lost
                self._recent_gaps.append([self._settled if self._settled is not None else stamp, stamp, lost])
            self._settled = stamp

    def _refund_gap(self, stamp: int) -> None:
        """A stamp first seen late inside a gap counted as missed: it was not missed after all."""
        for gap in self._recent_gaps:
            if gap[0] < stamp < gap[1] and gap[2] > 0:
                gap[2] -= 1
                self.missed_estimate -= 1
                return

    def _restart(self, back: int, stamp: int) -> None:
        """Every key went back below the settled stamps (to ``back``), then ``stamp`` too: a new stream (a looped
        or restarted source), or a block of frames sent newest first.

        The gaps counted missed that hold ``back`` or ``stamp`` are kept: the frames of a block sent newest first
        fill the gap its newest frame left (each refunds one as it comes); a looped bag's first stamps hold none.
        """
        self.restarts += 1
        self._back = None
        self.gaps.reset()
        self._done.clear()
        self._unsettled.clear()
        kept = [g for g in self._recent_gaps if g[0] < back < g[1] or g[0] < stamp < g[1]]
        self._recent_gaps.clear()
        self._recent_gaps.extend(kept)
        self._duplicates_unsettled = 0
        self._settled = self._last_returned = None


__all__ = [
    "REJECT_REASONS",
    "FrameLedger",
    "StampGapCounter",
    "StampMatcher",
    "T",
]
