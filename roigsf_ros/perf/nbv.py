"""NBV scoring speed: one candidate's ROI-GSurFisher cost against a training step, and 50-candidate score() calls.

The state: the synthetic room of :mod:`roigsf_ros.perf.render` (``--surfels`` surfels, 20k by
default), a TSDF fused from the map's rendered median depth (alpha >= 0.5) at four training poses in the
middle of the room (voxel 2 cm, truncation 8 cm: the mapper's and the stream policies' defaults), and
``h_train`` (the exact Fisher of those poses, as the Mapper keeps it). Candidates are 50 seeded random
poses inside the room (0.5 m clear of walls and boxes, any yaw, pitch -25..+10 deg), so every one sees
surface; the per-candidate view is :func:`~roigsf_ros.perf.render.room_camera`'s, which is not a
training pose.

Measured in one run, medians over ``--repeats`` after a warm-up, float32 on the CPU with ``--threads``
threads (torch and numba):

- ``train_fwd_bwd``: one training step's render of that view plus the backward pass of a loss over
  colour, depth and alpha (as ``roigsf perf render``'s "fwd+bwd");
- the candidate's scoring cost per phase, as :meth:`~roigsf_ros.nbv.scorer.NBVScorer.score` spends it: ``roi``
  (visibility, Eq. 7 weights, Eq. 8 splat), ``close_front`` (Eq. 14) and ``fisher`` (the ROI-weighted
  exact geometric Fisher and Eq. 10), their sum and its ratio to ``train_fwd_bwd`` (target <= 1, issue 12);
- ``score_50``: the wall time of one ``NBVScorer.score`` call over the 50 candidates with ``h_train``
  given (target <= 1 s at 160x120 with 20k surfels, issue 12), with its phase timings; it builds the TSDF's
  surface voxels and W_f itself;
- ``score_state_s``: the same 50 candidates as one request to the planner node, whose :class:`ScoringState`
  keeps the surface voxels and W_f between requests (its sync timer rebuilds them when a keyframe is fused);

for the modes ``roi-gsurfisher`` and ``fisherrf`` and ``fisher_downsample`` 1 and 2. Then, by keyframe count
(``--keyframes``: the four training poses and seeded room poses after them), one planner request of the same candidates
with the paper's score and with the unseen term of the variant README recommends (``F3``,
:data:`~roigsf_ros.nbv.config.RECOMMENDED_UNSEEN`: carved grid, ray measure; F2, an earlier variant, differs only in
the term's weight, which costs nothing), its grid rendered and carved again at every request (the default) or
kept (``unseen_carve_rerender=false``): ``request_s`` and its ``unseen_s`` phase, and ``sync_one_s``, the
work the planner's sync timer does between requests when one keyframe comes (TSDF fusion, W_f and, kept, one render and
carve). FisherRF's ``h_train`` (colour, every parameter) is computed once outside the timed calls, as a caller that
keeps it would. Environment notes as in ``roigsf perf render`` (``OMP_WAIT_POLICY=PASSIVE`` is set by the package; the
malloc variables make runs steadier).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.mapping.tsdf import TSDFVolume
from roigsf_ros.nbv.config import RECOMMENDED_UNSEEN, NBVConfig
from roigsf_ros.nbv.scorer import NBVScorer
from roigsf_ros.nbv.state import ScoringState
from roigsf_ros.perf import MAX_THREADS, check_options, check_out_file, environment, threads_text, write_results
from roigsf_ros.perf.render import BOXES, ROOM, room_camera, room_scene
from roigsf_ros.render.numba_setup import (
    PIN_ENV,
    numba_available,
    pin_workers,
    pinned_workers,
    set_numba_threads,
)
from roigsf_ros.render.rasterize import render_map
from roigsf_ros.render.surfels import SurfelMap

MODES = ("roi-gsurfisher", "fisherrf")
DOWNSAMPLES = (1, 2)
TRAIN_YAWS_DEG = (65.0, 155.0, 245.0, 335.0)
TARGET_RATIO = 1.0
"""One candidate (ROI + close-front + Fisher) over a training forward+backward (issue 12: no slower)."""
TARGET_FISHER_RATIO = 1.0
"""A candidate's Fisher phase over a training forward+backward (issue 12: no slower)."""
TARGET_SCORE_S = 1.0
"""One score() call over 50 candidates at 160x120, 20k surfels (issue 12)."""
REQUEST_VARIANTS: dict[str, dict[str, Any]] = {
    "roi-gsurfisher": {},
    "F3": dict(RECOMMENDED_UNSEEN),
    "F3, kept grid": {**RECOMMENDED_UNSEEN, "unseen_carve_rerender": False},
}
"""The planner requests timed by keyframe count: the paper's score, the recommended variant (F3) rendering its grid at
every request, and F3 with the grid kept between requests."""
MIN_WIDTH, MIN_HEIGHT = 8, 6
"""The smallest image the benchmark takes: Open3D's TSDF fusion samples the depth sparsely and stops when it finds no
surface: at 4x3 and smaller with the default surfels, and with tens of surfels at sizes under 8x6 more often than at
8x6 and over; a handful of surfels can fail at any size (:func:`build_state` then names ``--surfels``)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``roigsf perf nbv``."""
    parser.add_argument("--out", type=Path, metavar="FILE.json", help="also write the results as JSON here")
    parser.add_argument("--repeats", type=int, default=5, metavar="N", help="timed repeats; medians (default 5)")
    parser.add_argument("--threads", type=int, default=2, metavar="T", help="numba and torch threads (default 2)")
    parser.add_argument("--surfels", type=int, default=20_000, metavar="N", help="surfels in the room (default 20000)")
    parser.add_argument(
        "--width", type=int, default=160, metavar="W", help=f"image width (default 160, at least {MIN_WIDTH})"
    )
    parser.add_argument(
        "--height", type=int, default=120, metavar="H", help=f"image height (default 120, at least {MIN_HEIGHT})"
    )
    parser.add_argument("--candidates", type=int, default=50, metavar="M", help="candidates per score() (default 50)")
    parser.add_argument(
        "--voxel-size", type=float, default=0.02, metavar="M", help="TSDF voxel size in metres (default 0.02, <= 1)"
    )
    parser.add_argument(
        "--keyframes", default="4,16,64", metavar="K,K,...",
        help="keyframe counts of the planner requests with the unseen term (default 4,16,64)",
    )  # fmt: skip


