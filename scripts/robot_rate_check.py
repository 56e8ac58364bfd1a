"""The README's RealSense command at the camera's rate: a robot's bag at 30 Hz, 640x480, played by ``bag_player`` in one
process into ``active_mapping`` in another, and what each node took in, dropped and named.

    PYTHONPATH=. python scripts/robot_rate_check.py --out runs/robot_rate [--frames 300] [--set window=30] ...

Makes (once, in ``--work``) the synthetic room at 640x480 (``roigsf scene synth --seed 7``), its bag at ``--rate`` Hz
(``roigsf bag from-replica``) and the robot's layout of it (``roigsf bag to-robot --color-format jpeg``: JPEG colour,
compressedDepth, the pose on TF). Then starts ``active_mapping`` with config/*.yaml, the README's RealSense
parameters (``input_width`` 160) plus ``depth_transport: compressedDepth`` and any ``--set NAME=VALUE``, plays the
bag at real time, waits for the mapper to insert what the selector named, and writes ``robot_rate.json`` and a table
(``robot_rate.md``) to ``--out``: frames published and received per node, refused, dropped incomplete, estimated
missed, keyframes named and mapped, planner answers and fallbacks, the longest gap between two frames reaching the
selector and the planner's longest TSDF update. One run, nothing timed against a threshold.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from roigsf_ros.data.bags import bag_info, realsense_topics
from roigsf_ros.data.robot_bag import robot_node_parameters

REPO = Path(__file__).resolve().parents[1]
REALSENSE = robot_node_parameters() | {"input_width": "160"}
"""The README's RealSense parameters, with the depth transport of a bag recorded with compressed depth."""


def _run(cmd: list[str]) -> None:
    print("$", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=REPO)


def make_bag(work: Path, frames: int, rate_hz: float) -> Path:
    """The robot bag of the synthetic room at 640x480 (made once per frames / rate in ``work``)."""
    robot = work / f"robot_{frames}f_{rate_hz:g}hz"
    if (robot / "metadata.yaml").is_file():
        return robot
    roigsf = [sys.executable, "-m", "roigsf_ros.cli"]
    scene, raw = work / f"room_{frames}f", work / f"raw_{frames}f_{rate_hz:g}hz"
    if not (scene / "traj.txt").is_file():
        _run([*roigsf, "scene", "synth", "--out", str(scene), "--seed", "7", "--frames", str(frames),
              "--width", "640", "--height", "480", "--overwrite"])  # fmt: skip
    _run([*roigsf, "bag", "from-replica", str(scene), "--out", str(raw), "--rate", f"{rate_hz:g}",
          "--depth-encoding", "16UC1", "--overwrite", "--no-progress"])  # fmt: skip
    _run([*roigsf, "bag", "to-robot", str(raw), "--out", str(robot), "--color-format", "jpeg", "--overwrite",
          "--no-progress"])  # fmt: skip
    return robot


