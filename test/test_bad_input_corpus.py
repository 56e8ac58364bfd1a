"""Bad-input corpus: every kind of bad file and bad message met so far, each through a public entry point.

One parametrized test, :func:`test_bad_input_is_refused_clearly_and_loses_nothing`, runs every case of
:data:`CASES` and checks the same two things of each:

(a) **a clear refusal**: an error (exception, CLI message, service answer) that names the file, topic,
    field or option at fault, or, for a message stream, the bad frame counted in the node's status;
(b) **nothing lost**: the node still serves afterwards (a good frame is taken in, a good request
    answered, a save succeeds), earlier outputs are byte-for-byte intact, the node's map is untouched,
    and no partial output is left under the final name or beside it.

Entry points: the ``roigsf`` CLI (in-process, :func:`roigsf_ros.cli.main`), the nodes in-process
(``keyframe_selector``'s camera input, ``mapper``'s ``~/load_map`` and ``~/save_map``, ``nbv_planner``'s
``~/get_next_best_view``) and the library (``BagPlayer``). The terminal summary prints the number of cases
tried and survived (``pytest_terminal_summary`` in conftest.py); README's "Reliability" section quotes it.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("roigsf_interfaces")

import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image

from roigsf_interfaces.srv import GetNextBestView, LoadMap, SaveMap
from roigsf_ros.cli import main as roigsf
from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.data import bags
from roigsf_ros.data.replica import ReplicaSequence
from roigsf_ros.data.scene import render_sequence, synth_room, synth_trajectory
from roigsf_ros.mapping.mapper import Mapper, MapperConfig
from roigsf_ros.nodes.bag_player import BagPlayer, reliable_qos
from roigsf_ros.nodes.keyframe_selector import KeyframeSelectorNode
from roigsf_ros.nodes.map_msgs import header, pose_stamped, poses_to_array
from roigsf_ros.nodes.mapper import MapperNode
from roigsf_ros.nodes.nbv_planner import NBVPlannerNode
from roigsf_ros.nodes.node_process import BackgroundSpin
from roigsf_ros.nodes.shared_map import SharedMapper

pytestmark = pytest.mark.ros
INTR = Intrinsics(width=64, height=48, fx=40.0, fy=40.0, cx=31.5, cy=23.5)
N_FRAMES = 6
TOPICS = bags.CameraTopics()


# ----------------------------------------------------------------------------------------- the world
def tree_digest(path: Path) -> str:
    """A digest of every file under ``path`` (names and bytes): equal digests, identical outputs."""
    h = hashlib.sha256()
    for p in sorted(path.rglob("*")) if path.is_dir() else [path]:
        if p.is_file():
            h.update(str(p.relative_to(path) if path.is_dir() else p.name).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


class World:
    """What the cases run against: good inputs, earlier outputs, and nodes serving on one executor."""

    def __init__(self, root: Path, ctx: Any) -> None:
        self.root = root
        self.ctx = ctx
        self.scene = root / "scene"
        render_sequence(synth_room(3), synth_trajectory(3, N_FRAMES), INTR, self.scene, progress=False)
        self.frames = list(ReplicaSequence(self.scene))
        self.bag = root / "bag"
        bags.write_bag(ReplicaSequence(self.scene), self.bag, progress=False)
        self.a_file = root / "a_regular_file"
        self.a_file.write_text("not a folder\n")
        mapper = Mapper(INTR, MapperConfig(iters_per_keyframe=2))
        for i in (0, 3):
            assert mapper.add_keyframe(self.frames[i])
        self.shared = SharedMapper(mapper.config)
        self.shared.mapper = mapper
        self.mapper_node = MapperNode(context=ctx, shared=self.shared, node_name="corpus_mapper")
        self.planner = NBVPlannerNode(context=ctx, shared=self.shared, node_name="corpus_planner")
        selector_params = [
            Parameter("policy", value="every-n"),
            Parameter("every_n", value=1000),
            Parameter("keyframe_topic", value="/corpus/keyframe"),  # the mapper does not hear these
        ]
        self.selector = KeyframeSelectorNode(context=ctx, parameter_overrides=selector_params, node_name="corpus_sel")
        self.client = Node("corpus_client", context=ctx)
        types = {TOPICS.color: Image, TOPICS.depth: Image, TOPICS.camera_info: CameraInfo, TOPICS.pose: PoseStamped}
        self.pubs = {t: self.client.create_publisher(c, t, reliable_qos(100)) for t, c in types.items()}
        self.save = self.client.create_client(SaveMap, "/corpus_mapper/save_map")
        self.load = self.client.create_client(LoadMap, "/corpus_mapper/load_map")
        self.nbv = self.client.create_client(GetNextBestView, "/corpus_planner/get_next_best_view")
        self.nodes: list[Node] = [self.mapper_node, self.planner, self.selector, self.client]
        executor = MultiThreadedExecutor(num_threads=4, context=ctx)
        for node in self.nodes:
            executor.add_node(node)
        self.spin = BackgroundSpin(executor, "corpus_executor").start()
        self._stamp = 1_000_000_000
        self.wait(lambda: all(p.get_subscription_count() >= 2 for p in self.pubs.values()), "camera subscribers")
        for c in (self.save, self.load, self.nbv):
            assert c.wait_for_service(timeout_sec=20.0), c.srv_name
        self.saved_map = root / "saved_map"  # an earlier output the cases must leave intact
        res = self.call(self.save, SaveMap.Request(directory=str(self.saved_map)))
        assert res.success, res.message
        self.saved_digest = tree_digest(self.saved_map)
        self.previous_bag = root / "previous_bag"  # an earlier conversion, overwritten only by a complete one
        shutil.copytree(self.bag, self.previous_bag)
        self.previous_bag_digest = tree_digest(self.previous_bag)

    def close(self) -> None:
        self.spin.stop()
        for node in self.nodes:
            node.destroy_node()

    # ---------------------------------------------------------------------------------- helpers
    @staticmethod
    def wait(pred: Callable[[], bool], what: str, timeout_s: float = 20.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not pred():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
            time.sleep(0.02)

    def call(self, client: Any, req: Any, timeout_s: float = 60.0) -> Any:
        future = client.call_async(req)
        self.wait(future.done, f"an answer from {client.srv_name}", timeout_s)
        return future.result()

    def next_stamp(self) -> int:
        """A stamp after every one published so far (10 Hz)."""
        self._stamp += 100_000_000
        return self._stamp

    def frame_msgs(self, stamp_ns: int, k: int = 1) -> dict[str, Any]:
        """The four messages of frame ``k`` of the scene, stamped ``stamp_ns`` (rgb8, 32FC1 metres)."""
        f = self.frames[k]
        color = Image(header=header(stamp_ns, bags.CAMERA_FRAME_ID), height=INTR.height, width=INTR.width)
        color.encoding, color.step, color.data = "rgb8", 3 * INTR.width, np.ascontiguousarray(f.rgb).tobytes()
        depth = Image(header=header(stamp_ns, bags.CAMERA_FRAME_ID), height=INTR.height, width=INTR.width)
        depth.encoding, depth.step = "32FC1", 4 * INTR.width
        depth.data = np.ascontiguousarray(f.depth_m, dtype="<f4").tobytes()
        info = CameraInfo(header=header(stamp_ns, bags.CAMERA_FRAME_ID), height=INTR.height, width=INTR.width)
        info.k = INTR.K.reshape(-1).tolist()
        return {
            TOPICS.color: color,
            TOPICS.depth: depth,
            TOPICS.camera_info: info,
            TOPICS.pose: pose_stamped(f.T_wc, stamp_ns),
        }

    def publish(self, msgs: dict[str, Any], skip: tuple[str, ...] = ()) -> None:
        for topic, msg in msgs.items():
            if topic not in skip:
                self.pubs[topic].publish(msg)

    def selector_counts(self) -> dict[str, int]:
        """The selector's camera-input frame counters, rejections by reason as ``rejected:<reason>``."""
        st = self.selector.camera.stats()
        out = {k: v for k, v in st.items() if isinstance(v, int)}
        out |= {f"rejected:{k}": v for k, v in st["rejected"].items()}
        return out

    def map_state(self) -> tuple[Any, ...]:
        st = self.mapper_node.status()
        return (st["keyframe_ids"], st["surfels"], id(self.shared.mapper))

    def good_request(self) -> GetNextBestView.Request:
        req = GetNextBestView.Request(top_k=1)
        req.candidates = poses_to_array([self.frames[1].T_wc, self.frames[2].T_wc], 0, "map")
        return req


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Iterator[World]:
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
    w = None
    try:
        w = World(tmp_path_factory.mktemp("corpus"), ctx)
        yield w
    finally:
        if w is not None:
            w.close()
        ctx.try_shutdown()


