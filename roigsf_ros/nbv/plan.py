"""The unseen term planned over a few views (``NBVConfig.unseen_plan_views``): what a candidate and the best others
would show together, not the candidate alone.

The pool's greedy pick takes each view for what it adds on its own; the hindsight study ("Where the remaining misses
stand against views chosen with hindsight" in docs/measured-figures.md) found that on the first synthetic room even a
greedy pick that knows the true coverage misses the target, and the same pick with a few views swapped meets it. Here
the carved grid stands in for the truth: a candidate's unseen pixels are grouped by the frontier cell where their ray
enters unknown space, and U(x) becomes the share of pixels x and the ``k - 1`` views a greedy completion adds after it
would show, each cell counted once (by the first view of the plan that enters it). With ``k = 1`` it is x's own unseen
pixel fraction. A greedy max-coverage over a handful of views needs no library; scipy's sparse product does the sums.
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
    """[C] the fraction of the view's counted pixels (those whose ray meets the box) entering at each cell."""

    @classmethod
    def from_pixels(cls, cell: np.ndarray, counted: np.ndarray) -> UnseenCells:
        """From ``cell`` [H, W] (the entry cell of each pixel's unseen stretch, -1 where the ray meets observed surface
        through observed space) and ``counted`` [H, W] bool (the pixels U counts: those whose ray meets the box).
        """
        cell = np.asarray(cell)
        counted = np.asarray(counted, dtype=bool)
        if cell.shape != counted.shape:
            raise InputError("cell", f"expected the shape of the counted mask {counted.shape}, got {cell.shape}")
        cells, n = np.unique(cell[(cell >= 0) & counted], return_counts=True)
        return cls(cells.astype(np.int64), n / max(int(counted.sum()), 1))

    @property
    def fraction(self) -> float:
        """The view's own unseen pixel fraction (``unseen_measure="pixels"``)."""
        return float(self.share.sum())


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


__all__ = ["UnseenCells", "planned_unseen"]
