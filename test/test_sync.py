"""Exact-stamp matching of the four messages of an RGB-D frame."""

import numpy as np
import pytest

from roigsf_ros.data.sync import StampGapCounter, StampMatcher


def test_completes_in_any_arrival_order() -> None:
    m: StampMatcher[str] = StampMatcher(["c", "d", "i", "p"])
    assert m.add(2, "d", "d2") is None
    assert m.add(1, "c", "c1") is None
    for key in ("d", "i"):
        assert m.add(1, key, f"{key}1") is None
    assert m.add(1, "p", "p1") == {"c": "c1", "d": "d1", "i": "i1", "p": "p1"}
    assert (m.completed, m.pending, m.dropped) == (1, 1, 0)


def test_bounded_memory_drops_oldest_and_counts() -> None:
    m: StampMatcher[int] = StampMatcher(["a", "b"], max_pending=3)
    for stamp in range(10):
        m.add(stamp, "a", stamp)
    assert m.pending == 3 and m.dropped == 7
    assert m.add(9, "b", 0) == {"a": 9, "b": 0}  # the newest survived
    assert m.add(0, "b", 0) is None  # the oldest was given up
    assert m.flush() == 3 and m.dropped == 10 and m.pending == 0


def test_rejects_unknown_keys_and_bad_sizes() -> None:
    m: StampMatcher[int] = StampMatcher(["a"])
    with pytest.raises(KeyError, match="unknown key"):
        m.add(0, "z", 1)
    with pytest.raises(ValueError):
        StampMatcher([], max_pending=1)
    with pytest.raises(ValueError):
        StampMatcher(["a"], max_pending=0)


def test_gap_counter_counts_lost_messages_of_a_regular_stream() -> None:
    g = StampGapCounter()
    period = 100_000_000  # 10 Hz
    kept = [k for k in range(60) if k not in (10, 11, 12, 30, 45)]  # 5 lost after warm-up
    lost_at = {k: g.add(k * period) for k in kept}
    assert g.missed == 5 and lost_at[13] == 3 and lost_at[31] == 1 and lost_at[46] == 1
    assert g.period_ns == period
    # jitter of +-20 % is no loss; the first intervals (before a period is known) are never counted
    h = StampGapCounter()
    rng = np.random.default_rng(0)
    stamps = np.cumsum(rng.uniform(0.8, 1.2, 200) * period).astype(np.int64)
    for s in [0, 5 * period, *(stamps + 5 * period)]:
        h.add(int(s))
    assert h.missed == 0


def test_gap_counter_restarts_on_a_looped_bag_and_ignores_repeats() -> None:
    g = StampGapCounter()
    for _loop in range(3):  # the same 20 stamps three times: nothing lost
        for k in range(20):
            g.add(1_000 + 10 * k)
            g.add(1_000 + 10 * k)  # a repeated stamp
    assert (g.missed, g.restarts) == (0, 2)
    with pytest.raises(ValueError):
        StampGapCounter(gap_factor=1.0)