# ----------------------------------------------------------------------------------------- outcomes
@dataclass
class Outcome:
    """What a case observed: the refusal's text (or counter deltas) and anything found lost."""

    message: str = ""
    counted: dict[str, int] = field(default_factory=dict)
    lost: list[str] = field(default_factory=list)

    def __or__(self, other: Outcome) -> Outcome:
        """Both observations: the first message, every count, everything lost."""
        return Outcome(self.message or other.message, {**self.counted, **other.counted}, self.lost + other.lost)


@dataclass(frozen=True)
class Case:
    """One bad input: ``names`` must all appear in the refusal, or ``counter`` must grow by one."""

    name: str
    run: Callable[[World, Path], Outcome]
    names: tuple[str, ...] = ()
    counter: str = ""


def cli(*args: str) -> tuple[int, str]:
    """``roigsf ARGS`` in-process: (exit code, stderr)."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = roigsf(list(args))
        except SystemExit as exc:  # argparse
            code = int(exc.code or 0)
    return code, err.getvalue()


def leftovers(parent: Path, before: set[str]) -> list[str]:
    """Entries of ``parent`` that were not there ``before`` (partial outputs, temporary folders)."""
    return sorted(set(os.listdir(parent)) - before)


# ----------------------------------------------------------------------------------------- files via the CLI
def _scene_copy(w: World, tmp: Path) -> Path:
    out = tmp / "scene"
    shutil.copytree(w.scene, out)
    return out


def _convert(w: World, scene: Path) -> Outcome:
    """``roigsf bag from-replica SCENE --out PREVIOUS --overwrite``: must fail, leaving the earlier bag as it was."""
    before = set(os.listdir(w.root))
    code, err = cli("bag", "from-replica", str(scene), "--out", str(w.previous_bag), "--overwrite", "--no-progress")
    out = Outcome(message=err if code == 2 else f"exit {code}: {err}")
    if tree_digest(w.previous_bag) != w.previous_bag_digest:
        out.lost.append("the earlier bag at --out was changed")
    out.lost += [f"left behind: {n}" for n in leftovers(w.root, before)]
    return out


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])


def truncated_jpeg(w: World, tmp: Path) -> Outcome:
    scene = _scene_copy(w, tmp)
    _truncate(scene / "results" / "frame000002.jpg")
    return _convert(w, scene)


def truncated_depth_png(w: World, tmp: Path) -> Outcome:
    scene = _scene_copy(w, tmp)
    _truncate(scene / "results" / "depth000002.png")
    return _convert(w, scene)


def wrong_size_depth_png(w: World, tmp: Path) -> Outcome:
    scene = _scene_copy(w, tmp)
    cv2.imwrite(str(scene / "results" / "depth000002.png"), np.zeros((10, 10), np.uint16))
    return _convert(w, scene)


def wrong_size_colour_jpeg(w: World, tmp: Path) -> Outcome:
    scene = _scene_copy(w, tmp)
    cv2.imwrite(str(scene / "results" / "frame000002.jpg"), np.zeros((12, 16, 3), np.uint8))
    return _convert(w, scene)


def _edit_traj(w: World, tmp: Path, line: int, edit: Callable[[np.ndarray], np.ndarray]) -> Outcome:
    scene = _scene_copy(w, tmp)
    lines = (scene / "traj.txt").read_text().splitlines()
    T = np.array(lines[line].split(), dtype=float).reshape(4, 4)
    lines[line] = " ".join(repr(float(v)) for v in edit(T).reshape(-1))
    (scene / "traj.txt").write_text("\n".join(lines) + "\n")
    return _convert(w, scene)


def non_rigid_pose_line(w: World, tmp: Path) -> Outcome:
    def scaled(T: np.ndarray) -> np.ndarray:
        T = T.copy()
        T[:3, :3] *= 1.5
        return T

    return _edit_traj(w, tmp, 3, scaled)


def nan_pose_line(w: World, tmp: Path) -> Outcome:
    def nan(T: np.ndarray) -> np.ndarray:
        T = T.copy()
        T[0, 3] = math.nan
        return T

    return _edit_traj(w, tmp, 3, nan)


def short_pose_line(w: World, tmp: Path) -> Outcome:
    scene = _scene_copy(w, tmp)
    lines = (scene / "traj.txt").read_text().splitlines()
    lines[2] = " ".join(lines[2].split()[:12])
    (scene / "traj.txt").write_text("\n".join(lines) + "\n")
    return _convert(w, scene)


def fewer_poses_than_frames(w: World, tmp: Path) -> Outcome:
    scene = _scene_copy(w, tmp)
    lines = (scene / "traj.txt").read_text().splitlines()
    (scene / "traj.txt").write_text("\n".join(lines[:-2]) + "\n")
    return _convert(w, scene)


def cam_params_without_fx(w: World, tmp: Path) -> Outcome:
    scene = _scene_copy(w, tmp)
    cam = json.loads((scene / "cam_params.json").read_text())
    del cam["camera"]["fx"]
    (scene / "cam_params.json").write_text(json.dumps(cam))
    return _convert(w, scene)


def cam_params_not_json(w: World, tmp: Path) -> Outcome:
    scene = _scene_copy(w, tmp)
    (scene / "cam_params.json").write_text('{"camera": {"w": 64,')
    return _convert(w, scene)


def _copy_bag_without(w: World, out: Path, drop_topic: str) -> Path:
    """The good bag without ``drop_topic`` (a recording that missed a topic)."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    with AnyReader([w.bag]) as reader, Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {
            c.id: writer.add_connection(c.topic, c.msgtype, typestore=store)
            for c in reader.connections
            if c.topic != drop_topic
        }
        for conn, stamp, raw in reader.messages():
            if conn.id in conns:
                writer.write(conns[conn.id], stamp, raw)
    return out


