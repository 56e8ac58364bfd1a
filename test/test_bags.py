"""Replica folder -> rosbag2 MCAP bag -> frames: exact round trips, bag_info, the `roigsf bag` CLI, bad input."""

from __future__ import annotations

import json
import math
import re
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from roigsf_ros.cli import main as cli_main
from roigsf_ros.core import errors
from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.data import bags
from roigsf_ros.data.replica import ReplicaSequence
from roigsf_ros.perf.io import make_synthetic_replica

W, H, N = 64, 48, 5
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


@pytest.fixture(scope="module")
def replica(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A deterministic 64x48, 5-frame Replica folder (noise colour, smooth depth with an invalid corner)."""
    root = tmp_path_factory.mktemp("replica") / "scene"
    make_synthetic_replica(root, W, H, N, seed=3)
    return root


@pytest.fixture(scope="module")
def bag32(replica: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The replica fixture as a 32FC1 bag at 10 Hz."""
    out = tmp_path_factory.mktemp("bags") / "scene_bag"
    assert bags.write_bag(ReplicaSequence(replica), out, rate_hz=10.0, progress=False) == N
    return out


def _copy_replica(replica: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "scene"
    shutil.copytree(replica, dst)
    return dst


def _rewrite_bag(src: Path, dst: Path, edit: Callable[[str, int, Any], Any | None]) -> None:
    """Copy a bag message by message; ``edit(topic, index_on_topic, msg)`` returns the new message or None to drop."""
    with bags.open_any_reader(src) as any_reader:
        seen: dict[str, int] = {}
        with Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            conns: dict[str, Any] = {}
            for conn, stamp, raw in any_reader.messages():
                k = seen.get(conn.topic, 0)
                seen[conn.topic] = k + 1
                msg = edit(conn.topic, k, any_reader.deserialize(raw, conn.msgtype))
                if msg is None:
                    continue
                if conn.topic not in conns:
                    conns[conn.topic] = writer.add_connection(conn.topic, conn.msgtype, typestore=TYPESTORE)
                writer.write(conns[conn.topic], stamp, TYPESTORE.serialize_cdr(msg, conn.msgtype))


def _leftovers(parent: Path, name: str) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name == name or p.name.startswith(f".{name}."))


# ------------------------------------------------------------------------------------------ round trips


def test_roundtrip_32fc1_is_exact(replica: Path, bag32: Path) -> None:
    seq = ReplicaSequence(replica)
    with bags.BagReader(bag32) as reader:
        frames = list(reader.frames())
        assert reader.skipped_frames == 0
    assert len(frames) == N
    for k, fr in enumerate(frames):
        ref = seq.frame(k)
        assert fr.rgb.dtype == np.uint8 and fr.rgb.shape == (H, W, 3)
        assert np.array_equal(fr.rgb, ref.rgb)
        assert fr.depth_m.dtype == np.float32
        assert np.array_equal(fr.depth_m, ref.depth_m)  # exact float equality, zeros (invalid) included
        assert np.abs(fr.T_wc - ref.T_wc).max() < 1e-9
        intr = fr.intrinsics
        assert (intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy) == (
            W,
            H,
            seq.intrinsics.fx,
            seq.intrinsics.fy,
            seq.intrinsics.cx,
            seq.intrinsics.cy,
        )
        assert fr.stamp_ns == bags.DEFAULT_T0_NS + k * 100_000_000
    assert (frames[0].depth_m == 0).any(), "the synthetic depth has an invalid corner that must stay 0"
    # rosbag2 folder layout: metadata.yaml and the MCAP file named after the folder, no temp folders beside it.
    assert sorted(p.name for p in bag32.iterdir()) == sorted([f"{bag32.name}.mcap", "metadata.yaml"])
    assert _leftovers(bag32.parent, bag32.name) == [bag32.name]
    assert "storage_identifier: mcap" in (bag32 / "metadata.yaml").read_text()


def test_all_four_messages_share_the_stamp_and_frames(bag32: Path) -> None:
    with bags.open_any_reader(bag32) as any_reader:
        by_topic: dict[str, list[tuple[int, Any]]] = {}
        for conn, record_ns, raw in any_reader.messages():
            msg = any_reader.deserialize(raw, conn.msgtype)
            assert bags.stamp_to_ns(msg.header.stamp) == record_ns
            by_topic.setdefault(conn.topic, []).append((record_ns, msg))
    assert set(by_topic) == {bags.COLOR_TOPIC, bags.DEPTH_TOPIC, bags.CAMERA_INFO_TOPIC, bags.POSE_TOPIC}
    stamps = [[s for s, _ in v] for v in by_topic.values()]
    assert all(s == stamps[0] for s in stamps)
    assert np.all(np.diff(stamps[0]) == 100_000_000)
    assert {m.header.frame_id for _, m in by_topic[bags.POSE_TOPIC]} == {"map"}
    assert {m.header.frame_id for _, m in by_topic[bags.COLOR_TOPIC]} == {bags.CAMERA_FRAME_ID}
    info = by_topic[bags.CAMERA_INFO_TOPIC][0][1]
    assert info.distortion_model == "plumb_bob" and not np.any(info.d)
    assert np.array_equal(info.r, np.eye(3).ravel())
    assert np.array_equal(np.asarray(info.p).reshape(3, 4)[:, :3], np.asarray(info.k).reshape(3, 3))
    assert by_topic[bags.COLOR_TOPIC][0][1].encoding == "rgb8"
    assert by_topic[bags.DEPTH_TOPIC][0][1].encoding == "32FC1"


def test_roundtrip_16uc1_is_rounded_millimetres(replica: Path, tmp_path: Path) -> None:
    seq = ReplicaSequence(replica)
    out = tmp_path / "mm"
    assert bags.write_bag(seq, out, depth_encoding="16UC1", progress=False) == N
    frames, skipped = bags.read_bag_frames(out)
    assert skipped == 0 and len(frames) == N
    for k, fr in enumerate(frames):
        ref = seq.frame(k).depth_m
        mm = np.round(ref.astype(np.float64) * 1000.0).astype(np.uint16)
        assert np.array_equal(fr.depth_m, mm.astype(np.float32) / np.float32(1000.0))
        assert np.array_equal(fr.depth_m == 0, ref == 0)
        assert np.abs(fr.depth_m - ref).max() <= 0.0005 + 1e-6


def test_stride_max_frames_rate_and_bare_mcap(replica: Path, tmp_path: Path) -> None:
    seq = ReplicaSequence(replica)
    out = tmp_path / "strided"
    assert bags.write_bag(seq, out, rate_hz=20.0, stride=2, max_frames=2, progress=False) == 2
    frames, _ = bags.read_bag_frames(out / "strided.mcap")  # a bare .mcap reads too
    assert [f.stamp_ns - frames[0].stamp_ns for f in frames] == [0, 50_000_000]
    for fr, k in zip(frames, (0, 2), strict=True):
        assert np.abs(fr.T_wc - seq.frame(k).T_wc).max() < 1e-9
        assert np.array_equal(fr.rgb, seq.frame(k).rgb)


def test_incomplete_stamps_are_skipped_and_counted(bag32: Path, tmp_path: Path) -> None:
    out = tmp_path / "holey"
    _rewrite_bag(bag32, out, lambda topic, k, msg: None if (topic == bags.POSE_TOPIC and k == 2) else msg)
    frames, skipped = bags.read_bag_frames(out)
    assert skipped == 1
    assert [f.stamp_ns - bags.DEFAULT_T0_NS for f in frames] == [0, 100_000_000, 300_000_000, 400_000_000]
    info = bags.bag_info(out)
    assert info["frame_count"] == 4 and info["incomplete_stamps"] == 1
    assert info["topics"][bags.POSE_TOPIC]["count"] == 4


# ------------------------------------------------------------------------------------------ bag_info + CLI


def test_bag_info_numbers(bag32: Path) -> None:
    info = bags.bag_info(bag32)
    assert info["frame_count"] == N and info["incomplete_stamps"] == 0
    assert info["message_count"] == 4 * N
    assert math.isclose(info["duration_s"], (N - 1) / 10.0)
    assert (info["width"], info["height"]) == (W, H)
    assert (info["color_encoding"], info["depth_encoding"]) == ("rgb8", "32FC1")
    assert info["topics"] == {
        bags.COLOR_TOPIC: {"type": "sensor_msgs/msg/Image", "count": N},
        bags.DEPTH_TOPIC: {"type": "sensor_msgs/msg/Image", "count": N},
        bags.CAMERA_INFO_TOPIC: {"type": "sensor_msgs/msg/CameraInfo", "count": N},
        bags.POSE_TOPIC: {"type": "geometry_msgs/msg/PoseStamped", "count": N},
    }


def test_cli_info_text_and_json(bag32: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["bag", "info", str(bag32)]) == 0
    text = capsys.readouterr().out
    for needle in (bags.POSE_TOPIC, "geometry_msgs/msg/PoseStamped", f"{W}x{H}", "32FC1", "0.400 s", f"{N} complete"):
        assert needle in text
    assert cli_main(["bag", "info", str(bag32), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == json.loads(json.dumps(bags.bag_info(bag32)))


def test_bag_info_counts_the_frames_the_reader_refuses_with_the_reason(
    bag32: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A camera_info of another size (frame 1) and a depth image in an unknown encoding (frame 3): ``roigsf map``
    skips them as the nodes do, counted with the reason; ``bag info`` counts them as refused, not as complete.

    Before: ``bag info`` counted stamps only and said 5 complete frames; ``roigsf map`` then stopped on frame 1.
    """

    def edit(topic: str, k: int, msg: Any) -> Any:
        if topic == bags.CAMERA_INFO_TOPIC and k == 1:
            msg.width = W * 2
        if topic == bags.DEPTH_TOPIC and k == 3:
            msg.encoding = "mono8"
        return msg

    out = tmp_path / "bad_frames"
    _rewrite_bag(bag32, out, edit)
    with pytest.raises(InputError, match=re.escape(bags.CAMERA_INFO_TOPIC) + "|sizes disagree"):
        bags.read_bag_frames(out)
    with bags.BagReader(out, skip_refused=True) as reader:
        kept = [f.stamp_ns - bags.DEFAULT_T0_NS for f in reader.frames()]
        assert (reader.refused, reader.frames_read) == (2, N - 2) and "mono8" in reader.last_refusal
    assert kept == [k * 100_000_000 for k in range(N) if k not in (1, 3)]
    info = bags.bag_info(out)
    assert (info["frame_count"], info["frames_refused"], info["incomplete_stamps"]) == (N - 2, 2, 0)
    assert bags.DEPTH_TOPIC in info["refused_reason"] and "mono8" in info["refused_reason"]
    assert info["refused_reason"].count("1 x ") == 2 and "camera info 128x48" in info["refused_reason"]  # both said
    fast = bags.bag_info(out, decode=False)  # stamps only: the refused frames are counted, and it says so
    assert (fast["frame_count"], fast["frames_refused"], fast["refused_reason"]) == (N, None, None)
    assert cli_main(["bag", "info", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"frames:       {N - 2} complete, 2 refused, 0 incomplete stamps" in text, text
    both = r"^refused: +1 x \S+" + re.escape(bags.CAMERA_INFO_TOPIC) + r": sizes disagree.*; 1 x \S+"
    assert re.search(both + re.escape(bags.DEPTH_TOPIC) + ".*mono8", text, re.MULTILINE), text
    assert cli_main(["bag", "info", str(out), "--no-decode"]) == 0
    assert f"frames:       {N} complete (not decoded), 0 incomplete stamps" in capsys.readouterr().out
    # `roigsf map` skips them as the nodes do, counted with the reason, the others keeping their bag frame ids
    argv = ["map", str(out), "--policy", "all", "--out", str(tmp_path / "run"), "--no-progress", "--gt-mesh", ""]
    assert cli_main([*argv, "--iters-per-keyframe", "1", "--final-iters", "0", "--no-h-train"]) == 0
    text = capsys.readouterr().out
    assert re.search(r"skipped: refused\s+2 \(.*mono8", text), text
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert (metrics["n_frames"], metrics["frames_skipped_refused"], metrics["frames_skipped_incomplete"]) == (3, 2, 0)
    assert metrics["keyframe_ids"] == [0, 2, 4] and "mono8" in metrics["frames_skipped_refused_reason"]


def test_a_camera_that_changes_size_mid_bag_does_not_end_the_run(
    bag32: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Frames 3 and 4 at half the size (camera info, colour and depth alike, as after a driver restart with another
    profile): ``roigsf map`` maps frames 0-2, refuses and counts the others with the reason, as the nodes drop them;
    ``bag info`` counts them apart.

    Before (session 60's walk): the run stopped at frame 3 with an error, and nothing of frames 0-2 was written.
    """

    def edit(topic: str, k: int, msg: Any) -> Any:
        if k < 3:
            return msg
        if topic == bags.CAMERA_INFO_TOPIC:
            msg.width, msg.height = W // 2, H // 2
        elif topic in (bags.COLOR_TOPIC, bags.DEPTH_TOPIC):  # every other row and column, bytes per pixel kept
            px = np.frombuffer(bytes(msg.data), np.uint8).reshape(H, W, msg.step // W)[::2, ::2]
            msg.width, msg.height, msg.step = W // 2, H // 2, msg.step // 2
            msg.data = np.ascontiguousarray(px).reshape(-1)
        return msg

    out = tmp_path / "resized"
    _rewrite_bag(bag32, out, edit)
    info = bags.bag_info(out)
    assert (info["frame_count"], info["frames_other_size"]) == (3, 2)  # as roigsf map counts them
    stamp3 = f"{(bags.DEFAULT_T0_NS + 300_000_000) / 1e9:.3f} s"
    assert info["first_other_size"] == f"frame 3 (in the bag's order) at {stamp3}: {W // 2}x{H // 2}, not {W}x{H}"
    assert bags.bag_info(out, decode=False)["frames_other_size"] is None
    assert cli_main(["bag", "info", str(out)]) == 0
    out_text = capsys.readouterr().out
    assert "other size:   2 more frame(s) not at the first frame's image size (first: frame 3" in out_text
    argv = ["map", str(out), "--policy", "all", "--out", str(tmp_path / "run"), "--no-progress", "--gt-mesh", ""]
    assert cli_main([*argv, "--iters-per-keyframe", "1", "--final-iters", "0", "--no-h-train"]) == 0
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["keyframe_ids"] == [0, 1, 2] and metrics["frames_skipped_refused"] == 2
    assert (
        f"frame 3's image size {W // 2}x{H // 2} (at {stamp3}) differs from the first frame's {W}x{H}"
        in (metrics["frames_skipped_refused_reason"])
    )


def test_repeated_and_backward_stamps_are_counted_by_bag_info_and_map(
    bag32: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    """Frame 2 carries frame 1's stamp and frame 4 a stamp between frames 0 and 1 (every message of each): ``bag
    info`` and ``roigsf map`` agree on 4 frames, the repeat skipped and counted, the stamp gone back said.

    Before (session 60's walk): ``bag info`` said 5 complete frames, ``roigsf map`` mapped 4 without a word.
    """
    t0 = bags.DEFAULT_T0_NS

    def edit(topic: str, k: int, msg: Any) -> Any:
        stamp = {2: t0 + 100_000_000, 4: t0 + 50_000_000}.get(k)
        if stamp is not None:
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        return msg

    out = tmp_path / "stamps"
    _rewrite_bag(bag32, out, edit)
    with bags.BagReader(out) as reader:
        got = [f.stamp_ns - t0 for f in reader.frames()]
        assert reader.repeated_stamps == [t0 + 100_000_000] and reader.stamps_back == 1
        assert reader.first_back == (3, t0 + 50_000_000, t0 + 300_000_000)
    assert got == [0, 100_000_000, 300_000_000, 50_000_000]
    info = bags.bag_info(out)
    assert (info["frame_count"], info["frames_repeating_stamp"], info["frames_stamped_back"]) == (4, 1, 1)
    assert cli_main(["bag", "info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "repeated:     1 more frame(s) with an earlier frame's header stamp" in text, text
    assert "stamps back:  1 frame(s) stamped before the frame before them (first: frame 3" in text, text
    argv = ["map", str(out), "--policy", "all", "--out", str(tmp_path / "run"), "--no-progress", "--gt-mesh", ""]
    assert cli_main([*argv, "--iters-per-keyframe", "1", "--final-iters", "0", "--no-h-train"]) == 0
    text = capsys.readouterr().out
    assert re.search(r"skipped: repeated stamp\s+1$", text, re.MULTILINE), text
    assert re.search(r"stamps gone back\s+1$", text, re.MULTILINE), text
    # The warning names the frame as `bag info` does, by its stamp (its id is its place in stamp order, 1; bag info's
    # number its place in the bag, 3).
    back_s = f"{(t0 + 50_000_000) / 1e9:.3f} s"
    assert f"first: frame 1 (ids in stamp order) at {back_s}, after frame 3" in caplog.text, caplog.text
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert (metrics["n_frames"], metrics["frames_skipped_repeated_stamp"], metrics["frames_stamped_back"]) == (4, 1, 1)
    # frames mapped in the bag's order; ids are places in stamp order (0, 50, 100, 300 ms)
    assert metrics["keyframe_ids"] == [0, 2, 3, 1]


def test_cli_from_replica_resize_scales_intrinsics(replica: Path, tmp_path: Path) -> None:
    out = tmp_path / "small"
    argv = ["bag", "from-replica", str(replica), "--out", str(out), "--width", "32", "--height", "24"]
    assert cli_main([*argv, "--depth-encoding", "16UC1", "--rate", "5", "--no-progress"]) == 0
    seq = ReplicaSequence(replica, size=(32, 24))
    expected = ReplicaSequence(replica).intrinsics.resized(32, 24)
    frames, _ = bags.read_bag_frames(out)
    assert len(frames) == N
    for k, fr in enumerate(frames):
        got = fr.intrinsics
        assert (got.width, got.height) == (32, 24)
        assert np.allclose([got.fx, got.fy, got.cx, got.cy], [expected.fx, expected.fy, expected.cx, expected.cy])
        assert np.array_equal(fr.rgb, seq.frame(k).rgb)
        assert fr.stamp_ns - frames[0].stamp_ns == k * 200_000_000
    assert bags.bag_info(out)["depth_encoding"] == "16UC1"


def test_cli_overwrite(replica: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "again"
    argv = ["bag", "from-replica", str(replica), "--out", str(out), "--no-progress"]
    assert cli_main([*argv, "--max-frames", "2"]) == 0
    assert cli_main([*argv, "--max-frames", "2"]) == 2
    assert "already exists" in capsys.readouterr().err
    assert cli_main([*argv, "--max-frames", "3", "--overwrite"]) == 0
    assert bags.bag_info(out)["frame_count"] == 3
    assert _leftovers(tmp_path, "again") == ["again"]


def test_cli_from_replica_carries_the_scene_mesh_into_the_bag(
    replica: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A bag made from a scene folder kept nothing of its ground truth, so ``roigsf map BAG`` had no mesh metrics:
    the scene's mesh (``mesh.ply`` in it, or ``NAME_mesh.ply`` beside it as NICE-SLAM's Replica has it) now goes into
    the bag folder as ``mesh.ply``, which the bag's readers ignore and ``roigsf map``/``bench``/``demo`` find, and on
    into a ``bag to-robot`` of it; ``--no-mesh`` leaves it out, and a broken mesh is refused naming it.
    """
    import open3d as o3d

    from roigsf_ros.data.replica import scene_gt_mesh
    from roigsf_ros.data.sources import open_frames

    box, sphere = o3d.geometry.TriangleMesh.create_box(), o3d.geometry.TriangleMesh.create_sphere()
    scene = _copy_replica(replica, tmp_path)
    assert scene_gt_mesh(scene) is None
    assert o3d.io.write_triangle_mesh(str(tmp_path / "scene_mesh.ply"), box)  # NICE-SLAM: Replica/office0_mesh.ply
    assert scene_gt_mesh(scene) == tmp_path / "scene_mesh.ply"
    assert o3d.io.write_triangle_mesh(str(scene / "mesh.ply"), sphere)  # roigsf scene folders: their own, which wins
    assert scene_gt_mesh(scene) == scene / "mesh.ply" and open_frames(scene).gt_mesh_path == scene / "mesh.ply"
    out = tmp_path / "bag"
    argv = ["bag", "from-replica", str(scene), "--out", str(out), "--no-progress", "--max-frames", "2"]
    assert cli_main(argv) == 0
    assert f"with the ground-truth mesh {scene / 'mesh.ply'} as {out / 'mesh.ply'}" in capsys.readouterr().out
    assert (out / "mesh.ply").read_bytes() == (scene / "mesh.ply").read_bytes()
    assert bags.bag_info(out)["frame_count"] == 2 and len(bags.read_bag_frames(out)[0]) == 2  # read as before
    assert open_frames(out).gt_mesh_path == out / "mesh.ply"
    assert open_frames(out / "bag.mcap").gt_mesh_path == out / "mesh.ply"  # a .mcap stands for its folder
    assert cli_main(["bag", "info", str(out), "--no-decode"]) == 0
    assert f"ground truth: {out / 'mesh.ply'}\n" in capsys.readouterr().out  # bag info says what map will score against
    # bag to-robot keeps it (the poses stay in the source's world frame), unless --no-mesh
    assert cli_main(["bag", "to-robot", str(out), "--out", str(tmp_path / "robot"), "--no-progress"]) == 0
    assert (tmp_path / "robot" / "mesh.ply").read_bytes() == (scene / "mesh.ply").read_bytes()
    assert cli_main(["bag", "to-robot", str(out), "--out", str(tmp_path / "robot2"), "--no-progress", "--no-mesh"]) == 0
    assert not (tmp_path / "robot2" / "mesh.ply").exists()
    said = capsys.readouterr().out  # it said "none in BAG nor ... beside it, or --no-mesh": read as not found
    assert "  no ground-truth mesh: --no-mesh\n" in said and "none in" not in said, said
    assert cli_main([*argv[:4], str(tmp_path / "bare"), *argv[5:], "--no-mesh"]) == 0
    assert sorted(p.name for p in (tmp_path / "bare").iterdir()) == ["bare.mcap", "metadata.yaml"]
    assert open_frames(tmp_path / "bare").gt_mesh_path is None
    capsys.readouterr()
    assert cli_main(["bag", "info", str(tmp_path / "bare"), "--json", "--no-decode"]) == 0
    assert json.loads(capsys.readouterr().out)["gt_mesh"] is None
    # a broken mesh: refused before anything is written, naming the file it is, not the copy it would become
    data = (scene / "mesh.ply").read_bytes()
    (scene / "mesh.ply").write_bytes(data[: len(data) // 2])
    assert cli_main([*argv[:4], str(tmp_path / "broken"), *argv[5:]]) == 2
    err = capsys.readouterr().err
    assert f"{scene / 'mesh.ply'}: " in err and "--no-mesh: without it" in err, err
    assert not (tmp_path / "broken").exists()


# ------------------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    "option", [["--rate", "0"], ["--rate", "-5"], ["--rate", "nan"], ["--stride", "0"], ["--max-frames", "0"]]
)
def test_cli_bad_numbers_name_the_option_typed(
    option: list[str], replica: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["bag", "from-replica", str(replica), "--out", str(tmp_path / "b"), "--no-progress", *option]
    assert cli_main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"error: {option[0]}: " in err[0], err  # not write_bag's rate_hz / max_frames
    assert not (tmp_path / "b").exists()


def test_cli_traj_mismatch_exit_2_leaves_nothing(
    replica: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    scene = _copy_replica(replica, tmp_path)
    traj = scene / "traj.txt"
    traj.write_text(traj.read_text() + traj.read_text().splitlines()[0] + "\n")
    out = tmp_path / "out" / "bag"
    assert cli_main(["bag", "from-replica", str(scene), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "traj.txt" in err and "6 poses" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
    assert not out.parent.exists() or _leftovers(out.parent, "bag") == []
    # A partial download is accepted when asked for.
    assert cli_main(["bag", "from-replica", str(scene), "--out", str(out), "--allow-partial", "--no-progress"]) == 0
    assert bags.bag_info(out)["frame_count"] == N


def test_cli_missing_depth_names_the_file(replica: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scene = _copy_replica(replica, tmp_path)
    (scene / "results" / "depth000002.png").unlink()
    out = tmp_path / "bag"
    assert cli_main(["bag", "from-replica", str(scene), "--out", str(out), "--no-progress"]) == 2
    assert "depth000002.png" in capsys.readouterr().err
    assert _leftovers(tmp_path, "bag") == []


def test_failure_mid_write_leaves_no_partial_bag(
    replica: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    scene = _copy_replica(replica, tmp_path)
    (scene / "results" / "frame000003.jpg").write_bytes(b"not a jpeg")
    out = tmp_path / "bag"
    assert cli_main(["bag", "from-replica", str(scene), "--out", str(out), "--no-progress"]) == 2
    assert "frame000003.jpg" in capsys.readouterr().err
    assert _leftovers(tmp_path, "bag") == []


def test_bag_missing_a_topic_names_it(bag32: Path, tmp_path: Path) -> None:
    out = tmp_path / "no_pose"
    _rewrite_bag(bag32, out, lambda topic, k, msg: None if topic == bags.POSE_TOPIC else msg)
    with pytest.raises(InputError, match="/camera/pose") as exc:
        bags.read_bag_frames(out)
    assert str(out) in str(exc.value)


def test_missing_bag_path_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(InputError, match="bag not found"):
        bags.BagReader(tmp_path / "nope")
    assert cli_main(["bag", "info", str(tmp_path / "nope")]) == 2
    assert "nope" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("topic", "encoding"),
    [(bags.DEPTH_TOPIC, "8UC1"), (bags.DEPTH_TOPIC, "bgr8"), (bags.COLOR_TOPIC, "mono8")],
)
def test_unsupported_encoding_names_topic_and_encoding(bag32: Path, tmp_path: Path, topic: str, encoding: str) -> None:
    def edit(t: str, k: int, msg: Any) -> Any:
        if t == topic:
            msg.encoding = encoding
        return msg

    out = tmp_path / "bad_encoding"
    _rewrite_bag(bag32, out, edit)
    with pytest.raises(InputError) as exc:
        bags.read_bag_frames(out)
    assert topic in str(exc.value) and f"'{encoding}'" in str(exc.value)


def test_nan_pose_is_rejected(bag32: Path, tmp_path: Path) -> None:
    def edit(t: str, k: int, msg: Any) -> Any:
        if t == bags.POSE_TOPIC and k == 1:
            msg.pose.position.y = float("nan")
        return msg

    out = tmp_path / "nan_pose"
    _rewrite_bag(bag32, out, edit)
    with pytest.raises(InputError, match=r"/camera/pose.*not 3 finite numbers"):
        bags.read_bag_frames(out)


def test_non_unit_quaternion_is_rejected(bag32: Path, tmp_path: Path) -> None:
    def edit(t: str, k: int, msg: Any) -> Any:
        if t == bags.POSE_TOPIC:
            msg.pose.orientation.w *= 3.0
        return msg

    out = tmp_path / "bad_quat"
    _rewrite_bag(bag32, out, edit)
    with pytest.raises(InputError, match="not a finite unit quaternion"):
        bags.read_bag_frames(out)


# ------------------------------------------------------------------------------------------ converters


def _image(encoding: str, pixels: np.ndarray, pad: int = 0, big_endian: bool = False) -> Any:
    h, w = pixels.shape[:2]
    raw = pixels.astype(pixels.dtype.newbyteorder(">" if big_endian else "<")).reshape(h, -1).view(np.uint8)
    rows = np.concatenate([raw, np.zeros((h, pad), np.uint8)], axis=1) if pad else raw
    return TYPESTORE.types["sensor_msgs/msg/Image"](
        header=TYPESTORE.types["std_msgs/msg/Header"](
            stamp=TYPESTORE.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="cam"
        ),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=int(big_endian),
        step=rows.shape[1],
        data=np.ascontiguousarray(rows).reshape(-1),
    )


def test_converters_handle_bgr_padding_and_endianness() -> None:
    rng = np.random.default_rng(7)
    rgb = rng.integers(0, 256, size=(5, 7, 3), dtype=np.uint8)
    assert np.array_equal(bags.image_to_rgb(_image("bgr8", rgb[..., ::-1].copy(), pad=3)), rgb)
    rgba = np.concatenate([rgb, np.full((5, 7, 1), 9, np.uint8)], axis=2)
    assert np.array_equal(bags.image_to_rgb(_image("rgba8", rgba)), rgb)
    depth = rng.uniform(0.5, 4.0, size=(5, 7)).astype(np.float32)
    depth[0, 0] = np.nan
    got = bags.image_to_depth_m(_image("32FC1", depth, pad=4, big_endian=True))
    assert got[0, 0] == 0.0 and np.array_equal(got[1:], depth[1:])
    mm = rng.integers(0, 5000, size=(5, 7)).astype(np.uint16)
    assert np.array_equal(bags.image_to_depth_m(_image("16UC1", mm)), mm.astype(np.float32) / np.float32(1000))


def test_converters_reject_bad_sizes() -> None:
    msg = _image("rgb8", np.zeros((4, 6, 3), np.uint8))
    msg.data = msg.data[:-1]
    with pytest.raises(InputError, match=r"/camera/color/image_raw: data has 71 bytes"):
        bags.image_to_rgb(msg)
    msg = _image("32FC1", np.zeros((4, 6), np.float32))
    msg.step = 10
    with pytest.raises(InputError, match=r"/camera/depth/image_raw: step 10 is less than"):
        bags.image_to_depth_m(msg)


def test_converters_accept_rclpy_messages() -> None:
    """The converters read rclpy messages too (same field names), so nodes can reuse them."""
    sensor_msgs = pytest.importorskip("sensor_msgs.msg")
    geometry_msgs = pytest.importorskip("geometry_msgs.msg")
    rgb = np.arange(4 * 3 * 3, dtype=np.uint8).reshape(4, 3, 3)
    img = sensor_msgs.Image(height=4, width=3, encoding="rgb8", step=9, data=rgb.tobytes())
    assert np.array_equal(bags.image_to_rgb(img), rgb)
    depth = np.linspace(0.5, 2.0, 12, dtype=np.float32).reshape(4, 3)
    dimg = sensor_msgs.Image(height=4, width=3, encoding="32FC1", step=12, data=depth.tobytes())
    assert np.array_equal(bags.image_to_depth_m(dimg), depth)
    info = sensor_msgs.CameraInfo(width=3, height=4, k=[2.0, 0.0, 1.0, 0.0, 3.0, 1.5, 0.0, 0.0, 1.0])
    intr = bags.camera_info_to_intrinsics(info)
    assert (intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy) == (3, 4, 2.0, 3.0, 1.0, 1.5)
    pose = geometry_msgs.PoseStamped()
    pose.pose.position.x, pose.pose.orientation.z, pose.pose.orientation.w = 1.5, math.sqrt(0.5), math.sqrt(0.5)
    T = bags.pose_to_matrix(pose)
    assert np.allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]]) and T[0, 3] == 1.5


def test_a_pose_outside_the_map_frame_and_distortion_are_said_once_per_topic(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A pose stamped in ``odom`` and a camera_info with distortion coefficients were used without a word (the pose as
    if in ``map``, the images as if rectified): each is now said once per topic, and the frame still converts.
    """
    monkeypatch.setattr(errors, "_warned", set())
    pose = bags.TYPESTORE.types[bags.POSE_TYPE](
        header=bags.header_msg(1, "odom"),
        pose=bags.TYPESTORE.types["geometry_msgs/msg/Pose"](
            position=bags.TYPESTORE.types["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=3.0),
            orientation=bags.TYPESTORE.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        ),
    )
    intr_in = Intrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5)
    info = bags.camera_info_msg(1, intr_in)
    info.distortion_model, info.d = "plumb_bob", np.array([-0.3, 0.1, 0.001, 0.001, 0.0])
    with caplog.at_level("WARNING"):
        for _ in range(3):
            T = bags.pose_to_matrix(pose, "/camera/pose @ 1 ns")
            intr = bags.camera_info_to_intrinsics(info, "/camera/camera_info @ 1 ns")
    assert np.allclose(T[:3, 3], [1.0, 2.0, 3.0]) and intr == intr_in  # still converted
    notes = [r.getMessage() for r in caplog.records]
    assert len(notes) == 2, notes  # once each, not once a message
    assert notes[0].startswith("/camera/pose: poses in frame 'odom', not 'map', are taken as") and "TF" in notes[0]
    assert notes[1].startswith("/camera/camera_info: distortion coefficients (plumb_bob, D=[-0.3, 0.1, 0.001")
    caplog.clear()
    pose.header.frame_id = "map"
    info.d = np.zeros(5)
    with caplog.at_level("WARNING"):
        bags.pose_to_matrix(pose, "/other/pose @ 2 ns")
        bags.camera_info_to_intrinsics(info, "/other/camera_info @ 2 ns")
    assert not caplog.records  # in map, no distortion: nothing to say


def test_a_size_mismatch_blames_the_odd_one_out() -> None:
    """Images of 160x120 with a camera_info of 640x480 were blamed on the depth topic: the camera info is named when
    the two images agree (with what to do), the depth topic when the images disagree."""
    from roigsf_ros.core.camera import Intrinsics

    stamp = bags.DEFAULT_T0_NS
    rgb8 = bags._image_msg(stamp, np.zeros((12, 16, 3), np.uint8), "rgb8")
    depth = bags._image_msg(stamp, np.ones((12, 16), np.float32), "32FC1")
    wide = bags.camera_info_msg(stamp, Intrinsics(fx=20.0, fy=20.0, cx=32.0, cy=24.0, width=64, height=48))
    with pytest.raises(InputError, match=r"camera_info: sizes disagree: colour 16x12, depth 16x12, camera info 64x48; "
                       "the camera info is another stream's"):  # fmt: skip
        bags.assemble_images(rgb8, depth, wide)
    small = bags._image_msg(stamp, np.ones((6, 8), np.float32), "32FC1")
    with pytest.raises(InputError, match=r"image_raw: sizes disagree: colour 16x12, depth 8x6, .*aligned to the col"):
        bags.assemble_images(rgb8, small, wide)


def test_refusal_summary_counts_each_reason_most_frequent_first() -> None:
    """Five kinds of bad depth image in one bag were said as the last one only."""
    from collections import Counter

    reasons = Counter({"d: png": 3, "d: rvl": 5, "d: jpeg": 1})
    assert bags.refusal_summary(reasons) == "5 x d: rvl; 3 x d: png; 1 x d: jpeg"
    assert bags.refusal_summary(reasons, most=1) == "5 x d: rvl; and 2 other reason(s) for 4 frame(s)"
    assert bags.refusal_summary(Counter()) == ""
