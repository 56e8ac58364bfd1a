"""The ROS-free TF buffer: chains composed, static + dynamic, interpolation, bounds, clear errors naming frames."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from roigsf_ros.core.camera import matrix_to_quat_xyzw
from roigsf_ros.core.errors import InputError
from roigsf_ros.data.tf import TransformBuffer, TransformUnavailableError, slerp_xyzw

S = 1_000_000_000  # ns per second


def _pose(rotvec: tuple[float, float, float], t: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _set(buf: TransformBuffer, parent: str, child: str, T: np.ndarray, stamp_ns: int = 0, static: bool = False) -> None:
    buf.set_transform(parent, child, T[:3, 3], matrix_to_quat_xyzw(T[:3, :3]), stamp_ns, static)


def _tf_message(parent: str, child: str, T: np.ndarray, stamp_ns: int) -> SimpleNamespace:
    """A TFMessage-shaped object (the buffer reads fields only, like rosbags or rclpy messages)."""
    q = matrix_to_quat_xyzw(T[:3, :3])
    sec, nanosec = divmod(stamp_ns, S)
    ts = SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=nanosec), frame_id=parent),
        child_frame_id=child,
        transform=SimpleNamespace(
            translation=SimpleNamespace(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            rotation=SimpleNamespace(x=q[0], y=q[1], z=q[2], w=q[3]),
        ),
    )
    return SimpleNamespace(transforms=[ts])


def test_chain_of_static_and_dynamic_transforms_is_composed() -> None:
    buf = TransformBuffer()
    T_map_odom = _pose((0.0, 0.0, 0.3), (1.0, 2.0, 0.0))
    T_base_link = _pose((0.0, 0.1, 0.0), (0.2, 0.0, 0.5))
    T_link_optical = _pose((-np.pi / 2, 0.0, -np.pi / 2), (0.0, 0.0, 0.0))  # REP 103 -> optical axes
    _set(buf, "map", "odom", T_map_odom, static=True)
    _set(buf, "base_link", "camera_link", T_base_link, static=True)
    _set(buf, "camera_link", "camera_color_optical_frame", T_link_optical, static=True)
    T_odom_base = {k: _pose((0.0, 0.0, 0.1 * k), (0.5 * k, 0.0, 0.0)) for k in range(3)}
    for k, T in T_odom_base.items():
        buf.add_message(_tf_message("/odom", "base_link", T, 10 * S + k * S // 10))  # a leading "/" is ignored
    for k, T in T_odom_base.items():
        got = buf.lookup("map", "camera_color_optical_frame", 10 * S + k * S // 10)
        np.testing.assert_allclose(got, T_map_odom @ T @ T_base_link @ T_link_optical, atol=1e-12)
    # between two frames below the root: through their common ancestor, and the inverse the other way
    T_oc = buf.lookup("odom", "camera_link", 10 * S)
    np.testing.assert_allclose(T_oc, T_odom_base[0] @ T_base_link, atol=1e-12)
    np.testing.assert_allclose(buf.lookup("camera_link", "odom", 10 * S) @ T_oc, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(buf.lookup("map", "map", 0), np.eye(4))


def test_interpolation_is_slerp_and_linear_between_the_two_nearest() -> None:
    buf = TransformBuffer(tolerance_s=0.1)
    T0 = _pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    T1 = _pose((0.2, -0.4, 1.0), (1.0, -2.0, 3.0))
    _set(buf, "map", "cam", T0, 0)
    _set(buf, "map", "cam", T1, S // 10)
    got = buf.lookup("map", "cam", S // 40)  # a quarter of the way
    want_R = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([T0[:3, :3], T1[:3, :3]])))([0.25]).as_matrix()[0]
    np.testing.assert_allclose(got[:3, :3], want_R, atol=1e-12)
    np.testing.assert_allclose(got[:3, 3], [0.25, -0.5, 0.75], atol=1e-12)
    # the shortest arc, whatever the sign of the stored quaternions
    q = matrix_to_quat_xyzw(T1[:3, :3])
    np.testing.assert_allclose(slerp_xyzw(q, -q, 0.5), q, atol=1e-12)


def test_out_of_range_stamps_and_gaps_say_whether_to_wait() -> None:
    buf = TransformBuffer(tolerance_s=0.1)
    for k in (0, 1, 2, 10):  # 0.0, 0.1, 0.2 s, then nothing until 1.0 s
        _set(buf, "map", "cam", _pose((0.0, 0.0, 0.1 * k), (k, 0.0, 0.0)), 100 * S + k * S // 10)
    with pytest.raises(TransformUnavailableError, match="after the newest transform 'map' -> 'cam'") as future:
        buf.lookup("map", "cam", 101 * S + 1)
    assert future.value.retry  # a later message may still bring it
    with pytest.raises(TransformUnavailableError, match="before the oldest") as past:
        buf.lookup("map", "cam", 99 * S)
    assert not past.value.retry
    with pytest.raises(TransformUnavailableError, match=r"within 0\.1 s") as gap:
        buf.lookup("map", "cam", 100 * S + S // 2)  # 0.3 s after and 0.5 s before the samples around it
    assert not gap.value.retry and isinstance(gap.value, InputError)
    # tf2 would interpolate across the gap: the error says how often the edge comes and what widens the tolerance
    assert "the edge comes every 0.1 s here: a larger TF tolerance, tf_tolerance_s / --tf-tolerance" in str(gap.value)
    buf.lookup("map", "cam", 100 * S + S // 20)  # inside the regular part: fine


def test_unknown_or_unconnected_frames_are_named() -> None:
    buf = TransformBuffer()
    _set(buf, "map", "odom", np.eye(4), static=True)
    _set(buf, "base_link", "camera_color_optical_frame", np.eye(4), static=True)
    with pytest.raises(InputError, match="frame 'camera_optical' is unknown \\(frames known: base_link, "):
        buf.lookup("map", "camera_optical", 0)
    buf.child_hint = "; the images are in frame 'camera_color_optical_frame': set tf_child_frame"  # a reader's
    with pytest.raises(InputError, match=r"\); the images are in frame 'camera_color_optical_frame': set tf_child"):
        buf.lookup("map", "camera_optical", 0)
    with pytest.raises(InputError, match=r"frame 'world' is unknown .*; roots of the trees: base_link, map \(tf_paren"):
        buf.lookup("world", "camera_color_optical_frame", 0)  # a bag without map -> odom, or another world name
    with pytest.raises(TransformUnavailableError) as exc:
        buf.lookup("map", "camera_color_optical_frame", 0)  # odom -> base_link never came
    msg = str(exc.value)
    assert "'map' and 'camera_color_optical_frame' are not connected" in msg and "'base_link'" in msg
    assert "no transform with child 'base_link' has come yet" in msg  # a robot's odom -> base_link not in yet
    assert exc.value.retry and exc.value.where == "tf 'map' -> 'camera_color_optical_frame'"


def test_static_transforms_hold_at_every_stamp_and_replace_earlier_ones() -> None:
    buf = TransformBuffer()
    _set(buf, "map", "cam", _pose((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)), static=True)
    _set(buf, "map", "cam", _pose((0.0, 0.0, 0.0), (2.0, 0.0, 0.0)), static=True)
    for stamp in (0, 5 * S, 10**18):
        assert buf.lookup("map", "cam", stamp)[0, 3] == 2.0
    assert buf.history("cam") == 1


def test_history_is_bounded_by_time_and_count() -> None:
    buf = TransformBuffer(cache_s=1.0, max_history=50)
    for k in range(1000):  # 100 Hz for 10 s
        _set(buf, "map", "cam", _pose((0.0, 0.0, 0.0), (k, 0.0, 0.0)), k * S // 100)
    assert buf.history("cam") == 50 and buf.newest_stamp_ns("cam") == 999 * S // 100
    buf = TransformBuffer(cache_s=1.0, max_history=1000)
    for k in range(1000):
        _set(buf, "map", "cam", _pose((0.0, 0.0, 0.0), (k, 0.0, 0.0)), k * S // 100)
    assert buf.history("cam") == 101  # the newest second (both ends included)
    with pytest.raises(TransformUnavailableError, match="before the oldest"):
        buf.lookup("map", "cam", 0)
    buf = TransformBuffer(max_frames=3)
    for k in range(3):
        _set(buf, "map", f"f{k}", np.eye(4), static=True)
    with pytest.raises(InputError, match="more than 3 frames"):
        _set(buf, "map", "f3", np.eye(4), static=True)
    assert buf.frames_refused == 1 and len(buf.frames()) == 4


def test_out_of_order_messages_are_sorted_and_a_repeated_stamp_replaces() -> None:
    buf = TransformBuffer(tolerance_s=1.0)
    for k in (2, 0, 1):
        _set(buf, "map", "cam", _pose((0.0, 0.0, 0.0), (k, 0.0, 0.0)), k * S)
    _set(buf, "map", "cam", _pose((0.0, 0.0, 0.0), (7.0, 0.0, 0.0)), S)
    assert buf.lookup("map", "cam", S)[0, 3] == 7.0 and buf.history("cam") == 3
    assert buf.lookup("map", "cam", S // 2)[0, 3] == pytest.approx(3.5)


def test_bad_transforms_are_refused_naming_them_and_the_rest_kept() -> None:
    buf = TransformBuffer()
    good = _tf_message("map", "cam", np.eye(4), S).transforms[0]
    bad = _tf_message("map", "arm", np.eye(4), S).transforms[0]
    bad.transform.rotation.w = 2.0  # not a unit quaternion
    self_loop = _tf_message("cam", "cam", np.eye(4), S).transforms[0]
    errors = buf.add_message(SimpleNamespace(transforms=[bad, good, self_loop]), where="/tf")
    assert len(errors) == 2
    assert "/tf" in str(errors[0]) and "'map' -> 'arm'" in str(errors[0]) and "to itself" in str(errors[1])
    np.testing.assert_allclose(buf.lookup("map", "cam", S), np.eye(4))


def test_a_loop_of_transforms_is_an_error_not_a_hang() -> None:
    buf = TransformBuffer()
    _set(buf, "a", "b", np.eye(4), static=True)
    _set(buf, "b", "c", np.eye(4), static=True)
    _set(buf, "c", "a", np.eye(4), static=True)
    with pytest.raises(TransformUnavailableError, match="loop"):
        buf.lookup("x", "a", 0)


def test_vendored_tf2_msgs_has_the_jazzy_type_hash() -> None:
    """The TFMessage built here (tf2_msgs is not on PyPI) is the very type a full ROS 2 Jazzy install uses."""
    tf2_msgs = pytest.importorskip("tf2_msgs")
    from rosbags.typesys import Stores, get_typestore

    # <prefix>/lib/pythonX.Y/site-packages/tf2_msgs/__init__.py -> <prefix>/share/tf2_msgs/msg/TFMessage.json
    desc_path = Path(tf2_msgs.__file__).resolve().parents[4] / "share" / "tf2_msgs" / "msg" / "TFMessage.json"
    if not desc_path.is_file():
        pytest.skip(f"no type description at {desc_path}")
    desc = json.loads(desc_path.read_text())
    hashes = {h["type_name"]: h["hash_string"] for h in desc["type_hashes"]}
    want = get_typestore(Stores.ROS2_JAZZY).hash_rihs01("tf2_msgs/msg/TFMessage")
    assert (
        hashes["tf2_msgs/msg/TFMessage"]
        == want
        == ("RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087")
    )


def test_a_frame_that_changes_parent_is_counted_and_said_once_with_both_parents() -> None:
    """Two publishers of one frame (robot_state_publisher's static ``base_footprint -> base_link``, a driver's
    ``odom -> base_link``): the newest parent wins, as before, and the first change is said with both parents and
    where each came from, the later ones counted."""
    buf = TransformBuffer()
    T = _pose((0.0, 0.0, 0.2), (1.0, 0.0, 0.0))
    buf.set_transform("base_footprint", "base_link", T[:3, 3], matrix_to_quat_xyzw(T[:3, :3]), 0, True, "/tf_static")
    assert buf.reparented == 0 and buf.reparent_note == ""
    buf.add_message(_tf_message("odom", "base_link", np.eye(4), 5 * S), where="/tf")
    buf.add_message(_tf_message("odom", "base_link", np.eye(4), 6 * S), where="/tf")  # the same parent: no change
    assert buf.reparented == 1
    assert buf.reparent_note.startswith(
        "frame 'base_link' changed parent: 'base_footprint' (/tf_static), then 'odom' (/tf); a frame has one parent"
    )
    buf.set_transform("base_footprint", "base_link", T[:3, 3], matrix_to_quat_xyzw(T[:3, :3]), 0, True, "/tf_static")
    assert buf.reparented == 2 and "then 'odom' (/tf)" in buf.reparent_note  # the first change, said once
    np.testing.assert_allclose(buf.lookup("base_footprint", "base_link", 7 * S), T, atol=1e-12)  # the newest wins