def bag_missing_a_topic_map(w: World, tmp: Path) -> Outcome:
    bag = _copy_bag_without(w, tmp / "bag", TOPICS.depth)
    code, err = cli("map", str(bag), "--out", str(tmp / "run"), "--policy", "every-n", "--no-progress")
    out = Outcome(message=err if code == 2 else f"exit {code}: {err}")
    if (tmp / "run").exists():
        out.lost.append("a run folder was left")
    return out


def bag_missing_a_topic_demo(w: World, tmp: Path) -> Outcome:
    bag = _copy_bag_without(w, tmp / "bag", TOPICS.camera_info)
    code, err = cli("demo", "--bag", str(bag), "--out", str(tmp / "run"), "--gt-mesh", "", "--no-progress")
    out = Outcome(message=err if code == 2 else f"exit {code}: {err}")
    if (tmp / "run").exists():
        out.lost.append("a run folder was left")
    return out


def truncated_mcap(w: World, tmp: Path) -> Outcome:
    bag = tmp / "bag"
    shutil.copytree(w.bag, bag)
    _truncate(next(bag.glob("*.mcap")))
    code, err = cli("map", str(bag), "--out", str(tmp / "run"), "--policy", "every-n", "--no-progress")
    out = Outcome(message=err if code == 2 else f"exit {code}: {err}")
    if (tmp / "run").exists():
        out.lost.append("a run folder was left")
    return out


