"""Bag I/O: Replica -> bag conversion and read-back throughput, and bag_player rate accuracy.

Conversion runs on a synthetic Replica folder made in a temporary folder (deterministic noise colour,
smooth depth, rigid poses) at 1200x680 (native) and 240x136 (resized on load). The player is timed
in-process: a bag of small frames recorded at 10 Hz played at rate 1.0 and as fast as possible, with
a subscriber on a fresh rclpy context on the ROS domain of ``--domain-id`` (default ``ROS_DOMAIN_ID``, else a random
one; discovery on localhost). Every number is a median over repeats.
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import tempfile
import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.frame import Frame
from roigsf_ros.core.ros_domain import check_domain_id, domain_id_from_env
from roigsf_ros.data.bags import BagReader, CameraTopics, write_bag
from roigsf_ros.data.replica import ReplicaSequence, write_replica
from roigsf_ros.perf import check_options, check_out_file, environment, write_results

NATIVE_SIZE = (1200, 680)
SMALL_SIZE = (240, 136)
PLAYER_RATE_HZ = 10.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``roigsf perf io``."""
    parser.add_argument("--out", type=Path, metavar="FILE.json", help="also write the results as JSON here")
    parser.add_argument(
        "--frames", type=int, default=20, metavar="N", help="frames converted per run (default 20, at least 2)"
    )
    parser.add_argument(
        "--messages", type=int, default=30, metavar="M",
        help="frames in the 10 Hz player bag (default 30, at least 2; 4 msgs each)",
    )  # fmt: skip
    parser.add_argument(
        "--repeats", type=int, default=3, metavar="R", help="repeats; medians reported (default 3, at least 1)"
    )
    parser.add_argument("--skip-player", action="store_true", help="skip the ROS player timing (no rclpy needed)")
    parser.add_argument(
        "--domain-id", type=int, default=None, metavar="N",
        help="ROS domain id of the player timing (default: ROS_DOMAIN_ID, else a random one of 1..99); discovery "
        "stays on localhost",
    )  # fmt: skip


def choose_domain_id(given: int | None, environ: Mapping[str, str] | None = None) -> int:
    """The player timing's ROS domain id: ``--domain-id``, else ``ROS_DOMAIN_ID``, else a random one of 1..99 (so two
    runs on one machine rarely hear each other); an id out of 0..232 is an InputError naming where it came from.
    """
    if given is not None:
        return check_domain_id(given)
    from_env = domain_id_from_env(environ)
    return random.SystemRandom().randrange(1, 100) if from_env is None else from_env


