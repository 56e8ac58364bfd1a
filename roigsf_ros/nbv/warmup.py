"""Compile (or load from numba's disk cache) every CPU kernel mapping and NBV scoring use, on a tiny scene.

The numba kernels (rasteriser forward/backward, Fisher, ROI visibility) compile on their first call,
30-60 s on 2 cores with a cold cache: on a fresh machine the planner's first requests then took that
long and the keyframe selector decided most of the demo's first windows with its fallback.
:func:`warm_up_kernels` makes those first calls on a 32x24 textured wall (one keyframe, a few optimiser
steps, a scoring TSDF, two candidates scored in each Fisher mode and one alone, and once with the recommended unseen
term, :data:`~roigsf_ros.nbv.config.RECOMMENDED_UNSEEN`, whose carved grid has kernels of its own; the uncertainty
image), with the same argument types as the real calls, so the real work starts compiled. With a warm cache it takes
about a second (the cached machine code is loaded). ``python -m roigsf_ros.nbv.warmup`` runs it (set-up does).

Cold, that is one process on one core (151 s on a 2-core AMD EPYC). ``--jobs N`` first compiles the kernels on N
processes from :data:`SIGNATURES_PATH`, the argument types the warm-up's own calls compile (checked by a test against
a real warm-up; rewritten by ``scripts/kernel_compile_times.py --write-signatures``), and then runs the warm-up, which
loads them from the disk cache and compiles whatever the list missed: a stale list costs time, never a wrong kernel.
``--seed-from DIR`` first copies another copy's compiled kernels
(:func:`~roigsf_ros.render.numba_setup.seed_kernel_cache`): set-up compiles the installed copy once and seeds the
checkout the tests import with it.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.frame import Frame
from roigsf_ros.mapping.mapper import Mapper, MapperConfig
from roigsf_ros.nbv.config import RECOMMENDED_UNSEEN, NBVConfig
from roigsf_ros.nbv.scorer import NBVScorer
from roigsf_ros.nbv.state import ScoringState
from roigsf_ros.render.numba_setup import Kernels, seed_kernel_cache

WARMUP_INTRINSICS = Intrinsics(width=32, height=24, fx=24.0, fy=24.0, cx=15.5, cy=11.5)
"""The warm-up camera: small enough that, compiled, the whole pass takes well under a second."""

_ONCE = threading.Lock()
_WARMED: set[str] = set()
"""The phases this process has warmed up (``mapping``, ``scoring``): :func:`warm_up_once` runs each once."""


def _wall_frame(index: int, x_m: float) -> Frame:
    """A seeded random texture on a wall 1.5 m in front of a camera at (x_m, 0, 0) looking along +z."""
    rng = np.random.default_rng(index)
    h, w = WARMUP_INTRINSICS.height, WARMUP_INTRINSICS.width
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    T = np.eye(4)
    T[0, 3] = x_m
    return Frame(index=index, rgb=rgb, depth_m=np.full((h, w), 1.5, np.float32), T_wc=T)


def warm_up_mapping() -> tuple[Mapper, float]:
    """Map two keyframes of the tiny wall (densify, forward + backward, prune, the keyframes' Fisher): the mapping
    kernels compiled or loaded; the mapper and the seconds it took.

    The mapper node runs this alone at start-up: a process's first 640x480 keyframe took 1.1 s against 0.5 s for
    the next (the kernels loading from the disk cache), and in three processes the planner's first map came late.
    """
    t0 = time.perf_counter()
    mapper = Mapper(WARMUP_INTRINSICS, MapperConfig(iters_per_keyframe=2))
    for frame in (_wall_frame(1, 0.0), _wall_frame(2, 0.1)):
        mapper.add_keyframe(frame)
    mapper.h_train  # noqa: B018 - the keyframes' Fisher (the geometric kernels)
    return mapper, time.perf_counter() - t0


def warm_up_kernels(nbv: NBVConfig | None = None) -> dict[str, float]:
    """Run mapping and NBV scoring once on a tiny scene so every numba kernel is compiled; seconds per phase.

    ``nbv``: the scoring settings to warm up with (default ``NBVConfig()``); both Fisher modes
    (ROI-weighted and FisherRF's) are scored whatever its mode.
    """
    nbv = nbv or NBVConfig()
    times: dict[str, float] = {}
    mapper, times["mapping_s"] = warm_up_mapping()
    h_train = mapper.h_train

    t0 = time.perf_counter()
    frames = [_wall_frame(1, 0.0), _wall_frame(2, 0.1)]
    poses = np.stack([f.T_wc for f in frames])
    state = ScoringState(nbv, 0.02, 0.08, 10.0, cache_h_train=True)
    candidates = [_wall_frame(3, 0.05).T_wc, _wall_frame(4, -0.05).T_wc]
    outputs = tuple(mapper.config.fisher_outputs)
    for mode in ("roi-gsurfisher", "fisherrf"):
        state.score(mapper.map, h_train, outputs, poses, candidates, WARMUP_INTRINSICS, mapper.rendered_rgbd, mode)
    # A lone candidate: with fewer candidates than threads the ROI splits one camera's voxels (its own kernel).
    state.score(
        mapper.map, h_train, outputs, poses, candidates[:1], WARMUP_INTRINSICS, mapper.rendered_rgbd, "roi-gsurfisher"
    )
    # The recommended variant's unseen term, whatever ``nbv`` says: its carved grid's carve and ray-march kernels.
    carved = ScoringState(NBVConfig(**RECOMMENDED_UNSEEN), 0.02, 0.08, 10.0)
    carved.score(mapper.map, h_train, outputs, poses, candidates, WARMUP_INTRINSICS, mapper.rendered_rgbd)
    NBVScorer(nbv).uncertainty(mapper.map, h_train, candidates[0], WARMUP_INTRINSICS, None)
    times["scoring_s"] = time.perf_counter() - t0
    times["total_s"] = times["mapping_s"] + times["scoring_s"]
    return times


def warm_up_once(nbv: NBVConfig | None = None, scoring: bool = True) -> dict[str, float] | None:
    """:func:`warm_up_kernels` the first time a process calls it (its timings); None afterwards (already warm).

    ``scoring`` False: :func:`warm_up_mapping` alone (the mapper node), unless this process warmed mapping up already
    (an in-process planner's warm-up did both); timings ``mapping_s`` and ``total_s``.
    """
    with _ONCE:
        want = {"mapping", "scoring"} if scoring else {"mapping"}
        if want <= _WARMED:
            return None
        if scoring:
            times = warm_up_kernels(nbv)
        else:
            seconds = warm_up_mapping()[1]
            times = {"mapping_s": seconds, "total_s": seconds}
        _WARMED.update(want)
        return times


SIGNATURES_PATH = Path(__file__).with_name("kernel_signatures.json")
"""The kernels :func:`warm_up_kernels` compiles, each with its argument types and cold compile time (package data)."""


def kernel_groups() -> dict[str, Kernels]:
    """Every :class:`Kernels` group of the roigsf_ros modules imported so far, by ``"module:ATTRIBUTE"``."""
    groups: dict[str, Kernels] = {}
    seen: set[int] = set()  # a group imported into another module is listed once, under its first name
    for mod_name, module in sorted(sys.modules.items()):
        if not mod_name.startswith("roigsf_ros.") or module is None:
            continue
        for attr, value in sorted(vars(module).items()):
            if isinstance(value, Kernels) and id(value) not in seen:
                seen.add(id(value))
                groups[f"{mod_name}:{attr}"] = value
    return groups


def compiled_signatures() -> dict[str, list[str]]:
    """The argument types each kernel has compiled or loaded in this process: ``{"module:GROUP.name": [repr, ...]}``.

    The reprs are numba's (``Array(float64, 2, 'C', False, aligned=True)``), which :func:`parse_signature` reads back.
    """
    out: dict[str, list[str]] = {}
    for key, group in kernel_groups().items():
        for name, dispatcher in sorted(group.dispatchers().items()):
            sigs = sorted(repr(tuple(sig)) for sig in dispatcher.signatures)
            if sigs:
                out[f"{key}.{name}"] = sigs
    return out


def parse_signature(text: str) -> tuple[Any, ...]:
    """A signature written by :func:`compiled_signatures` back as a tuple of numba types."""
    from numba.core import types

    namespace = {name: getattr(types, name) for name in dir(types) if not name.startswith("_")}
    value = eval(text, {"__builtins__": {}}, namespace)  # the reprs of numba types: names in numba.core.types only
    if not (isinstance(value, tuple) and all(isinstance(t, types.Type) for t in value)):
        raise ValueError(f"not a signature tuple: {text!r}")
    return value


def load_signature_list(path: Path = SIGNATURES_PATH) -> list[dict[str, Any]]:
    """The rows of the kernel signature list: ``{"kernel": "module:GROUP.name", "compile_s": s, "signatures": [...]}``.

    Raises ValueError naming the file when it is not such a list.
    """
    try:
        rows = json.loads(path.read_text())["kernels"]
        for row in rows:
            if not (isinstance(row["kernel"], str) and ":" in row["kernel"] and isinstance(row["signatures"], list)):
                raise ValueError(f"bad row {row!r}")
            float(row["compile_s"])
    except (OSError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: not a kernel signature list ({exc})") from exc
    return rows


def _dispatcher(kernel: str) -> Any:
    """The numba dispatcher of ``"module:GROUP.name"`` (imports the module; makes the group's dispatchers)."""
    module, _, rest = kernel.partition(":")
    attr, _, name = rest.partition(".")
    group = getattr(importlib.import_module(module), attr, None)
    if not isinstance(group, Kernels) or name not in group.names():
        raise ValueError(
            f"no kernel {kernel!r}: the signature list is stale (scripts/kernel_compile_times.py --write-signatures)"
        )
    return group[name]


def compile_listed(rows: Sequence[dict[str, Any]]) -> int:
    """Compile (or load from the disk cache) each row's kernel for each of its signatures; the number of signatures."""
    n = 0
    for row in rows:
        dispatcher = _dispatcher(row["kernel"])
        for text in row["signatures"]:
            dispatcher.compile(parse_signature(text))
            n += 1
    return n


def split_by_cost(rows: Sequence[dict[str, Any]], parts: int) -> list[list[dict[str, Any]]]:
    """Deal the rows into ``parts`` shares of about equal total ``compile_s`` (longest first, each to the lightest
    share so far; ties by order), dropping empty shares.
    """
    shares: list[list[dict[str, Any]]] = [[] for _ in range(max(1, parts))]
    load = [0.0] * len(shares)
    for row in sorted(rows, key=lambda r: -float(r["compile_s"])):
        i = load.index(min(load))
        shares[i].append(row)
        load[i] += float(row["compile_s"])
    return [share for share in shares if share]


_CHILD = (
    "import sys; sys.path.insert(0, sys.argv[1]); import roigsf_ros.nbv.warmup as w; "
    "sys.exit(w._compile_share(sys.argv[2], sys.argv[3:]))"
)
"""A compiling process: the same copy of roigsf_ros as its parent (installed or checkout) first on the path."""


def _compile_share(path: str, kernels: list[str]) -> int:
    """A child of :func:`compile_in_parallel`: compile the listed kernels named in ``kernels``."""
    rows = [row for row in load_signature_list(Path(path)) if row["kernel"] in kernels]
    compile_listed(rows)
    return 0


def compile_in_parallel(jobs: int, path: Path = SIGNATURES_PATH) -> dict[str, Any]:
    """Compile the listed kernels into numba's disk cache on ``jobs`` processes (this one and ``jobs - 1`` children).

    Each process compiles its share (:func:`split_by_cost`), writing the cache files the next process loads; the
    stale caches are dropped here first, so two processes never drop each other's fresh files. Best effort: a
    missing or stale list or a failed child is reported in the result (``"error"``), and the warm-up that follows
    compiles what is missing. Returns ``{"jobs": processes used, "seconds": wall, "signatures": n, "error": str}``.
    """
    t0 = time.perf_counter()
    try:
        rows = load_signature_list(path)
        for row in rows:  # every group's stale cache dropped, and each dispatcher made, before any child starts
            _dispatcher(row["kernel"])
    except (ValueError, ImportError) as exc:
        return {"jobs": 0, "seconds": time.perf_counter() - t0, "signatures": 0, "error": str(exc)}
    shares = split_by_cost(rows, jobs)
    root = str(Path(__file__).resolve().parents[2])  # the folder holding this copy of roigsf_ros
    children = [
        subprocess.Popen([sys.executable, "-c", _CHILD, root, str(path), *(row["kernel"] for row in share)])
        for share in shares[1:]
    ]
    error = ""
    try:
        try:
            n = compile_listed(shares[0]) if shares else 0
        except Exception as exc:  # any compile failure: the warm-up that follows compiles (and reports) it again
            n, error = 0, f"compiling {[r['kernel'] for r in shares[0]]}: {exc}"
        for child, share in zip(children, shares[1:], strict=True):
            if child.wait() != 0:
                error = error or f"the process compiling {[r['kernel'] for r in share]} exited {child.returncode}"
            else:
                n += sum(len(r["signatures"]) for r in share)
    finally:  # interrupted (Ctrl-C): no compiling child outlives this process
        for child in children:
            if child.poll() is None:
                child.kill()
                child.wait()
    return {"jobs": len(shares), "seconds": time.perf_counter() - t0, "signatures": n, "error": error}


def _cpus() -> int:
    """The CPUs this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def main(argv: list[str] | None = None) -> int:
    """``python -m roigsf_ros.nbv.warmup [--jobs N] [--seed-from DIR]``: warm the kernels up; print how long it took."""
    parser = argparse.ArgumentParser(description="Compile (or load) every numba kernel mapping and NBV scoring use.")
    parser.add_argument(
        "--jobs",
        type=int,
        default=_cpus(),
        help="processes compiling the listed kernels first (default: the CPUs this process may use; 1: no split)",
    )
    parser.add_argument(
        "--seed-from",
        type=Path,
        metavar="DIR",
        help="another copy's roigsf_ros folder (set-up: the installed one): copy its compiled kernels first, for each "
        "module whose source is the same as this copy's, so they load instead of compiling again",
    )
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    extra = ""
    if args.seed_from is not None:
        if not args.seed_from.is_dir():
            parser.error(f"--seed-from: {args.seed_from} is not a folder")
        here = Path(__file__).resolve().parents[1]
        seeded = seed_kernel_cache(args.seed_from, here)
        extra = f"; {len(seeded)} kernels' compiled code copied from {args.seed_from}"
    if args.jobs > 1:
        par = compile_in_parallel(args.jobs)
        extra += f"; first {par['signatures']} listed signatures on {par['jobs']} processes, {par['seconds']:.1f} s"
        if par["error"]:
            print(f"warning: the parallel compile fell short ({par['error']}); the warm-up compiles the rest",
                  file=sys.stderr)  # fmt: skip
    times = warm_up_kernels()
    print(
        f"numba kernels ready in {time.perf_counter() - t0:.1f} s (warm-up: mapping {times['mapping_s']:.1f} s, "
        f"scoring {times['scoring_s']:.1f} s{extra})"
    )
    return 0


__all__ = [
    "SIGNATURES_PATH",
    "WARMUP_INTRINSICS",
    "compile_in_parallel",
    "compile_listed",
    "compiled_signatures",
    "kernel_groups",
    "load_signature_list",
    "parse_signature",
    "split_by_cost",
    "warm_up_kernels",
    "warm_up_mapping",
    "warm_up_once",
]


if __name__ == "__main__":
    sys.exit(main())
