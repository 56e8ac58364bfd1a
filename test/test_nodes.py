"""The ROS 2 nodes in-process: NBV service vs offline scoring, refusals, bad input, parameters, replay, save/load."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

pytest.importorskip("rclpy")
pytest.importorskip("roigsf_interfaces")

from geometry_msgs.msg import PoseArray, PoseStamped
from rcl_interfaces.srv import GetParameters
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import String
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker

from roigsf_interfaces.srv import GetNextBestView, LoadMap, SaveMap
from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame
from roigsf_ros.data import bags
from roigsf_ros.data.replica import ReplicaSequence
from roigsf_ros.data.scene import render_sequence, synth_room, synth_trajectory
from roigsf_ros.mapping.mapper import Mapper, MapperConfig, valid_depth_mask
from roigsf_ros.nbv import warmup
from roigsf_ros.nbv.config import NBVConfig
from roigsf_ros.nbv.novelty import ObservedSurface, fuse_novelty
from roigsf_ros.nbv.scorer import NBVScorer
from roigsf_ros.nbv.state import TrainFisherCache, carry_rows, match_surfels
from roigsf_ros.nodes import mapper as mapper_module
from roigsf_ros.nodes import nbv_planner as nbv_planner_module
from roigsf_ros.nodes.active_mapping import ActiveMapping, build_nodes
from roigsf_ros.nodes.bag_player import BagPlayer, reliable_qos
from roigsf_ros.nodes.keyframe_selector import ASK_AGAIN_S, KeyframeSelectorNode
from roigsf_ros.nodes.map_msgs import cloud_to_surfel_map, header, pose_stamped, poses_to_array, surfel_map_to_cloud
from roigsf_ros.nodes.mapper import MapperNode, latched_qos
from roigsf_ros.nodes.nbv_planner import NBVPlannerNode, map_not_ready
from roigsf_ros.nodes.node_process import GIL_SWITCH_INTERVAL_S, BackgroundSpin, reduce_gil_switch_interval
from roigsf_ros.nodes.shared_map import SharedMapper, decimate_mesh, read_keyframe_ids
from roigsf_ros.policies.base import make_policy

pytestmark = pytest.mark.ros
REPO = Path(__file__).resolve().parents[1]
INTR = Intrinsics(width=64, height=48, fx=40.0, fy=40.0, cx=31.5, cy=23.5)
N_FRAMES = 12


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[Frame], Path]:
    """12 frames of a synthetic room at 64x48 (rendered from its mesh), and the same as a 10 Hz bag."""
    root = tmp_path_factory.mktemp("nodes")
    render_sequence(synth_room(3), synth_trajectory(3, N_FRAMES), INTR, root / "scene", progress=False)
    bags.write_bag(ReplicaSequence(root / "scene"), root / "bag", progress=False)
    return list(ReplicaSequence(root / "scene")), root / "bag"


@pytest.fixture(scope="module")
def mapped(scene: tuple[list[Frame], Path]) -> Mapper:
    """A small map of keyframes 0, 4 and 8 (3 steps each), built offline with the library."""
    mapper = Mapper(INTR, MapperConfig(iters_per_keyframe=3))
    for i in (0, 4, 8):
        assert mapper.add_keyframe(scene[0][i])
    return mapper


def _shared(mapper: Mapper) -> SharedMapper:
    shared = SharedMapper(mapper.config)
    shared.mapper = mapper
    return shared


@contextmanager
def _spinning(ctx: Any, *nodes: Node) -> Iterator[MultiThreadedExecutor]:
    """Spin ``nodes`` on a multi-threaded executor in a thread; shut down, join and destroy on exit."""
    executor = MultiThreadedExecutor(num_threads=4, context=ctx)
    for node in nodes:
        executor.add_node(node)
    spin = BackgroundSpin(executor, "test_executor").start()
    try:
        yield executor
    finally:
        spin.stop()
        for node in nodes:
            node.destroy_node()


def _wait(pred: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.02)


def _call(client: Any, req: Any, timeout_s: float = 60.0) -> Any:
    assert client.wait_for_service(timeout_sec=10.0), f"service {client.srv_name} not available"
    future = client.call_async(req)
    _wait(future.done, timeout_s, f"an answer from {client.srv_name}")
    return future.result()


def _request(poses: np.ndarray | list[np.ndarray], frame_id: str = "map", mode: str = "") -> GetNextBestView.Request:
    req = GetNextBestView.Request(top_k=3, mode=mode)
    req.candidates = poses_to_array(poses, 0, frame_id)
    return req


# ---------------------------------------------------------------------------------------- planner
KEPT = {"unseen_weight": 1.0, "unseen_source": "carved", "unseen_measure": "rays", "unseen_carve_rerender": False}
"""F2's unseen term (the ray count) with its carved grid kept between requests."""


