"""The one numba set-up of every compiled CPU kernel (rasteriser, Fisher, NBV ROI visibility).

Kernels are written as plain Python (``for i in prange(n)`` for the parallel loops) and compiled by
:class:`Kernels` on first use, cached on disk. The threading layer is chosen here, before anything
starts numba's pool; every launch holds :data:`KERNEL_LOCK` (the workqueue layer is not re-entrant).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

KERNEL_LOCK = threading.Lock()
"""Held around every numba kernel launch (numba's workqueue threading layer is not re-entrant)."""


def prange(n: int) -> range:
    """Stand-in for ``numba.prange`` in kernel source; :class:`Kernels` swaps in the real one before compiling."""
    return range(n)


def numba_available() -> bool:
    """Whether the numba CPU backend can be used (numba importable)."""
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def use_numba(backend: str, t: Tensor) -> bool:
    """Whether ``backend`` ("auto", "numba" or "torch") runs the numba kernels for tensors like ``t``."""
    if backend not in ("auto", "numba", "torch"):
        raise ValueError(f"backend must be 'auto', 'numba' or 'torch', got {backend!r}")
    if backend == "torch":
        return False
    ok = t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) and numba_available()
    if backend == "numba" and not ok:
        raise ValueError("backend 'numba' needs numba installed and float32/float64 CPU tensors")
    return ok


def configure_numba() -> Any:
    """Pick numba's threading layer before anything starts it (see the comment inside); returns numba."""
    import numba

    if "NUMBA_THREADING_LAYER" not in os.environ:
        # The workqueue layer's threads sleep between kernels; OpenMP's spin-wait next to torch's
        # own OpenMP pool made runs up to 10x slower on 2 cores. Workqueue is not re-entrant, so
        # every kernel launch holds KERNEL_LOCK (concurrent renders take turns).
        numba.config.THREADING_LAYER_PRIORITY = ["workqueue", "omp", "tbb"]
    return numba


def set_numba_threads(n: int) -> int:
    """Use ``n`` threads (at most numba's maximum) in the numba kernels; returns the number set."""
    numba = configure_numba()
    n = max(1, min(int(n), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(n)
    return n


def n_threads() -> int:
    """Threads the parallel kernels use now."""
    import numba

    return int(numba.get_num_threads())


def balanced_bounds(cost: Tensor, parts: int) -> np.ndarray:
    """Split ``range(len(cost))`` into ``parts`` contiguous blocks of about equal total cost."""
    cum = torch.cumsum(cost.double(), 0)
    total = float(cum[-1]) if cost.numel() else 0.0
    cuts = torch.searchsorted(cum, torch.linspace(0, total, parts + 1, dtype=torch.float64)[1:-1])
    return np.concatenate([[0], cuts.numpy(), [cost.numel()]]).astype(np.int64)


class Kernels:
    """numba-compiled versions of plain-Python kernels, all compiled on the first lookup (cached on disk).

    ``helpers``: plain-Python functions the kernels call; each is compiled first (inlined into its
    callers at numba's IR level, so a call inside a loop does not stop LLVM from vectorising it) and
    put in place of the Python function in the calling kernel's module.
    """

    def __init__(
        self,
        parallel: bool = True,
        fastmath: bool | set[str] = False,
        helpers: tuple[Callable, ...] = (),
        **kernels: Callable,
    ) -> None:
        self._source = kernels
        self._helpers = helpers
        self._options: dict[str, Any] = {"cache": True, "nogil": True, "fastmath": fastmath}
        if parallel:
            self._options["parallel"] = True
        self._compiled: dict[str, Callable] = {}

    def __getitem__(self, name: str) -> Callable:
        if not self._compiled:
            numba = configure_numba()
            for h in self._helpers:
                h = getattr(h, "py_func", h)  # a helper another Kernels has compiled (and swapped in) already
                jitted = numba.njit(
                    cache=self._options["cache"], nogil=True, inline="always", fastmath=self._options["fastmath"]
                )(h)
                for fn in self._source.values():
                    if h.__name__ in fn.__code__.co_names:
                        fn.__globals__[h.__name__] = jitted
            for fn in self._source.values():
                if "prange" in fn.__code__.co_names:
                    fn.__globals__["prange"] = numba.prange
            self._compiled = {k: numba.njit(**self._options)(fn) for k, fn in self._source.items()}
        return self._compiled[name]


__all__ = [
    "KERNEL_LOCK",
    "Kernels",
    "balanced_bounds",
    "configure_numba",
    "n_threads",
    "numba_available",
    "prange",
    "set_numba_threads",
    "use_numba",
]