def _under_a_file(w: World, *args: str) -> Outcome:
    before = w.a_file.read_bytes()
    code, err = cli(*args)
    out = Outcome(message=err if code == 2 else f"exit {code}: {err}")
    if not w.a_file.is_file() or w.a_file.read_bytes() != before:
        out.lost.append("the regular file in the way was changed")
    return out


def convert_into_a_path_under_a_file(w: World, tmp: Path) -> Outcome:
    return _under_a_file(w, "bag", "from-replica", str(w.scene), "--out", str(w.a_file / "bag"), "--no-progress")


def map_into_a_path_under_a_file(w: World, tmp: Path) -> Outcome:
    return _under_a_file(w, "map", str(w.bag), "--out", str(w.a_file / "run"), "--no-progress")


def demo_into_a_path_under_a_file(w: World, tmp: Path) -> Outcome:
    return _under_a_file(w, "demo", "--bag", str(w.bag), "--out", str(w.a_file / "run"), "--gt-mesh", "")


def convert_with_rate_zero(w: World, tmp: Path) -> Outcome:
    code, err = cli("bag", "from-replica", str(w.scene), "--out", str(tmp / "bag"), "--rate", "0")
    out = Outcome(message=err if code == 2 else f"exit {code}: {err}")
    if (tmp / "bag").exists():
        out.lost.append("a bag was left")
    return out


def _bench_refused(w: World, tmp: Path, *args: str) -> Outcome:
    run = tmp / "bench"
    code, err = cli("bench", "--scene", str(w.scene), "--out", str(run), "--no-progress", *args)
    out = Outcome(message=err if code == 2 else f"exit {code}: {err}")
    if run.exists():
        out.lost.append("a bench folder was left")
    return out


def bench_policy_value_a_word(w: World, tmp: Path) -> Outcome:
    return _bench_refused(w, tmp, "--setting", "stream", "--policies", "random,roi-gsurfisher:window=abc")


def bench_policy_flag_a_number(w: World, tmp: Path) -> Outcome:
    return _bench_refused(w, tmp, "--setting", "stream", "--policies", "random:seed=true")


def pool_bench_score_option_a_word(w: World, tmp: Path) -> Outcome:
    return _bench_refused(w, tmp, "--setting", "pool", "--policies", "roi-gsurfisher:unseen_alpha=x")


def pool_bench_pool_set_a_word(w: World, tmp: Path) -> Outcome:
    return _bench_refused(w, tmp, "--setting", "pool", "--policies", "random", "--pool-set", "n_views=x")


