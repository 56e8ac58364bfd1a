"""The nodes' camera input: good frames delivered, bad messages dropped and counted, node keeps running."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rclpy")

from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from roigsf_ros.cli.demo import replay_bag
from roigsf_ros.data.bags import BagFrame, CameraTopics
from roigsf_ros.nodes.bag_player import reliable_qos
from roigsf_ros.nodes.camera_input import CameraInput

pytestmark = pytest.mark.ros
W, H = 8, 6


def _header(msg: Any, stamp_ns: int) -> Any:
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    msg.header.frame_id = "camera_color_optical_frame"
    return msg


def _messages(stamp_ns: int, *, depth_encoding: str = "32FC1", depth_w: int = W, qw: float = 1.0) -> dict[str, Any]:
    color = _header(Image(), stamp_ns)
    color.width, color.height, color.encoding, color.step = W, H, "rgb8", 3 * W
    color.data = np.full(H * W * 3, 100, np.uint8).tobytes()
    depth = _header(Image(), stamp_ns)
    depth.width, depth.height, depth.encoding = depth_w, H, depth_encoding
    bpp = 4 if depth_encoding == "32FC1" else 1
    depth.step = bpp * depth_w
    depth.data = (
        np.full(H * depth_w * bpp, 0, np.uint8).tobytes()
        if bpp == 1
        else np.full(H * depth_w, 1.5, np.float32).tobytes()
    )
    info = _header(CameraInfo(), stamp_ns)
    info.width, info.height = W, H
    info.k = [5.0, 0.0, 3.5, 0.0, 5.0, 2.5, 0.0, 0.0, 1.0]
    pose = _header(PoseStamped(), stamp_ns)
    pose.header.frame_id = "map"
    pose.pose.orientation.w = qw
    t = CameraTopics()
    return {t.color: color, t.depth: depth, t.camera_info: info, t.pose: pose}


def test_bad_messages_are_dropped_and_counted(ros_context: Any) -> None:
    frames: list[BagFrame] = []
    node = Node("camera_input_test", context=ros_context)
    qos = reliable_qos(50)
    camera = CameraInput(node, frames.append, qos, max_pending=4)
    pub_node = Node("camera_input_test_pub", context=ros_context)
    types = {"color": Image, "depth": Image, "camera_info": CameraInfo, "pose": PoseStamped}
    pubs = {
        getattr(camera.topics, k): pub_node.create_publisher(v, getattr(camera.topics, k), qos)
        for k, v in types.items()
    }
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(pub_node)
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    try:
        deadline = time.monotonic() + 5.0
        while any(p.get_subscription_count() == 0 for p in pubs.values()) and time.monotonic() < deadline:
            time.sleep(0.02)
        sets = [
            _messages(1_000),  # good
            _messages(2_000, depth_encoding="8UC1"),  # unsupported encoding
            _messages(3_000, depth_w=W + 2),  # size mismatch with camera_info
            _messages(4_000, qw=float("nan")),  # NaN pose
            _messages(6_000),  # good
            *(_messages(k * 1_000) for k in (7, 8, 9, 11, 12)),  # good; 10 000 never sent: a frame missed
        ]
        for msgs in sets:
            for topic, msg in msgs.items():
                pubs[topic].publish(msg)
        only_depth = _messages(5_000)  # depth without colour (and the rest): never completes
        pubs[camera.topics.depth].publish(only_depth[camera.topics.depth])
        deadline = time.monotonic() + 5.0
        while camera.stats()["received"].get(camera.topics.pose, 0) < 10 and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.1)
    finally:
        executor.shutdown()
        spin.join()
        node.destroy_node()
        pub_node.destroy_node()
    stats = camera.stats()
    assert [f.stamp_ns for f in frames] == [1_000, 6_000, 7_000, 8_000, 9_000, 11_000, 12_000]
    # the missing stamp shows as one message lost per topic, one frame (the gap 4 000 -> 6 000 comes
    # before a period is known; the lone depth at 5 000, sent last, is a stray in the depth stream)
    assert stats["missed_estimate"] == dict.fromkeys(camera.topics.types(), 1)
    assert stats["frames_missed_estimate"] == 1
    # counted by short categories (bounded), not by the error text
    assert stats["rejected"] == {"bad_encoding": 1, "size_mismatch": 1, "bad_pose": 1}
    assert "quaternion" in stats["last_rejection"]
    # the lone depth message: out of order if every topic had passed 5 000 when it came (it is sent
    # last), else it waits, bounded by max_pending; never delivered
    assert stats["out_of_order"] + stats["pending"] == 1
    # every frame sent is counted once: 7 delivered, 3 rejected, 1 missed (10 000), the lone depth (5 000)
    frame_counts = ("frames", "dropped_incomplete", "pending", "duplicate_stamp", "out_of_order")
    assert sum(stats[k] for k in frame_counts) + stats["frames_missed_estimate"] + sum(stats["rejected"].values()) == 12
    np.testing.assert_array_equal(frames[0].depth_m, np.full((H, W), 1.5, np.float32))


def test_demo_replay_delivers_every_frame(tmp_path: Path) -> None:
    from roigsf_ros.data import bags
    from roigsf_ros.data.replica import ReplicaSequence
    from roigsf_ros.perf.io import make_synthetic_replica

    make_synthetic_replica(tmp_path / "scene", 16, 12, 6, seed=2)
    bags.write_bag(ReplicaSequence(tmp_path / "scene"), tmp_path / "bag", progress=False)
    import os

    out = replay_bag(tmp_path / "bag", rate=0.0, domain_id=int(os.environ["ROS_DOMAIN_ID"]), progress=False)
    assert out["input"]["frames"] == 6 and len(out["frames"]) == 6
    assert [f.stamp_ns for f in out["frames"]] == sorted(f.stamp_ns for f in out["frames"])
    seq = ReplicaSequence(tmp_path / "scene")
    for got, want in zip(out["frames"], seq, strict=True):
        np.testing.assert_array_equal(got.depth_m, want.depth_m)
        np.testing.assert_allclose(got.T_wc, want.T_wc, atol=1e-12)


def test_demo_command_replays_and_maps(tmp_path: Path) -> None:
    import json

    from roigsf_ros.cli import main
    from roigsf_ros.data import bags
    from roigsf_ros.data.replica import ReplicaSequence
    from roigsf_ros.perf.io import make_synthetic_replica

    make_synthetic_replica(tmp_path / "scene", 32, 24, 4, seed=3)
    bags.write_bag(ReplicaSequence(tmp_path / "scene"), tmp_path / "bag", progress=False)
    run = tmp_path / "run"
    args = ["demo", "--bag", str(tmp_path / "bag"), "--out", str(run), "--rate", "0", "--gt-mesh", "", "--no-progress"]
    assert main([*args, "--policy", "every-n"]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["n_frames"] == 4 and metrics["n_keyframes"] >= 1
    assert (run / "mesh.ply").is_file() and (run / "map.ply").is_file() and (run / "replay.json").is_file()
