"""Exact-stamp matching of the four messages of an RGB-D frame."""

import numpy as np
import pytest

from roigsf_ros.data.sync import FrameLedger, StampGapCounter, StampMatcher


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


# ------------------------------------------------------------------------------ every frame accounted once
KEYS = ("color", "depth", "info", "pose")
PERIOD = 100_000_000  # 10 Hz
T0 = 1_700_000_000 * 10**9  # stamps as a real bag has them


def _stamp(k: float) -> int:
    return T0 + round(k * PERIOD)


def _frame(k: float, skip: tuple[str, ...] = ()) -> list[tuple[int, str]]:
    """The messages of frame ``k`` (all four unless some are skipped), in publishing order."""
    return [(_stamp(k), key) for key in KEYS if key not in skip]


def _feed(ledger: FrameLedger[int], messages: list[tuple[int, str]], reject_every: int = 0) -> list[int]:
    """Feed messages; the stamps returned complete (every ``reject_every``-th refused by the 'caller')."""
    delivered = []
    for stamp, key in messages:
        parts = ledger.add(stamp, key, stamp)
        if parts is not None:
            assert sorted(parts) == sorted(KEYS) and set(parts.values()) == {stamp}
            if reject_every and ledger.matched % reject_every == 0:
                ledger.reject("size_mismatch")
            else:
                delivered.append(stamp)
    return delivered


def _check(ledger: FrameLedger[int], sent: int, **expected: int) -> None:
    counts = ledger.counts()
    assert ledger.accounted() == sent, (counts, sent)  # every frame sent, exactly once
    for name, value in expected.items():
        assert counts[name] == value, (name, counts)


def test_ledger_regular_stream_with_losses_and_rejections() -> None:
    ledger: FrameLedger[int] = FrameLedger(KEYS)
    msgs: list[tuple[int, str]] = []
    for k in range(60):
        if k in (10, 11, 12, 30):  # lost on every topic: only the stamp gap shows them
            continue
        msgs += _frame(k, skip=("pose",) if k == 20 else ("color",) if k == 40 else ())
    delivered = _feed(ledger, msgs, reject_every=7)
    assert delivered == sorted(delivered) and len(delivered) + sum(ledger.rejected.values()) == 54
    _check(ledger, 60, missed_estimate=4, pending=2, rejected={"size_mismatch": 7})
    assert ledger.flush() == 2
    _check(ledger, 60, dropped_incomplete=2, pending=0)


def test_ledger_burst_of_500_through_bounded_queues() -> None:
    """20 frames at rate, then a burst of 500 into keep-last queues that keep the last 100/100/90/80
    messages of their topic; the subscriber drains them topic by topic, 25 at a time, more than the
    matcher's 16 pending frames."""
    ledger: FrameLedger[int] = FrameLedger(KEYS, max_pending=16)
    msgs = [m for k in range(20) for m in _frame(k)]
    depth = {"color": 100, "depth": 100, "info": 90, "pose": 80}
    queues = {key: [_stamp(k) for k in range(20, 520)][-depth[key] :] for key in KEYS}
    while any(queues.values()):
        for key in KEYS:
            msgs += [(s, key) for s in queues[key][:25]]
            del queues[key][:25]
    _feed(ledger, msgs)
    ledger.flush()
    # 20..419 lost on every topic; 420..439 lack pose, 420..429 camera info too: incomplete
    _check(ledger, 520, missed_estimate=400, duplicate_stamp=0, out_of_order=0)
    assert ledger.dropped_incomplete >= 20 and ledger.late_messages > 0  # stragglers absorbed, not recounted


def test_ledger_stray_zero_stamp_repeats_and_backwards_stamps() -> None:
    ledger: FrameLedger[int] = FrameLedger(KEYS)
    msgs = [m for k in range(30) for m in _frame(k)]
    msgs += [(0, key) for key in KEYS]  # a stray stamp of 0 (an unstamped frame)
    msgs += [m for k in range(30, 40) for m in _frame(k)]
    msgs += _frame(39)  # the last frame again: a repeated stamp
    msgs += _frame(40) + _frame(40) + _frame(40)  # sent three times
    msgs += _frame(41)[:2] + _frame(41) + _frame(41)[2:]  # two copies interleaved
    msgs += _frame(35) + _frame(42)  # a stamp seen before, going back, then the sequence goes on
    msgs += _frame(36.5) + _frame(43)  # a new stamp older than the newest: out of order
    msgs += [m for k in range(44, 60) for m in _frame(k)]
    delivered = _feed(ledger, msgs)
    sent = 30 + 1 + 10 + 1 + 3 + 2 + 2 + 2 + 16
    _check(ledger, sent, missed_estimate=0, duplicate_stamp=5, pending=0)
    assert delivered == sorted(delivered) and len(delivered) == len(set(delivered)) == ledger.frames
    assert ledger.out_of_order == 2  # the stray 0 and 36.5; neither delivered
    assert 0 not in delivered and _stamp(36.5) not in delivered and ledger.restarts == 0