# ----------------------------------------------------------------------------------------- library: the player
def player_for_a_topic_not_in_the_bag(w: World, tmp: Path) -> Outcome:
    overrides = [Parameter("bag", value=str(w.bag)), Parameter("topics", value=["/camera/imu"])]
    try:
        BagPlayer(context=w.ctx, parameter_overrides=overrides).destroy_node()
    except InputError as exc:
        return Outcome(message=str(exc))
    return Outcome(message="no error")


def player_with_negative_subscriber_count(w: World, tmp: Path) -> Outcome:
    overrides = [Parameter("bag", value=str(w.bag)), Parameter("wait_for_subscribers", value=-1)]
    try:
        BagPlayer(context=w.ctx, parameter_overrides=overrides).destroy_node()
    except InputError as exc:
        return Outcome(message=str(exc))
    return Outcome(message="no error")


# ----------------------------------------------------------------------------------------- messages via a node
def _stream(w: World, bad: Callable[[], None], counter: str) -> Outcome:
    """Publish bad frame(s), then a good one: ``counter`` must grow and the good frame must be taken in."""
    before = w.selector_counts()
    bad()
    w.publish(w.frame_msgs(w.next_stamp()))
    out = Outcome()
    try:
        w.wait(lambda: w.selector_counts().get(counter, 0) > before.get(counter, 0), f"{counter} to grow")
    except AssertionError as exc:
        out.message = str(exc)
    try:
        w.wait(lambda: w.selector_counts()["frames"] > before["frames"], "the good frame after it")
    except AssertionError:
        out.lost.append("the good frame after the bad one was not taken in")
    after = w.selector_counts()
    out.counted = {k: after.get(k, 0) - before.get(k, 0) for k in after if after.get(k, 0) != before.get(k, 0)}
    return out


def _bad_frame(w: World, edit: Callable[[dict[str, Any]], None], skip: tuple[str, ...] = ()) -> Callable[[], None]:
    def send() -> None:
        msgs = w.frame_msgs(w.next_stamp())
        edit(msgs)
        w.publish(msgs, skip)

    return send


def depth_mono8(w: World, tmp: Path) -> Outcome:
    def edit(m: dict[str, Any]) -> None:
        d = m[TOPICS.depth]
        d.encoding, d.step, d.data = "mono8", INTR.width, bytes(INTR.width * INTR.height)

    return _stream(w, _bad_frame(w, edit), "rejected:bad_encoding")


def colour_yuv(w: World, tmp: Path) -> Outcome:
    def edit(m: dict[str, Any]) -> None:
        c = m[TOPICS.color]
        c.encoding, c.step, c.data = "yuv422", 2 * INTR.width, bytes(2 * INTR.width * INTR.height)

    return _stream(w, _bad_frame(w, edit), "rejected:bad_encoding")


def depth_size_mismatch_with_camera_info(w: World, tmp: Path) -> Outcome:
    def edit(m: dict[str, Any]) -> None:
        d = m[TOPICS.depth]
        d.width, d.step = INTR.width - 2, 4 * (INTR.width - 2)
        d.data = bytes(4 * (INTR.width - 2) * INTR.height)

    return _stream(w, _bad_frame(w, edit), "rejected:size_mismatch")


def colour_size_mismatch_with_camera_info(w: World, tmp: Path) -> Outcome:
    def edit(m: dict[str, Any]) -> None:
        c = m[TOPICS.color]
        c.height, c.data = INTR.height // 2, bytes(3 * INTR.width * (INTR.height // 2))

    return _stream(w, _bad_frame(w, edit), "rejected:size_mismatch")


def image_data_too_short(w: World, tmp: Path) -> Outcome:
    def edit(m: dict[str, Any]) -> None:
        m[TOPICS.depth].data = bytes(100)

    return _stream(w, _bad_frame(w, edit), "rejected:bad_image")


def camera_info_nan_focal(w: World, tmp: Path) -> Outcome:
    def edit(m: dict[str, Any]) -> None:
        k = list(m[TOPICS.camera_info].k)
        k[0] = math.nan
        m[TOPICS.camera_info].k = k

    return _stream(w, _bad_frame(w, edit), "rejected:bad_camera_info")


def nan_pose(w: World, tmp: Path) -> Outcome:
    def edit(m: dict[str, Any]) -> None:
        m[TOPICS.pose].pose.position.x = math.nan

    return _stream(w, _bad_frame(w, edit), "rejected:bad_pose")


def non_unit_quaternion(w: World, tmp: Path) -> Outcome:
    def edit(m: dict[str, Any]) -> None:
        m[TOPICS.pose].pose.orientation.w += 0.5

    return _stream(w, _bad_frame(w, edit), "rejected:bad_pose")


