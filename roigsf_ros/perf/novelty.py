"""Lookahead novelty speed: what the keyframe selector computes per window of the recommended stream variant.

The stream variant (``RECOMMENDED_STREAM``: window 13, lookahead 13, novelty weight 4) decides each window once the
next 13 frames are in, by the planner's fused score plus the window's observed novelty judged against those frames
(:meth:`~roigsf_ros.nbv.novelty.ObservedSurface.frames_novelty`). The selector node computed it in its timer, holding
itself: the frames that came meanwhile waited, then arrived in a burst (the main job's fallbacks came from that, not
from the planner); now a thread of its own computes it while the planner scores.
Here, on the frames of a bag (default the shipped one), a keyframe is taken in the middle of each window (as a
selector would, roughly) and each window's novelty is timed twice:

- ``fast``: as the selector computes it (packed voxel keys, one bit-mask pass for every candidate's reach,
  :func:`~roigsf_ros.nbv.novelty.unreached_by_each`);
- ``plain``: the same counts the plain way, as the package computed them before (distinct voxels by sorting rows,
  a k-d tree per candidate, :func:`~roigsf_ros.nbv.novelty.lookahead_new_voxels_plain`), plus the frames'
  back-projection; every window's counts must equal the fast ones (``equal``).

Also the window's keyframe being added (``add``, :meth:`~roigsf_ros.nbv.novelty.ObservedSurface.add_frame`, which the
selector's novelty thread does too), and ``stall``: the longest a second Python thread, waking every millisecond, had to
wait while the fast path and the adds ran (a call that holds Python's lock holds up every thread of the node, the
executor's among them: open3d's hash set held it for whole inserts and rehashes, 0.07-0.2 s, before the package's own
set replaced it).

Medians over ``--repeats`` per window, then the median and the largest over the windows, and the ratio of the medians,
measured in one run; ``--out`` writes it all as JSON.
"""

from __future__ import annotations

import argparse
import os
import statistics
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame
from roigsf_ros.data.bags import SAMPLE_BAG, CameraTopics, read_bag_frames, sample_path
from roigsf_ros.mapping.mapper import MapperConfig
from roigsf_ros.nbv.novelty import (
    HASH_CAPACITY,
    HASH_CHUNK_ROWS,
    ObservedSurface,
    frame_points,
    lookahead_new_voxels_plain,
)
from roigsf_ros.perf import check_options, check_out_file, environment, write_results
from roigsf_ros.policies.stream import RECOMMENDED_STREAM


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``roigsf perf novelty``."""
    parser.add_argument(
        "--bag",
        type=Path,
        default=None,
        metavar="BAG",
        help=f"frames (default: the shipped sample, {SAMPLE_BAG} of the checkout, else of the installed package's "
        "share folder)",
    )
    parser.add_argument("--out", type=Path, metavar="FILE.json", help="also write the results as JSON here")
    parser.add_argument("--repeats", type=int, default=3, metavar="R", help="timed repeats per window (default 3)")
    window, lookahead = int(RECOMMENDED_STREAM["window"]), int(RECOMMENDED_STREAM["lookahead"])
    parser.add_argument("--window", type=int, default=window, metavar="W", help=f"frames a window (default {window})")
    parser.add_argument(
        "--lookahead", type=int, default=lookahead, metavar="L", help=f"frames ahead (default {lookahead})"
    )
    parser.add_argument("--hash-capacity", type=int, default=HASH_CAPACITY, metavar="N",
                        help=f"the observed surface's hash set's initial capacity (default {HASH_CAPACITY}; 65536 was "
                        "the earlier default)")  # fmt: skip
    parser.add_argument("--hash-chunk-rows", type=int, default=HASH_CHUNK_ROWS, metavar="N",
                        help=f"rows per call into it (default {HASH_CHUNK_ROWS}; a large number: one call, as "
                        "before)")  # fmt: skip


def _median_time(fn: Any, repeats: int) -> tuple[float, Any]:
    """Median wall seconds of ``repeats`` calls of ``fn()`` and its last result."""
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(statistics.median(times)), out


class StallWatch:
    """A thread that wakes every millisecond while in the ``with`` block; :attr:`worst_s` is the longest it waited
    (beyond its sleep) across every block: how long some other call held Python's lock.
    """

    def __init__(self) -> None:
        self.worst_s = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _watch(self) -> None:
        last = time.perf_counter()
        while not self._stop.wait(0.001):
            now = time.perf_counter()
            self.worst_s = max(self.worst_s, now - last - 0.001)
            last = now

    def __enter__(self) -> StallWatch:
        self._stop.clear()
        self._thread = threading.Thread(target=self._watch, name="stall_watch", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        assert self._thread is not None
        self._thread.join()


def run_windows(
    frames: list[Frame],
    intr: Intrinsics,
    window: int,
    lookahead: int,
    repeats: int,
    surface: ObservedSurface | None = None,
) -> list[dict[str, Any]]:
    """Each whole window's fast and plain novelty times (median of ``repeats``), whether their counts agree, the
    time its keyframe took to add and the longest stall of another thread during the fast path and the add.
    """
    for name, value, least in (("--window", window, 1), ("--lookahead", lookahead, 0), ("--repeats", repeats, 1)):
        if value < least:
            raise InputError(name, f"must be at least {least}, got {value}")
    if len(frames) < 1 + window + lookahead:
        need = 1 + window + lookahead  # the first keyframe, one window and its lookahead
        raise InputError("--window/--lookahead", f"need {need} frames (1 + window {window} + lookahead "
                         f"{lookahead}), the bag has {len(frames)}: a smaller --window or --lookahead, or a longer "
                         "--bag")  # fmt: skip
    config = MapperConfig()
    surface = surface or ObservedSurface()
    surface.add_frame(frames[0], intr, config)  # the first frame is always a keyframe
    rows = []
    for start in range(1, len(frames) - window - lookahead + 1, window):
        cands, ahead = frames[start : start + window], frames[start + window : start + window + lookahead]
        watch = StallWatch()
        with watch:
            fast_s, fast = _median_time(lambda c=cands, a=ahead: surface.frames_novelty(c, intr, config, a), repeats)
        cand_w = [frame_points(f, intr, config) for f in cands]
        ahead_w = [frame_points(f, intr, config) for f in ahead]
        pts_s, _ = _median_time(lambda c=cands, a=ahead: [frame_points(f, intr, config) for f in (*c, *a)], repeats)
        plain_s, plain_n = _median_time(lambda c=cand_w, a=ahead_w: lookahead_new_voxels_plain(surface, c, a), repeats)
        plain = plain_n.astype(np.float64) * surface.voxel_m**2
        t0 = time.perf_counter()
        with watch:
            surface.add_frame(cands[len(cands) // 2], intr, config)  # this window's keyframe
        add_s = time.perf_counter() - t0
        rows.append({"first_frame": start, "fast_s": fast_s, "plain_s": plain_s + pts_s, "add_s": add_s,
                     "stall_s": watch.worst_s, "equal": bool(np.array_equal(fast, plain))})  # fmt: skip
    return rows


READS_CAMERA_BAG = True
"""``roigsf perf novelty`` takes ``roigsf map``'s camera options (``--realsense``, ``--pose-source tf``, ...): the CLI
adds them and passes :func:`run` the topics, as this layer may not import the CLI's option code."""


