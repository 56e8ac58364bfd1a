"""Real-robot bags: camera poses on TF (+ tf_static, through a chain), compressed images, RealSense topic names.

A bag with the poses on ``/tf`` and the images as ``sensor_msgs/CompressedImage`` (PNG colour, compressedDepth
depth) under RealSense names is derived from a raw bag written by ``write_bag`` (``roigsf bag to-robot``,
:func:`write_robot_bag`); it must read back as the same frames and map through ``roigsf map`` to the same
keyframes and poses.
"""

from __future__ import annotations

import json
import re
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rosbags.interfaces import QosDurability
from rosbags.typesys import Stores, get_typestore

from roigsf_ros.cli import main as cli_main
from roigsf_ros.core.errors import InputError
from roigsf_ros.data import bags
from roigsf_ros.data.replica import ReplicaSequence
from roigsf_ros.data.robot_bag import check_namespace, write_robot_bag
from roigsf_ros.data.sources import open_frames
from roigsf_ros.perf.io import make_synthetic_replica

W, H, N = 64, 48, 6
TS = get_typestore(Stores.ROS2_JAZZY)
T_ = TS.types
RS_COLOR, RS_DEPTH, RS_INFO = (
    "/camera/color/image_raw",
    "/camera/aligned_depth_to_color/image_raw",
    "/camera/color/camera_info",
)
OPTICAL = "camera_color_optical_frame"


def _compressed(header: Any, fmt: str, data: bytes) -> Any:
    return T_["sensor_msgs/msg/CompressedImage"](header=header, format=fmt, data=np.frombuffer(data, np.uint8))


def realsense_bag(
    raw_bag: Path,
    out: Path,
    color_format: str = "png",
    depth_transport: str = "compressedDepth",
    keep_tf: Callable[[int], bool] | None = None,
) -> None:
    """``raw_bag`` rewritten as a robot records it (:func:`write_robot_bag`: RealSense names, compressed images,
    the pose through a TF chain recorded 1 ms after the images)."""
    n = write_robot_bag(raw_bag, out, color_format=color_format, depth_transport=depth_transport, keep_tf=keep_tf)
    assert n == N