def stray_stamp_zero(w: World, tmp: Path) -> Outcome:
    return _stream(w, lambda: w.publish(w.frame_msgs(0)), "out_of_order")


def repeated_stamp(w: World, tmp: Path) -> Outcome:
    def twice() -> None:
        msgs = w.frame_msgs(w.next_stamp())
        w.publish(msgs)
        w.publish(msgs)

    return _stream(w, twice, "duplicate_stamp")


def backwards_stamp(w: World, tmp: Path) -> Outcome:
    def back() -> None:
        last = w.next_stamp()
        w.publish(w.frame_msgs(last))
        w.publish(w.frame_msgs(last - 50_000_000))

    return _stream(w, back, "out_of_order")


def frame_missing_its_colour(w: World, tmp: Path) -> Outcome:
    """Held as pending (bounded by ``max_pending``, then counted as dropped), never delivered half."""
    return _stream(w, _bad_frame(w, lambda m: None, skip=(TOPICS.color,)), "pending")


# ----------------------------------------------------------------------------------------- map files via ~/load_map
def _load(w: World, tmp: Path, meta_edit: Callable[[dict[str, Any]], Any] | None, ply_edit: bool = False) -> Outcome:
    folder = tmp / "map"
    shutil.copytree(w.saved_map, folder)
    if meta_edit is not None:
        meta = json.loads((folder / "keyframes.json").read_text())
        new = meta_edit(meta)
        text = new if isinstance(new, str) else json.dumps(meta if new is None else new)
        (folder / "keyframes.json").write_text(text)
    if ply_edit:
        _truncate(folder / "map.ply")
    before = w.map_state()
    res = w.call(w.load, LoadMap.Request(directory=str(folder)))
    out = Outcome(message=res.message if not res.success else "loaded")
    if w.map_state() != before:
        out.lost.append("the node's map changed")
    return out | _still_saves(w, tmp)


def _still_saves(w: World, tmp: Path) -> Outcome:
    """The mapper still saves (to a new folder), and the earlier saved map is intact."""
    out = Outcome()
    res = w.call(w.save, SaveMap.Request(directory=str(tmp / "saved_after")))
    if not res.success:
        out.lost.append(f"the node no longer saves: {res.message}")
    if tree_digest(w.saved_map) != w.saved_digest:
        out.lost.append("the earlier saved map was changed")
    return out


def keyframes_json_is_a_list(w: World, tmp: Path) -> Outcome:
    return _load(w, tmp, lambda m: [m])


def keyframes_json_without_fx(w: World, tmp: Path) -> Outcome:
    def no_fx(m: dict[str, Any]) -> None:
        del m["intrinsics"]["fx"]

    return _load(w, tmp, no_fx)


def keyframes_json_width_a_string(w: World, tmp: Path) -> Outcome:
    def wide(m: dict[str, Any]) -> None:
        m["intrinsics"]["width"] = "wide"

    return _load(w, tmp, wide)


def keyframes_json_non_rigid_pose(w: World, tmp: Path) -> Outcome:
    def scaled(m: dict[str, Any]) -> None:
        m["keyframe_poses"][0] = (2 * np.eye(4)).tolist()

    return _load(w, tmp, scaled)


def keyframes_json_nan_pose(w: World, tmp: Path) -> Outcome:
    def nan(m: dict[str, Any]) -> None:
        m["keyframe_poses"][0][0][3] = math.nan  # json.dumps writes NaN, which json.loads reads back

    return _load(w, tmp, nan)


def keyframes_json_ids_and_poses_disagree(w: World, tmp: Path) -> Outcome:
    def one_more_id(m: dict[str, Any]) -> None:
        m["keyframe_ids"].append(123)

    return _load(w, tmp, one_more_id)


def keyframes_json_truncated(w: World, tmp: Path) -> Outcome:
    return _load(w, tmp, lambda m: json.dumps(m)[:40])


def keyframes_json_bad_config_value(w: World, tmp: Path) -> Outcome:
    """Through the library (the node loads with its own config, so the saved one does not matter to it)."""
    folder = tmp / "map"
    shutil.copytree(w.saved_map, folder)
    meta = json.loads((folder / "keyframes.json").read_text())
    meta["config"]["near_m"] = -1.0
    (folder / "keyframes.json").write_text(json.dumps(meta))
    try:
        Mapper.load(folder)
    except InputError as exc:
        out = Outcome(message=str(exc))
    else:
        out = Outcome(message="loaded")
    if tree_digest(w.saved_map) != w.saved_digest:
        out.lost.append("the earlier saved map was changed")
    return out


def map_ply_truncated(w: World, tmp: Path) -> Outcome:
    return _load(w, tmp, None, ply_edit=True)


