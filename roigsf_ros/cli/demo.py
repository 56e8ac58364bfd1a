"""``roigsf demo``: the main job on the shipped bag: replay it over ROS 2 and map what arrives.

The bag is played by the ``bag_player`` node and received by a camera-input node in the same
process (loopback DDS), so the demo exercises the same topics and conversions as a live robot.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

from roigsf_ros.bags import BagFrame, bag_info
from roigsf_ros.fileio import write_json

DEFAULT_BAG = Path("bags/synth_room")
DEFAULT_GT_MESH = Path("bags/synth_room_mesh.ply")


def replay_bag(bag: Path, rate: float, domain_id: int | None = None, progress: bool = True) -> dict[str, Any]:
    """Play ``bag`` with a :class:`BagPlayer` and collect the complete frames a subscriber receives.

    Returns ``{"frames": [BagFrame], "player": summary, "input": counters, "wall_s": s}``. The
    executor is shut down and its thread joined before returning.
    """
    import rclpy
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from tqdm import tqdm

    from roigsf_ros.nodes.bag_player import BagPlayer, reliable_qos
    from roigsf_ros.nodes.camera_input import CameraInput

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    frames: list[BagFrame] = []
    lock = threading.Lock()

    def on_frame(frame: BagFrame) -> None:
        with lock:
            frames.append(frame)

    t0 = time.monotonic()
    executor = MultiThreadedExecutor(num_threads=2, context=context)
    listener = Node("demo_listener", context=context)
    camera = CameraInput(listener, on_frame, reliable_qos(200))
    player = BagPlayer(
        context=context,
        parameter_overrides=[
            Parameter("bag", value=str(bag)),
            Parameter("rate", value=float(rate)),
            Parameter("progress_period_s", value=0.0),
        ],
    )
    executor.add_node(listener)
    executor.add_node(player)
    spin = threading.Thread(target=executor.spin, name="demo_executor", daemon=True)
    spin.start()
    try:
        with tqdm(total=player.total_per_loop, desc="replay", unit="msg", disable=not progress) as bar:
            while not player.wait(0.2):
                bar.update(player.published - bar.n)
            bar.update(player.published - bar.n)
        expected = player.total_per_loop // 4
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and camera.stats()["frames"] + camera.dropped_incomplete < expected:
            time.sleep(0.05)
    finally:
        executor.shutdown()
        spin.join()
        player.destroy_node()
        listener.destroy_node()
        context.try_shutdown()
    return {
        "frames": frames,
        "player": player.summary(),
        "input": camera.stats(),
        "wall_s": time.monotonic() - t0,
    }


def _run(args: argparse.Namespace) -> int:
    bag = Path(args.bag)
    info = bag_info(bag)  # validates the bag before anything runs
    print(
        f"bag {bag}: {info['frame_count']} frames of {info['width']}x{info['height']}, "
        f"depth {info['depth_encoding']}, {info['duration_s']:.1f} s"
    )
    replay = replay_bag(bag, args.rate, args.domain_id, progress=not args.no_progress)
    stats = replay["input"]
    print(f"\nreplayed over ROS 2 in {replay['wall_s']:.1f} s (rate x{args.rate:g}):")
    print(f"  {'topic':<28}{'in bag':>8}{'received':>10}")
    for topic, meta in sorted(info["topics"].items()):
        print(f"  {topic:<28}{meta['count']:>8}{stats['received'].get(topic, 0):>10}")
    print(
        f"  complete frames: {stats['frames']}, rejected: {sum(stats['rejected'].values())}, "
        f"incomplete: {stats['dropped_incomplete']}"
    )
    if not replay["frames"]:
        print("no complete frame arrived; nothing to map", file=sys.stderr)
        return 1

    from roigsf_ros.cli.map import print_summary
    from roigsf_ros.frames import MemoryFrameSource
    from roigsf_ros.keyframes import make_policy
    from roigsf_ros.mapping import MapperConfig, run_offline
    from roigsf_ros.replica import Frame

    frames = [Frame(index=k, rgb=f.rgb, depth_m=f.depth_m, T_wc=f.T_wc) for k, f in enumerate(replay["frames"])]
    source = MemoryFrameSource(frames, replay["frames"][0].intrinsics, f"ROS replay of {bag}")
    gt_mesh = Path(args.gt_mesh) if args.gt_mesh else None
    out = Path(args.out)
    print(f"\nmapping {len(frames)} received frames with keyframe policy {args.policy}")
    metrics = run_offline(
        source, make_policy(args.policy), MapperConfig(), out, gt_mesh=gt_mesh,
        progress=not args.no_progress, overwrite=True,
    )  # fmt: skip
    write_json(
        out / "replay.json", {"bag": str(bag), "player": replay["player"], "input": stats, "wall_s": replay["wall_s"]}
    )
    print(f"\nactive-mapping demo on {bag} -> {out}")
    print_summary(metrics)
    print(f"  results in {out}/: metrics.json, mesh.ply, map.ply, strip.png, replay.json")
    return 0 if stats["frames"] == info["frame_count"] else 1


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``demo`` subcommand."""
    p = sub.add_parser("demo", help="the main job: replay the shipped bag over ROS 2 and map it", description=__doc__)
    p.add_argument("--bag", default=str(DEFAULT_BAG), metavar="BAG", help=f"bag to replay (default {DEFAULT_BAG})")
    p.add_argument("--out", default="runs/demo", metavar="RUN", help="run folder for results (default runs/demo)")
    p.add_argument(
        "--rate",
        type=float,
        default=1.0,
        metavar="X",
        help="playback rate factor; 1.0 real time, <= 0 as fast as possible (default 1.0)",
    )
    p.add_argument(
        "--domain-id",
        type=int,
        default=None,
        metavar="N",
        help="ROS domain id (default: ROS_DOMAIN_ID or 0); discovery stays on localhost",
    )
    p.add_argument(
        "--policy",
        default="gaus-slam",
        metavar="P",
        help="keyframe policy for mapping the received frames (default gaus-slam)",
    )
    p.add_argument(
        "--gt-mesh",
        default=str(DEFAULT_GT_MESH),
        metavar="PLY",
        help=f"ground-truth mesh for the mesh metrics (default {DEFAULT_GT_MESH}; '' for none)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_run)
