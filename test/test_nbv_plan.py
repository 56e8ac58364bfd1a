"""What the candidates' unseen cells say together (:mod:`roigsf_ros.nbv.plan`): the unseen term planned over a few
views (``NBVConfig.unseen_plan_views``) and weighed by rarity (``NBVConfig.unseen_rarity``)."""

from __future__ import annotations

import numpy as np
import pytest

from roigsf_ros.core.errors import InputError
from roigsf_ros.nbv import NBVConfig, UnseenCells, planned_unseen, rarity_weighted


def view(cells: list[int], share: float = 0.1) -> UnseenCells:
    """A view entering unknown space at ``cells``, each with ``share`` of its counted pixels."""
    return UnseenCells(np.array(cells, dtype=np.int64), np.full(len(cells), share))


def reference(views: list[UnseenCells], k: int) -> np.ndarray:
    """The same greedy completion with Python sets and loops: the plain reference the sparse sums are checked on."""
    shares = [dict(zip(v.cells.tolist(), v.share.tolist(), strict=True)) for v in views]
    out = []
    for x in range(len(views)):
        entered, used, total = set(shares[x]), {x}, sum(shares[x].values())
        for _ in range(k - 1):
            best, best_gain = -1, 0.0
            for y in range(len(views)):
                gain = sum(s for c, s in shares[y].items() if c not in entered)
                if y not in used and gain > best_gain:
                    best, best_gain = y, gain
            if best < 0:
                break
            total += best_gain
            used.add(best)
            entered |= set(shares[best])
        out.append(total)
    return np.array(out)


def test_a_plan_of_two_prefers_the_view_whose_partner_sees_the_rest() -> None:
    """X sees the most on its own, but Y and Z together see all of X's cells and two more: with a plan of two views
    Y (and Z) score above X, where the myopic fraction ranks X first."""
    views = [view([1, 2, 3, 4]), view([1, 2, 5]), view([3, 4, 6])]
    assert planned_unseen(views, 1) == pytest.approx([0.4, 0.3, 0.3])
    planned = planned_unseen(views, 2)
    assert planned == pytest.approx([0.5, 0.6, 0.6])
    assert int(np.argmax(planned)) == 1
    assert planned_unseen(views, 3) == pytest.approx([0.6, 0.6, 0.6])  # every cell, whoever starts


def test_a_cell_counts_once_per_plan_and_the_completion_stops_when_nothing_is_added() -> None:
    """A view whose cells the plan already enters adds nothing, even with a larger share of its own pixels there;
    with nothing left to add, a longer plan is worth no more than the view alone."""
    views = [view([1, 2], 0.2), view([1, 2], 0.45), view([7], 0.05)]
    assert planned_unseen(views, 2) == pytest.approx([0.45, 0.95, 0.95])
    alone = [view([1, 2], 0.2), view([1], 0.3)]
    assert planned_unseen(alone, 4) == pytest.approx([0.4, 0.5])
    assert planned_unseen([view([1, 2]), view([])], 3) == pytest.approx([0.2, 0.2])


def test_planned_unseen_matches_the_plain_reference_on_random_views() -> None:
    """Random views over shared cells, plans of 1-5 views: the sparse sums equal the set-and-loop reference."""
    rng = np.random.default_rng(36)
    for trial in range(20):
        m = int(rng.integers(2, 12))
        views = []
        for _ in range(m):
            cells = np.unique(rng.integers(0, 60, size=int(rng.integers(0, 25))))
            share = rng.random(len(cells)) / max(len(cells), 1)
            views.append(UnseenCells(cells.astype(np.int64), share))
        for k in (1, 2, 3, 5):
            assert planned_unseen(views, k) == pytest.approx(reference(views, k), rel=1e-12, abs=1e-12), (trial, k)


def test_unseen_cells_from_pixels_counts_only_the_counted_pixels() -> None:
    """Shares are over the pixels whose ray meets the box: -1 pixels and pixels outside the box add nothing."""
    cell = np.array([[5, 5, -1], [7, 5, 9]])
    counted = np.array([[True, True, True], [True, True, False]])
    v = UnseenCells.from_pixels(cell, counted)
    assert v.cells.tolist() == [5, 7]
    assert v.share == pytest.approx([3 / 5, 1 / 5])
    assert v.fraction == pytest.approx(4 / 5)
    assert UnseenCells.from_pixels(cell, np.zeros_like(counted)).fraction == 0.0
    with pytest.raises(InputError, match="cell"):
        UnseenCells.from_pixels(cell, counted[:1])


def test_a_stop_check_runs_before_each_views_completion() -> None:
    """The plan's work grows as M^2: a scorer shutting down stops it between views (its check raises)."""
    calls: list[int] = []

    def check() -> None:
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("stop")

    views = [view([1, 2]), view([2, 3]), view([3, 4])]
    with pytest.raises(RuntimeError, match="stop"):
        planned_unseen(views, 2, check)
    assert len(calls) == 2
    calls.clear()
    planned_unseen(views[:1] + views[:1], 2, lambda: calls.append(1))
    assert len(calls) == 2


def test_bad_plan_settings_name_the_field() -> None:
    with pytest.raises(InputError, match="unseen_plan_views"):
        planned_unseen([view([1])], 0)
    with pytest.raises(InputError, match="unseen_plan_views"):
        NBVConfig(unseen_plan_views=0, unseen_source="carved")
    with pytest.raises(InputError, match="unseen_plan_views"):
        NBVConfig(unseen_plan_views=2)  # the map source has no cells
    with pytest.raises(InputError, match="unseen_plan_views"):
        NBVConfig(unseen_plan_views=2, unseen_source="carved", unseen_measure="area")
    assert NBVConfig(unseen_plan_views=3, unseen_source="carved").unseen_plan_views == 3