def map_folder_missing(w: World, tmp: Path) -> Outcome:
    before = w.map_state()
    res = w.call(w.load, LoadMap.Request(directory=str(tmp / "no_map_here")))
    out = Outcome(message=res.message if not res.success else "loaded")
    if w.map_state() != before:
        out.lost.append("the node's map changed")
    return out | _still_saves(w, tmp)


def save_map_under_a_file(w: World, tmp: Path) -> Outcome:
    res = w.call(w.save, SaveMap.Request(directory=str(w.a_file / "map")))
    out = Outcome(message=res.message if not res.success else "saved")
    if not w.a_file.is_file():
        out.lost.append("the regular file in the way was replaced")
    return out | _still_saves(w, tmp)


# ------------------------------------------------------------------------------ requests via ~/get_next_best_view
def _ask(w: World, edit: Callable[[GetNextBestView.Request], None]) -> Outcome:
    req = w.good_request()
    edit(req)
    res = w.call(w.nbv, req)
    out = Outcome(message=res.message if not res.success else f"scored: {res.message}")
    if not res.success and (res.best_index != -1 or len(res.fused_scores)):
        out.lost.append("a refusal carried scores")
    good = w.call(w.nbv, w.good_request())
    if not good.success or len(good.fused_scores) != 2:
        out.lost.append(f"the planner no longer answers: {good.message}")
    return out


def too_many_candidates(w: World, tmp: Path) -> Outcome:
    def many(req: GetNextBestView.Request) -> None:
        req.candidates = poses_to_array([w.frames[1 + i % 4].T_wc for i in range(10_000)], 0, "map")

    return _ask(w, many)


def candidate_nan_position(w: World, tmp: Path) -> Outcome:
    return _ask(w, lambda r: setattr(r.candidates.poses[1].position, "x", math.nan))


def candidate_non_unit_quaternion(w: World, tmp: Path) -> Outcome:
    return _ask(w, lambda r: setattr(r.candidates.poses[0].orientation, "w", r.candidates.poses[0].orientation.w + 0.3))


def candidates_in_another_frame(w: World, tmp: Path) -> Outcome:
    return _ask(w, lambda r: setattr(r.candidates.header, "frame_id", "odom"))


def unknown_score_mode(w: World, tmp: Path) -> Outcome:
    return _ask(w, lambda r: setattr(r, "mode", "best"))


def empty_candidate_list(w: World, tmp: Path) -> Outcome:
    return _ask(w, lambda r: setattr(r.candidates, "poses", []))


def stale_request(w: World, tmp: Path) -> Outcome:
    def old(req: GetNextBestView.Request) -> None:
        now = w.planner.get_clock().now().nanoseconds
        req.candidates.header = header(now - 60_000_000_000, "map")  # a minute ago

    return _ask(w, old)