@dataclass
class State:
    """A mapped room: surfels, training poses, TSDF, h_train per mode, candidates and the measured view."""

    surfel_map: SurfelMap
    intr: Intrinsics
    train_poses: list[np.ndarray]
    tsdf: TSDFVolume
    h_train: dict[str, dict[str, torch.Tensor]]
    candidates: np.ndarray
    view: np.ndarray


def _inside_box(p: np.ndarray, clearance: float) -> bool:
    for (cx, cy, _), (bx, by, bz) in BOXES:
        if abs(p[0] - cx) < bx / 2 + clearance and abs(p[1] - cy) < by / 2 + clearance and p[2] < bz + clearance:
            return True
    return False


def look_dir(position: np.ndarray, yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at ``position`` looking along yaw (about +z) and pitch (up > 0)."""
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    fwd = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)])
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, fwd], axis=1)
    T[:3, 3] = position
    return T


def room_candidates(n: int, seed: int = 0, clearance: float = 0.5) -> np.ndarray:
    """``n`` seeded poses [n, 4, 4] inside the room, ``clearance`` m from walls and boxes; any yaw, pitch -25..10."""
    rng = np.random.default_rng(seed)
    sx, sy, sz = ROOM
    out = []
    while len(out) < n:
        p = np.array([
            rng.uniform(-sx / 2 + clearance, sx / 2 - clearance),
            rng.uniform(-sy / 2 + clearance, sy / 2 - clearance),
            rng.uniform(0.9, min(1.9, sz - clearance)),
        ])  # fmt: skip
        if _inside_box(p, clearance):
            continue
        out.append(look_dir(p, rng.uniform(0.0, 360.0), rng.uniform(-25.0, 10.0)))
    return np.stack(out)


def map_rgbd(m: SurfelMap, T_wc: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """The map's own RGB-D at ``T_wc`` as TSDF fusion takes it: depth_m [H, W] float32 (median depth, 0 where the
    alpha is below 0.5) and rgb [H, W, 3] uint8.
    """
    with torch.no_grad():
        out = render_map(m, T_wc, intr)
    depth = torch.where(out.alpha >= 0.5, out.median_depth, 0.0).numpy().astype(np.float32)
    return depth, (out.color.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)


def build_state(
    n_surfels: int, width: int, height: int, n_candidates: int, voxel_size_m: float, scorer: NBVScorer
) -> State:
    """The mapped room of the module docstring (deterministic)."""
    m = room_scene(n_surfels)
    view, intr = room_camera(width, height)
    train = [room_camera(width, height, yaw)[0] for yaw in TRAIN_YAWS_DEG]
    tsdf = TSDFVolume(voxel_size_m=voxel_size_m, sdf_trunc_m=max(4 * voxel_size_m, 0.08))
    for T in train:
        depth, rgb = map_rgbd(m, T, intr)
        try:
            tsdf.integrate(depth, T, intr, rgb)
        except RuntimeError as exc:  # Open3D: "No block is touched in TSDF volume": too few pixels saw a surface
            if "No block is touched" not in str(exc):
                raise
            raise InputError(
                "--surfels",
                f"the training views at {width}x{height} with {n_surfels} surfels saw too little surface to fuse a "
                "TSDF; give more --surfels or a larger --width/--height",
            ) from None
    h = {mode: scorer.train_fisher(m, train, intr, mode) for mode in MODES}
    return State(m, intr, train, tsdf, h, room_candidates(n_candidates), view)


def _median_ms(fn: Callable[[], Any], repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def _train_step(m: SurfelMap, T_wc: np.ndarray, intr: Intrinsics) -> Callable[[], None]:
    """One training forward+backward of view ``T_wc`` (loss over colour, depth and alpha, as perf render)."""
    leaf = m.clone().requires_grad_()

    def step() -> None:
        out = render_map(leaf, T_wc, intr)
        (out.color.sum() + out.depth.sum() + out.alpha.sum()).backward()
        for p in leaf.parameters():
            p.grad = None

    return step


def bench_candidate(st: State, scorer: NBVScorer, mode: str, repeats: int) -> dict[str, Any]:
    """Training fwd+bwd of the view and one candidate's scoring phases, interleaved, medians (ms).

    Wall-clock times and, as a load-robust check, process CPU times (all threads) of the same runs.
    """
    step = _train_step(st.surfel_map, st.view, st.intr)

    def score_one() -> dict[str, float]:
        res = scorer.score(st.surfel_map, st.h_train[mode], st.tsdf, st.train_poses, [st.view], st.intr, mode=mode)
        return res.timings_s

    step()
    score_one()
    phases = ("roi", "close_front", "fisher", "setup")
    rows: dict[str, list[float]] = {k: [] for k in ("train_fwd_bwd", "train_fwd_bwd_cpu", *phases)}
    rows |= {f"{k}_cpu": [] for k in phases}
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        step()
        rows["train_fwd_bwd"].append(time.perf_counter() - t0)
        rows["train_fwd_bwd_cpu"].append(time.process_time() - c0)
        t = score_one()
        for k in phases:
            rows[k].append(t[k])
            rows[f"{k}_cpu"].append(t[f"{k}_cpu"])
    med = {f"{k}_ms": statistics.median(v) * 1e3 for k, v in rows.items()}
    for suffix in ("", "_cpu"):
        parts = [rows[f"{k}{suffix}"] for k in ("roi", "close_front", "fisher")]
        per_rep = [sum(p) for p in zip(*parts, strict=True)]
        med[f"candidate{suffix}_ms"] = statistics.median(per_rep) * 1e3
        ratios = [c / t for c, t in zip(per_rep, rows[f"train_fwd_bwd{suffix}"], strict=True)]
        med[f"ratio{suffix}_candidate_over_train"] = statistics.median(ratios)
        fisher = [f / t for f, t in zip(rows[f"fisher{suffix}"], rows[f"train_fwd_bwd{suffix}"], strict=True)]
        med[f"ratio{suffix}_fisher_over_train"] = statistics.median(fisher)
    return med


def bench_score(st: State, scorer: NBVScorer, mode: str, repeats: int) -> dict[str, Any]:
    """Wall time (s) of one score() call over every candidate, median over repeats, with its phases."""
    walls, cpus, phases = [], [], []
    for _ in range(max(1, repeats // 2)):
        t0, c0 = time.perf_counter(), time.process_time()
        res = scorer.score(st.surfel_map, st.h_train[mode], st.tsdf, st.train_poses, st.candidates, st.intr, mode=mode)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
        phases.append(res.timings_s)
    i = int(np.argsort(walls)[len(walls) // 2])
    return {
        "score_s": statistics.median(walls),
        "score_cpu_s": statistics.median(cpus),
        "phases_s": {k: round(v, 4) for k, v in phases[i].items()},
        "n_candidates": len(st.candidates),
        "n_flagged": int(res.flagged.sum()),
        "best_index": int(res.best_index),
    }


def bench_state_score(st: State, scorer: NBVScorer, mode: str, repeats: int) -> dict[str, Any]:
    """Wall time (s) of the candidates scored as one planner request, median over repeats, with the phases.

    :class:`ScoringState` keeps the TSDF, its surface voxels, W_f and (FisherRF) its H_train between requests (the
    planner's sync timer prepares them when a keyframe comes), so a request pays the texture test, the ROI and the
    Fisher.
    """
    cfg = scorer.config
    state = ScoringState(cfg, st.tsdf.voxel_size_m, st.tsdf.sdf_trunc_m, st.tsdf.depth_max_m, cache_h_train=True)
    poses = np.stack(st.train_poses)

    def render_rgbd(T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return map_rgbd(st.surfel_map, T_wc, st.intr)

    h = st.h_train[mode]
    outputs = tuple(cfg.fisherrf_outputs if mode == "fisherrf" else cfg.fisher_outputs)
    state.update(st.surfel_map, h, outputs, poses, st.intr, render_rgbd, mode)  # the sync timer's work, not timed
    walls, phases = [], []
    for _ in range(max(1, repeats // 2)):
        t0 = time.perf_counter()
        res = state.score(st.surfel_map, h, outputs, poses, st.candidates, st.intr, render_rgbd, mode=mode)
        walls.append(time.perf_counter() - t0)
        phases.append(res.timings_s)
    i = int(np.argsort(walls)[len(walls) // 2])
    return {
        "score_state_s": statistics.median(walls),
        "state_phases_s": {k: round(v, 4) for k, v in phases[i].items()},
        "state_best_index": int(res.best_index),
    }


def keyframe_poses(st: State, n: int) -> np.ndarray:
    """[n, 4, 4] keyframe poses: the training poses, then seeded room poses (another seed than the candidates')."""
    train = np.stack(st.train_poses)
    if n <= len(train):
        return train[:n]
    return np.concatenate([train, room_candidates(n - len(train), seed=1)])


def bench_requests(st: State, n_keyframes: int, repeats: int) -> list[dict[str, Any]]:
    """For each of :data:`REQUEST_VARIANTS`: a planner state synced to ``n_keyframes`` keyframes (untimed but for the
    last keyframe's sync, ``sync_one_s``), then one request of every candidate, median wall time of ``repeats``.
    """
    poses = keyframe_poses(st, n_keyframes)
    h = st.h_train["roi-gsurfisher"]
    outputs = tuple(NBVConfig().fisher_outputs)

    def render_rgbd(T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return map_rgbd(st.surfel_map, T_wc, st.intr)

    rows = []
    for name, params in REQUEST_VARIANTS.items():
        state = ScoringState(NBVConfig(**params), st.tsdf.voxel_size_m, st.tsdf.sdf_trunc_m, st.tsdf.depth_max_m)
        if n_keyframes > 1:
            state.update(st.surfel_map, h, outputs, poses[:-1], st.intr, render_rgbd)
        t0 = time.perf_counter()
        state.update(st.surfel_map, h, outputs, poses, st.intr, render_rgbd)  # what the sync timer does
        sync_s = time.perf_counter() - t0
        walls, unseen = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            res = state.score(st.surfel_map, h, outputs, poses, st.candidates, st.intr, render_rgbd)
            walls.append(time.perf_counter() - t0)
            unseen.append(res.timings_s["unseen"])
        rows.append({
            "variant": name, "params": params, "keyframes": n_keyframes, "request_s": statistics.median(walls),
            "unseen_s": statistics.median(unseen), "sync_one_s": sync_s, "best_index": int(res.best_index),
            "renders": state.carved.renders if state.carved is not None else None,
        })  # fmt: skip
    return rows


def _keyframe_counts(text: str) -> list[int]:
    """``--keyframes``: comma-separated counts >= 1."""
    try:
        counts = [int(t) for t in str(text).split(",") if t.strip()]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        raise InputError("--keyframes", f"expected comma-separated counts >= 1, got {text!r}")
    return counts


MAX_VOXEL_M = 1.0
"""The largest ``--voxel-size``: the benchmark's room is a few metres (a typo's 1e11 m failed in numpy)."""


def run(args: argparse.Namespace) -> int:
    """Build the state, time every (mode, fisher_downsample), print a table, optionally write JSON."""
    least = dict.fromkeys(("repeats", "threads", "surfels", "candidates"), 1) | {
        "width": MIN_WIDTH,
        "height": MIN_HEIGHT,
    }
    check_options(args, least, positive=("voxel_size",), most={"threads": MAX_THREADS, "voxel_size": MAX_VOXEL_M})
    keyframe_counts = _keyframe_counts(args.keyframes)
    check_out_file(args.out, "nbv")
    torch.set_num_threads(args.threads)
    backend = "torch"
    numba_threads = None
    if numba_available():
        numba_threads = set_numba_threads(args.threads)
        pin_workers()  # one worker per CPU where they use every CPU: no scheduler modes in the timings
        backend = "numba"
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    st = build_state(args.surfels, args.width, args.height, args.candidates, args.voxel_size, NBVScorer())
    build_s = time.perf_counter() - t0
    vox = NBVScorer().surface(st.tsdf)
    rows = []
    for ds in DOWNSAMPLES:
        scorer = NBVScorer(NBVConfig(fisher_downsample=ds))
        for mode in MODES:
            row: dict[str, Any] = {"mode": mode, "fisher_downsample": ds}
            row |= bench_candidate(st, scorer, mode, args.repeats)
            row |= bench_score(st, scorer, mode, args.repeats)
            row |= bench_state_score(st, scorer, mode, args.repeats)
            rows.append(row)
    requests = [r for n in keyframe_counts for r in bench_requests(st, n, args.repeats)]
    result = {
        "benchmark": "nbv",
        "backend": backend,
        "width": args.width,
        "height": args.height,
        "surfels": args.surfels,
        "surface_voxels": len(vox.centres_m),
        "voxel_size_m": args.voxel_size,
        "train_poses": len(st.train_poses),
        "candidates": args.candidates,
        "repeats": args.repeats,
        "build_state_s": build_s,
        "environment": environment(load_before)
        | {
            "threads": args.threads,
            "numba_threads": numba_threads,  # fewer than asked where numba has fewer (its most: the CPUs)
            "env": {
                k: os.environ.get(k) for k in ("MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_", "OMP_WAIT_POLICY", PIN_ENV)
            },
            "pinned_workers": len(pinned_workers()),
        },
        "targets": {
            "ratio_candidate_over_train": TARGET_RATIO,
            "ratio_fisher_over_train": TARGET_FISHER_RATIO,
            "score_s_roi_gsurfisher_ds1": TARGET_SCORE_S,
        },
        "rows": rows,
        "requests": requests,
    }
    print(
        f"{'mode':>15} {'ds':>2} {'fwd+bwd':>8} {'ROI':>7} {'c-front':>7} {'Fisher':>7} {'F ratio':>7} {'cand':>7} "
        f"{'ratio':>6} {'cpu ratio':>9} {'score(' + str(args.candidates) + ')':>10} {'cpu':>7} {'planner':>10}"
    )
    for r in rows:
        print(
            f"{r['mode']:>15} {r['fisher_downsample']:>2} {r['train_fwd_bwd_ms']:8.1f} {r['roi_ms']:7.1f} "
            f"{r['close_front_ms']:7.2f} {r['fisher_ms']:7.1f} {r['ratio_fisher_over_train']:7.2f} "
            f"{r['candidate_ms']:7.1f} "
            f"{r['ratio_candidate_over_train']:6.2f} {r['ratio_cpu_candidate_over_train']:9.2f} {r['score_s']:9.2f}s "
            f"{r['score_cpu_s']:6.2f}s {r['score_state_s']:9.2f}s"
        )
    print(
        f"({args.width}x{args.height}, {args.surfels} surfels, {result['surface_voxels']} surface voxels; backend "
        f"{backend}, {threads_text(args.threads, numba_threads)}; milliseconds, medians of {args.repeats}; "
        "F ratio = Fisher / fwd+bwd "
        f"per repeat (target <= {TARGET_FISHER_RATIO}); ratio = candidate / fwd+bwd "
        f"per repeat (target <= {TARGET_RATIO}), cpu ratio the same in process CPU time; score = one score() "
        f"call (target <= {TARGET_SCORE_S} s for roi-gsurfisher at ds 1), cpu its process CPU time; planner = the "
        f"same candidates as one planner request with the TSDF's products kept between requests (ScoringState); "
        f"1-min load {load_before:.1f} -> {os.getloadavg()[0]:.1f})"
    )
    print(f"\n{'planner request':>16} {'keyframes':>9} {'request':>9} {'unseen':>8} {'sync one':>9}")
    for r in requests:
        print(
            f"{r['variant']:>16} {r['keyframes']:>9} {r['request_s']:8.3f}s {r['unseen_s']:7.3f}s "
            f"{r['sync_one_s']:8.3f}s"
        )
    print(
        f"(one request of the {args.candidates} candidates after the state was synced to that many keyframes, median "
        f"of {args.repeats}; unseen = its unseen-term phase; sync one = the sync timer's work for the "
        f"last keyframe; F3 = {':'.join(f'{k}={v}' for k, v in RECOMMENDED_UNSEEN.items())}, kept grid = "
        f"unseen_carve_rerender=false)"
    )
    write_results(args.out, result)
    return 0
