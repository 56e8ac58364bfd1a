"""Exact-stamp matching of the four messages of an RGB-D frame."""

import pytest

from roigsf_ros.sync import StampMatcher


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