def test_unseen_cells_from_pixels_sums_each_pixels_weight_per_cell() -> None:
    """With a weight per pixel (``unseen_measure="rays"``: its stretch in cells) a cell's share is its pixels' summed
    weight over the counted pixels, and the view's U their sum over the counted pixels; a weight of 1 everywhere is the
    pixel count."""
    cell = np.array([[5, 5, -1], [7, 5, 9]])
    counted = np.array([[True, True, True], [True, True, False]])
    weight = np.array([[2.0, 3.0, 40.0], [1.5, 4.0, 8.0]])
    v = UnseenCells.from_pixels(cell, counted, weight)
    assert v.cells.tolist() == [5, 7]
    assert v.share == pytest.approx([9.0 / 5, 1.5 / 5])
    assert v.fraction == pytest.approx(10.5 / 5)
    ones = UnseenCells.from_pixels(cell, counted, np.ones(cell.shape))
    assert ones.share == pytest.approx(UnseenCells.from_pixels(cell, counted).share)
    with pytest.raises(InputError, match="weight"):
        UnseenCells.from_pixels(cell, counted, weight[:, :2])


def test_rarity_lets_a_pocket_only_one_view_sees_outweigh_a_larger_one_every_view_sees() -> None:
    """Four views look into a pocket of cells 1-3 (0.3 of their pixels); X also sees cell 9, that no other view
    sees (0.1), Y nothing else. Unweighed (beta 0, as before) Y and X tie at the common pocket's share plus X's own;
    with beta 1 the common pocket weighs a quarter, so X, the one view of cell 9, ranks first by far; beta 0.5 lies
    between. Blocks group cells: with cells 1-3 and 9 in one block every view counts in it."""
    common = [1, 2, 3]
    views = [view([*common, 9]), view(common), view(common), view(common)]
    assert planned_unseen(rarity_weighted(views, 0.0), 1) == pytest.approx([0.4, 0.3, 0.3, 0.3])
    weighted = planned_unseen(rarity_weighted(views, 1.0), 1)
    assert weighted == pytest.approx([0.3 / 4 + 0.1, 0.3 / 4, 0.3 / 4, 0.3 / 4])
    assert weighted[0] > 2 * weighted[1]
    half = planned_unseen(rarity_weighted(views, 0.5), 1)
    assert half == pytest.approx([0.3 / 2 + 0.1, 0.3 / 2, 0.3 / 2, 0.3 / 2])
    one_block = planned_unseen(rarity_weighted(views, 1.0, lambda c: np.zeros_like(c)), 1)
    assert one_block == pytest.approx([0.4 / 4, 0.3 / 4, 0.3 / 4, 0.3 / 4])
    assert rarity_weighted([], 1.0) == []
    for bad in (-1.0, float("nan")):
        with pytest.raises(InputError, match="unseen_rarity"):
            rarity_weighted(views, bad)


def test_rarity_counts_views_not_cells_and_matches_a_plain_reference_on_random_views() -> None:
    """n of a block is the number of views with any cell in it (a view entering it at several cells counts once);
    checked against a dict-and-loop reference on random views and blocks."""
    rng = np.random.default_rng(48)
    for trial in range(20):
        views = []
        for _ in range(int(rng.integers(1, 10))):
            cells = np.unique(rng.integers(0, 80, size=int(rng.integers(0, 20))))
            views.append(UnseenCells(cells.astype(np.int64), rng.random(len(cells))))
        size = int(rng.integers(1, 6))
        beta = float(rng.choice([0.5, 1.0, 2.0]))
        got = rarity_weighted(views, beta, lambda c, size=size: c // size)
        n: dict[int, int] = {}
        for v in views:
            for b in {int(c) // size for c in v.cells}:
                n[b] = n.get(b, 0) + 1
        for v, g in zip(views, got, strict=True):
            want = [s / n[int(c) // size] ** beta for c, s in zip(v.cells, v.share, strict=True)]
            assert g.cells.tolist() == v.cells.tolist()
            assert g.share == pytest.approx(want, rel=1e-12), trial


def test_bad_rarity_settings_name_the_field() -> None:
    """``unseen_rarity`` weighs the carved grid's entry cells: it needs the carved source, the pixel or ray measure
    and no minimum stretch; its block is a positive size."""
    for bad in (
        {"unseen_rarity": 1.0},
        {"unseen_rarity": 1.0, "unseen_source": "carved", "unseen_measure": "area"},
        {"unseen_rarity": 1.0, "unseen_source": "carved", "unseen_measure": "cells"},
        {"unseen_rarity": 1.0, "unseen_source": "carved", "unseen_min_stretch_m": 0.2},
        {"unseen_rarity": -0.5, "unseen_source": "carved"},
    ):
        with pytest.raises(InputError, match="unseen_rarity"):
            NBVConfig(**bad)
    with pytest.raises(InputError, match="unseen_rarity_block_m"):
        NBVConfig(unseen_rarity_block_m=0.0)
    cfg = NBVConfig(unseen_rarity=0.5, unseen_source="carved", unseen_measure="rays", unseen_plan_views=1)
    assert (cfg.unseen_rarity, cfg.unseen_rarity_block_m) == (0.5, 0.1)