class Statuses:
    """The latest ``~/status`` of each node, from a watcher node of this process."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from std_msgs.msg import String

        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
        self.node = rclpy.create_node("robot_rate_watcher", context=self.context)
        self.latest: dict[str, dict[str, Any]] = {}
        self._lock = threading.Lock()
        for name in ("mapper", "keyframe_selector", "nbv_planner"):
            self.node.create_subscription(String, f"/{name}/status", lambda m, n=name: self._on(n, m), 10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def _on(self, name: str, msg: Any) -> None:
        with self._lock:
            self.latest[name] = json.loads(msg.data)

    def get(self, name: str) -> dict[str, Any]:
        """The latest status of node ``name`` ({} before the first)."""
        with self._lock:
            return dict(self.latest.get(name, {}))

    def close(self) -> None:
        """Stop the watcher's executor, join its thread, shut its context down."""
        self.executor.shutdown()
        self.thread.join(timeout=10)
        self.node.destroy_node()
        self.context.try_shutdown()


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def run(bag: Path, out: Path, sets: list[str]) -> dict[str, Any]:
    """Play ``bag`` into ``active_mapping`` (two processes) and gather the nodes' counters."""
    params = dict(REALSENSE)
    for item in sets:
        name, _, value = item.partition("=")
        params[name] = value
    node_args = ["--ros-args"]
    for name in ("mapper", "nbv", "keyframe_selector"):
        node_args += ["--params-file", str(REPO / "config" / f"{name}.yaml")]
    for name, value in params.items():
        node_args += ["-p", f"{name}:={value}"]
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    watcher = Statuses()
    with (out / "active_mapping.log").open("wb") as log, (out / "bag_player.log").open("wb") as plog:
        nodes = subprocess.Popen([sys.executable, "-m", "roigsf_ros.nodes.active_mapping", *node_args], cwd=REPO,
                                 env=env, stdout=log, stderr=subprocess.STDOUT)  # fmt: skip
        try:
            deadline = time.monotonic() + 120
            while not (watcher.get("mapper") and watcher.get("keyframe_selector")) and time.monotonic() < deadline:
                time.sleep(0.2)
            player_args = ["--ros-args", "-p", f"bag:={bag}", "-p", "rate:=1.0", "-p", "wait_for_subscribers:=2"]
            t0 = time.monotonic()
            player = subprocess.Popen([sys.executable, "-m", "roigsf_ros.nodes.bag_player", *player_args], cwd=REPO,
                                      env=env, stdout=plog, stderr=subprocess.STDOUT)  # fmt: skip
            player.wait(timeout=600)
            played_s = time.monotonic() - t0
            deadline = time.monotonic() + 60  # the mapper's queue drains, then one more status
            while time.monotonic() < deadline:
                m = watcher.get("mapper")
                if m and m.get("pending_keyframes", 1) == 0 and m.get("waiting_keyframes", 1) == 0:
                    break
                time.sleep(0.5)
            time.sleep(1.5)
            m, s, p = watcher.get("mapper"), watcher.get("keyframe_selector"), watcher.get("nbv_planner")
        finally:
            _stop(nodes)
            watcher.close()
    frames_in_bag = bag_info(bag, realsense_topics(color_transport="auto", depth_transport="auto"))["frame_count"]
    return {
        "bag": str(bag),
        "parameters": params,
        "player_wall_s": round(played_s, 2),
        "frames_in_bag": frames_in_bag,
        "mapper": {k: m.get(k) for k in ("frames_received", "frames_rejected", "frames_dropped_incomplete",
                                         "frames_missed_estimate", "frames_pending", "keyframes",
                                         "keyframes_inserted", "keyframes_missing", "keyframes_dropped_overflow")},
        "selector": {k: s.get(k) for k in ("frames", "frames_rejected", "frames_dropped_incomplete",
                                           "frames_missed_estimate", "keyframes_published", "planner_answers",
                                           "fallbacks", "planner_waited", "max_frame_gap_s", "max_answer_s")},
        "planner": {k: p.get(k) for k in ("requests", "answered", "failed", "max_sync_s", "max_request_wait_s")},
    }  # fmt: skip


def table(result: dict[str, Any]) -> str:
    """A readable table of :func:`run`'s counters."""
    rows = [f"| bag frames | {result['frames_in_bag']} (played in {result['player_wall_s']} s) |"]
    for node in ("mapper", "selector", "planner"):
        rows += [f"| {node}.{k} | {json.dumps(v)} |" for k, v in result[node].items()]
    return "| figure | value |\n|---|---|\n" + "\n".join(rows) + "\n"


def main() -> int:
    """Make the bag if needed, run once, write robot_rate.json and robot_rate.md."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="folder for robot_rate.json, robot_rate.md and logs")
    ap.add_argument("--work", type=Path, default=Path("/tmp/roigsf_robot_rate"), help="scene and bags (kept)")
    ap.add_argument("--frames", type=int, default=300, help="frames of the bag (default 300: 10 s at 30 Hz)")
    ap.add_argument("--rate", type=float, default=30.0, help="camera rate of the bag, Hz (default 30)")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="another node parameter")
    args = ap.parse_args()
    if os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") != "LOCALHOST" or not os.environ.get("ROS_DOMAIN_ID"):
        ap.error("set ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a ROS_DOMAIN_ID of this run")
    args.work.mkdir(parents=True, exist_ok=True)
    bag = make_bag(args.work, args.frames, args.rate)
    result = run(bag, args.out, args.set)
    (args.out / "robot_rate.json").write_text(json.dumps(result, indent=2) + "\n")
    (args.out / "robot_rate.md").write_text(table(result))
    print(table(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