# ----------------------------------------------------------------------------------------- the corpus
CASES = [
    # Replica folders -> roigsf bag from-replica --overwrite over an earlier bag
    Case("truncated JPEG", truncated_jpeg, ("frame000002.jpg", "truncated")),
    Case("truncated depth PNG", truncated_depth_png, ("depth000002.png", "truncated")),
    Case("wrong-size depth PNG", wrong_size_depth_png, ("depth000002.png", "10x10")),
    Case("wrong-size colour JPEG", wrong_size_colour_jpeg, ("frame000002.jpg", "16x12")),
    Case("non-rigid pose line", non_rigid_pose_line, ("traj.txt",)),
    Case("NaN pose line", nan_pose_line, ("traj.txt",)),
    Case("pose line of 12 numbers", short_pose_line, ("traj.txt",)),
    Case("fewer poses than frames", fewer_poses_than_frames, ("traj.txt",)),
    Case("cam_params.json without fx", cam_params_without_fx, ("cam_params.json", "fx")),
    Case("cam_params.json not JSON", cam_params_not_json, ("cam_params.json",)),
    # bags -> roigsf map / demo
    Case("bag missing a topic (map)", bag_missing_a_topic_map, (TOPICS.depth, "missing")),
    Case("bag missing a topic (demo)", bag_missing_a_topic_demo, (TOPICS.camera_info, "missing")),
    Case("truncated .mcap", truncated_mcap, ("bag", "cut short")),
    # outputs that cannot be written
    Case("bag output under a regular file", convert_into_a_path_under_a_file, ("a_regular_file",)),
    Case("map run under a regular file", map_into_a_path_under_a_file, ("a_regular_file",)),
    Case("demo run under a regular file", demo_into_a_path_under_a_file, ("a_regular_file",)),
    Case("save_map under a regular file", save_map_under_a_file, ("a_regular_file",)),
    Case("bag from-replica --rate 0", convert_with_rate_zero, ("--rate",)),
    # policy and config values of the wrong type on the command line
    Case("bench policy value a word", bench_policy_value_a_word, ("--policies", "window", "whole number", "'abc'")),
    Case("bench policy seed a bool", bench_policy_flag_a_number, ("--policies", "seed", "whole number", "True")),
    Case("pool score option a word", pool_bench_score_option_a_word, ("--policies", "unseen_alpha", "a number")),
    Case("bench --pool-set a word", pool_bench_pool_set_a_word, ("--pool-set n_views", "'x'")),
    # the player's parameters
    Case("player topic not in the bag", player_for_a_topic_not_in_the_bag, ("/camera/imu", "not in the bag")),
    Case("player wait_for_subscribers -1", player_with_negative_subscriber_count, ("wait_for_subscribers",)),
    # camera messages -> keyframe_selector's camera input (counted; the next good frame is taken in)
    Case("depth encoding mono8", depth_mono8, counter="rejected:bad_encoding"),
    Case("colour encoding yuv422", colour_yuv, counter="rejected:bad_encoding"),
    Case("depth size vs camera info", depth_size_mismatch_with_camera_info, counter="rejected:size_mismatch"),
    Case("colour size vs camera info", colour_size_mismatch_with_camera_info, counter="rejected:size_mismatch"),
    Case("image data too short", image_data_too_short, counter="rejected:bad_image"),
    Case("camera info NaN focal", camera_info_nan_focal, counter="rejected:bad_camera_info"),
    Case("NaN pose message", nan_pose, counter="rejected:bad_pose"),
    Case("non-unit quaternion message", non_unit_quaternion, counter="rejected:bad_pose"),
    Case("stray stamp 0", stray_stamp_zero, counter="out_of_order"),
    Case("repeated stamp", repeated_stamp, counter="duplicate_stamp"),
    Case("backwards stamp", backwards_stamp, counter="out_of_order"),
    Case("frame missing its colour", frame_missing_its_colour, counter="pending"),
    # map folders -> mapper ~/load_map (the node keeps its map and still saves), or Mapper.load
    Case("keyframes.json a list", keyframes_json_is_a_list, ("keyframes.json", "JSON object")),
    Case("keyframes.json without fx", keyframes_json_without_fx, ("keyframes.json", "intrinsics.fx")),
    Case("keyframes.json width a string", keyframes_json_width_a_string, ("keyframes.json", "intrinsics.width")),
    Case("keyframes.json non-rigid pose", keyframes_json_non_rigid_pose, ("keyframes.json", "keyframe_poses[0]")),
    Case("keyframes.json NaN pose", keyframes_json_nan_pose, ("keyframes.json", "keyframe_poses[0]")),
    Case("keyframes.json ids vs poses", keyframes_json_ids_and_poses_disagree, ("keyframes.json", "keyframe_poses")),
    Case("keyframes.json truncated", keyframes_json_truncated, ("keyframes.json",)),
    Case("keyframes.json bad config value", keyframes_json_bad_config_value, ("keyframes.json", "near_m")),
    Case("map.ply truncated", map_ply_truncated, ("map.ply", "truncated")),
    Case("map folder missing", map_folder_missing, ("no_map_here",)),
    # requests -> nbv_planner ~/get_next_best_view (refused with a reason; the next good one answered)
    Case("10,000 candidates", too_many_candidates, ("candidates", "max_candidates")),
    Case("candidate NaN position", candidate_nan_position, ("candidates[1]",)),
    Case("candidate non-unit quaternion", candidate_non_unit_quaternion, ("candidates[0]",)),
    Case("candidates in another frame", candidates_in_another_frame, ("candidates.header.frame_id", "odom")),
    Case("unknown score mode", unknown_score_mode, ("mode", "best")),
    Case("empty candidate list", empty_candidate_list, ("candidates", "empty")),
    Case("stale request", stale_request, ("candidates.header.stamp", "stale")),
]


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input_is_refused_clearly_and_loses_nothing(case: Case, world: World, tmp_path: Path) -> None:
    outcome = case.run(world, tmp_path)
    if case.counter:  # (a) a message stream: the bad frame is counted, under its reason
        assert outcome.counted.get(case.counter, 0) >= 1, f"not counted as {case.counter}: {outcome}"
    else:  # (a) a clear error naming what is at fault
        missing = [n for n in case.names if n not in outcome.message]
        assert not missing, f"the error does not name {missing}: {outcome.message!r}"
        assert "Traceback" not in outcome.message and len(outcome.message.strip().splitlines()) <= 2, outcome.message
    assert not outcome.lost, outcome.lost  # (b) nothing lost
