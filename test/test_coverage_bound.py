"""scripts/coverage_bound.py: the oracles behind the stream-feasibility table (issue 10; docs/measured-figures.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import load_script

cb = load_script("coverage_bound")


def _obs(frames: dict[int, set[int]], n_frames: int, n_samples: int) -> np.ndarray:
    obs = np.zeros((n_frames, n_samples), dtype=bool)
    for f, samples in frames.items():
        obs[f, sorted(samples)] = True
    return obs


def test_a_perfect_window_scorer_is_myopic_and_hindsight_is_not() -> None:
    """Windows [1, 2] and [3, 4]: frame 2 adds the most when its window closes, but frame 3 sees the same and more
    later, so choosing frame 1 then frame 3 covers more. The window oracle takes 2 (then 3), coordinate ascent
    re-chooses 1, and the one-window-late oracle leaves what window 2 shows again to it."""
    obs = _obs({0: {0}, 1: {1, 2}, 2: {3, 4, 5}, 3: {3, 4, 5, 7}, 4: {6}}, 5, 8)
    windows = cb.trigger_windows(5, 2)
    assert windows == [[1, 2], [3, 4]]
    oracle = cb.stream_oracle(obs, windows)
    assert oracle == [0, 2, 3] and cb.coverage(obs, oracle) == 5 / 8
    ascent = cb.refine_windows(obs, oracle, windows)
    assert ascent == [0, 1, 3] and cb.coverage(obs, ascent) == 7 / 8
    assert cb.delayed_oracle(obs, windows) == [0, 1, 3]
    # the policies' lookahead rule: frame 1 (2 new) plus the 4 that frame 3 still adds after it beats frame 2 (3 new)
    # plus 1; without a frame to look at (lookahead 0) it is the plain window oracle
    assert cb.lookahead_oracle(obs, windows, 2) == [0, 1, 3]
    assert cb.lookahead_oracle(obs, windows, 0) == oracle
    greedy, curve = cb.offline_greedy(obs, 4)
    assert greedy == [0, 3, 1, 4] and curve == [1 / 8, 5 / 8, 7 / 8, 8 / 8]


def test_threshold_and_budget_oracles_keep_their_budgets() -> None:
    """The threshold found by bisection gives at most the budget, one sample less gives more; the budget trigger
    never inserts more than its bank allows (1 + (F - 1) // budget_every)."""
    rng = np.random.default_rng(0)
    obs = rng.random((60, 400)) < 0.05
    for k in (5, 10, 20):
        t, picks = cb.threshold_for(obs, k)
        assert len(picks) <= k < len(cb.threshold_picks(obs, t - 1)) and picks[0] == 0
    picks, when, left = cb.budget_oracle(obs, window=6, trigger_every=2, budget_every=6.0)
    assert len(picks) <= 1 + 59 // 6 and 0 <= left <= 3.0
    assert all(when[p] >= p for p in picks)  # a pick is inserted at or after its arrival


def test_mapper_overrides_are_checked_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`--set` takes MapperConfig fields as `roigsf bench --set` does: an unknown field, the seed and an out-of-range
    value exit 2 with the flag or field named, as does a negative `--lookahead`, before the scene is read (the scene
    here does not exist) and nothing is written."""
    base = ["--scene", str(tmp_path / "no_scene"), "--out", str(tmp_path / "out")]
    cases = [
        (["--set", "nope=1"], "--set nope=1"),
        (["--set", "seed=3"], "--set seed=3"),
        (["--set", "init_max_stretch=-1"], "stretch"),
        (["--lookahead", "-1"], "--lookahead"),
    ]
    for args, word in cases:
        assert cb.main([*base, *args]) == 2
        assert word in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
