"""The one numba set-up of every compiled CPU kernel (rasteriser, Fisher, NBV ROI visibility).

Kernels are written as plain Python (``for i in prange(n)`` for the parallel loops, the only ones run in
parallel) and compiled by :class:`Kernels` on first use, cached on disk (a stamp drops a stale cache). The
threading layer is chosen here, before anything starts numba's pool; every launch holds :data:`KERNEL_LOCK`
(the workqueue layer is not re-entrant); :func:`pin_workers` pins the workers one per CPU where they use every
CPU (benchmarks; ``ROIGSF_PIN_THREADS=1``).
"""

from __future__ import annotations

import ctypes
import hashlib
import inspect
import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

KERNEL_LOCK = threading.RLock()
"""Held around every numba kernel launch (numba's workqueue threading layer is not re-entrant); re-entrant itself
because the first kernel lookup, made under it, may launch :func:`pin_workers`' probe."""


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


PIN_ENV = "ROIGSF_PIN_THREADS"
"""Environment variable: ``1`` pins numba's workers at the first kernel, ``0`` never (see :func:`pin_workers`)."""
_PINNED: dict[int, int] = {}  # worker thread id -> the CPU it is pinned to
_PROBE: dict[str, Callable | None] = {}
_AUTO_PINNED: list[bool] = []  # non-empty once the first parallel Kernels has pinned the workers


def _thread_probe() -> Callable[[np.ndarray], None] | None:
    """A parallel kernel writing into each slot the OS id of the thread that ran it (None: no ``gettid``)."""
    if "probe" not in _PROBE:
        _PROBE["probe"] = None
        try:
            gettid = ctypes.CDLL(None).gettid
        except (AttributeError, OSError):
            return None
        gettid.restype, gettid.argtypes = ctypes.c_int, []
        numba = configure_numba()

        @numba.njit(parallel=True, nogil=True)  # not cached on disk: the ctypes function's address is in the code
        def probe(out: np.ndarray) -> None:
            for i in numba.prange(out.shape[0]):
                out[i] = gettid()

        _PROBE["probe"] = probe
    return _PROBE["probe"]


def worker_ids() -> list[int]:
    """OS thread ids of numba's active workers (starts numba's pool); empty where they cannot be read."""
    probe = _thread_probe()
    if probe is None:
        return []
    import numba

    out = np.zeros(numba.get_num_threads() * 8, np.int64)
    with KERNEL_LOCK:
        probe(out)
    return sorted(set(out.tolist()))


def pin_workers() -> dict[int, int]:
    """Pin each of numba's active workers to its own CPU when they are as many as the CPUs this process may use.

    Why: on 2 cores the scheduler at times woke both workers of a kernel on the same core and left them there for
    hundreds of milliseconds, so kernels ran in two modes (``scripts/measure_numba_threads.py``). One worker per
    core removes the slow mode, which is what a benchmark wants (``roigsf perf`` calls this). But beside another
    busy process a pinned worker cannot move off its shared core (training steps 13 % slower, measured), so
    the library pins only when asked: here, or with ``ROIGSF_PIN_THREADS=1`` at the first kernel (a robot whose
    cores are the mapper's); ``ROIGSF_PIN_THREADS=0`` makes this a no-op. With fewer workers than CPUs nothing
    is pinned (several such processes would crowd the first CPUs); other threads (the caller's, torch's) never
    are. Returns ``{thread id: CPU}`` of the pinned workers (empty: none).
    """
    _PINNED.clear()
    if os.environ.get(PIN_ENV) == "0" or not hasattr(os, "sched_getaffinity"):
        return {}
    numba = configure_numba()  # before get_num_threads, which starts the pool
    cpus = sorted(os.sched_getaffinity(0))
    if numba.get_num_threads() != len(cpus) or len(cpus) < 2:
        return {}
    tids = worker_ids()
    if len(tids) < 2 or len(tids) != len(cpus):
        return {}
    for tid, cpu in zip(tids, cpus, strict=True):
        try:
            os.sched_setaffinity(tid, {cpu})
        except OSError:  # the thread ended, or the container forbids it: leave the scheduler in charge
            continue
        _PINNED[tid] = cpu
    return dict(_PINNED)


def pinned_workers() -> dict[int, int]:
    """``{thread id: CPU}`` of the workers :func:`pin_workers` pinned last (empty: none)."""
    return dict(_PINNED)


def n_threads() -> int:
    """Threads the parallel kernels use now."""
    import numba

    return int(numba.get_num_threads())