def run(args: argparse.Namespace, topics: CameraTopics | None = None) -> int:
    """``roigsf perf novelty``: time the windows, print the table, write the JSON. ``topics``: how the bag is read
    (default this package's own names).
    """
    check_options(args, {"repeats": 1, "window": 1, "lookahead": 0, "hash_capacity": 1, "hash_chunk_rows": 1})
    check_out_file(args.out, "novelty")
    load_before = os.getloadavg()[0]
    bag = args.bag if args.bag is not None else sample_path(SAMPLE_BAG)
    bag_frames, _ = read_bag_frames(bag, topics)
    if not bag_frames:
        raise InputError(bag, "no complete frame in the bag")
    frames = [Frame(i, f.rgb, f.depth_m, f.T_wc) for i, f in enumerate(bag_frames)]
    surface = ObservedSurface(hash_capacity=args.hash_capacity, hash_chunk_rows=args.hash_chunk_rows)
    rows = run_windows(frames, bag_frames[0].intrinsics, args.window, args.lookahead, args.repeats, surface)
    fast = [r["fast_s"] for r in rows]
    plain = [r["plain_s"] for r in rows]
    summary = {
        "fast_median_s": statistics.median(fast),
        "fast_max_s": max(fast),
        "plain_median_s": statistics.median(plain),
        "plain_max_s": max(plain),
        "plain_over_fast": statistics.median(plain) / statistics.median(fast),
        "add_median_s": statistics.median(r["add_s"] for r in rows),
        "add_max_s": max(r["add_s"] for r in rows),
        "max_stall_s": max(r["stall_s"] for r in rows),
        "all_equal": all(r["equal"] for r in rows),
    }
    result = {"benchmark": "novelty", "bag": str(bag), "camera_topics": (topics or CameraTopics()).record(),
              "window": args.window, "lookahead": args.lookahead,
              "repeats": args.repeats, "hash_capacity": args.hash_capacity, "hash_chunk_rows": args.hash_chunk_rows,
              "environment": environment(load_before), "windows": rows, "summary": summary}  # fmt: skip
    print(f"lookahead novelty of {len(rows)} windows of {args.window} frames, {args.lookahead} ahead ({bag})")
    print(f"  {'':22s}{'median (s)':>12s}{'largest (s)':>13s}")
    print(f"  {'fast (the selector)':22s}{summary['fast_median_s']:12.3f}{summary['fast_max_s']:13.3f}")
    print(f"  {'plain (k-d trees)':22s}{summary['plain_median_s']:12.3f}{summary['plain_max_s']:13.3f}")
    print(f"  {'add a keyframe':22s}{summary['add_median_s']:12.3f}{summary['add_max_s']:13.3f}")
    print(f"  plain / fast: {summary['plain_over_fast']:.1f}x; counts equal in every window: {summary['all_equal']}")
    print(f"  longest another thread waited for Python's lock (fast path and adds): {summary['max_stall_s']:.3f} s")
    write_results(args.out, result)
    return 0 if summary["all_equal"] else 1


__all__ = ["StallWatch", "add_arguments", "run", "run_windows"]
