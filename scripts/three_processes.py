#!/usr/bin/env python3
r"""The README's three-process run (mapper, nbv_planner, keyframe_selector and bag_player, each a process of its own)
repeated ``--runs`` times; writes the keyframe selector's final counters of each run (JSON + a table).

How many windows the planner decided, and how many went to the fallback and why, depends on when the planner's first
map came and how fast it answers: a measurement over several runs, not a test (session 57: the first windows came
before the mapper had published its first keyframe's map). Parameters go to the selector (``--selector``) and the
planner (``--planner``) as ``NAME=VALUE``; ROS discovery stays on this machine, in the domain ``--domain-id``. The
nodes run from this tree, in the environment of ``source scripts/setup.sh``.

    source scripts/setup.sh
    python scripts/three_processes.py --runs 3 --out runs/s57/three_wait5 \
        --selector policy=roi-gsurfisher --selector map_wait_s=5.0
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
COUNTERS = (
    "frames",
    "keyframes_published",
    "planner_calls",
    "planner_answers",
    "planner_not_ready",
    "planner_failures",
    "planner_timeouts",
    "planner_waited",
    "fallbacks",
    "frames_skipped_map_lag",
    "max_answer_s",
)


def node_command(name: str, params: list[str]) -> list[str]:
    """A node of this tree in a process of its own, with ``-p NAME:=VALUE`` for each of ``params``."""
    args = [a for p in params for a in ("-p", p.replace("=", ":=", 1))]
    return [sys.executable, "-m", "roigsf_ros.nodes.console", name, *(["--ros-args", *args] if args else [])]


class StatusListener:
    """Keeps the keyframe selector's latest ``~/status`` (JSON) from a node spun in a thread of its own."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from std_msgs.msg import String

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("three_processes_status", context=self.context)
        self.latest: dict[str, Any] = {}
        self.node.create_subscription(String, "/keyframe_selector/status", self._on_status, 10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, name="three_processes_spin", daemon=True)
        self.thread.start()

    def _on_status(self, msg: Any) -> None:
        self.latest = json.loads(msg.data)

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            while self.context.ok():
                self.executor.spin_once(timeout_sec=0.1)
        except ExternalShutdownException:  # close() shut the context down while it waited
            pass

    def close(self) -> None:
        """Stop spinning, join the thread and shut the context down."""
        import rclpy

        rclpy.shutdown(context=self.context)
        self.thread.join(timeout=5.0)
        self.executor.shutdown()
        self.node.destroy_node()


def one_run(args: argparse.Namespace, listener: StatusListener, logs: Path) -> dict[str, Any]:
    """Start the three nodes, play the bag once, wait for the selector to settle; its final counters."""
    listener.latest = {}
    procs: list[subprocess.Popen] = []
    logs.mkdir(parents=True, exist_ok=True)

    def start(name: str, params: list[str]) -> subprocess.Popen:
        log = (logs / f"{name}.log").open("w")
        proc = subprocess.Popen(node_command(name, params), cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
        procs.append(proc)
        return proc

    try:
        start("mapper", args.mapper)
        start("nbv_planner", args.planner)
        start("keyframe_selector", args.selector)
        player = start("bag_player", [f"bag={args.bag}", f"rate={args.rate}", "wait_for_subscribers=2"])
        if player.wait(timeout=args.timeout_s) != 0:
            raise RuntimeError(f"bag_player failed: see {logs / 'bag_player.log'}")
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:  # the last windows' answers, and a status published after them
            s = listener.latest
            if s and not s.get("planner_pending") and not s.get("planner_window_waiting"):
                time.sleep(1.5)
                break
            time.sleep(0.1)
        status = dict(listener.latest)
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in procs:
            try:
                proc.wait(timeout=20.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    if not status:
        raise RuntimeError(f"no status from the keyframe selector: see {logs / 'keyframe_selector.log'}")
    return {k: status.get(k) for k in COUNTERS}


def main(argv: list[str] | None = None) -> int:
    """Run the three processes ``--runs`` times; write ``results.json`` (each run, medians) and ``table.md``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, type=Path, help="folder for results.json, table.md and the logs")
    parser.add_argument("--runs", type=int, default=3, help="runs, one after the other (default 3)")
    parser.add_argument("--bag", default=None, help="bag to play (default: the shipped sample)")
    parser.add_argument("--rate", type=float, default=1.0, help="playback rate (default 1.0)")
    parser.add_argument("--selector", action="append", default=[], metavar="NAME=VALUE", help="selector parameter")
    parser.add_argument("--planner", action="append", default=[], metavar="NAME=VALUE", help="planner parameter")
    parser.add_argument("--mapper", action="append", default=[], metavar="NAME=VALUE", help="mapper parameter")
    parser.add_argument("--domain-id", type=int, default=57, help="ROS_DOMAIN_ID of the run (default 57)")
    parser.add_argument("--timeout-s", type=float, default=300.0, help="longest a playback may take (default 300)")
    args = parser.parse_args(argv)
    if args.bag is None:
        from roigsf_ros.data.bags import sample_path

        args.bag = str(sample_path())
    if args.runs < 1 or args.rate <= 0:
        parser.error("--runs must be >= 1 and --rate > 0 (the player's rate 0 is lossy across processes)")
    for p in (*args.selector, *args.planner, *args.mapper):
        if "=" not in p:
            parser.error(f"'{p}': a parameter is NAME=VALUE")
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)
    listener = StatusListener()
    runs: list[dict[str, Any]] = []
    try:
        for i in range(args.runs):
            runs.append(one_run(args, listener, args.out / f"run{i + 1}"))
            print(f"run {i + 1}: " + ", ".join(f"{k} {runs[-1][k]}" for k in COUNTERS), flush=True)
    finally:
        listener.close()
    medians = {k: statistics.median(float(r[k] or 0) for r in runs) for k in COUNTERS}
    result = {"bag": args.bag, "rate": args.rate, "selector": args.selector, "planner": args.planner,
              "mapper": args.mapper, "runs": runs, "median": medians}  # fmt: skip
    tmp = args.out / "results.json.tmp"
    tmp.write_text(json.dumps(result, indent=2) + "\n")
    tmp.replace(args.out / "results.json")
    rows = ["| run | " + " | ".join(COUNTERS) + " |", "|---" * (len(COUNTERS) + 1) + "|"]
    rows += [f"| {i + 1} | " + " | ".join(f"{r[k]:.2f}" if k.endswith("_s") else str(r[k]) for k in COUNTERS) + " |"
             for i, r in enumerate(runs)]  # fmt: skip
    rows.append("| median | " + " | ".join(f"{medians[k]:g}" for k in COUNTERS) + " |")
    (args.out / "table.md").write_text("\n".join(rows) + "\n")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