def balanced_bounds(cost: Tensor | np.ndarray, parts: int) -> np.ndarray:
    """Split ``range(len(cost))`` into ``parts`` contiguous blocks of about equal total cost (a tensor or a numpy
    array, split by torch or numpy: the per-view numpy callers make no torch call).
    """
    if isinstance(cost, np.ndarray):
        cum_np = np.cumsum(cost.astype(np.float64))
        total_np = float(cum_np[-1]) if cost.size else 0.0
        cuts_np = np.searchsorted(cum_np, np.linspace(0.0, total_np, parts + 1)[1:-1])
        return np.concatenate([[0], cuts_np, [cost.size]]).astype(np.int64)
    cum = torch.cumsum(cost.double(), 0)
    total = float(cum[-1]) if cost.numel() else 0.0
    cuts = torch.searchsorted(cum, torch.linspace(0, total, parts + 1, dtype=torch.float64)[1:-1])
    return np.concatenate([[0], cuts.numpy(), [cost.numel()]]).astype(np.int64)


STAMP_SUFFIX = ".roigsf-stamp"
"""A kernel's stamp file in its module's ``__pycache__`` (``MODULE.KERNEL.roigsf-stamp``), written by
:class:`Kernels` beside numba's own cache files (``MODULE.KERNEL-LINE.pyXY.nbi`` and ``.nbc``)."""


def _copy_file(src: Path, dst: Path) -> None:
    """Copy ``src`` to ``dst`` by way of a temporary name, so a reader never sees half a file."""
    tmp = dst.with_name(f"{dst.name}.seed.{os.getpid()}")
    try:
        tmp.write_bytes(src.read_bytes())
        tmp.replace(dst)
    finally:
        tmp.unlink(missing_ok=True)


def seed_kernel_cache(src_package: Path, dst_package: Path) -> list[str]:
    """Copy the kernels' disk cache from one copy of roigsf_ros to another; the kernels seeded
    (``"render/fisher._k_fisher"``). ``src_package``, ``dst_package``: the two ``roigsf_ros`` folders.

    Why: numba stamps a cache with the hash of its module's source and names it by module, function and line, not
    by path, so code compiled for one copy (set-up's installed one) loads in the other (the checkout the tests
    import) instead of being compiled a second time, 80-160 s on 2 cores. A kernel is seeded when its module's
    source is byte-identical in both copies and the destination has no cache of the same stamp (:data:`STAMP_SUFFIX`):
    a current cache there is kept (it may hold signatures the source lacks). The kernel's old files go first and its
    stamp is written last, so a seeding cut short reads as stale. Best effort: what cannot be read or written is
    skipped, and that kernel compiles as before. The in-tree caches only (``__pycache__``, numba's default; not a
    ``NUMBA_CACHE_DIR``).
    """
    src_root, dst_root = Path(src_package).resolve(), Path(dst_package).resolve()
    if src_root == dst_root:
        return []
    seeded: list[str] = []
    for stamp in sorted(src_root.rglob(f"__pycache__/*{STAMP_SUFFIX}")):
        prefix = stamp.name.removesuffix(STAMP_SUFFIX)  # MODULE.KERNEL
        rel = stamp.parent.parent.relative_to(src_root)
        src_cache, dst_cache = stamp.parent, dst_root / rel / "__pycache__"
        module = f"{prefix.split('.', 1)[0]}.py"
        dst_stamp = dst_cache / stamp.name
        files = sorted(src_cache.glob(f"{prefix}-*.nb[ic]"))
        if not any(f.suffix == ".nbi" for f in files):  # stamped but not compiled there (or into a NUMBA_CACHE_DIR)
            continue
        try:
            if (src_root / rel / module).read_bytes() != (dst_root / rel / module).read_bytes():
                continue
            current = dst_stamp.is_file() and dst_stamp.read_bytes() == stamp.read_bytes()
            if current and any(dst_cache.glob(f"{prefix}-*.nbi")):
                continue
            dst_cache.mkdir(exist_ok=True)
            dst_stamp.unlink(missing_ok=True)
            for old in dst_cache.glob(f"{prefix}-*.nb[ic]"):
                old.unlink()
            for f in files:
                _copy_file(f, dst_cache / f.name)
            _copy_file(stamp, dst_stamp)
        except OSError:
            continue
        seeded.append(f"{rel.as_posix()}/{prefix}")
    return seeded


_AUTO_PARALLEL = ("comprehension", "reduction", "inplace_binop", "setitem", "numpy", "stencil")
"""numba's automatic parallelisation passes, all off: only the kernels' explicit ``prange`` loops run in parallel."""