def synthetic_frames(intr: Intrinsics, n_frames: int, seed: int = 0) -> Iterator[Frame]:
    """Deterministic frames: uniform noise colour, smooth depth in [1, 3] m with an invalid (0) corner, rigid poses."""
    rng = np.random.default_rng(seed)
    h, w = intr.height, intr.width
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    for k in range(n_frames):
        rgb = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
        depth_m = 2.0 + 0.5 * np.sin(2 * np.pi * xx / w + 0.3 * k) + 0.5 * np.cos(2 * np.pi * yy / h)
        depth_m[: max(1, h // 8), : max(1, w // 8)] = 0.0
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(0.0, np.pi)
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        T_wc = np.eye(4)
        T_wc[:3, :3] = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)
        T_wc[:3, 3] = rng.uniform(-2.0, 2.0, size=3)
        yield Frame(index=k, rgb=rgb, depth_m=depth_m.astype(np.float32), T_wc=T_wc)


def make_synthetic_replica(out_dir: str | Path, width: int, height: int, n_frames: int, seed: int = 0) -> Intrinsics:
    """Write a deterministic ``width`` x ``height`` Replica-layout folder of ``n_frames``; return its intrinsics."""
    intr = Intrinsics(
        width=width, height=height, fx=0.5 * width, fy=0.5 * width, cx=(width - 1) / 2, cy=(height - 1) / 2
    )
    write_replica(out_dir, intr, synthetic_frames(intr, n_frames, seed))
    return intr


def _median(values: list[float]) -> float:
    return float(statistics.median(values)) if values else float("nan")


def bench_conversion(root: Path, n_frames: int, repeats: int) -> dict[str, Any]:
    """Frames/s of Replica -> bag (native and 1/5 size) and of reading each bag back."""
    scene = root / "replica"
    make_synthetic_replica(scene, *NATIVE_SIZE, n_frames)
    results: dict[str, Any] = {}
    for label, size in (("1200x680", None), ("240x136", SMALL_SIZE)):
        seq = ReplicaSequence(scene, size=size)
        write_fps, read_fps, bag_mb = [], [], 0.0
        for r in range(repeats):
            bag = root / f"bag_{label}_{r}"
            t0 = time.perf_counter()
            n = write_bag(seq, bag, progress=False)
            write_fps.append(n / (time.perf_counter() - t0))
            bag_mb = sum(p.stat().st_size for p in bag.iterdir()) / 1e6
            t0 = time.perf_counter()
            with BagReader(bag) as reader:
                n_read = sum(1 for _ in reader.frames())
            read_fps.append(n_read / (time.perf_counter() - t0))
        results[label] = {
            "frames": n_frames,
            "write_fps": _median(write_fps),
            "read_fps": _median(read_fps),
            "bag_mb": bag_mb,
        }
    return results


def _play_and_listen(bag: Path, rate: float, domain_id: int) -> dict[str, Any]:
    """Play ``bag`` in-process at ``rate`` with a subscriber on one executor; arrival times per topic."""
    import rclpy
    import rclpy.logging
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from roigsf_ros.nodes.bag_player import BagPlayer, message_class, reliable_qos

    rclpy.logging.set_logger_level("bag_player", rclpy.logging.LoggingSeverity.WARN)  # no per-run chatter
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    arrivals: dict[str, list[float]] = {}
    nodes: list[Any] = []
    executor = SingleThreadedExecutor(context=ctx)
    thread = threading.Thread(target=executor.spin, name="perf_io_executor")
    try:
        sink = rclpy.create_node("perf_io_sink", context=ctx)
        nodes.append(sink)
        types = CameraTopics().types()
        with BagReader(bag) as reader:
            expected = reader.message_count()
        for topic, typ in types.items():
            arrivals[topic] = []
            sink.create_subscription(
                message_class(typ),
                topic,
                lambda _msg, times=arrivals[topic]: times.append(time.monotonic()),
                reliable_qos(100),
                raw=True,
            )
        player = BagPlayer(
            context=ctx,
            parameter_overrides=[
                Parameter("bag", value=str(bag)),
                Parameter("rate", value=float(rate)),
                Parameter("start_delay_s", value=0.5),
                Parameter("progress_period_s", value=0.0),
            ],
        )
        nodes.append(player)
        executor.add_node(sink)
        executor.add_node(player)
        thread.start()
        player.wait()
        deadline = time.monotonic() + 2.0
        while sum(map(len, arrivals.values())) < expected and time.monotonic() < deadline:
            time.sleep(0.01)
        summary = player.summary()
    finally:
        executor.shutdown()
        if thread.is_alive():
            thread.join()
        for node in nodes:
            node.destroy_node()
        ctx.try_shutdown()
    received = sum(map(len, arrivals.values()))
    return {"arrivals": arrivals, "expected": expected, "lost": expected - received, "summary": summary}


def bench_player(root: Path, n_frames: int, repeats: int, domain_id: int) -> dict[str, Any]:
    """Inter-arrival error and achieved rate of bag_player at rate 1.0 (10 Hz bag) and unthrottled, on ``domain_id``
    (:func:`choose_domain_id`).
    """
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    scene = root / "player_replica"
    make_synthetic_replica(scene, 32, 24, n_frames, seed=1)
    bag = root / "player_bag"
    write_bag(ReplicaSequence(scene), bag, rate_hz=PLAYER_RATE_HZ, progress=False)
    pose_topic = "/camera/pose"
    timed: dict[str, list[float]] = {"median_err_ms": [], "p95_err_ms": [], "rate_hz": [], "lost": []}
    fast: dict[str, list[float]] = {"msgs_per_s": [], "lost": []}
    for _ in range(repeats):
        res = _play_and_listen(bag, 1.0, domain_id)
        t = np.asarray(res["arrivals"][pose_topic])
        if t.size >= 2:
            err_ms = np.abs(np.diff(t) - 1.0 / PLAYER_RATE_HZ) * 1e3
            timed["median_err_ms"].append(float(np.median(err_ms)))
            timed["p95_err_ms"].append(float(np.percentile(err_ms, 95)))
            timed["rate_hz"].append((t.size - 1) / float(t[-1] - t[0]))
        timed["lost"].append(res["lost"])
        res = _play_and_listen(bag, 0.0, domain_id)
        every = np.sort(np.concatenate([np.asarray(v) for v in res["arrivals"].values()]))
        if every.size >= 2:
            fast["msgs_per_s"].append((every.size - 1) / float(every[-1] - every[0]))
        fast["lost"].append(res["lost"])
    return {
        "frames": n_frames,
        "messages": 4 * n_frames,
        "bag_rate_hz": PLAYER_RATE_HZ,
        "domain_id": domain_id,
        "rate_1": {k: _median(v) for k, v in timed.items()},
        "unthrottled": {k: _median(v) for k, v in fast.items()},
    }


def format_table(results: dict[str, Any]) -> str:
    """A readable table of the results."""
    lines = ["bag conversion (synthetic Replica, 32FC1 depth)", f"  {'size':<10} {'write fr/s':>11} {'read fr/s':>10}"]
    for label, r in results["conversion"].items():
        lines.append(f"  {label:<10} {r['write_fps']:>11.1f} {r['read_fps']:>10.1f}   ({r['bag_mb']:.1f} MB)")
    player = results.get("player")
    if player:
        r1, fast = player["rate_1"], player["unthrottled"]
        lines += [
            f"bag_player ({player['frames']} frames x 4 topics recorded at {player['bag_rate_hz']:g} Hz)",
            f"  rate 1.0: inter-arrival error median {r1['median_err_ms']:.2f} ms, p95 {r1['p95_err_ms']:.2f} ms, "
            f"achieved {r1['rate_hz']:.3f} Hz, lost {r1['lost']:.0f}",
            f"  rate max: {fast['msgs_per_s']:.0f} msgs/s, lost {fast['lost']:.0f}",
        ]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Run the I/O benchmarks, print a table, and write JSON if asked."""
    check_options(args, {"frames": 2, "messages": 2, "repeats": 1})
    if args.domain_id is not None:  # also with --skip-player: a nonsense id is refused wherever it is typed
        check_domain_id(args.domain_id)
    check_out_file(args.out, "io")
    load_before = os.getloadavg()[0]
    domain_id = None if args.skip_player else choose_domain_id(args.domain_id)
    results: dict[str, Any] = {"benchmark": "io", "repeats": args.repeats}
    with tempfile.TemporaryDirectory(prefix="roigsf_perf_io_") as tmp:
        results["conversion"] = bench_conversion(Path(tmp), args.frames, args.repeats)
        if domain_id is not None:
            results["player"] = bench_player(Path(tmp), args.messages, args.repeats, domain_id)
    results["environment"] = environment(load_before)
    print(format_table(results))
    write_results(args.out, results)
    return 0