def test_ledger_looped_bag_restarts() -> None:
    ledger: FrameLedger[int] = FrameLedger(KEYS)
    msgs = [m for _loop in range(3) for k in range(40) for m in _frame(k)]
    delivered = _feed(ledger, msgs)
    _check(ledger, 120, missed_estimate=0)
    # The first frame of each new loop is not delivered: a duplicate of a stamp still remembered, or
    # out of order; the next frame, back there too, shows the restart and the loop is delivered again.
    assert ledger.out_of_order + ledger.duplicate_stamp == 2 and ledger.restarts == 2 and len(delivered) == 118


def test_ledger_late_first_message_in_a_gap_is_not_counted_twice() -> None:
    ledger: FrameLedger[int] = FrameLedger(KEYS)
    msgs = [m for k in range(30) if k != 20 for m in _frame(k)]
    msgs += [(_stamp(20), "depth")]  # frame 20's depth straggles in after the gap was counted
    _feed(ledger, msgs)
    _check(ledger, 30, missed_estimate=0, out_of_order=1)


def test_ledger_counters_and_memory_stay_bounded() -> None:
    rng = np.random.default_rng(1)
    ledger: FrameLedger[int] = FrameLedger(KEYS, max_pending=8, memory=64)
    sent = 0
    for k in range(5000):
        sent += 1
        if rng.random() < 0.05:
            continue  # lost entirely
        msgs = [(s, key) for s, key in _frame(k) if rng.random() > 0.02]
        for stamp, key in msgs:
            if ledger.add(stamp, key, stamp) is not None and rng.random() < 0.1:
                ledger.reject(f"error text {k} that differs every time")  # unbounded text: one category
        assert ledger.pending <= 8 and len(ledger._done) <= 64 and len(ledger._unsettled) <= 64
    ledger.flush()
    assert set(ledger.rejected) == {"other"} and len(ledger.counts()) == 7
    assert abs(ledger.accounted() - sent) <= 0.01 * sent  # random losses: the gap estimate is near-exact


def test_gap_counter_ignores_a_stray_zero_and_implausible_jumps() -> None:
    g = StampGapCounter()
    stamps = [_stamp(k) for k in range(20)] + [0] + [_stamp(k) for k in range(20, 40)]
    for s in stamps:
        g.add(s)
    assert (g.missed, g.restarts, g.outliers) == (0, 0, 1)
    for s in (_stamp(40), _stamp(41), _stamp(10**7), _stamp(10**7 + 1)):  # a clock jump of ~12 days
        g.add(s)
    assert (g.missed, g.restarts) == (0, 1)
    h = StampGapCounter()
    for k in [*range(20), 23, *range(24, 30)]:  # a real loss is still counted
        h.add(_stamp(k))
    assert h.missed == 3  # 20, 21, 22


def test_ledger_a_frame_stamped_as_the_one_before_is_not_also_counted_missed() -> None:
    """A frame that carries its predecessor's stamp (a recorder's repeated stamp): its own stamp never comes, and
    the gap it leaves is that frame, already counted as a duplicate (walk of session 60: 152 for 150 sent)."""
    ledger: FrameLedger[int] = FrameLedger(KEYS)
    msgs = [m for k in range(150) for m in _frame(k - 1 if k in (41, 91) else k)]
    delivered = _feed(ledger, msgs)
    _check(ledger, 150, duplicate_stamp=2, missed_estimate=0)
    assert len(delivered) == 148


def test_ledger_a_block_sent_in_reverse_stamp_order_is_counted_once() -> None:
    """Frames 60-69 sent newest first: the forward jump is counted missed until the frames of the block come in
    (out of order or, once the stamps kept going back, as a restarted sequence); 158 for 150 before session 60."""
    ledger: FrameLedger[int] = FrameLedger(KEYS)
    order = [*range(60), *range(69, 59, -1), *range(70, 150)]
    delivered = _feed(ledger, [m for k in order for m in _frame(k)])
    _check(ledger, 150, missed_estimate=0, duplicate_stamp=0)
    assert len(delivered) + ledger.out_of_order == 150


def test_ledger_a_loss_before_a_loop_restarts_stays_counted() -> None:
    """A frame lost near the end of the first loop is still counted missed after the loop replays its stamp."""
    ledger: FrameLedger[int] = FrameLedger(KEYS)
    msgs = [m for loop in range(3) for k in range(40) if (loop, k) != (0, 37) for m in _frame(k)]
    _feed(ledger, msgs)
    _check(ledger, 120, missed_estimate=1)