class Kernels:
    """numba-compiled versions of plain-Python kernels, all compiled on the first lookup (cached on disk).

    ``helpers``: plain-Python functions the kernels call; each is compiled first (inlined into its
    callers at numba's IR level, so a call inside a loop does not stop LLVM from vectorising it) and
    put in place of the Python function in the calling kernel's module. ``error_model="numpy"``: a float
    division by zero gives inf or nan as in numpy instead of raising; numba's default ("python") tests every
    divisor, and that branch keeps a loop with a division by a loaded value from vectorising.
    """

    def __init__(
        self,
        parallel: bool = True,
        fastmath: bool | set[str] = False,
        helpers: tuple[Callable, ...] = (),
        error_model: str = "python",
        **kernels: Callable,
    ) -> None:
        self._source = kernels
        self._helpers = helpers
        self._options: dict[str, Any] = {"cache": True, "nogil": True, "fastmath": fastmath, "error_model": error_model}
        self._parallel = parallel
        self._compiled: dict[str, Callable] = {}

    def _parallel_option(self) -> dict[str, Any]:
        """The ``parallel`` option for numba: the ``prange`` loops only (a fresh dict: numba empties the one it gets).

        With numba's default every array expression of a parallel kernel (``np.zeros``, ``.max()``, a helper's
        ``np.arange``) became a parallel loop of its own, each waking the thread pool: the binning kernel of a
        160x120 view took 2.5x as long, with the same result (``scripts/measure_numba_threads.py``).
        """
        return {"parallel": dict.fromkeys(_AUTO_PARALLEL, False)} if self._parallel else {}

    def stamp(self) -> str:
        """SHA-256 of how these kernels are compiled: the options and the sources of this module, the kernels' and
        the helpers' modules (the same in every process: no hash-seeded ordering).
        """
        fns = [getattr(f, "py_func", f) for f in (*self._source.values(), *self._helpers)]
        options = {**self._options, **self._parallel_option()}
        fastmath = options["fastmath"]  # a set: its repr's order changes with each process's hash seed
        options["fastmath"] = sorted(fastmath) if isinstance(fastmath, set) else fastmath
        h = hashlib.sha256(repr(sorted(options.items())).encode())
        for f in sorted({inspect.getsourcefile(f) or "" for f in fns} | {__file__}):
            h.update(Path(f).read_bytes() if f and Path(f).is_file() else f.encode())
        return h.hexdigest()

    def _drop_stale_cache(self) -> None:
        """Delete numba's cached code of these kernels when how they are compiled has changed.

        numba keys a kernel's disk cache on its own source file alone: not on the options set here (this
        module) nor on helpers from other modules (``vecmath.exp_neg`` in the rasteriser and the Fisher kernel), so a
        change there would load old machine code. A stamp of those sources and the options, kept beside the
        cache per kernel, says when to drop it. Best effort: a read-only ``__pycache__`` is left alone.
        """
        stamp = self.stamp()
        for fn in self._source.values():
            src = inspect.getsourcefile(fn)
            if not src:
                continue
            cache, prefix = Path(src).parent / "__pycache__", f"{Path(src).stem}.{fn.__qualname__}"
            marker = cache / f"{prefix}{STAMP_SUFFIX}"
            try:
                if marker.is_file() and marker.read_text() == stamp:
                    continue
                for old in cache.glob(f"{prefix}-*.nb[ic]"):
                    old.unlink(missing_ok=True)
                cache.mkdir(exist_ok=True)
                tmp = cache / f"{prefix}{STAMP_SUFFIX}.{os.getpid()}"
                tmp.write_text(stamp)
                tmp.replace(marker)
            except OSError:
                continue

    def __getitem__(self, name: str) -> Callable:
        if not self._compiled:
            numba = configure_numba()
            self._drop_stale_cache()
            for h in self._helpers:
                h = getattr(h, "py_func", h)  # a helper another Kernels has compiled (and swapped in) already
                jitted = numba.njit(
                    cache=self._options["cache"],
                    nogil=True,
                    inline="always",
                    fastmath=self._options["fastmath"],
                    error_model=self._options["error_model"],
                )(h)
                for fn in (*self._source.values(), *self._helpers):  # helpers may call helpers
                    fn = getattr(fn, "py_func", fn)
                    if h.__name__ in fn.__code__.co_names:
                        fn.__globals__[h.__name__] = jitted
            for fn in self._source.values():
                if "prange" in fn.__code__.co_names:
                    fn.__globals__["prange"] = numba.prange
            self._compiled = {k: numba.njit(**self._options, **self._parallel_option())(fn)
                              for k, fn in self._source.items()}  # fmt: skip
            if self._parallel and not _AUTO_PINNED and os.environ.get(PIN_ENV) == "1":
                _AUTO_PINNED.append(True)  # once per process, before its first parallel kernel
                pin_workers()
        return self._compiled[name]

    def names(self) -> tuple[str, ...]:
        """The kernels' names (the keyword names given to the constructor)."""
        return tuple(self._source)

    def dispatchers(self) -> dict[str, Any]:
        """The numba dispatchers made so far, by kernel name (empty before the first lookup); each dispatcher's
        ``signatures`` are the argument types it has compiled or loaded from the disk cache in this process.
        """
        return dict(self._compiled)


__all__ = [
    "KERNEL_LOCK",
    "PIN_ENV",
    "STAMP_SUFFIX",
    "Kernels",
    "balanced_bounds",
    "configure_numba",
    "n_threads",
    "numba_available",
    "pin_workers",
    "pinned_workers",
    "prange",
    "seed_kernel_cache",
    "set_numba_threads",
    "use_numba",
    "worker_ids",
]