@pytest.mark.parametrize(
    "params", [{}, {"unseen_weight": 1.0, "unseen_source": "carved"}, KEPT], ids=["paper", "carved", "kept-grid"]
)
def test_service_ranks_like_offline_scoring(ros_context: Any, scene: Any, mapped: Mapper, params: dict) -> None:
    """The planner's service answers as the library scores, in the paper's mode and with options beyond it set as
    ROS parameters (the carved unseen term, which needs the keyframe poses the shared map carries; the same with its
    grid kept, rendered once per keyframe, which on an unchanged map scores as rendering at every request)."""
    frames, _ = scene
    cands = [frames[i].T_wc for i in (1, 2, 5, 10, 11)]
    # The library's own path: the stream policy's TSDF of rendered depth at the keyframes, its scorer.
    policy = make_policy("roi-gsurfisher", **params)
    policy.sync_tsdf(mapped)
    scorer = NBVScorer(policy.config)
    offline = scorer.score(mapped.map, mapped.h_train, policy.tsdf, mapped.keyframe_poses, cands, INTR)
    assert (offline.unseen is not None) == bool(params)

    overrides = [Parameter(k, value=v) for k, v in params.items()]
    planner = NBVPlannerNode(context=ros_context, shared=_shared(mapped), parameter_overrides=overrides)
    client_node = Node("nbv_test_client", context=ros_context)
    best_poses: list[PoseStamped] = []
    client_node.create_subscription(PoseStamped, "/nbv_planner/best_view", best_poses.append, latched_qos())
    images: list[Image] = []
    client_node.create_subscription(Image, "/nbv_planner/uncertainty", images.append, latched_qos())
    published: list[dict[str, Any]] = []
    client_node.create_subscription(String, "/nbv_planner/status", lambda m: published.append(json.loads(m.data)), 10)
    client = client_node.create_client(GetNextBestView, "/nbv_planner/get_next_best_view")
    with _spinning(ros_context, planner, client_node):
        res = _call(client, _request(cands))
        again = _call(client, _request(cands))
        _wait(lambda: bool(best_poses) and bool(images), 10.0, "best view and uncertainty image")
        _wait(lambda: any(p["answered"] == 2 for p in published), 10.0, "~/status after both answers")
        status = planner.status()
    assert [p for p in published if p["answered"] == 2][-1]["slowest_phases_s"] == status["slowest_phases_s"]
    assert res.success, res.message
    assert list(again.fused_scores) == list(res.fused_scores)
    kept = 3 if params.get("unseen_carve_rerender") is False else 0  # each of the 3 keyframes rendered once
    assert (status["carved_renders"], status["carved_carves"]) == (kept, kept)
    phases = status["last_phases_s"]  # where the last request's time went: the map work, then the scorer's phases
    assert {"map_update", "scoring", "setup", "h_train", "roi", "fisher", "unseen"} <= set(phases), phases
    assert all(v >= 0 for v in phases.values()), phases
    slowest = status["slowest_phases_s"]
    assert slowest.keys() == phases.keys()
    assert slowest["map_update"] + slowest["scoring"] >= phases["map_update"] + phases["scoring"]
    assert res.best_index == offline.best_index
    assert list(res.top_k_indices) == offline.ranking[:3].tolist()
    np.testing.assert_allclose(res.fused_scores, offline.fused, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(res.fisher_scores, offline.fisher, rtol=1e-6)
    np.testing.assert_allclose(res.close_front_scores, offline.close_front, rtol=1e-6)
    assert np.ptp(offline.fused) > 0.5  # the candidates really differ: a ranking to agree on
    best = best_poses[-1].pose.position
    np.testing.assert_allclose([best.x, best.y, best.z], cands[offline.best_index][:3, 3], atol=1e-9)
    u = np.frombuffer(bytes(images[-1].data), "<f4").reshape(INTR.height, INTR.width)
    assert images[-1].encoding == "32FC1" and np.isfinite(u).all() and u.max() > 0


def test_service_refuses_with_a_reason(ros_context: Any, scene: Any, capfd: Any) -> None:
    """Each refusal says why to its caller; the log says each kind of fault (a walk's eight bad requests in a second
    logged the first, an empty list, alone: one throttle for all)."""
    frames, _ = scene
    shared = SharedMapper()
    planner = NBVPlannerNode(context=ros_context, shared=shared)
    client_node = Node("nbv_test_client2", context=ros_context)
    client = client_node.create_client(GetNextBestView, "/nbv_planner/get_next_best_view")
    poses = [frames[1].T_wc, frames[2].T_wc]
    with _spinning(ros_context, planner, client_node):
        no_map = _call(client, _request(poses))
        shared.ensure(INTR)  # a map object with no keyframe yet
        empty_map = _call(client, _request(poses))
        shared.mapper.add_keyframe(frames[0])
        empty_list = _call(client, _request([]))
        bad = _request(poses)
        bad.candidates.poses[1].orientation.w += 0.3
        bad_quat = _call(client, bad)
        wrong_frame = _call(client, _request(poses, frame_id="odom"))
        wrong_mode = _call(client, _request(poses, mode="best"))
        ok = _call(client, _request(poses, mode="close-front"))
    for res, reason in (
        (no_map, "map: not ready: no keyframe in the shared map yet"),
        (empty_map, "map: not ready: 0 keyframes, 0 surfels"),
        (empty_list, "empty candidate list"),
        (bad_quat, "candidates[1]"),
        (wrong_frame, "'odom' is not the map frame"),
        (wrong_mode, "unknown score mode 'best'"),
    ):
        assert not res.success and reason in res.message and res.best_index == -1
        assert not res.fused_scores
    assert ok.success and all(np.isfinite(ok.fused_scores)) and len(ok.close_front_scores) == 2
    assert planner.status()["failed"] == 6 and planner.status()["answered"] == 1
    # a walk: the status counted refusals without a word of why, and "map: not ready" among them
    assert planner.status()["not_ready"] == 2 and "unknown score mode 'best'" in planner.status()["last_refusal"]
    err = capfd.readouterr().err
    for said in ("empty candidate list", "candidates[1]", "'odom' is not the map frame", "unknown score mode 'best'"):
        assert "get_next_best_view: " in err and said in err, (said, err)
    # on its own (three processes), the planner names the topics it has heard nothing on: a planner given the
    # camera settings of the other two but not camera_info_topic failed every window with "no map yet"
    alone = NBVPlannerNode(context=ros_context, parameter_overrides=[Parameter("warm_up", value=False)])
    try:
        assert alone._waiting_for() == (
            "nothing received yet: a map on /roigsf/map and camera info on /roigsf/map_camera_info (the mapper's) or "
            "/camera/camera_info"
        )
    finally:
        alone.destroy_node()


def test_service_refuses_more_than_max_candidates_and_serves_on(ros_context: Any, scene: Any, mapped: Mapper) -> None:
    """65 candidates (default ``max_candidates`` 64): ``success: false`` naming the limit, before any scoring.

    Before: any number was scored; 10,000 held the service for minutes and every request queued behind it.
    """
    frames, _ = scene
    planner = NBVPlannerNode(context=ros_context, shared=_shared(mapped))
    client_node = Node("nbv_test_client_max", context=ros_context)
    client = client_node.create_client(GetNextBestView, "/nbv_planner/get_next_best_view")
    with _spinning(ros_context, planner, client_node):
        t0 = time.monotonic()
        too_many = _call(client, _request([frames[1 + i % 10].T_wc for i in range(65)]))
        refused_in_s = time.monotonic() - t0
        ok = _call(client, _request([frames[1].T_wc, frames[2].T_wc]))
    assert not too_many.success and too_many.best_index == -1 and not too_many.fused_scores
    assert "candidates: 65 poses, more than max_candidates (64)" in too_many.message
    assert refused_in_s < 5.0  # nothing scored (65 candidates take several seconds here)
    assert ok.success and len(ok.fused_scores) == 2
    assert planner.status()["failed"] == 1 and planner.status()["answered"] == 1


def test_a_burst_of_requests_is_answered_every_one(ros_context: Any, scene: Any, mapped: Mapper) -> None:
    """30 requests sent at once: each gets its answer. Before: the service kept the last 10 waiting (rclpy's
    default), 19 of 30 got none, and a client without a timeout waited forever.
    """
    frames, _ = scene
    planner = NBVPlannerNode(context=ros_context, shared=_shared(mapped))
    client_node = Node("nbv_test_client_burst", context=ros_context)
    client = client_node.create_client(GetNextBestView, "/nbv_planner/get_next_best_view")
    with _spinning(ros_context, planner, client_node):
        assert client.wait_for_service(timeout_sec=10.0)
        futures = [client.call_async(_request([frames[1 + i % 10].T_wc, frames[2].T_wc])) for i in range(30)]
        _wait(lambda: all(f.done() for f in futures), 120.0, "30 answers")
        answers = [f.result() for f in futures]
    assert all(a.success and len(a.fused_scores) == 2 for a in answers)
    assert planner.status()["answered"] == 30


def test_stop_interrupts_scoring_within_a_candidate(ros_context: Any, scene: Any, mapped: Mapper) -> None:
    """``stop()`` (what Ctrl-C calls) during a long request: it answers ``success: false`` within a candidate's work.

    Before: the callback scored every candidate (minutes for thousands) and shutdown waited for it.
    """
    frames, _ = scene
    planner = NBVPlannerNode(
        context=ros_context, shared=_shared(mapped), parameter_overrides=[Parameter("max_candidates", value=5000)]
    )
    req = _request([frames[i % N_FRAMES].T_wc for i in range(3000)])
    answer: list[GetNextBestView.Response] = []
    worker = threading.Thread(
        target=lambda: answer.append(planner._on_request(req, GetNextBestView.Response())), daemon=True
    )
    try:
        worker.start()
        time.sleep(1.5)
        assert worker.is_alive() and not answer  # scoring 3000 candidates: a minute or more
        t0 = time.monotonic()
        planner.stop()
        worker.join(timeout=30)
        took_s = time.monotonic() - t0
    finally:
        planner.stop()
        worker.join(timeout=120)
        planner.destroy_node()
    assert not worker.is_alive() and took_s < 3.0, f"scoring went on for {took_s:.1f} s after stop()"
    assert not answer[0].success and "shutting down" in answer[0].message and answer[0].best_index == -1
    assert planner.status()["failed"] == 1 and planner.status()["answered"] == 0


def test_scoring_does_not_block_the_executor(ros_context: Any, scene: Any, mapped: Mapper) -> None:
    frames, _ = scene
    planner = NBVPlannerNode(context=ros_context, shared=_shared(mapped))
    release = threading.Event()
    started = threading.Event()
    score = planner.score_request

    def held_score(req: Any) -> Any:  # holds the scoring callback until the test saw other callbacks run
        started.set()
        assert release.wait(30.0)
        return score(req)

    planner.score_request = held_score  # type: ignore[method-assign]
    client_node = Node("nbv_test_client3", context=ros_context)
    nbv = client_node.create_client(GetNextBestView, "/nbv_planner/get_next_best_view")
    params = client_node.create_client(GetParameters, "/nbv_planner/get_parameters")
    with _spinning(ros_context, planner, client_node):
        assert nbv.wait_for_service(timeout_sec=10.0) and params.wait_for_service(timeout_sec=10.0)
        pending = nbv.call_async(_request([frames[1].T_wc, frames[2].T_wc]))
        assert started.wait(10.0)
        answer = _call(params, GetParameters.Request(names=["mode", "epsilon"]), timeout_s=10.0)
        assert not pending.done()  # the planner node answered while its scoring callback was running
        release.set()
        _wait(pending.done, 60.0, "the NBV answer")
    assert [v.string_value for v in answer.values[:1]] == ["roi-gsurfisher"] and answer.values[1].double_value == 0.4
    assert pending.result().success


# ---------------------------------------------------------------------------------------- camera input
def _frame_msgs(frame: Frame, stamp_ns: int, *, encoding: str = "32FC1", width: int = INTR.width) -> dict[str, Any]:
    t = bags.CameraTopics()
    color = Image(header=header(stamp_ns, "cam"), height=INTR.height, width=INTR.width, encoding="rgb8")
    color.step, color.data = 3 * INTR.width, np.ascontiguousarray(frame.rgb).tobytes()
    depth_m = np.zeros((INTR.height, width), np.float32)
    depth_m[:, : min(width, INTR.width)] = frame.depth_m[:, :width]
    depth = Image(header=header(stamp_ns, "cam"), height=INTR.height, width=width, encoding=encoding)
    depth.step, depth.data = 4 * width, depth_m.tobytes()
    info = CameraInfo(header=header(stamp_ns, "cam"), height=INTR.height, width=INTR.width)
    info.k = INTR.K.reshape(-1).tolist()
    return {t.color: color, t.depth: depth, t.camera_info: info, t.pose: pose_stamped(frame.T_wc, stamp_ns)}


class _Camera:
    """Publishes frames on the camera topics (reliable, as the bag player)."""

    def __init__(self, ctx: Any) -> None:
        self.node = Node("test_camera", context=ctx)
        types = {"color": Image, "depth": Image, "camera_info": CameraInfo, "pose": PoseStamped}
        t = bags.CameraTopics()
        self.pubs = {
            getattr(t, k): self.node.create_publisher(v, getattr(t, k), reliable_qos(100)) for k, v in types.items()
        }
        self.keyframes = self.node.create_publisher(PoseStamped, "/roigsf/keyframe", reliable_qos(100))

    def wait_for(self, n_subscribers: int = 1) -> None:
        _wait(lambda: all(p.get_subscription_count() >= n_subscribers for p in self.pubs.values()), 10, "subscribers")

    def publish(self, msgs: dict[str, Any], skip: tuple[str, ...] = ()) -> None:
        for topic, msg in msgs.items():
            if topic not in skip:
                self.pubs[topic].publish(msg)


def test_bad_camera_messages_are_dropped_and_counted(ros_context: Any, scene: Any) -> None:
    frames, _ = scene
    t = bags.CameraTopics()
    # A keyframe waits keyframe_wait_s (default 10 s) for its frame: 2 s here, and the test waits far longer for the
    # count (a wait equal to the node's own failed on a loaded 2-core machine).
    overrides = [Parameter("iters_per_keyframe", value=1), Parameter("keyframe_wait_s", value=2.0)]
    mapper = MapperNode(context=ros_context, parameter_overrides=overrides)
    cam = _Camera(ros_context)
    with _spinning(ros_context, mapper, cam.node):
        cam.wait_for()
        cam.publish(_frame_msgs(frames[0], 1_000, encoding="8UC1"))  # unsupported encoding
        cam.publish(_frame_msgs(frames[0], 2_000, width=INTR.width - 2))  # size mismatch with camera_info
        nan_pose = _frame_msgs(frames[0], 3_000)
        nan_pose[t.pose].pose.orientation.x = float("nan")
        cam.publish(nan_pose)
        cam.publish(_frame_msgs(frames[0], 4_000), skip=(t.color,))  # depth without colour
        cam.publish(_frame_msgs(frames[1], 5_000))  # good
        _wait(lambda: mapper.status()["frames_received"] == 1, 10.0, "the good frame")
        cam.keyframes.publish(pose_stamped(frames[1].T_wc, 5_000))
        cam.keyframes.publish(pose_stamped(frames[1].T_wc, 4_000))  # its frame never completed: missing
        _wait(lambda: mapper.status()["keyframes"] == 1, 30.0, "the keyframe")
        _wait(lambda: mapper.status()["keyframes_missing"] == 1, 30.0, "the missing keyframe counted")
        cam.keyframes.publish(pose_stamped(frames[1].T_wc, 5_000))  # named again (a looped bag): said, not only counted
        _wait(lambda: mapper.status()["keyframes_duplicate"] == 1, 30.0, "the repeated keyframe counted")
        status = mapper.status()
    assert status["last_keyframe_drop"].startswith("keyframe 5000: named before (in the map or on its way), not ")
    assert status["frames_rejected"] == {"bad_encoding": 1, "size_mismatch": 1, "bad_pose": 1}  # short categories
    assert mapper.camera.stats()["pending"] == 1  # the colourless stamp waits, bounded
    assert status["keyframe_ids"] == [5_000] and status["surfels"] > 0 and status["keyframes_failed"] == 0


def test_a_keyframe_whose_frame_is_gone_says_why(ros_context: Any, scene: Any, capfd: Any) -> None:
    """A keyframe named on a refused frame, or on one older than the frame buffer reaches back (the README's
    RealSense command at 30 Hz with a window of 30: 5 of 10 keyframes), said "never received or already left the
    buffer"; now the refusal's reason, or how far back the buffer reaches and the parameter to raise."""
    frames, _ = scene
    overrides = [Parameter("iters_per_keyframe", value=1), Parameter("frame_buffer_size", value=2)]
    mapper = MapperNode(context=ros_context, parameter_overrides=overrides)
    cam = _Camera(ros_context)
    with _spinning(ros_context, mapper, cam.node):
        cam.wait_for()
        cam.publish(_frame_msgs(frames[0], 1_000, encoding="8UC1"))  # refused: unsupported encoding
        for k, stamp in enumerate((2_000, 3_000, 4_000)):
            cam.publish(_frame_msgs(frames[k], stamp))
        _wait(lambda: mapper.status()["frames_received"] == 3, 10.0, "three good frames")
        cam.keyframes.publish(pose_stamped(frames[0].T_wc, 1_000))
        _wait(lambda: mapper.status()["keyframes_missing"] == 1, 10.0, "the refused frame's keyframe")
        refused = mapper.status()["last_keyframe_drop"]
        cam.keyframes.publish(pose_stamped(frames[0].T_wc, 2_000))  # the buffer holds 3_000 and 4_000 only
        _wait(lambda: mapper.status()["keyframes_missing"] == 2, 10.0, "the old frame's keyframe")
        old = mapper.status()["last_keyframe_drop"]  # in ~/status: the second warning is throttled
        other_camera = _frame_msgs(frames[3], 5_000)
        other_camera[bags.CameraTopics().camera_info].k[0] *= 1.5  # another focal length than the map's
        cam.publish(other_camera)
        _wait(lambda: mapper.status()["frames_bad_intrinsics"] == 1, 10.0, "the other camera's frame")
        cam.keyframes.publish(pose_stamped(frames[3].T_wc, 5_000))
        _wait(lambda: mapper.status()["keyframes_missing"] == 3, 10.0, "the other camera's keyframe")
        other = mapper.status()["last_keyframe_drop"]
        # named before its frame came, then the frame refused: dropped with the reason at once, not after the wait
        cam.keyframes.publish(pose_stamped(frames[3].T_wc, 6_000))
        _wait(lambda: mapper.status()["pending_keyframes"] == 0 and mapper._waiting, 10.0, "the keyframe waiting")
        t0 = time.monotonic()
        cam.publish(_frame_msgs(frames[3], 6_000, encoding="8UC1"))
        _wait(lambda: mapper.status()["keyframes_missing"] == 4, 5.0, "the waiting keyframe's refusal")
        waited = time.monotonic() - t0
        early = mapper.status()["last_keyframe_drop"]
    assert waited < 3.0 and early.startswith("keyframe 6000: its frame was refused (bad_encoding: "), (waited, early)
    # was: "their frames did not arrive within 10 s", for frames that came with another camera's intrinsics
    assert other.startswith("keyframe 5000: its frame was refused (bad_intrinsics: camera_info: intrinsics "), other
    assert "the map takes its camera from the first frame it receives" in other  # a wrong first camera_info: restart
    assert refused.startswith("keyframe 1000: its frame was refused (bad_encoding: "), refused
    assert "keyframe 1000: its frame was refused (bad_encoding: " in capfd.readouterr().err
    assert old.startswith("keyframe 2000: its frame was already out of the buffer, which holds the last 2 frames"), old
    assert old.endswith("raise frame_buffer_size; dropped")


def test_a_keyframe_without_valid_depth_is_said_with_its_topic(ros_context: Any, scene: Any, capfd: Any) -> None:
    """A keyframe whose depth image has no valid pixel was counted as ``keyframes_failed`` ("inserting them failed")
    and said only as the library's "frame N: no valid depth": the sensor's fault read as the mapper's, with no topic.
    Now its own counter, the depth topic and the values in the warning and in ``last_keyframe_drop``."""
    frames, _ = scene
    mapper = MapperNode(context=ros_context, parameter_overrides=[Parameter("iters_per_keyframe", value=1)])
    cam = _Camera(ros_context)
    depth_topic = bags.CameraTopics().depth
    with _spinning(ros_context, mapper, cam.node):
        cam.wait_for()
        cam.publish(_frame_msgs(frames[0], 1_000))
        cam.publish(_frame_msgs(replace(frames[1], depth_m=np.zeros_like(frames[1].depth_m)), 2_000))
        cam.publish(_frame_msgs(replace(frames[2], depth_m=frames[2].depth_m * 1000.0), 3_000))  # mm as metres
        _wait(lambda: mapper.status()["frames_received"] == 3, 10.0, "three frames")
        cam.keyframes.publish(pose_stamped(frames[0].T_wc, 1_000))
        _wait(lambda: mapper.status()["keyframes"] == 1, 30.0, "the good keyframe")
        cam.keyframes.publish(pose_stamped(frames[1].T_wc, 2_000))
        _wait(lambda: mapper.status()["keyframes_no_depth"] == 1, 30.0, "the depthless keyframe counted")
        empty = mapper.status()["last_keyframe_drop"]
        cam.keyframes.publish(pose_stamped(frames[2].T_wc, 3_000))
        _wait(lambda: mapper.status()["keyframes_no_depth"] == 2, 30.0, "the millimetre keyframe counted")
        status = mapper.status()
    assert status["keyframes_failed"] == 0 and status["keyframe_ids"] == [1_000], status
    said = f"its depth image on {depth_topic} has no valid depth"
    assert empty.startswith(f"keyframe 2000: {said} (every value NaN"), empty
    assert empty.endswith("; not mapped"), empty
    mm = status["last_keyframe_drop"]
    assert mm.startswith(f"keyframe 3000: {said} (finite values "), mm
    assert "millimetres given as metres?" in mm
    assert f"keyframe 2000: its depth image on {depth_topic}" in capfd.readouterr().err  # said, not only counted


# ---------------------------------------------------------------------------------------- selector
def _windowed_selector(
    ctx: Any, service: str, timeout_s: float = 10.0, **params: Any
) -> tuple[KeyframeSelectorNode, _Camera, list[int]]:
    """A roi-fisher selector with windows of 2 asking ``service`` (and ``params``), a camera, and the keyframe stamps
    it publishes."""
    overrides = [
        Parameter("policy", value="roi-fisher"),
        Parameter("window", value=2),
        Parameter("planner_service", value=service),
        Parameter("planner_timeout_s", value=timeout_s),
        *(Parameter(k, value=v) for k, v in params.items()),
    ]
    selector = KeyframeSelectorNode(context=ctx, parameter_overrides=overrides)
    cam = _Camera(ctx)
    published: list[int] = []
    cam.node.create_subscription(
        PoseStamped, "/roigsf/keyframe", lambda m: published.append(bags.stamp_to_ns(m.header.stamp)), reliable_qos(50)
    )
    return selector, cam, published


def _publish_window(cam: _Camera, frames: list[Frame], k: int) -> None:
    """Frames 2k+1 and 2k+2 (stamps (i + 1) * 1000): one full window of 2 after the first frame."""
    for i in (2 * k + 1, 2 * k + 2):
        cam.publish(_frame_msgs(frames[i], (i + 1) * 1000))


def test_keyframes_named_before_the_mapper_subscribed_are_held_and_sent_in_order(ros_context: Any, scene: Any) -> None:
    """Three processes: the selector named the first keyframes before discovery matched the mapper's subscription,
    and the volatile topic dropped them without a word (every-n lost frames 0, 5 and 10). They are held until a
    subscriber matches, then sent in order; the status counts those still held.
    """
    frames, _ = scene
    # startup_wait_s 0: the camera read before any keyframe subscriber (as after the start-up wait ran out)
    overrides = [
        Parameter("policy", value="every-n"),
        Parameter("every_n", value=2),
        Parameter("startup_wait_s", value=0.0),
    ]
    selector = KeyframeSelectorNode(context=ros_context, parameter_overrides=overrides)
    cam = _Camera(ros_context)
    late = Node("test_late_mapper", context=ros_context)
    got: list[int] = []
    with _spinning(ros_context, selector, cam.node, late):
        cam.wait_for()
        for i in range(5):
            cam.publish(_frame_msgs(frames[i], (i + 1) * 1000))
        _wait(lambda: selector.status()["keyframes_published"] == 3, 10.0, "three keyframes named")
        time.sleep(0.3)
        assert selector.status()["keyframes_unsent"] == 3  # nobody subscribed: held, not lost
        late.create_subscription(
            PoseStamped, "/roigsf/keyframe", lambda m: got.append(bags.stamp_to_ns(m.header.stamp)), reliable_qos(50)
        )
        _wait(lambda: len(got) == 3, 10.0, "the held keyframes")
        cam.publish(_frame_msgs(frames[5], 6000))
        cam.publish(_frame_msgs(frames[6], 7000))
        _wait(lambda: len(got) == 4, 10.0, "a keyframe named after the match")
        status = selector.status()
    assert got == [1000, 3000, 5000, 7000] and status["keyframes_unsent"] == 0
    assert status["keyframes_dropped_unsent"] == 0


@contextmanager
def _stub_planner(ctx: Any, name: str, serve: Callable[..., Any]) -> Iterator[None]:
    """A node ``name`` serving ``~/nbv`` (GetNextBestView) with ``serve`` on its own two-thread executor."""
    planner = Node(name, context=ctx)
    planner.create_service(GetNextBestView, "~/nbv", serve, callback_group=ReentrantCallbackGroup())
    executor = MultiThreadedExecutor(num_threads=2, context=ctx)
    executor.add_node(planner)
    spin = BackgroundSpin(executor, f"{name}_executor").start()
    try:
        yield
    finally:
        spin.stop()
        planner.destroy_node()


def test_selector_reads_the_camera_once_its_keyframe_subscriber_and_planner_are_there(ros_context: Any) -> None:
    """Three processes: in a third of the runs the mapper's discovery came 2.5-3 s after the player's, and the
    selector, reading frames already, held its first keyframe that long and asked a planner with no map about its
    first windows (fallbacks). It now subscribes to the camera only once a keyframe subscriber and (planner policy)
    the planner's service are there, so a player waiting for its subscribers waits for the whole pipeline; without
    them it reads the camera after ``startup_wait_s``, saying what is missing. A hidden node's subscriber (a
    ``ros2 topic echo``) opened the gate too; it no longer does."""
    color = "/camera/color/image_raw"
    probe = Node("test_gate_probe", context=ros_context)
    echo = Node("_test_gate_echo", context=ros_context)
    params = [Parameter("policy", value="roi-fisher"), Parameter("planner_service", value="/test_gate/nbv")]
    selector = KeyframeSelectorNode(context=ros_context, parameter_overrides=params, node_name="gate_selector")
    alone = KeyframeSelectorNode(
        context=ros_context,
        parameter_overrides=[Parameter("policy", value="every-n"), Parameter("startup_wait_s", value=0.5),
                             Parameter("keyframe_topic", value="/test_gate/nobody")],
        node_name="gate_alone",
    )  # fmt: skip
    with _spinning(ros_context, selector, alone, probe, echo):
        _wait(lambda: alone.status()["reading_camera"], 5.0, "the lone selector giving up waiting")
        time.sleep(0.5)
        assert probe.count_subscribers(color) == 1  # the lone one only
        assert not selector.status()["reading_camera"]
        assert selector.outputs_missing() == [
            "subscriber on /roigsf/keyframe (the mapper)",
            "planner service /test_gate/nbv",
        ]
        # a hidden node's subscriber (``ros2 topic echo /roigsf/keyframe`` is one) is not the mapper
        echo.create_subscription(PoseStamped, "/roigsf/keyframe", lambda m: None, reliable_qos(10))
        _wait(lambda: selector._pub.get_subscription_count() == 1, 10.0, "the hidden subscriber's match")
        time.sleep(0.3)
        assert len(selector.outputs_missing()) == 2 and not selector.status()["reading_camera"]
        probe.create_subscription(PoseStamped, "/roigsf/keyframe", lambda m: None, reliable_qos(10))
        _wait(lambda: len(selector.outputs_missing()) == 1, 10.0, "the keyframe subscriber")
        time.sleep(0.3)
        assert probe.count_subscribers(color) == 1  # still no planner: still not reading
        with _stub_planner(ros_context, "test_gate", lambda req, res: res):
            _wait(lambda: probe.count_subscribers(color) == 2, 10.0, "the selector's camera subscription")
            assert selector.status()["reading_camera"] and selector.outputs_missing() == []


def test_a_window_asks_again_while_the_planners_map_is_not_ready(ros_context: Any, scene: Any) -> None:
    """Three processes: the first windows came before the mapper had published its first keyframe's map, the planner
    answered "map: not ready", and they went to the fallback. A window now asks again (``map_wait_s``) and is decided
    by the planner once its map is in; past ``map_wait_s``, or when a newer window waits, it falls back, and
    ``map_wait_s`` 0 falls back at once."""
    frames, _ = scene
    not_ready = {"left": 2}
    asks: list[float] = []

    def serve(req: GetNextBestView.Request, res: GetNextBestView.Response) -> GetNextBestView.Response:
        asks.append(time.monotonic())
        if not_ready["left"] > 0:
            not_ready["left"] -= 1
            res.success, res.best_index = False, -1
            res.message = str(map_not_ready("nothing received yet: a map on /roigsf/map"))
            return res
        res.success, res.best_index = True, 0  # the fallback (random, seed 0) picks the other frame
        return res

    def run(map_wait_s: float, n_not_ready: int) -> tuple[dict[str, Any], list[int]]:
        not_ready["left"] = n_not_ready
        asks.clear()
        selector, cam, published = _windowed_selector(ros_context, "/test_planner/nbv", map_wait_s=map_wait_s)
        with _spinning(ros_context, selector, cam.node):
            _wait(selector._client.service_is_ready, 10.0, "the stub planner")
            cam.wait_for()
            cam.publish(_frame_msgs(frames[0], 1000))
            _publish_window(cam, frames, 0)
            _wait(lambda: len(published) == 2, 10.0, "the window's keyframe")
            return selector.status(), published

    with _stub_planner(ros_context, "test_planner", serve):
        status, published = run(5.0, 2)
        assert published == [1000, 2000]  # the planner's pick (index 0), not the fallback's
        assert status["planner_not_ready"] == 2 and status["planner_calls"] == 3 and status["planner_answers"] == 1
        assert status["fallbacks"] == 0 and status["planner_failures"] == 0
        assert asks[2] - asks[0] >= 2 * ASK_AGAIN_S - 0.05  # asked again after a pause, not in a busy loop
        status, _ = run(1.0, 100)  # never ready: falls back once map_wait_s has passed
        assert status["fallbacks"] == 1 and status["planner_failures"] == 1 and status["planner_answers"] == 0
        assert status["planner_not_ready"] >= 1 and status["planner_calls"] == status["planner_not_ready"] + 1
        # no ask started after map_wait_s: the last one started before 1.0 s, and came within one ask-again period
        # (1.02 s once in a fresh clone on two loaded cores: the stub received it 20 ms after it was sent)
        assert asks[-1] - asks[0] < 1.0 + ASK_AGAIN_S
        status, _ = run(0.0, 1)  # map_wait_s 0: the old behaviour, at once
        assert status["fallbacks"] == 1 and status["planner_calls"] == 1 and status["planner_not_ready"] == 0
        # A newer window comes while the older waits for the map: the older goes to the fallback at once and the
        # newer is asked (waiting on, the older would hold it back, and a third window would drop the newer).
        not_ready["left"] = 10_000
        selector, cam, published = _windowed_selector(ros_context, "/test_planner/nbv", map_wait_s=30.0)
        with _spinning(ros_context, selector, cam.node):
            _wait(selector._client.service_is_ready, 10.0, "the stub planner")
            cam.wait_for()
            cam.publish(_frame_msgs(frames[0], 1000))
            _publish_window(cam, frames, 0)
            _wait(lambda: selector.status()["planner_not_ready"] >= 1, 10.0, "a 'map not ready' answer")
            _publish_window(cam, frames, 1)
            _wait(lambda: selector.status()["fallbacks"] == 1, 10.0, "the older window's fallback")
            not_ready["left"] = 0
            _wait(lambda: len(published) == 3, 10.0, "the newer window's keyframe")
            status = selector.status()
        assert published[0] == 1000 and published[1] in (2000, 3000) and published[2] == 4000  # the planner's pick
        assert status["planner_answers"] == 1 and status["planner_failures"] == 1 and status["planner_timeouts"] == 0


def test_selector_falls_back_and_resumes_with_the_planner(ros_context: Any, scene: Any) -> None:
    frames, _ = scene
    selector, cam, published = _windowed_selector(ros_context, "/test_planner/nbv", 0.3, startup_wait_s=0.0)
    mode = {"answer": True}
    seen: list[str] = []

    def serve(req: GetNextBestView.Request, res: GetNextBestView.Response) -> GetNextBestView.Response:
        seen.append(req.mode)
        if not mode["answer"]:
            time.sleep(1.0)  # longer than planner_timeout_s
        res.success, res.best_index = True, 1
        return res

    with _spinning(ros_context, selector, cam.node):
        cam.wait_for()
        cam.publish(_frame_msgs(frames[0], 1000))  # the first frame: always a keyframe
        _publish_window(cam, frames, 0)  # no planner yet: fallback (random)
        _wait(lambda: selector.status()["fallbacks"] == 1 and len(published) == 2, 10.0, "a fallback keyframe")
        with _stub_planner(ros_context, "test_planner", serve):
            _wait(selector._client.service_is_ready, 10.0, "the stub planner")
            _publish_window(cam, frames, 1)  # answered: the planner's pick (index 1 = frame 4, stamp 5000)
            _wait(lambda: selector.status()["planner_answers"] == 1, 10.0, "the planner's answer")
            mode["answer"] = False
            _publish_window(cam, frames, 2)  # the planner is too slow: timeout, fallback
            _wait(lambda: selector.status()["planner_timeouts"] == 1, 10.0, "a timeout")
            time.sleep(0.8)  # let the slow call end
            mode["answer"] = True
            _publish_window(cam, frames, 3)  # and back to the planner
            _wait(lambda: selector.status()["planner_answers"] == 2, 10.0, "the planner again")
            _wait(lambda: len(published) == 5, 10.0, "five keyframes")
        status = selector.status()
    assert published[0] == 1000 and published[2] == 5000 and published[4] == 9000
    assert published[1] in (2000, 3000) and published[3] in (6000, 7000)
    assert status["fallbacks"] == 2 and status["planner_calls"] == 3 and seen[0] == "roi-fisher"
    assert status["keyframe_ids"] == published


def test_a_fallback_says_when_no_planner_serves_the_service_and_counts_them(
    ros_context: Any, scene: Any, capfd: Any
) -> None:
    """A planner killed mid-run: the selector logged "is still busy with two windows before this one" and "did not
    answer within 10 s", never that the planner was gone, and its throttled log showed 4 fallbacks where ~/status
    counted 11. Each fallback line now says when no node serves the service, and how many fallbacks so far."""
    frames, _ = scene
    selector, cam, _ = _windowed_selector(ros_context, "/test_gone/nbv")
    try:
        with selector._lock:
            selector._fall_back(frames[1:3], INTR, "did not answer within 10 s", [])
            selector._fall_back(frames[3:5], INTR, "is not available", [])
        err = capfd.readouterr().err
        assert (
            "planner /test_gone/nbv did not answer within 10 s; no node serves it now (the planner stopped?): "
            "fallback random (1 so far)" in err
        ), err
        assert "planner /test_gone/nbv is not available: fallback random (2 so far)" in err, err
        assert selector.status()["fallbacks"] == 2
    finally:
        selector.destroy_node()
        cam.node.destroy_node()


def test_a_window_that_comes_while_the_planner_answers_waits_for_it(ros_context: Any, scene: Any) -> None:
    """A window due while the previous one is in flight waits for its answer (no fallback); of two, the older
    waiting one goes to the fallback, so the selector is never more than one window behind."""
    frames, _ = scene
    selector, cam, published = _windowed_selector(ros_context, "/test_planner_wait/nbv", 10.0)
    release = threading.Event()
    sizes: list[int] = []

    def serve(req: GetNextBestView.Request, res: GetNextBestView.Response) -> GetNextBestView.Response:
        sizes.append(len(req.candidates.poses))
        release.wait(10.0)  # answer only when the test says so
        res.success, res.best_index = True, 1
        return res

    with _stub_planner(ros_context, "test_planner_wait", serve), _spinning(ros_context, selector, cam.node):
        try:
            cam.wait_for()
            _wait(selector._client.service_is_ready, 10.0, "the stub planner")
            cam.publish(_frame_msgs(frames[0], 1000))  # the first frame: always a keyframe
            _publish_window(cam, frames, 0)  # sent; held by the planner
            _wait(lambda: len(sizes) == 1, 10.0, "the first request")
            _publish_window(cam, frames, 1)  # due while window 0 is in flight: waits
            _wait(lambda: selector.status()["planner_window_waiting"], 10.0, "a waiting window")
            _wait(lambda: len(published) == 1, 10.0, "the first keyframe")
            waiting = selector.status()
            assert waiting["fallbacks"] == 0 and waiting["planner_calls"] == 1 and len(published) == 1
            release.set()  # window 0 answered (frame 2, stamp 3000), then window 1 sent and answered (stamp 5000)
            _wait(lambda: selector.status()["planner_answers"] == 2, 10.0, "both answers")
            release.clear()
            _publish_window(cam, frames, 2)  # sent, held
            _wait(lambda: len(sizes) == 3, 10.0, "the third request")
            _publish_window(cam, frames, 3)  # waits
            _publish_window(cam, frames, 4)  # a second waiting window: the older one (window 3) goes to the fallback
            _wait(lambda: selector.status()["fallbacks"] == 1, 10.0, "the older waiting window decided alone")
            release.set()
            _wait(lambda: selector.status()["planner_answers"] == 4, 10.0, "the answers to windows 2 and 4")
            _wait(lambda: len(published) == 6, 10.0, "six keyframes")
            status = selector.status()
        finally:
            release.set()  # a handler still waiting returns before the executors stop
    assert published[:3] == [1000, 3000, 5000] and published[3] in (8000, 9000)  # window 3's fallback
    assert sorted(published[4:]) == [7000, 11000]
    assert status["planner_calls"] == 4 and status["planner_waited"] == 3 and status["fallbacks"] == 1
    assert not status["planner_pending"] and not status["planner_window_waiting"]


def _novelty_sequence(frames: list[Frame], n_windows: int) -> list[Frame]:
    """Frame 0, then windows of 2 whose second frame is, in odd windows, frame 0 again (nothing new to show)."""
    seq = [frames[0]]
    for k in range(n_windows):
        seq += [frames[2 * k + 1], frames[0] if k % 2 else frames[2 * k + 2]]
    return seq


def _novelty_picks(seq: list[Frame], fused: list[float] | None = None) -> tuple[list[int], list[int]]:
    """Stamps ((i + 1) * 1000 for seq[i]) and window positions the observed novelty picks for the windows of 2 after
    the first frame: the library's ObservedSurface with the default settings and depth range, alone or fused with
    ``fused`` at weight 1."""
    surface, cfg = ObservedSurface(), MapperConfig()

    def novelty(f: Frame) -> float:
        return surface.new_area_m2(f.depth_m, f.T_wc, INTR, valid_depth_mask(f.depth_m, cfg))

    surface.add(seq[0].depth_m, seq[0].T_wc, INTR, valid_depth_mask(seq[0].depth_m, cfg))
    stamps, positions = [1000], []
    for first in range(1, len(seq) - 1, 2):
        n = np.array([novelty(seq[first]), novelty(seq[first + 1])])
        i = int(np.argmax(n if fused is None else fuse_novelty(np.array(fused), n, 1.0)))
        win = seq[first + i]
        surface.add(win.depth_m, win.T_wc, INTR, valid_depth_mask(win.depth_m, cfg))
        stamps.append((first + i + 1) * 1000)
        positions.append(i)
    return stamps, positions


@pytest.mark.parametrize("policy", ["novelty", "roi-fisher"])
def test_selector_picks_by_observed_novelty_alone_and_as_the_fallback(
    ros_context: Any, scene: Any, policy: str
) -> None:
    """Policy novelty decides alone; with a planner policy and no planner, fallback_policy novelty decides."""
    frames, _ = scene
    overrides = [
        Parameter("policy", value=policy),
        Parameter("window", value=2),
        Parameter("fallback_policy", value="novelty"),
        Parameter("planner_service", value="/no_planner_here/nbv"),
        Parameter("startup_wait_s", value=0.0),  # no mapper, no planner: read the camera at once
    ]
    selector = KeyframeSelectorNode(context=ros_context, parameter_overrides=overrides)
    cam = _Camera(ros_context)
    seq = _novelty_sequence(frames, 5)
    expected, positions = _novelty_picks(seq)
    assert positions == [1, 0, 1, 0, 1]  # the repeated frame 0 never wins: a fixed position would fail
    with _spinning(ros_context, selector, cam.node):
        cam.wait_for()
        for i, frame in enumerate(seq):
            cam.publish(_frame_msgs(frame, (i + 1) * 1000))
        _wait(lambda: selector.status()["keyframes_published"] == 6, 20.0, "six keyframes")
        status = selector.status()
    assert status["keyframe_ids"] == expected
    assert status["fallbacks"] == (5 if policy == "roi-fisher" else 0)


@pytest.mark.parametrize("policy", ["random", "roi-fisher"])
def test_status_window_shows_the_frames_held_by_a_policy_deciding_alone_too(
    ros_context: Any, scene: Any, policy: str
) -> None:
    """``~/status``'s ``window`` showed the planner path's window only: with ``random`` (its window held by the
    library's policy) it was always empty. Both now list the candidate window; ``~/finish`` without lookahead said
    "nothing held" beside it, and now says why there is nothing to decide.
    """
    frames, _ = scene
    overrides = [
        Parameter("policy", value=policy),
        Parameter("window", value=4),
        Parameter("planner_service", value="/no_planner_here/nbv"),
        Parameter("startup_wait_s", value=0.0),
    ]
    selector = KeyframeSelectorNode(context=ros_context, parameter_overrides=overrides)
    cam = _Camera(ros_context)
    with _spinning(ros_context, selector, cam.node):
        cam.wait_for()
        for i in range(3):  # the first is a keyframe; the next two wait for the window to fill
            cam.publish(_frame_msgs(frames[i], (i + 1) * 1000))
        _wait(lambda: selector.status()["frames"] == 3, 20.0, "three frames")
        status = selector.status()
    assert status["keyframe_ids"] == [1000] and status["window"] == [2000, 3000], status  # frame ids: stamps (ns)
    answer = selector._on_finish(Trigger.Request(), Trigger.Response())
    assert answer.success and "with lookahead 0 every window was decided at its trigger (the 2 frames" in answer.message


def test_a_parameter_set_at_run_time_is_refused_saying_it_is_read_at_start(ros_context: Any) -> None:
    """``ros2 param set /nbv_planner max_candidates -5`` answered successful and the node went on with its old value
    (it reads its parameters once): every parameter is now read-only once declared, and its description says how to
    change it; the value stays the one the node runs with.
    """
    from roigsf_ros.nodes.node_params import READ_AT_START

    selector = KeyframeSelectorNode(context=ros_context, parameter_overrides=[Parameter("startup_wait_s", value=0.0)])
    try:
        result = selector.set_parameters([Parameter("window", value=-5)])[0]
        assert not result.successful and "read-only parameter: window" in result.reason, result
        assert selector.get_parameter("window").value == 8 and selector.window == 8
        assert selector.describe_parameter("window").description.endswith(f"({READ_AT_START})")
        assert selector.describe_parameter("window").read_only
    finally:
        selector.destroy_node()


def test_a_policy_added_to_the_library_runs_in_the_selector_by_name(
    ros_context: Any, scene: Any, mapped: Mapper, monkeypatch: pytest.MonkeyPatch
) -> None:
    """docs/architecture.md: a policy registered in the library is found by name in the keyframe_selector node too,
    with the node's parameters its constructor takes and ``policy_params`` for its own; one that returns nonsense or
    raises leaves the frame undecided, counted, and the node goes on (the node refused any name but the built-ins)."""
    from roigsf_ros.policies import base

    monkeypatch.setattr(base, "_REGISTRY", dict(base._REGISTRY))  # registered for this test only

    @base.register_policy("test-every-k")
    class EveryK(base.KeyframePolicy):
        def __init__(self, k: int = 2, window: int = 1, fail_at: int = -1) -> None:
            self.k, self.window, self.fail_at, self.seen, self.surfels = k, window, fail_at, 0, []

        def params(self) -> dict[str, Any]:
            return {"k": self.k, "window": self.window, "fail_at": self.fail_at}

        def observe(self, frame: Frame, keyframe_map: Any) -> list[Frame]:
            self.seen += 1
            if self.seen == self.fail_at:
                return frame  # type: ignore[return-value]  # a bare Frame, not a list
            if self.seen == self.fail_at + 1:
                raise RuntimeError("the policy's own bug")
            self.surfels.append(keyframe_map.n_surfels)  # it reads the map the mapper publishes
            return [frame] if self.seen % self.k == 1 else []

    frames, _ = scene
    overrides = [Parameter("policy", value="test-every-k"), Parameter("policy_params", value="k=3:fail_at=4"),
                 Parameter("window", value=5), Parameter("startup_wait_s", value=0.0)]  # fmt: skip
    selector = KeyframeSelectorNode(context=ros_context, parameter_overrides=overrides)
    policy = selector._alone
    assert isinstance(policy, EveryK) and (policy.k, policy.window, policy.fail_at) == (3, 5, 4)
    cam = _Camera(ros_context)
    map_pub = cam.node.create_publisher(PointCloud2, "/roigsf/map", latched_qos())  # as the mapper in its process
    map_pub.publish(surfel_map_to_cloud(mapped.map, 1, "map", mapped.h_train, mapped.config.fisher_outputs))
    with _spinning(ros_context, selector, cam.node):
        cam.wait_for()
        _wait(lambda: selector._cloud is not None, 10.0, "the map")  # it subscribed to gaus-slam's map only
        for i in range(8):
            cam.publish(_frame_msgs(frames[i % len(frames)], (i + 1) * 1000))
        _wait(lambda: selector.status()["frames"] == 8, 20.0, "eight frames")
        status = selector.status()
    # seen 1, 4 (refused: a bare Frame), 5 (raised), 7: the 4th and 5th frames were not decided, the node went on
    assert status["keyframe_ids"] == [1000, 7000] and status["policy_errors"] == 2, status
    assert policy.surfels and set(policy.surfels) == {mapped.n_surfels}
    assert status["policy_params"] == {"k": 3, "window": 5, "fail_at": 4}  # what it ran with, not only its name
    for why, words in (
        ("k", "^parameter 'keyframe_selector.policy_params': expected NAME=VALUE pairs"),
        ("k=2:nosuch=1", r"^parameter 'keyframe_selector.policy_params': takes no parameter\(s\) nosuch"),
        ("window=3", "^parameter 'keyframe_selector.policy_params': window is a parameter of the node itself: set it"),
    ):
        params = [Parameter("policy", value="test-every-k"), Parameter("policy_params", value=why)]
        with pytest.raises(InputError, match=words):
            KeyframeSelectorNode(context=ros_context, parameter_overrides=params)
    typo = r"unknown policy 'test-every-kk' \(did you mean 'test-every-k'\?\); choose one of roi-gsurfisher"
    with pytest.raises(InputError, match=typo):
        KeyframeSelectorNode(context=ros_context, parameter_overrides=[Parameter("policy", value="test-every-kk")])
    with pytest.raises(InputError, match=r"policy_params.*asks the planner"):
        KeyframeSelectorNode(context=ros_context, parameter_overrides=[Parameter("policy_params", value="k=1")])


def test_the_planner_says_when_the_maps_publisher_is_gone(ros_context: Any, mapped: Mapper, capfd: Any) -> None:
    """The mapper killed mid-run: the planner went on answering from its last map and neither its log nor its
    ~/status said the map no longer came. Now it warns once, ``map_publisher_gone`` is in its status, and it says
    when a publisher is back."""
    planner = NBVPlannerNode(context=ros_context, parameter_overrides=[Parameter("warm_up", value=False)])
    probe = Node("test_map_source", context=ros_context)
    cloud = surfel_map_to_cloud(mapped.map, 1, "map", mapped.h_train, mapped.config.fisher_outputs)
    try:
        with _spinning(ros_context, planner, probe):
            map_pub = probe.create_publisher(PointCloud2, "/roigsf/map", latched_qos())
            map_pub.publish(cloud)
            _wait(lambda: planner._cloud is not None, 10.0, "the map")
            assert planner.status()["map_publisher_gone"] is False
            probe.destroy_publisher(map_pub)  # the mapper stopped
            _wait(lambda: planner.status()["map_publisher_gone"], 10.0, "the publisher's absence noticed")
            probe.create_publisher(PointCloud2, "/roigsf/map", latched_qos())
            _wait(lambda: not planner.status()["map_publisher_gone"], 10.0, "a publisher back")
    finally:
        planner.destroy_node()
        probe.destroy_node()
    err = capfd.readouterr().err
    assert "no node publishes the map on /roigsf/map now (the mapper stopped?): requests are answered from the " \
        "last map received, which no longer grows" in err, err  # fmt: skip
    assert "a node publishes the map on /roigsf/map again" in err, err


def test_remapped_topics_are_watched_and_named_as_subscribed(mapped: Mapper, capfd: Any) -> None:
    """A walk: with ``-r /roigsf/map:=/x/map`` the planner mapped and scored, yet said "no node publishes the map on
    /roigsf/map now (the mapper stopped?)" and set ``map_publisher_gone``: it counted publishers on the parameter's
    name, not on the topic it subscribed to. Its graph checks and the camera input's start-up line now use the names
    as subscribed (namespace and remapping applied).

    Each name is remapped once, as ROS does (the first rule that matches): the review found the nodes subscribing
    with the remapped name, which rcl remapped again, so a chain of rules (``a:=b b:=c``, here the second rule of each
    pair) took them a step further than ROS goes."""
    import rclpy

    from roigsf_ros.nodes.camera_input import CameraInput, describe_topics

    ctx = rclpy.Context()
    remaps = ["--ros-args", "-r", "/roigsf/map:=/x/map", "-r", "/x/map:=/y/map",
              "-r", "/camera/color/image_raw:=/my/cam/image", "-r", "/my/cam/image:=/other/image"]  # fmt: skip
    rclpy.init(args=remaps, context=ctx, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
    try:
        planner = NBVPlannerNode(context=ctx, parameter_overrides=[Parameter("warm_up", value=False)])
        probe = Node("test_remapped_source", context=ctx)
        camera = CameraInput(probe, lambda bf: None, reliable_qos(10), subscribe=False)
        assert camera.topics.color == "/my/cam/image" and "colour /my/cam/image (raw)" in describe_topics(camera.topics)
        camera.subscribe()
        subscribed = {name for name, _ in probe.get_subscriber_names_and_types_by_node("test_remapped_source", "/")}
        assert "/my/cam/image" in subscribed and "/other/image" not in subscribed, subscribed
        cloud = surfel_map_to_cloud(mapped.map, 1, "map", mapped.h_train, mapped.config.fisher_outputs)
        source = Node("test_unremapped_source", context=ctx, use_global_arguments=False)  # publishes on /x/map itself
        with _spinning(ctx, planner, probe, source):  # destroys them on exit
            source.create_publisher(PointCloud2, "/x/map", latched_qos()).publish(cloud)
            _wait(lambda: planner._cloud is not None, 10.0, "the map on the remapped topic")
            planner._watch_map_publisher()
            assert planner.status()["map_publisher_gone"] is False
    finally:
        ctx.try_shutdown()
    err = capfd.readouterr().err
    assert "no node publishes the map" not in err and "/x/map" in err, err  # the start-up line names it


def test_use_sim_time_is_read_only_and_a_silent_clock_is_said(
    ros_context: Any, scene: Any, mapped: Mapper, capfd: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A walk: ``use_sim_time`` was the one parameter a running node let change; switched on with nothing on /clock,
    every timer stopped (``~/status`` too, and ``roigsf ros status`` asked whether status_rate_hz was 0) and every
    request stamped on wall time was refused as "from the future" without naming the clock. It is refused at run time
    now; a node started with it says when no time comes on /clock, and the planner's refusal names /clock."""
    import roigsf_ros.nodes.node_params

    frames, _ = scene
    monkeypatch.setattr(roigsf_ros.nodes.node_params, "SIM_CLOCK_GRACE_S", 0.2)
    planner = NBVPlannerNode(context=ros_context, shared=_shared(mapped),
                             parameter_overrides=[Parameter("use_sim_time", value=True)])  # fmt: skip
    awake = NBVPlannerNode(context=ros_context, shared=_shared(mapped), node_name="awake")
    with _spinning(ros_context, planner, awake):  # destroys both on exit
        refused = awake.set_parameters([Parameter("use_sim_time", value=True)])[0]
        assert not refused.successful and "use_sim_time is read at start-up" in refused.reason, refused
        assert awake.get_parameter("use_sim_time").value is False
        _wait(lambda: "no time came on /clock" in capfd.readouterr().err, 5.0, "the /clock warning")
        req = _request([frames[1].T_wc, frames[2].T_wc])
        req.candidates.header = header(time.time_ns(), "map")  # a client on wall time
        res = planner._on_request(req, GetNextBestView.Response())
    assert not res.success and "the planner runs on /clock, use_sim_time, which reads 0.0 s" in res.message, res.message


def test_an_empty_frame_id_is_refused_and_a_leading_slash_is_the_same_frame(
    ros_context: Any, scene: Any, mapped: Mapper, capfd: Any
) -> None:
    """A walk: ``-p frame_id:=''`` was taken, so every request in the map frame would be refused as "'map' is not the
    map frame ''" and every output stamped in no frame; and a request in ``/map`` was refused against ``map``, which
    TF reads as one frame. Now the empty one is refused at start-up by each node, and ``/map`` is ``map``."""
    for cls in (NBVPlannerNode, KeyframeSelectorNode, MapperNode):
        with pytest.raises(InputError, match=r"parameter '\w+\.frame_id': must name a TF frame \(e.g. map\), got an"):
            cls(context=ros_context, parameter_overrides=[Parameter("frame_id", value=""), *(
                [Parameter("warm_up", value=False)] if cls is NBVPlannerNode else [])])  # fmt: skip
    with pytest.raises(InputError, match=r"TF frame ids do not start with '/' \(tf2 refuses them\): write 'map'"):
        MapperNode(context=ros_context, parameter_overrides=[Parameter("frame_id", value="/map")])
    frames, _ = scene
    planner = NBVPlannerNode(context=ros_context, shared=_shared(mapped))
    try:
        req = _request([frames[1].T_wc, frames[2].T_wc])
        req.candidates.header.frame_id = "/map"
        assert planner._on_request(req, GetNextBestView.Response()).success
        req.candidates.header.frame_id = "odom"
        res = planner._on_request(req, GetNextBestView.Response())
        assert not res.success and "'odom' is not the map frame 'map'" in res.message, res.message
        capfd.readouterr()
        req.candidates.header.frame_id = "map"
        for position in ((float("nan"), 0.0, 0.0), (1e6, 0.0, 0.0)):  # two faults of one field: each logged
            req.candidates.poses[0].position.x, req.candidates.poses[0].position.y = position[:2]
            assert not planner._on_request(req, GetNextBestView.Response()).success
        logged = [line for line in capfd.readouterr().err.splitlines() if "get_next_best_view: candidates[0]" in line]
        assert len(logged) == 2, logged
    finally:
        planner.destroy_node()


def test_start_up_lines_name_the_nodes_own_settings_off_their_defaults(ros_context: Any, capfd: Any) -> None:
    """A walk: the planner's start-up line named only the method's settings, so ``max_candidates:=16`` and
    ``input_width:=80`` (the README: it "names the settings it runs with that differ from the defaults") went
    unsaid. The three nodes' lines now name their own settings off the defaults too."""
    overrides = [Parameter("warm_up", value=False), Parameter("max_candidates", value=16),
                 Parameter("input_width", value=80), Parameter("unseen_weight", value=2.0)]  # fmt: skip
    NBVPlannerNode(context=ros_context, parameter_overrides=overrides).destroy_node()
    MapperNode(context=ros_context, parameter_overrides=[Parameter("frame_buffer_size", value=7)]).destroy_node()
    default = MapperNode(context=ros_context, node_name="plain_mapper")
    default.destroy_node()
    err = capfd.readouterr().err
    assert "scoring (roi-gsurfisher; unseen_weight=2.0, input_width=80, max_candidates=16) against" in err, err
    assert "(own map; frame_buffer_size=7)" in err and "(own map)" in err, err  # and nothing on the defaults


def test_a_missing_load_map_folder_is_said_as_the_parameter_and_a_folder(ros_context: Any, tmp_path: Path) -> None:
    """``mapper -p load_map:=/nope`` said "/nope/keyframes.json: not found (not a saved map folder)": neither the
    parameter nor that the folder itself is missing."""
    (tmp_path / "file").write_text("x")
    for path, why in ((tmp_path / "nope", "no such map folder"), (tmp_path / "file", "is a file, not a saved map")):
        with pytest.raises(InputError, match=f"^parameter 'mapper.load_map': {path}: {why}"):
            MapperNode(context=ros_context, parameter_overrides=[Parameter("load_map", value=str(path))])


def test_under_a_namespace_the_selector_asks_its_own_planner() -> None:
    """``active_mapping ... -r __ns:=/robot1`` served the planner at ``/robot1/nbv_planner/get_next_best_view`` while
    the selector asked the absolute default ``/nbv_planner/...``: no answer, every window to the random fallback. The
    default is relative now, so both resolve in the namespace (and without one, as before)."""
    import rclpy

    for args, where in (([], "/nbv_planner/get_next_best_view"),
                        (["--ros-args", "-r", "__ns:=/robot1"], "/robot1/nbv_planner/get_next_best_view")):  # fmt: skip
        ctx = rclpy.Context()
        rclpy.init(args=args, context=ctx, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
        try:
            planner = NBVPlannerNode(context=ctx, parameter_overrides=[Parameter("warm_up", value=False)])
            selector = KeyframeSelectorNode(context=ctx, parameter_overrides=[Parameter("startup_wait_s", value=0.0)])
            served = [srv.service_name for srv in planner.services if srv.srv_name.endswith("get_next_best_view")]
            assert served == [where] and selector.service_name == where, (served, selector.service_name)
            selector.destroy_node()
            planner.destroy_node()
        finally:
            ctx.try_shutdown()


def test_the_selector_takes_the_map_only_for_a_policy_that_reads_it(
    ros_context: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The selector kept its own list of the policies that need no map beside the library's registry, so a policy
    added to the library was always given the map; now each policy says (``KeyframePolicy.reads_map``) and the
    selector subscribes to the mapper's map for those that read it only (alone, or as the fallback)."""
    from roigsf_ros.policies import base

    monkeypatch.setattr(base, "_REGISTRY", dict(base._REGISTRY))  # registered for this test only

    @base.register_policy("test-no-map")
    class NoMap(base.KeyframePolicy):
        reads_map = False

        def observe(self, frame: Frame, keyframe_map: Any) -> list[Frame]:
            return [frame]

    cases = [("gaus-slam", "random", True), ("random", "random", False), ("every-n", "random", False),
             ("all", "random", False), ("novelty", "random", False), ("test-no-map", "random", False),
             ("roi-gsurfisher", "random", False), ("roi-gsurfisher", "gaus-slam", True)]  # fmt: skip
    for policy, fallback, reads in cases:
        params = [Parameter("policy", value=policy), Parameter("fallback_policy", value=fallback),
                  Parameter("startup_wait_s", value=0.0)]  # fmt: skip
        node = KeyframeSelectorNode(context=ros_context, parameter_overrides=params)
        try:
            subscribed = any(sub.topic_name == "/roigsf/map" for sub in node.subscriptions)
            assert (node.reads_map, subscribed) == (reads, reads), (policy, fallback)
        finally:
            node.destroy_node()


@pytest.mark.parametrize(("policy", "measure"), [("novelty", "area"), ("roi-fisher", "area"), ("novelty", "pixels")])
def test_selector_lookahead_decides_each_window_as_the_library_does(
    ros_context: Any, scene: Any, policy: str, measure: str
) -> None:
    """``lookahead`` 2: each window of 2 is decided once the next 2 frames judged it, as the library's policy decides
    (alone, and as the fallback of a planner policy without a planner), with the novelty in either measure."""
    frames, _ = scene
    seq = [replace(f, index=i) for i, f in enumerate(_novelty_sequence(frames, 5))]
    library = make_policy("novelty", window=2, lookahead=2, novelty_measure=measure)
    view = Mapper(INTR, MapperConfig())
    expected = [(f.index + 1) * 1000 for frame in seq for f in library.observe(frame, view)]
    assert len(expected) == 5 and library.triggers == 4  # the first window waits for the frames after it
    last = [(f.index + 1) * 1000 for f in library.finish(view)]  # the end of the stream decides the rest
    assert len(last) == 1
    plain = make_policy("novelty", window=2)
    assert expected != [(f.index + 1) * 1000 for frame in seq[:-2] for f in plain.observe(frame, view)]
    if measure != "area":  # the measure changes the picks here: a node that dropped it would publish others
        area = make_policy("novelty", window=2, lookahead=2)
        assert expected != [(f.index + 1) * 1000 for frame in seq for f in area.observe(frame, view)]
    overrides = [
        Parameter("policy", value=policy),
        Parameter("window", value=2),
        Parameter("lookahead", value=2),
        Parameter("novelty_measure", value=measure),
        Parameter("fallback_policy", value="novelty"),
        Parameter("novelty_weight", value=1.0 if policy != "novelty" else 0.0),
        Parameter("planner_service", value="/no_planner_here/nbv"),
        Parameter("startup_wait_s", value=0.0),  # no mapper, no planner: read the camera at once
    ]
    selector = KeyframeSelectorNode(context=ros_context, parameter_overrides=overrides)
    cam = _Camera(ros_context)
    with _spinning(ros_context, selector, cam.node):
        cam.wait_for()
        for frame in seq:
            cam.publish(_frame_msgs(frame, (frame.index + 1) * 1000))
        _wait(lambda: selector.status()["keyframes_published"] == 5, 20.0, "five keyframes")
        time.sleep(0.3)
        status = selector.status()
        assert status["keyframe_ids"] == expected
        client = cam.node.create_client(Trigger, "/keyframe_selector/finish")
        assert client.wait_for_service(timeout_sec=10.0)
        answer = _call(client, Trigger.Request())
        assert answer.success and "held frames" in answer.message
        _wait(lambda: selector.status()["keyframes_published"] == 6, 20.0, "the last keyframe")
        assert selector.finish() == 0  # once: nothing is held any more
        status = selector.status()
    assert status["keyframe_ids"] == expected + last
    assert status["fallbacks"] == (5 if policy == "roi-fisher" else 0)
    with pytest.raises(InputError, match=r"parameter 'keyframe_selector.novelty_measure'.*area, pixels"):
        KeyframeSelectorNode(context=ros_context, parameter_overrides=[Parameter("novelty_measure", value="volume")])
    with pytest.raises(InputError, match=r"parameter 'keyframe_selector.novelty_measure'.*counts the observed novelty"):
        pixels_alone = [Parameter("policy", value="random"), Parameter("novelty_measure", value="pixels")]
        KeyframeSelectorNode(context=ros_context, parameter_overrides=pixels_alone)
    # checked though nothing counts novelty
    with pytest.raises(InputError, match=r"parameter 'keyframe_selector.novelty_voxel_m'.*> 0"):
        KeyframeSelectorNode(context=ros_context, parameter_overrides=[Parameter("novelty_voxel_m", value=0.0)])
    # a policy's range error names the node's parameter, not the library's field or a CLI flag (--every-n, --tau-k)
    with pytest.raises(InputError, match=r"^parameter 'keyframe_selector.every_n': must be at least 1, got 0$"):
        every_n0 = [Parameter("policy", value="every-n"), Parameter("every_n", value=0)]
        KeyframeSelectorNode(context=ros_context, parameter_overrides=every_n0)
    with pytest.raises(InputError, match=r"^parameter 'keyframe_selector.tau_k': must be in \[0, 1\), got 1\.5$"):
        KeyframeSelectorNode(context=ros_context, parameter_overrides=[Parameter("fallback_policy", value="gaus-slam"),
                                                                       Parameter("tau_k", value=1.5)])  # fmt: skip
    with pytest.raises(InputError, match="lookahead"):  # it judges the novelty: none to judge here
        KeyframeSelectorNode(context=ros_context, parameter_overrides=[Parameter("policy", value="roi-fisher"),
                                                                       Parameter("lookahead", value=2)])  # fmt: skip


def test_selector_adds_the_novelty_term_to_the_planners_fused_scores(ros_context: Any, scene: Any) -> None:
    """novelty_weight 1: the pick is argmax(fused + z(N)), not the planner's best_index (always 0 here)."""
    frames, _ = scene
    selector, cam, published = _windowed_selector(ros_context, "/test_planner_novelty/nbv", novelty_weight=1.0)

    def serve(req: GetNextBestView.Request, res: GetNextBestView.Response) -> GetNextBestView.Response:
        res.success, res.best_index = True, 0
        res.fused_scores = [0.1] + [-0.1] * (len(req.candidates.poses) - 1)
        return res

    seq = _novelty_sequence(frames, 4)
    expected, positions = _novelty_picks(seq, fused=[0.1, -0.1])
    assert positions == [1, 0, 1, 0]  # the novelty overrules the planner's pick in windows 0 and 2
    with _stub_planner(ros_context, "test_planner_novelty", serve), _spinning(ros_context, selector, cam.node):
        cam.wait_for()
        _wait(selector._client.service_is_ready, 10.0, "the stub planner")
        cam.publish(_frame_msgs(seq[0], 1000))
        for first in range(1, len(seq), 2):
            cam.publish(_frame_msgs(seq[first], (first + 1) * 1000))
            cam.publish(_frame_msgs(seq[first + 1], (first + 2) * 1000))
            _wait(lambda n=(first + 3) // 2: len(published) == n, 10.0, f"keyframe {(first + 3) // 2}")
        status = selector.status()
    assert published == expected and status["planner_answers"] == 4 and status["fallbacks"] == 0


def test_selector_status_times_its_answers_novelty_and_frame_gaps(ros_context: Any, scene: Any) -> None:
    """``max_answer_s`` is the longest wait for an answer to a window of the stream, the held frames ``finish`` sends
    left out (nothing comes after them); ``max_novelty_s`` and ``max_frame_gap_s`` time what can hold the frames."""
    frames, _ = scene
    selector, cam, _ = _windowed_selector(ros_context, "/test_planner_times/nbv", lookahead=2, novelty_weight=1.0)
    sizes: list[int] = []

    def serve(req: GetNextBestView.Request, res: GetNextBestView.Response) -> GetNextBestView.Response:
        sizes.append(len(req.candidates.poses))
        time.sleep(1.5 if len(sizes) > 3 else 0.2)  # the windows of the stream answered in 0.2 s, finish's in 1.5 s
        res.success, res.best_index = True, 0
        res.fused_scores = [0.0] * len(req.candidates.poses)
        return res

    seq = _novelty_sequence(frames, 4)
    with _stub_planner(ros_context, "test_planner_times", serve), _spinning(ros_context, selector, cam.node):
        cam.wait_for()
        _wait(selector._client.service_is_ready, 10.0, "the stub planner")
        for k, frame in enumerate(seq):  # a window every 0.6 s: each answered before the next comes
            cam.publish(_frame_msgs(frame, (k + 1) * 1000))
            time.sleep(0.3)
        _wait(lambda: selector.status()["planner_answers"] == 3, 20.0, "three windows answered")
        assert selector.finish() > 0
        _wait(lambda: selector.status()["planner_answers"] == 4, 20.0, "the held frames answered")
        status = selector.status()
    assert sizes[:3] == [2, 2, 2] and len(sizes) == 4
    assert 0.2 <= status["max_answer_s"] < 1.5, status  # finish's 1.5 s answer is not a window of the stream
    assert status["max_novelty_s"] > 0 and status["max_frame_gap_s"] > 0.2, status  # frames sent 0.3 s apart
    assert status["fallbacks"] == 0


def test_selector_takes_frames_while_a_windows_novelty_or_a_keyframes_depth_is_still_counted(
    ros_context: Any, scene: Any
) -> None:
    """The planner's answer is in but the window's novelty is not (or the new keyframe's depth is still being added):
    frames keep reaching the selector meanwhile, and the pick is the same as when nothing waits."""
    frames, _ = scene
    selector, cam, published = _windowed_selector(ros_context, "/test_planner_slow_novelty/nbv", novelty_weight=1.0)
    answered = threading.Event()

    def serve(req: GetNextBestView.Request, res: GetNextBestView.Response) -> GetNextBestView.Response:
        res.success, res.best_index = True, 0
        res.fused_scores = [0.1] + [-0.1] * (len(req.candidates.poses) - 1)
        answered.set()
        return res

    novelty_gate, add_gate = threading.Event(), threading.Event()
    observed = selector._observed
    assert observed is not None
    count, add = observed.frames_novelty, observed.add_frame
    adds: list[int] = []

    def slow_count(*args: Any, **kwargs: Any) -> Any:
        novelty_gate.wait(10.0)
        return count(*args, **kwargs)

    def slow_add(frame: Frame, *args: Any) -> None:
        adds.append(frame.index)
        if len(adds) > 1:  # the first frame's goes through
            add_gate.wait(10.0)
        add(frame, *args)

    observed.frames_novelty, observed.add_frame = slow_count, slow_add  # type: ignore[method-assign]
    seq = _novelty_sequence(frames, 2)
    expected, _ = _novelty_picks(seq, fused=[0.1, -0.1])
    try:
        with _stub_planner(ros_context, "test_planner_slow_novelty", serve), _spinning(ros_context, selector, cam.node):
            cam.wait_for()
            _wait(selector._client.service_is_ready, 10.0, "the stub planner")
            for k in range(3):  # frame 0 (a keyframe), then window 0: sent, its novelty held
                cam.publish(_frame_msgs(seq[k], (k + 1) * 1000))
            _wait(answered.is_set, 10.0, "the planner's answer")
            time.sleep(0.2)  # a few of the selector's 50 ms ticks with the answer in and the novelty not
            cam.publish(_frame_msgs(seq[3], 4000))
            _wait(lambda: selector._seen == 4, 5.0, "a frame while the window's novelty is counted")
            # frame 0's keyframe may wait the selector's grace after the subscription matched (MATCH_GRACE_S)
            _wait(lambda: len(published) >= 1, 5.0, "frame 0's keyframe")
            assert published == [1000]  # the window is not decided before its novelty is in
            novelty_gate.set()
            _wait(lambda: len(published) == 2, 10.0, "window 0's keyframe")
            _wait(lambda: len(adds) == 2, 10.0, "the keyframe's depth being added")
            cam.publish(_frame_msgs(seq[4], 5000))  # window 1 complete: sent, its novelty waits for that depth
            _wait(lambda: selector._seen == 5, 5.0, "a frame while the keyframe's depth is added")
            add_gate.set()
            _wait(lambda: len(published) == 3, 10.0, "window 1's keyframe")
            status = selector.status()
    finally:
        novelty_gate.set()
        add_gate.set()
    assert published == expected and status["planner_answers"] == 2 and status["fallbacks"] == 0


def _gaus_slam_selector(
    ctx: Any, shared: SharedMapper | None, **params: Any
) -> tuple[KeyframeSelectorNode, _Camera, list[int]]:
    """A gaus-slam selector (on ``shared``, else on the map topics), a camera, and the keyframe stamps it publishes."""
    overrides = [Parameter("policy", value="gaus-slam"), *(Parameter(k, value=v) for k, v in params.items())]
    selector = KeyframeSelectorNode(context=ctx, parameter_overrides=overrides, shared=shared)
    cam = _Camera(ctx)
    published: list[int] = []
    cam.node.create_subscription(
        PoseStamped, "/roigsf/keyframe", lambda m: published.append(bags.stamp_to_ns(m.header.stamp)), reliable_qos(50)
    )
    return selector, cam, published


def test_gaus_slam_judges_a_frame_once_the_map_holds_the_keyframes_named_before_it(
    ros_context: Any, scene: Any
) -> None:
    """Live, the mapper inserts a keyframe after the selector names it: a frame waits until the map holds it (as
    GauS-SLAM judges each frame on a map with every earlier keyframe), so a view the keyframe already shows is not
    named again. Before, it was judged at once on a map without that keyframe, and nearly every frame became one."""
    frames, _ = scene
    shared = SharedMapper(MapperConfig(iters_per_keyframe=2))
    selector, cam, published = _gaus_slam_selector(ros_context, shared, map_wait_s=30.0)
    with _spinning(ros_context, selector, cam.node):
        cam.wait_for()
        cam.publish(_frame_msgs(frames[0], 1000))  # an empty map: a keyframe
        _wait(lambda: published == [1000], 10.0, "the first keyframe")
        cam.publish(_frame_msgs(frames[0], 2000))  # the same view, the map without keyframe 1000 yet: it waits
        cam.publish(_frame_msgs(frames[6], 3000))  # another view
        _wait(lambda: selector.status()["frames_held_for_map"] == 2, 10.0, "two frames held for the map")
        time.sleep(0.3)
        assert published == [1000]
        mapper = shared.ensure(INTR)
        with shared.lock:  # what the mapper's worker does with the keyframe
            assert mapper.add_keyframe(replace(frames[0], index=1000))
            shared.touch()
        # 2000 is judged on a map that shows it: not a keyframe; 3000 looks elsewhere: one
        _wait(lambda: published == [1000, 3000], 10.0, "the other view named")
        status = selector.status()
    assert status["frames_held_for_map"] == 0 and status["map_waits_expired"] == 0
    assert status["frames_skipped_map_lag"] == 0


def test_gaus_slam_waits_for_the_map_at_most_map_wait_s_and_map_wait_frames(
    ros_context: Any, scene: Any, capfd: Any
) -> None:
    """A keyframe the map never holds (the mapper dropped it) holds frames up only ``map_wait_s``; beyond
    ``map_wait_frames`` held frames the oldest are skipped, and said (a walk found 105 of 150 frames skipped with no
    line in the log). Without a shared map the map's keyframe poses say which keyframes it holds."""
    frames, _ = scene
    selector, cam, published = _gaus_slam_selector(ros_context, None, map_wait_s=2.0, map_wait_frames=2)
    poses = cam.node.create_publisher(PoseArray, "/roigsf/keyframe_poses", latched_qos())
    with _spinning(ros_context, selector, cam.node):
        cam.wait_for()
        cam.publish(_frame_msgs(frames[0], 1000))
        _wait(lambda: published == [1000], 10.0, "the first keyframe")
        for k in range(3):  # three frames for two places: the oldest skipped
            cam.publish(_frame_msgs(frames[k + 1], 2000 + k * 1000))
        _wait(lambda: selector.status()["frames_skipped_map_lag"] == 1, 10.0, "a frame skipped")
        err = capfd.readouterr().err  # no mapper here: said, where it advised a slower --rate
        assert "1 frame(s) skipped so far, not judged: the map lags more than map_wait_frames (2) frames behind the " \
            "camera (no node publishes the map on /roigsf/map now: the mapper stopped?)" in err, err  # fmt: skip
        map_pub = cam.node.create_publisher(PointCloud2, "/roigsf/map", latched_qos())  # a mapper, slow
        _wait(lambda: "a larger map_wait_frames" in selector._map_lag_hint(), 10.0, "the advice for a slow map")
        cam.node.destroy_publisher(map_pub)
        # no map ever comes: after 2 s the wait for keyframe 1000 expires, 3000 is judged (an empty map: named),
        # and 4000 waits for it
        _wait(lambda: published == [1000, 3000], 10.0, "the wait expired")
        assert selector.status()["map_waits_expired"] == 1
        msg = poses_to_array([frames[0].T_wc, frames[2].T_wc], 0, "map")  # the map now holds 1000 and 3000
        poses.publish(msg)
        _wait(lambda: published == [1000, 3000, 4000], 10.0, "4000 judged once the map's poses hold 3000")
        status = selector.status()
    assert status["map_waits_expired"] == 1 and status["frames_held_for_map"] == 0
    answer = selector._on_finish(Trigger.Request(), Trigger.Response())  # it spoke of windows and lookahead
    assert answer.message == "nothing to decide: gaus-slam judges each frame as it comes (0 still wait for a map " \
        "holding the keyframes named before them, and are judged then)", answer.message  # fmt: skip


def test_parameters_reach_the_method_and_bad_ones_are_named(ros_context: Any) -> None:
    mapper = MapperNode(
        context=ros_context,
        parameter_overrides=[
            Parameter("iters_per_keyframe", value=3),
            Parameter("mesh_depth", value="expected"),
            Parameter("fisher_outputs", value=["depth"]),
        ],
    )
    planner = NBVPlannerNode(
        context=ros_context, parameter_overrides=[Parameter("mode", value="fisherrf"), Parameter("epsilon", value=0.7)]
    )
    selector = KeyframeSelectorNode(
        context=ros_context, parameter_overrides=[Parameter("policy", value="gaus-slam"), Parameter("tau_k", value=0.2)]
    )
    try:
        assert mapper.config.iters_per_keyframe == 3 and mapper.config.mesh_depth == "expected"
        assert mapper.config.fisher_outputs == ("depth",) and mapper.shared.config == mapper.config
        assert planner.nbv.mode == "fisherrf" and planner.nbv.epsilon == 0.7
        assert not selector.uses_planner and selector._alone.params() == {"tau_k": 0.2, "alpha_threshold": 0.5}
    finally:
        for node in (mapper, planner, selector):
            node.destroy_node()
    with pytest.raises(InputError, match="unknown policy 'nope'"):
        KeyframeSelectorNode(context=ros_context, parameter_overrides=[Parameter("policy", value="nope")])
    with pytest.raises(InputError, match="fallback_policy"):
        KeyframeSelectorNode(context=ros_context, parameter_overrides=[Parameter("fallback_policy", value="fisherrf")])
    with pytest.raises(InputError, match=r"unknown policy 'randm' \(did you mean 'random'\?\); choose one of random"):
        KeyframeSelectorNode(context=ros_context, parameter_overrides=[Parameter("fallback_policy", value="randm")])
    with pytest.raises(InputError, match=r"mapper\.near_m"):
        MapperNode(context=ros_context, parameter_overrides=[Parameter("near_m", value=-1.0)])
    with pytest.raises(InputError, match=r"'nbv_planner\.tsdf_sync_period_s'.*float.*e\.g\. 0\.0"):  # an int
        NBVPlannerNode(context=ros_context, parameter_overrides=[Parameter("tsdf_sync_period_s", value=0)])
    with pytest.raises(InputError, match="mode"):
        NBVPlannerNode(context=ros_context, parameter_overrides=[Parameter("mode", value="best")])


def _console(module: str, *ros_args: str) -> subprocess.Popen[str]:
    env = dict(os.environ)
    assert env.get("ROS_DOMAIN_ID") and env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    cmd = [sys.executable, "-m", module, "--ros-args", *ros_args]
    return subprocess.Popen(cmd, env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def test_console_script_takes_params_file_and_overrides(tmp_path: Path) -> None:
    params = tmp_path / "selector.yaml"
    params.write_text("keyframe_selector:\n  ros__parameters:\n    policy: every-n\n    every_n: 4\n")
    proc = _console(
        "roigsf_ros.nodes.keyframe_selector", "--params-file", str(params), "-p", "policy:=gaus-slam", "-p", "window:=3"
    )
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout or []), daemon=True)
    reader.start()
    try:
        started = "policy gaus-slam (window 3; every_n=4): deciding alone"  # every setting off its default
        _wait(lambda: any(started in x for x in lines), 60.0, "the node's start-up line")
    finally:
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=30)
        reader.join(timeout=10)
    assert rc == 0, "".join(lines)
    bad = _console("roigsf_ros.nodes.keyframe_selector", "-p", "policy:=nope")
    out, _ = bad.communicate(timeout=60)
    assert bad.returncode == 2 and "parameter 'keyframe_selector.policy'" in out and "unknown policy 'nope'" in out


def test_planner_process_takes_the_recommended_overlay_and_says_so() -> None:
    """The planner as its own process, as a user starts it with the README's recommendation for choosing views:
    config/nbv.yaml, then the overlay config/recommended/planner.yaml; its start-up line names the three settings
    the overlay changes (the scorer built from the parameters), and a mapper's names its own."""
    from roigsf_ros.nbv.config import RECOMMENDED_UNSEEN

    planner = _console(
        "roigsf_ros.nodes.nbv_planner", "--params-file", "config/nbv.yaml",
        "--params-file", "config/recommended/planner.yaml", "-p", "warm_up:=false",
    )  # fmt: skip
    mapper = _console("roigsf_ros.nodes.mapper", "--params-file", "config/recommended/stream.yaml")
    lines: list[str] = []
    procs = (planner, mapper)
    readers = [threading.Thread(target=lambda p=p: lines.extend(p.stdout or []), daemon=True) for p in procs]
    for reader in readers:
        reader.start()
    expected = {f"{k}={v}" for k, v in RECOMMENDED_UNSEEN.items()}  # in NBVConfig's field order

    def planner_started() -> bool:
        said = [x.split("scoring (roi-gsurfisher; ", 1)[1].split(") against", 1)[0] for x in lines if "scoring (" in x]
        return bool(said) and set(said[0].split(", ")) == expected

    try:
        _wait(planner_started, 60.0, "the planner's start-up line with the overlay's settings")
        _wait(lambda: any("own map; init_max_stretch=4.0)" in x for x in lines), 60.0, "the mapper's start-up line")
        # the map's intrinsics topic, which it prefers, named beside the camera's (it named the camera's alone)
        source = "against /roigsf/map + /roigsf/keyframe_poses + /roigsf/map_camera_info (else /camera/camera_info)"
        assert any(source in x for x in lines), [x for x in lines if "scoring (" in x]
    finally:
        for proc in procs:
            proc.send_signal(signal.SIGINT)
        codes = [proc.wait(timeout=30) for proc in procs]
        for reader in readers:
            reader.join(timeout=10)
    assert codes == [0, 0], "".join(lines)


def _run_script(program: str, *args: str, module: str = "roigsf_ros.nodes.console") -> subprocess.CompletedProcess:
    """Run console script ``program`` as installed (``roigsf_ros.nodes.console``) or as its node ``module``."""
    env = dict(os.environ)
    assert env.get("ROS_DOMAIN_ID") and env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    head = [program] if module == "roigsf_ros.nodes.console" else []
    cmd = [sys.executable, "-m", module, *head, *args]
    return subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("program", ["mapper", "nbv_planner", "keyframe_selector", "active_mapping", "bag_player"])
def test_console_scripts_name_a_bad_params_file_or_ros_argument_in_one_line(program: str, tmp_path: Path) -> None:
    """A missing params file, one that is not valid YAML and ``-p NAME`` without ``:=VALUE`` exit 2 with one line
    naming the file or the argument (before: rclpy's RCLInvalidROSArgsError as a traceback, exit 1)."""
    missing, bad = tmp_path / "nope.yaml", tmp_path / "bad.yaml"
    bad.write_text(f"{program}:\n  ros__parameters:\n    window: [1,\n")
    cases = {
        ("--params-file", str(missing)): f"{program}: error: {missing}: params file not found",
        ("--params-file", str(bad)): f"{program}: error: {bad}: not a valid YAML params file (",
        (
            "-p",
            "iters_per_keyframe",
        ): f"{program}: error: '-p iters_per_keyframe': a parameter is set as -p NAME:=VALUE",
    }
    for ros_args, said in cases.items():
        proc = _run_script(program, "--ros-args", *ros_args)
        assert proc.returncode == 2, proc.stderr
        assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert proc.stderr.startswith(said), proc.stderr
    if program == "mapper":  # the node module's own main (run_nodes) answers the same
        proc = _run_script(program, "--ros-args", "--params-file", str(missing), module="roigsf_ros.nodes.mapper")
        assert proc.returncode == 2 and proc.stderr.strip() == f"mapper: error: {missing}: params file not found"


@contextmanager
def _context_with(*ros_args: str) -> Iterator[Any]:
    """A fresh rclpy Context on this run's domain initialised with ``--ros-args ROS_ARGS``, shut down on exit."""
    import rclpy

    ctx = rclpy.Context()
    rclpy.init(args=["test", "--ros-args", *ros_args], context=ctx, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
    try:
        yield ctx
    finally:
        ctx.try_shutdown()


def test_undeclared_overrides_of_params_files_and_p_are_logged_once_with_the_closest_name(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """``-p unseen_wieght:=2.0`` left the planner on its defaults without a word (ROS ignores an override no node
    declares); now each node logs one warning naming such overrides and the declared name closest to each. A
    params file's ``/**:`` section holding another node's parameter does not fail a node; in one process
    (active_mapping) a name one of the three nodes declares is no typo for the other two, and a node on its own
    does not warn about a name another node of the package declares (the README gives the three processes the
    same camera arguments: the planner warned about pose_source and suggested unseen_source)."""
    params = tmp_path / "all.yaml"
    params.write_text(
        "/**:\n  ros__parameters:\n    policy: every-n\nkeyframe_selector:\n  ros__parameters:\n    window: 3\n"
    )
    camera = ("-p", "pose_source:=tf", "-p", "color_transport:=compressed")
    with _context_with("-p", "unseen_wieght:=2.0", *camera, "--params-file", str(params)) as ctx:
        planner = NBVPlannerNode(context=ctx, parameter_overrides=[Parameter("warm_up", value=False)])
        selector = KeyframeSelectorNode(context=ctx)
        try:
            assert planner.nbv == NBVConfig() and planner.ignored_parameters == ["unseen_wieght"]
            assert selector.policy == "every-n" and selector.window == 3
            assert selector.ignored_parameters == ["unseen_wieght"]
        finally:
            planner.destroy_node()
            selector.destroy_node()
        err = capfd.readouterr().err
        warnings = [line.split("]: ", 1)[1] for line in err.splitlines() if "ignored parameter" in line]
        assert warnings == [
            "ignored parameter(s) not declared by this node nor by any other roigsf node: unseen_wieght (closest "
            "declared: unseen_weight)",
            "ignored parameter(s) not declared by this node nor by any other roigsf node: unseen_wieght",
        ], err
        assert "[nbv_planner]: ignored parameter(s)" in err
        nodes = build_nodes(ctx, {"nbv_planner": {"warm_up": False}})
        try:
            assert [node.ignored_parameters for node in nodes] == [["unseen_wieght"]] * 3  # policy: the selector's
            assert nodes[2].policy == "every-n"
        finally:
            for node in nodes:
                node.destroy_node()
        err = capfd.readouterr().err
        warnings = [line for line in err.splitlines() if "ignored parameter" in line]
        assert len(warnings) == 3 and all("nor by" in w and "unseen_wieght (closest declared: unseen_weight)" in w
                                          for w in warnings), err  # fmt: skip


def test_active_mapping_warms_the_planner_up_before_any_camera_subscription(
    ros_context: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The README's one-process command: the planner's warm-up (1 s, a minute with a cold cache) came between the
    mapper's camera subscriptions and the selector's, and a bag player waiting for one subscriber (its default)
    started on the mapper's alone: the selector missed the first frames (37 of 40 in a new user's run). With the
    planner built before the mapper (the selector first, its camera deferred), the process subscribes to the camera
    only after the warm-up, mapper and selector together."""
    probe = Node("test_probe", context=ros_context)
    seen: list[int] = []

    def warm_up(cfg: Any) -> dict[str, float]:
        seen.append(probe.count_subscribers("/camera/color/image_raw"))
        return {"total_s": 0.0}

    monkeypatch.setattr(nbv_planner_module, "warm_up_once", warm_up)
    nodes = build_nodes(ros_context)
    try:  # both there before anything spins: with the shared map the selector does not wait for its outputs
        assert seen == [0]  # nothing subscribed while the planner warmed up
        _wait(lambda: probe.count_subscribers("/camera/color/image_raw") == 2, 10.0, "the mapper's and selector's")
    finally:
        for node in (*nodes, probe):
            node.destroy_node()


def test_active_mapping_refuses_a_mistyped_selector_policy_before_the_planner_warms_up(
    ros_context: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One process with ``policy:=roi-gsurfishr``: the planner warmed up (a minute with a cold cache) and the mapper
    started before the selector refused the name. Built first, the selector refuses it before either is built (and,
    deferred, its camera is not read until the mapper's is)."""
    built: list[str] = []
    monkeypatch.setattr(nbv_planner_module, "warm_up_once", lambda cfg: built.append("warm-up") or {"total_s": 0.0})
    with pytest.raises(InputError, match=r"parameter 'keyframe_selector.policy'.*did you mean 'roi-gsurfisher'"):
        build_nodes(ros_context, {"keyframe_selector": {"policy": "roi-gsurfishr"}})
    assert built == []
    probe = Node("test_probe", context=ros_context)
    try:
        assert not any(name in {"mapper", "nbv_planner", "keyframe_selector"} for name in probe.get_node_names())
    finally:
        probe.destroy_node()


def test_mapper_warms_its_kernels_up_before_it_subscribes(ros_context: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """Three processes: the mapper's first 640x480 keyframe took 1.1 s against 0.5 s for the next (its kernels
    loading), and the planner's first map came that much later. The mapper node now maps a tiny scene first, before
    any subscription (so a player waiting for its subscribers waits for it), and says how long it took."""
    probe = Node("test_warm_probe", context=ros_context)
    seen: list[tuple[int, bool]] = []

    def warm_up(nbv: Any = None, scoring: bool = True) -> dict[str, float]:
        seen.append((probe.count_subscribers("/camera/color/image_raw"), scoring))
        return {"mapping_s": 0.25, "total_s": 0.25}

    monkeypatch.setattr(mapper_module, "warm_up_once", warm_up)
    mapper = MapperNode(context=ros_context, node_name="warm_mapper")
    cold = MapperNode(context=ros_context, parameter_overrides=[Parameter("warm_up", value=False)], node_name="cold")
    try:
        assert seen == [(0, False)]  # once (not for warm_up false), mapping only, before any subscription
        assert mapper.status()["warm_up_s"] == 0.25 and cold.status()["warm_up_s"] == 0.0
        assert probe.count_subscribers("/camera/color/image_raw") == 2
    finally:
        for node in (mapper, cold, probe):
            node.destroy_node()


def test_warm_up_once_runs_each_phase_once_per_process(monkeypatch: pytest.MonkeyPatch) -> None:
    """The mapper node warms mapping up, the planner mapping and scoring: in one process (``roigsf demo``, the
    one-process node) the planner's warm-up covers the mapper's, and a mapping warm-up first does not skip scoring."""
    calls: list[str] = []
    monkeypatch.setattr(warmup, "_WARMED", set())
    monkeypatch.setattr(warmup, "warm_up_mapping", lambda: (calls.append("mapping"), 0.5))
    monkeypatch.setattr(warmup, "warm_up_kernels", lambda nbv=None: calls.append("both") or {"total_s": 1.0})
    assert warmup.warm_up_once(scoring=False) == {"mapping_s": 0.5, "total_s": 0.5}
    assert warmup.warm_up_once(scoring=False) is None
    assert warmup.warm_up_once() == {"total_s": 1.0}
    assert warmup.warm_up_once() is None and warmup.warm_up_once(scoring=False) is None
    assert calls == ["mapping", "both"]
    monkeypatch.setattr(warmup, "_WARMED", set())
    assert warmup.warm_up_once() is not None and warmup.warm_up_once(scoring=False) is None  # planner first


def test_an_undeclared_parameter_given_to_a_node_constructor_is_an_error(ros_context: Any, scene: Any) -> None:
    """``parameter_overrides`` (the Python API, ``roigsf demo --set NODE.NAME=VALUE``) name one node, so a name
    it does not declare is an InputError naming it and the closest declared names (before: silently ignored)."""
    with pytest.raises(InputError, match=r"^parameter 'keyframe_selector\.nosuch': not declared by this node$"):
        KeyframeSelectorNode(context=ros_context, parameter_overrides=[Parameter("nosuch", value=1)])
    with pytest.raises(InputError, match=r"^parameter 'nbv_planner\.unseen_wieght'.*closest declared: unseen_weight"):
        NBVPlannerNode(
            context=ros_context,
            parameter_overrides=[Parameter("warm_up", value=False), Parameter("unseen_wieght", value=2.0)],
        )
    with pytest.raises(InputError, match=r"^parameters 'mapper\.itrs_per_keyframe', 'mapper\.nosuch'.*iters_per_key"):
        ActiveMapping(ros_context, params={"mapper": {"nosuch": 1, "itrs_per_keyframe": 2}})
    with pytest.raises(InputError, match=r"^parameter 'bag_player\.rat'.*closest declared: rate"):
        BagPlayer(
            context=ros_context,
            parameter_overrides=[Parameter("bag", value=str(scene[1])), Parameter("rat", value=2.0)],
        )
    selector = KeyframeSelectorNode(context=ros_context, parameter_overrides=[Parameter("window", value=4)])
    try:  # declared names pass, and the failed nodes are gone (one name, one node)
        assert selector.window == 4 and selector.ignored_parameters == []
        assert ros_context.ok()
    finally:
        selector.destroy_node()


def test_gil_switch_interval_is_lowered_never_raised(monkeypatch: pytest.MonkeyPatch) -> None:
    """Node processes run at a 0.5 ms switch interval (see GIL_SWITCH_INTERVAL_S); the variable overrides it."""
    before = sys.getswitchinterval()
    try:
        sys.setswitchinterval(0.005)
        monkeypatch.delenv("ROIGSF_GIL_SWITCH_INTERVAL_S", raising=False)
        assert reduce_gil_switch_interval() == pytest.approx(GIL_SWITCH_INTERVAL_S)
        monkeypatch.setenv("ROIGSF_GIL_SWITCH_INTERVAL_S", "0.002")
        assert reduce_gil_switch_interval() == pytest.approx(GIL_SWITCH_INTERVAL_S)  # never raised
        sys.setswitchinterval(0.005)
        assert reduce_gil_switch_interval() == pytest.approx(0.002)
        monkeypatch.setenv("ROIGSF_GIL_SWITCH_INTERVAL_S", "0")
        assert reduce_gil_switch_interval() == pytest.approx(0.002)  # 0: left as it is
        monkeypatch.setenv("ROIGSF_GIL_SWITCH_INTERVAL_S", "fast")
        with pytest.raises(InputError, match=r"ROIGSF_GIL_SWITCH_INTERVAL_S.*'fast'"):
            reduce_gil_switch_interval()
    finally:
        sys.setswitchinterval(before)
    env = dict(os.environ, ROIGSF_GIL_SWITCH_INTERVAL_S="fast", PYTHONPATH=str(REPO))
    bad = subprocess.run(
        [sys.executable, "-m", "roigsf_ros.nodes.bag_player"], env=env, capture_output=True, text=True, timeout=60
    )
    assert bad.returncode == 2 and "bag_player: error: ROIGSF_GIL_SWITCH_INTERVAL_S" in bad.stderr, bad.stderr


@pytest.mark.parametrize("value", ["abc", "999"])
def test_a_bad_ros_domain_id_is_one_line_naming_it(value: str) -> None:
    """Before (session 61's walk): rcl's RCLError traceback for "abc", and for 999 Fast DDS's bare "port number is too
    high" with its /dev/shm files left behind; now one line naming the variable, exit 2, before ROS starts."""
    env = dict(os.environ, ROS_DOMAIN_ID=value, PYTHONPATH=str(REPO))
    bad = subprocess.run(
        [sys.executable, "-m", "roigsf_ros.nodes.mapper"], env=env, capture_output=True, text=True, timeout=60
    )
    assert bad.returncode == 2 and "mapper: error: ROS_DOMAIN_ID: " in bad.stderr, bad.stderr
    assert "Traceback" not in bad.stderr


# ---------------------------------------------------------------------------------------- whole system
def test_active_mapping_replay_gives_keyframes_map_and_mesh(ros_context: Any, scene: Any, tmp_path: Path) -> None:
    _, bag = scene
    system = ActiveMapping(
        ros_context,
        {
            "mapper": {"iters_per_keyframe": 3, "idle_iters_per_keyframe": 2, "map_publish_rate_hz": 5.0},
            "keyframe_selector": {"policy": "roi-gsurfisher", "window": 4, "planner_timeout_s": 60.0},
        },
    )
    player = BagPlayer(
        context=ros_context,
        parameter_overrides=[Parameter("bag", value=str(bag)), Parameter("rate", value=0.5)],
    )
    late = Node("late_joiner", context=ros_context)
    clouds: list[PointCloud2] = []
    meshes: list[Marker] = []
    system.executor.add_node(player)
    system.executor.add_node(late)
    system.start()
    try:
        assert player.wait(60.0) and player.error is None
        _wait(lambda: system.selector.status()["frames"] == N_FRAMES, 20.0, "every frame at the selector")
        _wait(lambda: not system.selector.status()["planner_pending"], 60.0, "the last planner answer")
        _wait(lambda: system.mapper.wait_idle(0.1) and system.mapper.status()["frames_received"] == N_FRAMES, 60, "map")
        # A late joiner still gets the map (transient local), and the mesh on request.
        late.create_subscription(PointCloud2, "/roigsf/map", clouds.append, latched_qos())
        late.create_subscription(Marker, "/mapper/mesh", meshes.append, latched_qos())
        system.mapper.publish_map(force=True)
        mesh_res = _call(late.create_client(Trigger, "/mapper/publish_mesh"), Trigger.Request())
        _wait(lambda: bool(clouds) and bool(meshes), 10.0, "map cloud and mesh marker")
        save = SaveMap.Request(directory=str(tmp_path / "saved"), with_mesh=True)
        save_res = _call(late.create_client(SaveMap, "/mapper/save_map"), save)
        status = system.status()
    finally:
        system.executor.remove_node(player)
        system.executor.remove_node(late)
        system.shutdown()
        player.destroy_node()
        late.destroy_node()
    sel, mapper = status["selector"], status["mapper"]
    # 12 frames, windows of 4 after the first: the first frame + one keyframe per full window.
    assert sel["keyframe_ids"][0] == bags.frame_stamp_ns(0, bags.DEFAULT_RATE_HZ)
    assert len(sel["keyframe_ids"]) == 3 and sel["planner_calls"] == 2
    assert sel["planner_answers"] + sel["fallbacks"] == 2 and status["nbv_planner"]["answered"] >= 1
    assert mapper["keyframe_ids"] == sel["keyframe_ids"] and mapper["keyframes_missing"] == 0
    assert len(cloud_to_surfel_map(clouds[-1])) == mapper["surfels"] > 0
    assert mesh_res.success and len(meshes[-1].points) > 0 and len(meshes[-1].points) % 3 == 0
    assert save_res.success and save_res.keyframes == 3, save_res.message
    assert read_keyframe_ids(tmp_path / "saved") == sel["keyframe_ids"]
    assert (tmp_path / "saved" / "mesh.ply").stat().st_size > 0


def test_saved_map_is_resumed_by_a_new_mapper(ros_context: Any, scene: Any, mapped: Mapper, tmp_path: Path) -> None:
    frames, _ = scene
    first = MapperNode(context=ros_context, shared=_shared(mapped), node_name="mapper_a")
    client_node = Node("save_client", context=ros_context)
    save = client_node.create_client(SaveMap, "/mapper_a/save_map")
    with _spinning(ros_context, first, client_node):
        res = _call(save, SaveMap.Request(directory=str(tmp_path / "map")))
        again = _call(save, SaveMap.Request(directory=str(tmp_path / "map")))  # exists, no overwrite
    assert res.success and res.keyframes == 3 and res.surfels == mapped.n_surfels
    assert not again.success and "already exists" in again.message
    # A restarted mapper resumes from the saved folder and keeps its keyframes; new ones go on top.
    second = MapperNode(
        context=ros_context,
        parameter_overrides=[
            Parameter("load_map", value=str(tmp_path / "map")),
            Parameter("iters_per_keyframe", value=1),
        ],
        node_name="mapper_b",
    )
    cam = _Camera(ros_context)
    load = cam.node.create_client(LoadMap, "/mapper_b/load_map")
    with _spinning(ros_context, second, cam.node):
        assert second.status()["keyframe_ids"] == [0, 4, 8] and second.status()["surfels"] == mapped.n_surfels
        cam.wait_for()
        cam.publish(_frame_msgs(frames[6], 6))
        _wait(lambda: second.status()["frames_received"] == 1, 10.0, "a frame")
        cam.keyframes.publish(pose_stamped(frames[6].T_wc, 6))
        _wait(lambda: second.status()["keyframes"] == 4, 30.0, "the new keyframe")
        bad = _call(load, LoadMap.Request(directory=str(tmp_path / "nothing")))
        status = second.status()
    assert status["keyframe_ids"] == [0, 4, 8, 6]
    assert not bad.success and "nothing: no such map folder" in bad.message


def test_the_first_keyframes_map_is_published_at_once_not_at_the_next_tick(ros_context: Any, scene: Any) -> None:
    """The map goes out at most ``map_publish_rate_hz`` times a second, on a timer: a planner in another process waited
    up to a period more for the first map it can score, and the first windows of a three-process run went to the
    fallback. The first keyframe's map is published as soon as it is in (here: with a timer of 100 s)."""
    frames, _ = scene
    mapper = MapperNode(
        context=ros_context,
        parameter_overrides=[Parameter("map_publish_rate_hz", value=0.01), Parameter("iters_per_keyframe", value=1)],
        node_name="mapper_first",
    )
    cam = _Camera(ros_context)
    clouds: list[PointCloud2] = []
    cam.node.create_subscription(PointCloud2, "/roigsf/map", clouds.append, latched_qos())
    with _spinning(ros_context, mapper, cam.node):
        cam.wait_for()
        cam.publish(_frame_msgs(frames[0], 1000))
        _wait(lambda: mapper.status()["frames_received"] == 1, 10.0, "a frame")
        cam.keyframes.publish(pose_stamped(frames[0].T_wc, 1000))
        _wait(lambda: any(c.width > 0 for c in clouds), 30.0, "a map with the first keyframe's surfels")
        # The mapper counts a publication once its three messages are out; the cloud can arrive here first.
        _wait(lambda: mapper.status()["map_publishes"] >= 1, 5.0, "the publication counted")
        status = mapper.status()
    assert status["keyframes_inserted"] == 1 and status["map_publishes"] == 1


def test_a_planner_in_its_own_process_scores_a_loaded_map_before_any_camera_publishes(
    ros_context: Any, scene: Any, mapped: Mapper, tmp_path: Path
) -> None:
    """A mapper resumed from a saved map beside a planner reading topics: the planner had the map and its poses but
    no intrinsics until a camera published camera info, and answered every request "map: not ready". The mapper now
    publishes the map's intrinsics (``/roigsf/map_camera_info``), and the planner scores with them."""
    frames, _ = scene
    _shared(mapped).save(tmp_path / "map")
    mapper = MapperNode(
        context=ros_context, parameter_overrides=[Parameter("load_map", value=str(tmp_path / "map"))],
        node_name="mapper_loaded",
    )  # fmt: skip
    planner = NBVPlannerNode(
        context=ros_context, parameter_overrides=[Parameter("warm_up", value=False)], node_name="nbv_loaded"
    )
    client_node = Node("loaded_map_client", context=ros_context)
    client = client_node.create_client(GetNextBestView, "/nbv_loaded/get_next_best_view")
    with _spinning(ros_context, mapper, planner, client_node):
        _wait(lambda: planner.snapshot() is not None, 20.0, "the loaded map, its poses and intrinsics")
        res = _call(client, _request([frames[i].T_wc for i in (1, 5, 10)]))
        snap = planner.snapshot()
    assert res.success, res.message
    assert snap is not None and snap.intrinsics == mapped.intr and len(snap.keyframe_poses) == 3
    assert planner._intr is None  # no camera info was published: the map's intrinsics alone


def test_save_map_refusals_name_the_request_field_and_a_file_in_the_path(
    ros_context: Any, mapped: Mapper, tmp_path: Path
) -> None:
    """`~/save_map` onto an existing folder says to set `overwrite: true` (the request field, not the command line's
    `--overwrite`); a folder under a regular file is named "not a folder" (the CLI's check), not a raw Errno 17."""
    node = MapperNode(context=ros_context, shared=_shared(mapped), node_name="mapper_s")
    client_node = Node("save_refusal_client", context=ros_context)
    save = client_node.create_client(SaveMap, "/mapper_s/save_map")
    (tmp_path / "map").mkdir()
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    with _spinning(ros_context, node, client_node):
        exists = _call(save, SaveMap.Request(directory=str(tmp_path / "map")))
        under = _call(save, SaveMap.Request(directory=str(blocker / "map")))
        replaced = _call(save, SaveMap.Request(directory=str(tmp_path / "map"), overwrite=True))
    assert not exists.success and "already exists (set overwrite: true in the request" in exists.message
    assert "--overwrite" not in exists.message
    assert not under.success and f"{blocker}: is not a folder" in under.message and "Errno" not in under.message
    assert replaced.success and read_keyframe_ids(tmp_path / "map") == [0, 4, 8], replaced.message


def test_save_map_refuses_a_path_naming_no_folder_replaces_only_a_map_and_expands_home(
    ros_context: Any, mapped: Mapper, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``directory: "."`` with ``overwrite: true`` raised a ValueError out of the callback: the mapper died (rc 1) and
    left a hidden temporary map in its working folder (``..`` failed on the rename, leaving a complete-looking one).
    ``overwrite`` replaced a regular file or a folder of other things without a word, and ``~/x`` made a folder named
    ``~``. Now: refused naming the path, only a saved map (or
    an empty folder) is replaced, ``~`` is the home folder and the reply names the absolute path."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    node = MapperNode(context=ros_context, shared=_shared(mapped), node_name="mapper_dot")
    client_node = Node("save_dot_client", context=ros_context)
    save = client_node.create_client(SaveMap, "/mapper_dot/save_map")
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "keep.txt").write_text("mine")
    (tmp_path / "file.txt").write_text("mine")
    with _spinning(ros_context, node, client_node):
        answers = {d: _call(save, SaveMap.Request(directory=d, overwrite=True)) for d in (".", "..", "sub/..")}
        not_map = _call(save, SaveMap.Request(directory="notes", overwrite=True))
        a_file = _call(save, SaveMap.Request(directory="file.txt", overwrite=True))
        home = _call(save, SaveMap.Request(directory="~/maps/m"))
        twice = _call(save, SaveMap.Request(directory="~/maps/m", overwrite=True))  # a map: replaced
    for d, res in answers.items():  # made absolute first: the node's working folder or its parent
        assert not res.success and "is the working folder or one above it" in res.message, (d, res.message)
    assert not not_map.success and "notes: is a folder without keyframes.json, not a saved map" in not_map.message
    assert (tmp_path / "notes" / "keep.txt").read_text() == "mine"
    assert not a_file.success and "file.txt: is not a folder, not a saved map" in a_file.message
    assert (tmp_path / "file.txt").read_text() == "mine"
    assert home.success and f"to {tmp_path / 'home' / 'maps' / 'm'}" in home.message, home.message
    assert twice.success and read_keyframe_ids(tmp_path / "home" / "maps" / "m") == [0, 4, 8]
    assert not (tmp_path / "~").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.txt", "home", "notes"]  # no temporary left


def test_an_autosave_dir_that_cannot_hold_a_map_is_refused_at_start_and_a_failed_autosave_is_no_failed_keyframe(
    ros_context: Any, mapped: Mapper, tmp_path: Path
) -> None:
    """``autosave_dir`` under a regular file was accepted; each autosave then failed inside the keyframe step, logged
    as "mapping step failed: [Errno 17]" and counted in ``keyframes_failed`` though the keyframe was mapped."""
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    for bad, why in ((blocker / "x", "is not a folder"), (tmp_path, "not a saved map")):
        (tmp_path / "other.txt").write_text("mine")  # tmp_path itself: a folder of other things
        with pytest.raises(InputError) as caught:
            MapperNode(context=ros_context, parameter_overrides=[Parameter("autosave_dir", value=str(bad))])
        assert str(caught.value).startswith("parameter 'mapper.autosave_dir':") and why in str(caught.value)
    node = MapperNode(
        context=ros_context,
        shared=_shared(mapped),
        parameter_overrides=[
            Parameter("autosave_dir", value=str(tmp_path / "auto")),
            Parameter("autosave_every", value=1),
        ],
    )
    try:
        assert node.autosave() and read_keyframe_ids(tmp_path / "auto") == [0, 4, 8]
        shutil.rmtree(tmp_path / "auto")
        (tmp_path / "auto").write_text("in the way")  # e.g. another program wrote there meanwhile
        assert not node.autosave()
        assert node.counters["autosaves"] == 1 and node.counters["autosaves_failed"] == 1
        assert node.counters["keyframes_failed"] == 0 and (tmp_path / "auto").read_text() == "in the way"
    finally:
        node.destroy_node()


def test_a_restarted_mapper_does_not_replace_the_map_its_last_run_autosaved(
    ros_context: Any, mapped: Mapper, tmp_path: Path
) -> None:
    """Restarting a mapper with the same ``autosave_dir`` (the usual restart after a crash) replaced the last run's
    autosave at the new run's first keyframe without a word (session 60's walk). Start-up now refuses it unless
    ``load_map`` resumes that map or ``autosave_overwrite`` says to replace it."""
    auto = tmp_path / "auto"
    mapped.save(auto)
    with pytest.raises(InputError) as caught:
        MapperNode(context=ros_context, parameter_overrides=[Parameter("autosave_dir", value=str(auto))])
    text = str(caught.value)
    assert text.startswith("parameter 'mapper.autosave_dir':") and f"load_map:={auto}" in text, text
    assert "autosave_overwrite:=true" in text and read_keyframe_ids(auto) == [0, 4, 8]
    for extra in (Parameter("load_map", value=str(auto)), Parameter("autosave_overwrite", value=True)):
        node = MapperNode(context=ros_context, parameter_overrides=[Parameter("autosave_dir", value=str(auto)), extra])
        node.destroy_node()
    assert read_keyframe_ids(auto) == [0, 4, 8]  # nothing replaced before a keyframe is mapped


def test_destroy_node_waits_for_service_work_the_shutdown_abandoned(ros_context: Any, mapped: Mapper) -> None:
    """Ctrl-C during ``~/publish_mesh``: the request was answered "shutting down" at once (kept), but the process
    then exited with the mesh thread still inside Open3D and aborted (rc 134) or failed (rc 1). destroy_node now
    waits for that work."""
    mapper = MapperNode(context=ros_context, shared=_shared(mapped), node_name="mapper_wait")
    client_node = Node("mesh_wait_client", context=ros_context)
    client = client_node.create_client(Trigger, "/mapper_wait/publish_mesh")
    release, finished = threading.Event(), threading.Event()

    def slow_mesh() -> str:
        release.wait(60.0)
        finished.set()
        return "done"

    mapper.publish_mesh = slow_mesh  # type: ignore[method-assign] - a mesh that takes long
    executor = MultiThreadedExecutor(num_threads=4, context=ros_context)
    for n in (mapper, client_node):
        executor.add_node(n)
    spin = BackgroundSpin(executor, "test_executor").start()
    try:
        pending = client.call_async(Trigger.Request())
        _wait(lambda: any(t.is_alive() for t in mapper._service_threads), 10.0, "the mesh work")
        mapper.stop()
        _wait(pending.done, 5.0, "the abandoned mesh request")
    finally:
        spin.stop()
    destroyer = threading.Thread(target=mapper.destroy_node)
    destroyer.start()
    destroyer.join(0.5)
    waited = destroyer.is_alive()
    release.set()
    destroyer.join(30.0)
    client_node.destroy_node()
    assert "shutting down" in pending.result().message
    assert waited and not destroyer.is_alive() and finished.is_set()


def test_load_map_of_a_malformed_folder_answers_false_and_keeps_the_map(
    ros_context: Any, mapped: Mapper, tmp_path: Path
) -> None:
    import json

    shared = _shared(mapped)
    node = MapperNode(context=ros_context, shared=shared, node_name="mapper_c")
    client_node = Node("load_client", context=ros_context)
    save = client_node.create_client(SaveMap, "/mapper_c/save_map")
    load = client_node.create_client(LoadMap, "/mapper_c/load_map")
    answers = {}
    with _spinning(ros_context, node, client_node):
        assert _call(save, SaveMap.Request(directory=str(tmp_path / "good"))).success
        meta = json.loads((tmp_path / "good" / "keyframes.json").read_text())
        before = (node.status()["keyframe_ids"], node.status()["surfels"], shared.mapper)
        wrong_width = json.loads(json.dumps(meta))
        wrong_width["intrinsics"]["width"] = "wide"
        no_fx = json.loads(json.dumps(meta))
        del no_fx["intrinsics"]["fx"]
        for name, content in (("list", [meta]), ("width", wrong_width), ("fx", no_fx)):
            folder = tmp_path / name
            folder.mkdir()
            (folder / "map.ply").write_bytes((tmp_path / "good" / "map.ply").read_bytes())
            (folder / "keyframes.json").write_text(json.dumps(content))
            answers[name] = _call(load, LoadMap.Request(directory=str(folder)), timeout_s=20.0)
        after = (node.status()["keyframe_ids"], node.status()["surfels"], shared.mapper)
        reload = _call(load, LoadMap.Request(directory=str(tmp_path / "good")), timeout_s=20.0)
    for name, field in (("list", "JSON object"), ("width", "'intrinsics.width'"), ("fx", "'intrinsics.fx'")):
        res = answers[name]
        assert not res.success and str(tmp_path / name / "keyframes.json") in res.message, res.message
        assert field in res.message, res.message
    assert after == before and after[2] is mapped  # the old map is kept, untouched
    assert reload.success and reload.keyframes == 3, reload.message


# ---------------------------------------------------------------------------------------- planner load (bug 3)
def test_stale_requests_are_refused_before_any_map_work(ros_context: Any, scene: Any, mapped: Mapper) -> None:
    frames, _ = scene
    planner = NBVPlannerNode(
        context=ros_context, shared=_shared(mapped), parameter_overrides=[Parameter("max_request_age_s", value=2.0)]
    )
    try:
        now = planner.get_clock().now().nanoseconds
        old = _request([frames[1].T_wc, frames[2].T_wc])
        old.candidates.header = header(now - 5_000_000_000, "map")  # sent 5 s ago: the selector gave up
        res = planner._on_request(old, GetNextBestView.Response())
        assert not res.success and "stale request: sent 5." in res.message and "max_request_age_s 2" in res.message
        assert planner.status()["stale"] == 1 and planner.status()["tsdf_frames"] == 0  # refused before any work
        ahead = _request([frames[1].T_wc, frames[2].T_wc])
        ahead.candidates.header = header(now + 3_600_000_000_000, "map")  # a clock an hour ahead: was scored
        res = planner._on_request(ahead, GetNextBestView.Response())
        assert not res.success and "request stamped 3600." in res.message and "in the future" in res.message
        assert planner.status()["stale"] == 2 and planner.status()["tsdf_frames"] == 0
        fresh = _request([frames[1].T_wc, frames[2].T_wc])
        fresh.candidates.header = header(planner.get_clock().now().nanoseconds, "map")
        assert planner._on_request(fresh, GetNextBestView.Response()).success
        unstamped = planner._on_request(_request([frames[1].T_wc]), GetNextBestView.Response())  # stamp 0: served
        assert unstamped.success and planner.status()["answered"] == 2
    finally:
        planner.destroy_node()


def test_match_surfels_follows_prune_and_append() -> None:
    rng = np.random.default_rng(0)
    old = rng.uniform(-2, 2, size=(500, 3))
    keep = np.ones(500, bool)
    keep[[3, 7, 8]] = False
    keep[100:180] = False  # a whole region pruned
    new = np.concatenate([old[keep] + rng.normal(scale=1e-4, size=(keep.sum(), 3)), rng.uniform(-2, 2, (40, 3))])
    rows = match_surfels(old, new, tol_m=0.005)
    np.testing.assert_array_equal(rows[: keep.sum()], np.flatnonzero(keep))
    assert (rows[keep.sum() :] == -1).sum() >= 38  # appended surfels start from zero (bar a chance neighbour)
    h = {"means": torch.arange(1500.0).reshape(500, 3)}
    carried = carry_rows(h, rows)["means"]
    assert torch.equal(carried[: keep.sum()], h["means"][torch.as_tensor(np.flatnonzero(keep))])


def test_train_fisher_cache_adds_only_new_poses(scene: Any) -> None:
    """The planner's own H_train: a keyframe set that extends the last one costs one Fisher pass per new pose."""
    frames, _ = scene
    mapper = Mapper(INTR, MapperConfig(iters_per_keyframe=2, track_h_train=False))
    for i in (0, 4):
        assert mapper.add_keyframe(frames[i])
    cache = TrainFisherCache(NBVConfig())
    map_a, poses_a = mapper.map.detach().clone(), mapper.keyframe_poses
    h_a = cache.get(map_a, poses_a, INTR, "fisherrf")
    assert cache.full_computations == 1 and cache.poses_added == 0
    assert mapper.add_keyframe(frames[8])  # densify (surfels appended), optimise, prune
    map_b, poses_b = mapper.map.detach().clone(), mapper.keyframe_poses
    h_b = cache.get(map_b, poses_b, INTR, "fisherrf")
    assert cache.full_computations == 1 and cache.poses_added == 1
    rows = match_surfels(map_a.means.numpy(), map_b.means.numpy(), 0.01)
    assert (rows >= 0).sum() > 0.8 * min(len(map_a), len(map_b))
    new = NBVScorer(NBVConfig()).train_fisher(map_b, poses_b[2:], INTR, "fisherrf")
    for k, h in carry_rows(h_a, rows).items():
        torch.testing.assert_close(h_b[k], h + new[k])
    assert cache.get(map_b, poses_b, INTR, "fisherrf") is h_b  # nothing new: no pass at all
    cache.get(map_b, poses_b[::-1].copy(), INTR, "fisherrf")  # not an extension: from scratch
    assert cache.full_computations == 2


def test_planner_from_topics_uses_the_mappers_fisher_like_in_process(
    ros_context: Any, scene: Any, mapped: Mapper
) -> None:
    """Topic mode: the cloud's htrain_ fields make the scores those of the in-process planner, no Fisher pass."""
    frames, _ = scene
    cands = [frames[i].T_wc for i in (1, 5, 10)]
    shared = NBVPlannerNode(context=ros_context, shared=_shared(mapped), node_name="nbv_shared")
    remote = NBVPlannerNode(context=ros_context, node_name="nbv_remote")
    try:
        expected = shared._on_request(_request(cands), GetNextBestView.Response())
        cloud = surfel_map_to_cloud(mapped.map, 1, "map", mapped.h_train, mapped.config.fisher_outputs)
        info = CameraInfo(header=header(1, "cam"), height=INTR.height, width=INTR.width)
        info.k = INTR.K.reshape(-1).tolist()
        remote._on_cloud(cloud)
        remote._on_poses(poses_to_array(mapped.keyframe_poses, 1))
        remote._on_info(info)
        got = remote._on_request(_request(cands), GetNextBestView.Response())
    finally:
        shared.destroy_node()
        remote.destroy_node()
    assert expected.success and got.success, got.message
    assert got.best_index == expected.best_index
    np.testing.assert_allclose(got.fused_scores, expected.fused_scores, rtol=1e-5, atol=1e-8)
    assert remote.status()["h_train_full"] == 0 and remote.status()["h_train_poses_added"] == 0


# ---------------------------------------------------------------------------------------- mesh service (bug 2)
def test_decimate_mesh_bounds_the_triangles() -> None:
    import open3d as o3d

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=60)
    sphere.vertex_colors = o3d.utility.Vector3dVector(np.full((len(sphere.vertices), 3), 0.25))
    small = decimate_mesh(sphere, 1000)
    assert 250 < len(small.triangles) <= 1000 < len(sphere.triangles)
    np.testing.assert_allclose(np.asarray(small.vertex_colors), 0.25)
    assert decimate_mesh(sphere, 0) is sphere


def test_mesh_service_decimates_and_never_holds_shutdown(ros_context: Any, mapped: Mapper) -> None:
    mapper = MapperNode(
        context=ros_context,
        shared=_shared(mapped),
        parameter_overrides=[Parameter("mesh_marker_max_triangles", value=500)],
    )
    client_node = Node("mesh_client", context=ros_context)
    meshes: list[Marker] = []
    client_node.create_subscription(Marker, "/mapper/mesh", meshes.append, latched_qos())
    client = client_node.create_client(Trigger, "/mapper/publish_mesh")
    release = threading.Event()
    with _spinning(ros_context, mapper, client_node):
        res = _call(client, Trigger.Request())
        _wait(lambda: bool(meshes), 10.0, "the mesh marker")
        mapper.publish_mesh = lambda: str(release.wait(60.0))  # type: ignore[method-assign] - a mesh that takes long
        pending = client.call_async(Trigger.Request())
        time.sleep(0.5)
        t0 = time.monotonic()
        mapper.stop()  # what Ctrl-C does first (run_nodes, ActiveMapping.shutdown)
        _wait(pending.done, 5.0, "the abandoned mesh request")
        waited_s = time.monotonic() - t0
        release.set()
    assert res.success and " of " in res.message, res.message  # "N of M triangles": decimated
    assert 0 < len(meshes[-1].points) <= 3 * 500 and len(meshes[-1].colors) in (0, len(meshes[-1].points))
    assert not pending.result().success and "shutting down" in pending.result().message and waited_s < 2.0


def test_the_nodes_save_map_keeps_the_training_fisher_when_computed(mapped: Mapper, tmp_path: Path) -> None:
    """``~/save_map`` wrote no training Fisher, so ``~/load_map`` (or ``load_map:=``) scored views under another
    H_train than the map that was saved. It is saved now when computed (the planner and the map topic compute it),
    and a map whose Fisher was never read is saved without paying for it."""
    fresh = Mapper(mapped.intr, mapped.config)
    fresh.map, fresh.keyframes = mapped.map.detach().clone(), list(mapped.keyframes)
    fresh._reset_h_train()
    fresh._fisher_pending = list(fresh.keyframes)  # inserted, its Fisher not read yet (lazy)
    _shared(fresh).save(tmp_path / "lazy")
    assert not (tmp_path / "lazy" / "h_train.npz").exists() and fresh._fisher_pending  # not computed for the save
    h = {k: v.clone() for k, v in mapped.h_train.items()}  # computed, as a planner reads it
    _shared(mapped).save(tmp_path / "map")
    loaded = SharedMapper(MapperConfig()).load(tmp_path / "map")
    assert loaded.h_train_complete
    for k, v in h.items():
        torch.testing.assert_close(loaded.h_train[k], v)


def test_loaded_map_catch_up_once_then_requests_reuse_tsdf_work(
    ros_context: Any, scene: Any, mapped: Mapper, tmp_path: Path
) -> None:
    """A loaded map without its saved H_train (an older folder; no keyframe images, so no mapper H_train): one
    catch-up, then only new keyframes cost work.

    Before the fix every request re-extracted the TSDF's surface and rebuilt W_f over all keyframe poses
    (with a loaded room map ~2/3 of the scorer's set-up: 1-4 s a request, past the selector's timeout).
    """
    frames, _ = scene
    mapped.save(tmp_path / "map")
    (tmp_path / "map" / "h_train.npz").unlink()  # saved before the training Fisher travelled with the map
    shared = SharedMapper(MapperConfig(iters_per_keyframe=1))
    shared.load(tmp_path / "map")
    planner = NBVPlannerNode(
        context=ros_context, shared=shared, parameter_overrides=[Parameter("tsdf_sync_period_s", value=0.0)]
    )
    try:
        snap = shared.snapshot()
        assert snap is not None and snap.h_train is None  # the mapper has no Fisher of loaded keyframes
        planner._sync_timer()  # the catch-up, as the timer does it before any request
        caught_up = planner.status()
        assert caught_up["tsdf_frames"] == 3 and caught_up["h_train_full"] == 1
        assert caught_up["surface_extractions"] == 1 and caught_up["close_front_builds"] == 1
        assert caught_up["close_front_views_added"] == 0
        cands = [frames[i].T_wc for i in (2, 6, 10)]
        answers = [planner._on_request(_request(cands), GetNextBestView.Response()) for _ in range(2)]
        now = planner.status()
        assert all(a.success for a in answers) and now == {
            **caught_up,
            "requests": 2,
            "answered": 2,
            **{k: now[k] for k in ("last_scoring_s", "max_scoring_s", "last_phases_s", "slowest_phases_s")},
        }  # no map work at all in the requests
        # The cached products score exactly as the library does from scratch with the same inputs.
        scorer = NBVScorer(replace(NBVConfig(), top_k=3))
        h = scorer.train_fisher(snap.surfel_map, snap.keyframe_poses, INTR, "roi-gsurfisher")
        want = scorer.score(snap.surfel_map, h, planner.state.tsdf, snap.keyframe_poses, cands, INTR)
        np.testing.assert_allclose(answers[1].fused_scores, want.fused, rtol=1e-6, atol=1e-9)
        assert answers[1].best_index == want.best_index
        # A new keyframe on top: its TSDF frame, one surface extraction, W_f folds in that one keyframe (no
        # rebuild from every pose), one Fisher pass; no full recompute.
        with shared.lock:
            assert shared.mapper.add_keyframe(frames[11], optimise=False)
            shared.touch()
        assert planner._on_request(_request(cands), GetNextBestView.Response()).success
        after = planner.status()
        assert after["tsdf_frames"] == 4 and after["h_train_full"] == 1 and after["h_train_poses_added"] == 1
        assert after["surface_extractions"] == 2 and after["close_front_builds"] == 1
        assert after["close_front_views_added"] == 1
    finally:
        planner.destroy_node()


def test_the_mapper_pauses_while_the_in_process_planner_answers(ros_context: Any, scene: Any, mapped: Mapper) -> None:
    """The planner marks its requests as answering; the mapper's pause between slices waits for them (capped)."""
    frames, _ = scene
    shared = _shared(mapped)
    assert shared.yield_to_answers(5.0) < 0.05  # nobody answering: no pause
    release = threading.Event()

    def answer() -> None:
        with shared.answering():
            release.wait(5.0)

    t = threading.Thread(target=answer)
    t.start()
    try:
        time.sleep(0.05)
        assert 0.09 <= shared.yield_to_answers(0.1) < 1.0  # capped at max_s
        threading.Timer(0.3, release.set).start()
        assert shared.yield_to_answers(5.0, stop=lambda: True) < 0.05  # a node stopping does not wait
        assert 0.2 <= shared.yield_to_answers(5.0) < 2.0  # until the answer is done
    finally:
        release.set()
        t.join()
    planner = NBVPlannerNode(context=ros_context, shared=shared)
    seen: list[int] = []
    real_score = planner.state.score

    def score(*args: Any, **kwargs: Any) -> Any:
        seen.append(shared._answering)
        return real_score(*args, **kwargs)

    planner.state.score = score  # type: ignore[method-assign]
    client_node = Node("nbv_test_client_pause", context=ros_context)
    client = client_node.create_client(GetNextBestView, "/nbv_planner/get_next_best_view")
    with _spinning(ros_context, planner, client_node):
        res = _call(client, _request([frames[1].T_wc, frames[2].T_wc]))
    assert res.success and seen == [1] and shared._answering == 0