@pytest.fixture(scope="module")
def raw_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 64x48, 6-frame 10 Hz bag with 16UC1 depth (what compressedDepth carries, so the frames compare exactly)."""
    root = tmp_path_factory.mktemp("rs")
    make_synthetic_replica(root / "scene", W, H, N, seed=5)
    bags.write_bag(ReplicaSequence(root / "scene"), root / "raw", depth_encoding="16UC1", progress=False)
    return root / "raw"


@pytest.fixture(scope="module")
def rs_bag(raw_bag: Path) -> Path:
    """The raw bag through ``roigsf bag to-robot`` (its defaults: PNG colour, compressedDepth, /camera)."""
    out = raw_bag.parent / "realsense"
    assert cli_main(["bag", "to-robot", str(raw_bag), "--out", str(out), "--no-progress"]) == 0
    return out


def _assert_same_frames(got: list[bags.BagFrame], want: list[bags.BagFrame], rgb_atol: int = 0) -> None:
    assert [f.stamp_ns for f in got] == [f.stamp_ns for f in want]
    for g, w in zip(got, want, strict=True):
        if rgb_atol:
            assert np.abs(g.rgb.astype(int) - w.rgb.astype(int)).mean() < rgb_atol
        else:
            np.testing.assert_array_equal(g.rgb, w.rgb)
        np.testing.assert_array_equal(g.depth_m, w.depth_m)
        np.testing.assert_allclose(g.T_wc, w.T_wc, atol=1e-12)
        assert g.intrinsics == w.intrinsics


def test_tf_and_compressed_bag_reads_as_the_raw_bag(raw_bag: Path, rs_bag: Path) -> None:
    want, _ = bags.read_bag_frames(raw_bag)
    with bags.BagReader(rs_bag, bags.realsense_topics(color_transport="auto", depth_transport="auto")) as reader:
        got = list(reader.frames())
        assert reader.topics.color == f"{RS_COLOR}/compressed" and reader.topics.color_transport == "compressed"
        assert reader.topics.depth == f"{RS_DEPTH}/compressedDepth"
        assert reader.no_tf == 0 and reader.skipped_frames == 0
    assert len(got) == N
    _assert_same_frames(got, want)
    # the transports named instead of detected: the same frames
    topics = bags.realsense_topics(color_transport="compressed", depth_transport="compressedDepth")
    _assert_same_frames(bags.read_bag_frames(rs_bag, topics)[0], want)


def test_robot_bag_is_a_tf_chain_with_latched_statics_and_late_dynamic_transforms(rs_bag: Path) -> None:
    """The camera's pose is nowhere on TF as one transform: three static links (offered transient local, as tf2's
    static broadcaster does) and odom -> base_link on /tf, each recorded 1 ms after the images of its stamp."""
    with bags.open_any_reader(rs_bag) as reader:
        conns = {c.topic: c for c in reader.connections}
        assert conns["/tf_static"].ext.offered_qos_profiles[0].durability == QosDurability.TRANSIENT_LOCAL
        links, dynamic, image_records = set(), [], []
        for conn, record_ns, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == "/tf_static":
                links |= {(t.header.frame_id, t.child_frame_id) for t in msg.transforms}
            elif conn.topic == "/tf":
                (t,) = msg.transforms
                dynamic.append((t.header.frame_id, t.child_frame_id, record_ns - bags.stamp_to_ns(t.header.stamp)))
            elif conn.topic == f"{RS_COLOR}/compressed":
                image_records.append(record_ns)
    assert links == {("map", "odom"), ("base_link", "camera_link"), ("camera_link", OPTICAL)}
    assert dynamic == [("odom", "base_link", 1_000_000)] * N and len(image_records) == N


def test_robot_bag_refuses_bad_settings_and_leaves_nothing(raw_bag: Path, tmp_path: Path, capsys: Any) -> None:
    for kwargs, word in (({"color_format": "bmp"}, "color_format"), ({"depth_transport": "raw"}, "depth_transport"),
                         ({"tf_lag_s": -1.0}, "tf_lag_s")):  # fmt: skip
        with pytest.raises(InputError, match=word):
            write_robot_bag(raw_bag, tmp_path / "bad", **kwargs)
    with pytest.raises(InputError, match="bag not found"):
        write_robot_bag(tmp_path / "nosuch", tmp_path / "bad")
    assert not (tmp_path / "bad").exists() and not list(tmp_path.glob(".*"))
    assert cli_main(["bag", "to-robot", str(raw_bag), "--out", str(tmp_path / "b"), "--tf-lag-ms", "nan"]) == 2
    assert "--tf-lag-ms" in capsys.readouterr().err and not (tmp_path / "b").exists()
    before = sorted((p.name, p.stat().st_size) for p in raw_bag.iterdir())  # --overwrite replaced the source itself
    assert cli_main(["bag", "to-robot", str(raw_bag), "--out", str(raw_bag), "--overwrite"]) == 2
    assert "is the bag being rewritten" in capsys.readouterr().err
    assert sorted((p.name, p.stat().st_size) for p in raw_bag.iterdir()) == before
    with pytest.raises(InputError, match="is the bag being rewritten"):
        write_robot_bag(raw_bag, raw_bag, overwrite=True)
    # a namespace no ROS node can use was written ("/a b/color/image_raw/compressed") and read back without a word
    assert cli_main(["bag", "to-robot", str(raw_bag), "--out", str(tmp_path / "ns"), "--namespace", "/a b"]) == 2
    err = capsys.readouterr().err
    assert "--namespace: '/a b' is no ROS namespace: 'a b' is not letters, digits and '_'" in err, err
    assert not (tmp_path / "ns").exists()
    for bad in ("/1cam", "cam-era", "/cam/ok/x.y"):
        with pytest.raises(InputError, match="is no ROS namespace"):
            write_robot_bag(raw_bag, tmp_path / "ns", namespace=bad)
    scene = raw_bag.parent / "scene"  # a Replica folder said only "not a rosbag2 folder"
    assert cli_main(["bag", "to-robot", str(scene), "--out", str(tmp_path / "fromscene")]) == 2
    assert "is a Replica scene folder, not a bag: make a camera bag of it with `roigsf bag from-replica`" in (
        capsys.readouterr().err
    )
    assert [check_namespace(ns) for ns in ("/camera/camera", "camera/", "/", "")] == [
        "/camera/camera",
        "/camera",
        "/",
        "/",
    ]


def test_jpeg_colour_and_png_depth_transport(raw_bag: Path, tmp_path: Path) -> None:
    out = tmp_path / "jpeg"
    realsense_bag(raw_bag, out, color_format="jpeg", depth_transport="compressed")
    got, _ = bags.read_bag_frames(out, bags.realsense_topics(color_transport="auto", depth_transport="auto"))
    want, _ = bags.read_bag_frames(raw_bag)
    _assert_same_frames(got, want, rgb_atol=10)  # JPEG is lossy (here on noise: ~6 levels); depth PNG is not
    err = np.abs(got[0].rgb.astype(int) - want[0].rgb.astype(int)).mean()
    swapped = np.abs(got[0].rgb[..., ::-1].astype(int) - want[0].rgb.astype(int)).mean()
    assert swapped > 2 * err  # RGB, not OpenCV's BGR (the PNG test checks the order exactly)


def test_frames_without_tf_are_skipped_and_counted_with_the_reason(raw_bag: Path, tmp_path: Path) -> None:
    out = tmp_path / "tf_gap"
    realsense_bag(raw_bag, out, keep_tf=lambda k: k != N - 1)  # the last frame's pose never comes
    with bags.BagReader(out, bags.realsense_topics(color_transport="auto", depth_transport="auto")) as reader:
        got = list(reader.frames())
        assert reader.no_tf == 1 and "after the newest transform 'odom' -> 'base_link'" in reader.last_tf_error
    assert len(got) == N - 1
    # a wrong child frame: no frame at all, and the error names the frames
    with pytest.raises(InputError, match=r"no complete RGB-D frame \(no pose on TF: .*'camera_depth_optical_frame'"):
        open_frames(out, topics=bags.realsense_topics(tf_child_frame="camera_depth_optical_frame",
                                                     color_transport="auto", depth_transport="auto"))  # fmt: skip


def test_bag_info_counts_frames_of_a_tf_bag(rs_bag: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["bag", "info", str(rs_bag), "--realsense", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frame_count"] == N and info["incomplete_stamps"] == 0 and info["pose_source"] == "tf"
    assert (info["width"], info["height"]) == (W, H) and "compressedDepth" in info["depth_encoding"]


def test_map_with_realsense_options_gives_the_raw_bags_keyframes_and_poses(
    raw_bag: Path, rs_bag: Path, tmp_path: Path
) -> None:
    common = ["--policy", "gaus-slam", "--iters-per-keyframe", "2", "--no-progress", "--no-h-train"]
    assert cli_main(["map", str(raw_bag), "--out", str(tmp_path / "raw"), *common]) == 0
    rs_args = ["--depth-topic", RS_DEPTH, "--color-topic", RS_COLOR, "--camera-info-topic", RS_INFO]
    assert cli_main(["map", str(rs_bag), "--out", str(tmp_path / "rs"), *common, *rs_args, "--pose-source", "tf"]) == 0
    assert cli_main(["map", str(rs_bag), "--out", str(tmp_path / "preset"), *common, "--realsense"]) == 0
    raw = json.loads((tmp_path / "raw" / "keyframes.json").read_text())
    for run in ("rs", "preset"):
        got = json.loads((tmp_path / run / "keyframes.json").read_text())
        assert got["keyframe_ids"] == raw["keyframe_ids"] and len(raw["keyframe_ids"]) >= 2
        np.testing.assert_allclose(got["keyframe_poses"], raw["keyframe_poses"], atol=1e-9)
        assert json.loads((tmp_path / run / "metrics.json").read_text())["n_frames"] == N


def test_cli_camera_options_fail_naming_the_option_or_topic(rs_bag: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["bag", "info", str(rs_bag), "--realsense", "--tf-tolerance", "-1"]) == 2
    assert "--tf-tolerance" in capsys.readouterr().err
    out = rs_bag.parent / "never"
    assert cli_main(["map", str(rs_bag), "--out", str(out), "--no-progress"]) == 2  # default names: not in this bag
    err = capsys.readouterr().err
    assert "/camera/depth/image_raw" in err and "missing" in err and not out.exists()


# ------------------------------------------------------------------------------------------ converters


def test_compressed_converters_round_trip_and_reject_bad_data_naming_the_topic() -> None:
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, size=(12, 16, 3), dtype=np.uint8)
    depth_m = np.round(rng.uniform(0.3, 5.0, size=(12, 16)), 3).astype(np.float32)
    depth_m[0, :4] = 0.0
    hdr = T_["std_msgs/msg/Header"](stamp=T_["builtin_interfaces/msg/Time"](sec=1, nanosec=2), frame_id="cam")
    fmt, data = bags.encode_compressed_rgb(rgb, "png")
    assert fmt == "rgb8; png compressed bgr8"
    np.testing.assert_array_equal(bags.image_to_rgb(_compressed(hdr, fmt, data)), rgb)
    for transport in ("compressed", "compressedDepth"):
        fmt, data = bags.encode_compressed_depth(depth_m, transport)
        got = bags.image_to_depth_m(_compressed(hdr, fmt, data))
        np.testing.assert_allclose(got, depth_m, atol=1e-6)
        assert (got[0, :4] == 0).all()
    # compressedDepth of float depth: quantised inverse depth, decoded as image_transport does
    quant_a, quant_b = 100.0 * 101.0, 1.0 - 100.0 * 101.0 / 10.0
    inv = np.where(depth_m > 0, quant_a / np.where(depth_m > 0, depth_m, 1) + quant_b, 0).astype(np.uint16)
    png = cv2.imencode(".png", inv)[1].tobytes()
    got = bags.image_to_depth_m(
        _compressed(hdr, "32FC1; compressedDepth png", struct.pack("<iff", 0, quant_a, quant_b) + png)
    )
    assert (got[0, :4] == 0).all() and np.abs(got - depth_m)[depth_m > 0].max() < 0.01 * 5.0**2  # quantisation step
    # bad data: named by the topic
    fmt, data = bags.encode_compressed_rgb(rgb, "jpeg")
    for bad in (data[: len(data) // 2], data[:-2], b"not an image"):
        with pytest.raises(InputError, match=r"^/camera/color/image_raw/compressed: .*(truncated|cannot decode)"):
            bags.image_to_rgb(_compressed(hdr, fmt, bad), "/camera/color/image_raw/compressed")
    fmt, data = bags.encode_compressed_depth(depth_m, "compressedDepth")
    with pytest.raises(InputError, match=r"^/d: .*truncated"):
        bags.image_to_depth_m(_compressed(hdr, fmt, data[:-20]), "/d")
    with pytest.raises(InputError, match=r"^/d: compressedDepth data has 12 bytes"):
        bags.image_to_depth_m(_compressed(hdr, fmt, data[:12]), "/d")
    # a plain PNG sent as compressedDepth (no header): said as such, with the transport that reads it
    with pytest.raises(InputError, match=r"^/d: compressedDepth message .* starts with a PNG, not the 12-byte header"):
        bags.image_to_depth_m(_compressed(hdr, fmt, data[12:]), "/d")
    # ... and compressedDepth's header + PNG under a plain format: it was "truncated or not JPEG/PNG"
    with pytest.raises(InputError, match=r"^/d: format 'png' names a plain PNG, but the data holds a 12-byte header"):
        bags.image_to_depth_m(_compressed(hdr, "png", data), "/d")
    with pytest.raises(InputError, match=r"^/d: .*RVL.*not supported"):
        bags.image_to_depth_m(_compressed(hdr, "16UC1; compressedDepth rvl", data), "/d")
    with pytest.raises(InputError, match=r"^/d: .*expected a 16-bit PNG"):
        bags.image_to_depth_m(_compressed(hdr, "png", cv2.imencode(".png", rgb)[1].tobytes()), "/d")


# ------------------------------------------------------------------------------------------ frames without TF

AUTO_RS = {"color_transport": "auto", "depth_transport": "auto"}


@pytest.fixture(scope="module")
def tf_gap_bag(raw_bag: Path) -> Path:
    """The robot bag with frames 2 and 3 never posed on TF (their odom -> base_link lost)."""
    out = raw_bag.parent / "tf_gap_2_3"
    realsense_bag(raw_bag, out, keep_tf=lambda k: k not in (2, 3))
    return out


def test_bag_frame_ids_name_bag_frames_past_frames_skipped_for_tf(tf_gap_bag: Path) -> None:
    """A frame's index is its place among all the bag's frames, the skipped ones counted: stride and cap too."""
    src = open_frames(tf_gap_bag, topics=bags.realsense_topics(**AUTO_RS))
    assert len(src) == N and [f.index for f in src] == [0, 1, 4, 5]
    assert (src.skipped_no_tf, src.skipped_incomplete) == (2, 0) and "'odom' -> 'base_link'" in src.no_tf_reason
    strided = open_frames(tf_gap_bag, stride=2, topics=bags.realsense_topics(**AUTO_RS))
    assert len(strided) == 3 and [f.index for f in strided] == [0, 4] and strided.skipped_no_tf == 1
    capped = open_frames(tf_gap_bag, max_frames=3, topics=bags.realsense_topics(**AUTO_RS))
    assert len(capped) == 3 and [f.index for f in capped] == [0, 1] and capped.skipped_no_tf == 1


def test_map_reports_frames_skipped_without_tf_and_keeps_bag_frame_ids(
    raw_bag: Path, tf_gap_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`roigsf map` says how many frames TF never posed and why (summary and metrics.json), and its keyframe ids
    are bag frame numbers: keyframe 4 is the bag's frame 4, at its pose."""
    argv = ["map", str(tf_gap_bag), "--realsense", "--policy", "all", "--out", str(tmp_path / "run"), "--no-progress"]
    assert cli_main([*argv, "--iters-per-keyframe", "1", "--final-iters", "0", "--no-h-train"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"skipped: no TF pose\s+2 \(.*'odom' -> 'base_link'", out), out
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert (metrics["n_frames"], metrics["frames_skipped_no_tf"], metrics["frames_skipped_incomplete"]) == (4, 2, 0)
    assert "'odom' -> 'base_link'" in metrics["frames_skipped_no_tf_reason"]
    keyframes = json.loads((tmp_path / "run" / "keyframes.json").read_text())
    assert metrics["keyframe_ids"] == keyframes["keyframe_ids"] == [0, 1, 4, 5]
    want = {k: f.T_wc for k, f in enumerate(bags.read_bag_frames(raw_bag)[0])}
    np.testing.assert_allclose(keyframes["keyframe_poses"], [want[k] for k in (0, 1, 4, 5)], atol=1e-9)


def test_bag_info_counts_frames_tf_does_not_pose_with_the_reason(
    rs_bag: Path, tf_gap_bag: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli_main(["bag", "info", str(tf_gap_bag), "--realsense", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["frame_count"], info["frames_without_tf"], info["incomplete_stamps"]) == (N - 2, 2, 0)
    assert "'odom' -> 'base_link'" in info["no_tf_reason"] and info["missing_topics"] == []
    assert cli_main(["bag", "info", str(tf_gap_bag), "--realsense"]) == 0
    text = capsys.readouterr().out
    assert f"frames:       {N - 2} complete and posed by TF, 2 complete without a TF pose" in text
    assert "no TF pose:   tf 'map' -> 'camera_color_optical_frame'" in text
    assert cli_main(["bag", "info", str(rs_bag), "--realsense", "--tf-child-frame", "nope", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["frame_count"], info["frames_without_tf"]) == (0, N) and "'nope' is unknown" in info["no_tf_reason"]
    assert cli_main(["bag", "info", str(rs_bag), "--realsense", "--json"]) == 0  # every frame posed
    info = json.loads(capsys.readouterr().out)
    assert (info["frame_count"], info["frames_without_tf"], info["no_tf_reason"]) == (N, 0, None)


def test_bag_info_names_missing_topics_and_hints_realsense(
    raw_bag: Path, rs_bag: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Wrong topics: each missing one is named (exit 0: info inspects unknown bags), with `--realsense` to try."""
    assert cli_main(["bag", "info", str(rs_bag)]) == 0
    text = capsys.readouterr().out
    assert "missing:      depth topic /camera/depth/image_raw" in text
    assert "missing:      topic /camera/camera_info" in text and "missing:      topic /camera/pose" in text
    assert "hint:         the bag holds a RealSense camera under /camera: try --realsense\n" in text
    assert cli_main(["bag", "info", str(rs_bag), "--realsense", "--color-transport", "raw", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frame_count"] == 0 and info["missing_topics"] == [
        f"topic {RS_COLOR} (sensor_msgs/msg/Image) is missing (the bag has {RS_COLOR}/compressed)"
    ]
    assert info["hint"] == "the bag holds a RealSense camera under /camera: try --realsense without --color-transport"
    assert cli_main(["bag", "info", str(raw_bag), "--json"]) == 0  # nothing missing: no hint
    info = json.loads(capsys.readouterr().out)
    assert info["missing_topics"] == [] and "hint" not in info and info["realsense_namespace"] is None


def test_a_tf_frame_with_two_parents_is_said_by_bag_info_and_map(
    rs_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A robot whose robot_state_publisher gives ``base_footprint -> base_link`` on /tf_static while its driver gives
    ``odom -> base_link`` on /tf: the frame changes parent and every pose through it moves (a walk saw recall fall
    from 0.957 to 0.068 without a word; the buffer counted it where nothing read the count). ``bag info``, ``roigsf
    map``'s metrics.json and its table now say it, naming the frame, both parents and where each came from."""
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    from roigsf_ros.data.robot_bag import BASE_FRAME_ID, _tf_message, _transform

    out = tmp_path / "two_parents"
    with Reader(rs_bag) as reader, Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {
            c.topic: writer.add_connection(c.topic, c.msgtype, typestore=bags.TYPESTORE) for c in reader.connections
        }
        first = True
        for conn, t_ns, raw in reader.messages():
            if first:  # the second publisher's static transform, before the driver's first
                stray = _tf_message(_transform("base_footprint", BASE_FRAME_ID, np.eye(4), t_ns - 2))
                writer.write(
                    conns["/tf_static"], t_ns - 2, bags.TYPESTORE.serialize_cdr(stray, "tf2_msgs/msg/TFMessage")
                )
                first = False
            writer.write(conns[conn.topic], t_ns, raw)
    assert cli_main(["bag", "info", str(out), "--realsense", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    note = f"frame '{BASE_FRAME_ID}' changed parent: 'base_footprint' ({out}:/tf_static), then 'odom' ({out}:/tf)"
    assert info["tf_reparented"] == 1 and info["tf_reparent_note"].startswith(note), info
    assert cli_main(["bag", "info", str(rs_bag), "--realsense", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["tf_reparented"] == 0
    run = tmp_path / "run"
    args = ["map", str(out), "--out", str(run), "--realsense", "--policy", "every-n", "--no-progress", "--no-h-train"]
    assert cli_main([*args, "--iters-per-keyframe", "2"]) == 0
    printed = capsys.readouterr().out
    assert f"TF: {note}" in printed and "the poses, and every figure, may be wrong" in printed, printed
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["tf_reparented"] == 1 and metrics["tf_reparent_note"].startswith(note)


def test_an_unknown_tf_child_frame_is_said_with_the_images_own_frame(
    rs_bag: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A robot's images in ``camera_optical`` read with the RealSense default child frame: every frame failed on
    "frame 'camera_color_optical_frame' is unknown" with no word of the frame the images carry. The reason now names
    it and the option (the images' header, read from the raw CDR: :func:`bags.header_frame_id`)."""
    assert cli_main(["bag", "info", str(rs_bag), "--realsense", "--tf-child-frame", "camera_optical", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frame_count"] == 0 and info["frames_without_tf"] == N, info
    assert info["no_tf_reason"].endswith(
        f"; the images are in frame '{OPTICAL}': set tf_child_frame / --tf-child-frame to it"
    ), info["no_tf_reason"]
    assert bags.child_frame_hint(OPTICAL, f"/{OPTICAL}") == ""  # tf2 compares names without a leading "/"


def test_to_robot_of_a_robots_bag_says_to_map_it_as_it_is(
    rs_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``roigsf bag to-robot`` of a bag a robot (or this command) recorded failed on a missing depth topic with no
    word of what to do instead: it needs no rewriting, only ``--realsense`` to be read."""
    assert cli_main(["bag", "to-robot", str(rs_bag), "--out", str(tmp_path / "again"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "is missing" in err and "this one is already a robot's, to be read as it is" in err, err
    # to-robot has no --realsense: the hint names the command that has it (it said "try --realsense")
    assert (
        f"the bag has a RealSense camera's topics under /camera: map it with `roigsf map {rs_bag} --realsense`" in err
    )
    assert cli_main(["map", str(rs_bag), "--realsense", "/camera/camera", "--out", str(tmp_path / "m")]) == 2
    err = capsys.readouterr().err  # --realsense typed with another namespace: the one to give is written out
    assert err.rstrip().endswith("under /camera: try --realsense /camera"), err
    assert cli_main(["bag", "info", str(rs_bag), "--realsense", "/camera/camera", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["hint"].endswith("under /camera: try --realsense /camera")
    assert not (tmp_path / "again").exists()


def test_a_tf_child_frame_that_is_not_the_images_frame_is_said_by_bag_info_and_map(
    rs_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--tf-child-frame camera_link`` on a robot's bag whose images are in ``camera_color_optical_frame``: every image
    was placed at the link's pose (axes turned), F@5cm 0.000, and neither `bag info` ("150 complete and posed by TF")
    nor `roigsf map` said a word. Both now name the two frames and what to set; the right frame says nothing, and the
    run records how it read the bag (``camera_topics``)."""
    argv = ["bag", "info", str(rs_bag), "--realsense", "--json"]
    assert cli_main([*argv, "--tf-child-frame", "camera_link"]) == 0
    note = json.loads(capsys.readouterr().out)["tf_child_frame_note"]
    assert note is not None and note.startswith(
        f"the poses are TF frame 'camera_link', but the images are in '{OPTICAL}'"
    )
    assert note.endswith(f"--tf-child-frame to '{OPTICAL}')"), note
    assert cli_main(argv) == 0 and json.loads(capsys.readouterr().out)["tf_child_frame_note"] is None
    common = ["--policy", "every-n", "--every-n", "3", "--iters-per-keyframe", "1", "--final-iters", "0",
              "--no-progress", "--no-h-train", "--realsense"]  # fmt: skip
    assert (
        cli_main(["map", str(rs_bag), "--out", str(tmp_path / "wrong"), *common, "--tf-child-frame", "camera_link"])
        == 0
    )
    assert f"TF: {note}; every figure is wrong" in capsys.readouterr().out
    assert json.loads((tmp_path / "wrong" / "metrics.json").read_text())["tf_child_frame_note"] == note
    assert cli_main(["map", str(rs_bag), "--out", str(tmp_path / "right"), *common]) == 0
    assert "every figure is wrong" not in capsys.readouterr().out
    metrics = json.loads((tmp_path / "right" / "metrics.json").read_text())
    assert metrics["tf_child_frame_note"] is None
    assert metrics["camera_topics"]["pose_source"] == "tf" and metrics["camera_topics"]["tf_child_frame"] == OPTICAL
    assert "pose" not in metrics["camera_topics"] and metrics["intrinsics"]["width"] == W  # no unused /camera/pose


def test_bench_reads_a_robots_bag_with_the_camera_options_and_rescores_it(
    rs_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`roigsf bench` had none of `roigsf map`'s camera options: a robot's bag was refused ("topic
    /camera/color/image_raw is missing") with no way round it, so neither `--rescore-ause` nor `roigsf targets` could
    be tried on one. It takes them now, says "try --realsense" as map does, and a rescore reads the bag as the bench
    did (``camera_topics`` in results.json)."""
    out = tmp_path / "bench"
    argv = ["bench", "--scene", str(rs_bag), "--setting", "stream", "--policies", "every-n:every_n=3", "--out",
            str(out), "--set", "iters_per_keyframe=1", "--set", "final_iters=0", "--uncertainty-views", "2",
            "--uncertainty-maps", "1", "--no-progress"]  # fmt: skip
    assert cli_main(argv) == 2
    err = capsys.readouterr().err
    assert "is missing" in err and "try --realsense" in err and not out.exists(), err
    assert cli_main([*argv, "--realsense"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["n_frames"] == N and results["camera_topics"]["pose_source"] == "tf"
    assert results["cam"] is None and results["allow_partial"] is False  # what a rescore reads a folder with
    capsys.readouterr()
    assert cli_main(["bench", "--rescore-ause", "--out", str(out), "--realsense"]) == 2
    assert "not used with --rescore-ause" in capsys.readouterr().err
    assert cli_main(["bench", "--rescore-ause", "--out", str(out), "--no-progress"]) == 0
    assert json.loads((out / "results.json").read_text())["ause_rescore"]
    assert results["tf_child_frame_note"] is None and "every figure is wrong" not in (out / "results.md").read_text()
    wrong = tmp_path / "wrong"  # the child frame a link, not the images' frame: said on the report, not only logged
    argv[argv.index(str(out))] = str(wrong)
    capsys.readouterr()
    assert cli_main([*argv, "--realsense", "--tf-child-frame", "camera_link"]) == 0
    assert "**TF: the poses are TF frame 'camera_link'" in capsys.readouterr().out
    assert "every figure is wrong" in (wrong / "results.md").read_text()


def test_a_test_scene_is_read_with_the_sources_camera_options_and_its_error_says_so(
    raw_bag: Path, rs_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`roigsf map ROBOT_BAG --realsense --test-scene CAMERA_BAG` failed on "depth topic ... is missing" naming neither
    --test-scene nor why: the camera options apply to it too. The error says so, and the way round."""
    out = tmp_path / "run"
    argv = ["map", str(rs_bag), "--realsense", "--test-scene", str(raw_bag), "--out", str(out), "--no-progress"]
    assert cli_main(argv) == 2
    err = capsys.readouterr().err
    assert "is missing" in err and "(--test-scene is read with the source's camera options" in err, err
    assert "`roigsf bag to-robot`" in err and "leave out --realsense" not in err and not out.exists(), err
    assert cli_main(["map", str(raw_bag), "--realsense", "--out", str(out)]) == 2  # the source itself: leave it out
    err = capsys.readouterr().err
    assert err.rstrip().endswith("the bag has this package's camera topics (`roigsf bag from-replica`'s): leave out "
                                 "--realsense"), err  # fmt: skip


def test_perf_novelty_reads_a_robots_bag_with_the_camera_options(
    rs_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`roigsf perf novelty --bag` read only this package's layout: a robot's bag was refused ("is missing") with no
    option to read it. It takes `roigsf map`'s camera options (the perf layer gets the topics from the CLI), gives
    the --realsense hint, and the JSON says how the bag was read."""
    out = tmp_path / "novelty.json"
    argv = ["perf", "novelty", "--bag", str(rs_bag), "--window", "2", "--lookahead", "1", "--repeats", "1"]
    assert cli_main(argv) == 2
    err = capsys.readouterr().err
    assert "is missing" in err and "try --realsense" in err, err
    assert cli_main([*argv, "--realsense", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["camera_topics"]["pose_source"] == "tf" and data["summary"]["all_equal"], data
    assert [w["first_frame"] for w in data["windows"]] == [1, 3], data["windows"]  # 6 frames: two windows of 2
    assert cli_main(["perf", "novelty", "--realsense", "--window", "2", "--lookahead", "1", "--repeats", "1"]) == 2
    assert "leave out --realsense" in capsys.readouterr().err  # the shipped sample is in this package's layout
