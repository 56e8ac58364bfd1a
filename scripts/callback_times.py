"""Where do frames wait on their way to the keyframe selector? The main job with every node callback timed.

    PYTHONPATH=. python scripts/callback_times.py --out /tmp/run [--params-file config/recommended/stream.yaml]

Runs ``roigsf demo`` in this process with the callbacks of the three nodes (and the selector's novelty work)
wrapped in timers, then prints the run's figures, the longest gaps between two frames reaching the selector with
every callback that overlapped each by more than 20 ms (name, thread, start, end), and per callback its count, total
and longest time. A diagnostic (fifty-third and fifty-fourth sessions): what held the frames up shows as a long
selector callback overlapping a gap; a gap with only other nodes' work in it is the cores being shared.
"""

from __future__ import annotations

import argparse
import functools
import itertools
import os
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from roigsf_ros.cli import demo
from roigsf_ros.data.bags import SAMPLE_BAG, sample_path
from roigsf_ros.nodes import camera_input, keyframe_selector, mapper, nbv_planner

Event = tuple[str, str, float, float]
"""(callback, thread, start, end), monotonic seconds."""

TIMED: dict[type, tuple[str, ...]] = {
    keyframe_selector.KeyframeSelectorNode: (
        "_on_frame",
        "_check_request",
        "_settle_request",
        "_publish",
        "_with_novelty",
        "_novelty",
        "_add_observed",
        "_ask_planner",
        "_send",
        "_judge_held",
        "publish_status",
    ),
    mapper.MapperNode: ("_on_frame", "_on_keyframe", "_expire_waiting", "publish_map", "publish_status"),
    nbv_planner.NBVPlannerNode: ("_on_request", "_sync_timer", "publish_status"),
    camera_input.CameraInput: ("_on_message",),
}
"""The methods timed, per class (those a class lacks are skipped: the script runs on older commits too)."""


def _timed(label: str, f: Callable[..., Any], events: list[Event], lock: threading.Lock) -> Callable[..., Any]:
    @functools.wraps(f)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t0 = time.monotonic()
        try:
            return f(*args, **kwargs)
        finally:
            t1 = time.monotonic()
            with lock:
                events.append((label, threading.current_thread().name, t0, t1))

    return wrapper


def main(argv: list[str] | None = None) -> int:
    """Run the demo with the callbacks timed and print the report."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="the demo's run folder (replaced)")
    parser.add_argument("--bag", type=Path, default=None, help="bag to replay (default: the shipped sample)")
    parser.add_argument("--gt-mesh", default=None, help="its mesh (default: the sample's for the sample bag)")
    parser.add_argument("--params-file", type=Path, action="append", default=[])
    parser.add_argument("--gaps", type=int, default=6, help="how many of the longest frame gaps to show")
    args = parser.parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    events: list[Event] = []
    lock = threading.Lock()
    for cls, names in TIMED.items():  # before the nodes exist: their callbacks bind the wrapped methods
        for name in names:
            if hasattr(cls, name):
                setattr(cls, name, _timed(f"{cls.__name__}.{name}", getattr(cls, name), events, lock))
    bag = args.bag if args.bag is not None else sample_path(SAMPLE_BAG)
    gt_mesh, _ = demo.default_gt_mesh(bag, args.gt_mesh)
    m = demo.run_demo(bag, args.out, gt_mesh=gt_mesh, params_files=args.params_file, progress=False)
    keys = ("keyframes_published", "planner", "fallbacks", "recall@5cm", "psnr", "selector_max_frame_gap_s",
            "selector_max_novelty_s", "selector_max_answer_s")  # fmt: skip
    print("run:", ", ".join(f"{k} {m.get(k):.3g}" if isinstance(m.get(k), float) else f"{k} {m.get(k)}" for k in keys))
    events.sort(key=lambda e: e[2])
    t_origin = events[0][2] if events else 0.0
    frames = [e for e in events if e[0] == "KeyframeSelectorNode._on_frame"]
    gaps = sorted(((b[2] - a[2], a[2], b[2]) for a, b in itertools.pairwise(frames)), reverse=True)
    for gap, a, b in gaps[: args.gaps]:
        print(f"gap {gap:.3f} s between frames at {a - t_origin:.3f} and {b - t_origin:.3f} s")
        for name, thread, t0, t1 in events:
            if t1 > a and t0 < b and t1 - t0 > 0.02:
                print(f"    {name:44s} {thread:28s} {t0 - t_origin:8.3f} {t1 - t_origin:8.3f} ({t1 - t0:.3f} s)")
    totals: dict[str, list[float]] = {}
    for name, _, t0, t1 in events:
        count_total_max = totals.setdefault(name, [0, 0.0, 0.0])
        count_total_max[0] += 1
        count_total_max[1] += t1 - t0
        count_total_max[2] = max(count_total_max[2], t1 - t0)
    print(f"{'callback':44s} {'count':>6s} {'total s':>8s} {'max s':>7s}")
    for name, (count, total, longest) in sorted(totals.items(), key=lambda kv: -kv[1][1]):
        print(f"{name:44s} {int(count):6d} {total:8.3f} {longest:7.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
