"""What the candidates' unseen cells say together: the unseen term planned over a few views
(``NBVConfig.unseen_plan_views``), and weighed by how few candidates look into each part of the unseen space
(``NBVConfig.unseen_rarity``), rather than each candidate alone.

The pool's greedy pick takes each view for what it adds on its own; the hindsight study ("Where the remaining misses
stand against views chosen with hindsight" in docs/measured-figures.md) found that on the first synthetic room even a
greedy pick that knows the true coverage misses the target, and the same pick with a few views swapped meets it. Here
the carved grid stands in for the truth: a candidate's unseen pixels are grouped by the frontier cell where their ray
enters unknown space. The plan makes U(x) the share of pixels x and the ``k - 1`` views a greedy completion adds after
it would show, each cell counted once (by the first view of the plan that enters it); with ``k = 1`` it is x's own
unseen pixel fraction. The rarity weight divides each cell's share by the number of candidates that enter its block,
to a power: the frequency weighting of greedy set cover, where an element few sets cover weighs more, since one of
those few must be taken for it. A greedy max-coverage over a handful of views needs no library; scipy's sparse
product does the sums, numpy's unique the counts.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import sparse

from roigsf_ros.core.errors import InputError


@dataclass(frozen=True)
class UnseenCells:
    """One view's unseen pixels grouped by the carved cell where their unknown stretch begins."""

    cells: np.ndarray
    """[C] int64 distinct flat cell indices (into the carved grid's state)."""
    share: np.ndarray
    """[C] the pixels entering at each cell (each weighed as ``from_pixels`` says) over the view's counted pixels
    (those whose ray meets the box)."""

    @classmethod
    def from_pixels(cls, cell: np.ndarray, counted: np.ndarray, weight: np.ndarray | None = None) -> UnseenCells:
        """From ``cell`` [H, W] (the entry cell of each pixel's unseen stretch, -1 where the ray meets observed surface
        through observed space), ``counted`` [H, W] bool (the pixels U counts: those whose ray meets the box) and
        ``weight`` [H, W] (what each unseen pixel weighs: its stretch in cells for ``unseen_measure="rays"``; None: 1,
        the pixel fraction).
        """
        cell = np.asarray(cell)
        counted = np.asarray(counted, dtype=bool)
        if cell.shape != counted.shape:
            raise InputError("cell", f"expected the shape of the counted mask {counted.shape}, got {cell.shape}")
        keep = (cell >= 0) & counted
        if weight is not None:
            weight = np.asarray(weight, dtype=np.float64)
            if weight.shape != cell.shape:
                raise InputError("weight", f"expected the shape of the cell map {cell.shape}, got {weight.shape}")
        cells, inverse = np.unique(cell[keep], return_inverse=True)
        summed = np.bincount(inverse, weights=None if weight is None else weight[keep], minlength=len(cells))
        return cls(cells.astype(np.int64), summed / max(int(counted.sum()), 1))

    @property
    def fraction(self) -> float:
        """The view's own U: its unseen pixel fraction (``unseen_measure="pixels"``), or the weighed sum over its
        counted pixels.
        """
        return float(self.share.sum())


def rarity_weighted(
    views: Sequence[UnseenCells], beta: float, block_of: Callable[[np.ndarray], np.ndarray] | None = None
) -> list[UnseenCells]:
    """``views`` with each cell's share divided by n^``beta``, n the number of views with a cell in the same block
    (``block_of`` maps [C] cells to [C] block ids; None: each cell its own block); ``beta`` 0: unchanged. Unseen space
    that every candidate looks into then weighs little, space only one looks into its full share.
    """
    if not (np.isfinite(beta) and beta >= 0):
        raise InputError("unseen_rarity", f"must be a finite number >= 0, got {beta!r}")
    if beta == 0 or not views:
        return list(views)
    blocks = [np.asarray(block_of(v.cells) if block_of is not None else v.cells, dtype=np.int64) for v in views]
    keys, n = np.unique(np.concatenate([np.unique(b) for b in blocks]), return_counts=True)
    return [
        UnseenCells(v.cells, v.share * n[np.searchsorted(keys, b)].astype(np.float64) ** -float(beta))
        for v, b in zip(views, blocks, strict=True)
    ]


def planned_unseen(views: Sequence[UnseenCells], k: int, between_views: Callable[[], None] | None = None) -> np.ndarray:
    """[M] for each view x: the summed share of the cells that x and the ``k - 1`` views a greedy completion adds
    after it enter (each step the view adding the most share through cells not yet entered; ties to the lower index;
    the completion stops early when no view adds any). ``k = 1``: each view's own fraction. The work grows as
    M^2 (k - 1); ``between_views`` is called before each view's completion (a scorer's stop check raises there).
    """
    if int(k) != k or k < 1:
        raise InputError("unseen_plan_views", f"must be a positive integer, got {k!r}")
    m = len(views)
    own = np.array([v.fraction for v in views], dtype=np.float64)
    if k == 1 or m < 2:
        return own
    all_cells = np.concatenate([v.cells for v in views])
    keys, col = np.unique(all_cells, return_inverse=True)
    row = np.repeat(np.arange(m), [len(v.cells) for v in views])
    share = sparse.csr_matrix(
        (np.concatenate([v.share for v in views]), (row, col)), shape=(m, len(keys)), dtype=np.float64
    )
    out = own.copy()
    for x in range(m):
        if between_views is not None:
            between_views()
        open_cells = np.ones(len(keys))
        open_cells[share.indices[share.indptr[x] : share.indptr[x + 1]]] = 0.0
        used = np.zeros(m, dtype=bool)
        used[x] = True
        for _ in range(int(k) - 1):
            gain = share @ open_cells
            gain[used] = -np.inf
            y = int(np.argmax(gain))
            if not gain[y] > 0.0:
                break
            out[x] += gain[y]
            used[y] = True
            open_cells[share.indices[share.indptr[y] : share.indptr[y + 1]]] = 0.0
    return out


__all__ = ["UnseenCells", "planned_unseen", "rarity_weighted"]
