"""Surfel map <-> PointCloud2 and pose <-> message conversions: exact round trips, bad clouds named."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("rclpy")

from sensor_msgs.msg import PointField

from roigsf_ros.core.errors import InputError
from roigsf_ros.data.scene import synth_trajectory
from roigsf_ros.nodes.map_msgs import (
    BASE_FIELDS,
    RGB_FIELD,
    array_to_poses,
    cloud_h_train,
    cloud_to_surfel_map,
    fisher_field_names,
    mesh_marker,
    mesh_marker_cdr,
    pose_stamped,
    poses_to_array,
    surfel_map_to_cloud,
)
from roigsf_ros.render.surfels import SurfelMap


def _random_map(n: int, sh_degree: int, seed: int = 0) -> SurfelMap:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    return SurfelMap(r(n, 3), r(n, 4), r(n, 2) - 3, r(n), r(n, 3), r(n, 3, 3) if sh_degree else None)


@pytest.mark.parametrize("sh_degree", [0, 1])
def test_cloud_round_trip_is_exact(sh_degree: int) -> None:
    m = _random_map(257, sh_degree)
    msg = surfel_map_to_cloud(m, stamp_ns=1_700_000_000_123_456_789, frame_id="map")
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert msg.width == 257 and msg.height == 1 and msg.is_dense and not msg.is_bigendian
    names = [f.name for f in msg.fields]
    assert names[: len(BASE_FIELDS)] == list(BASE_FIELDS) and names[-1] == RGB_FIELD
    assert len(names) == len(BASE_FIELDS) + (9 if sh_degree else 0) + 1
    back = cloud_to_surfel_map(msg)
    for name, t in m.named_parameters().items():
        assert torch.equal(getattr(back, name), t), name
    assert (back.sh_rest is None) == (sh_degree == 0)
    # The display colour is the activated surfel colour, packed 0x00RRGGBB.
    rgb = np.frombuffer(bytes(msg.data), "<f4").reshape(257, -1)[:, -1].view(np.uint32)
    want = (np.clip(m.colors().numpy(), 0, 1) * 255 + 0.5).astype(np.uint32)
    np.testing.assert_array_equal(rgb, (want[:, 0] << 16) | (want[:, 1] << 8) | want[:, 2])


def test_empty_map_round_trips() -> None:
    back = cloud_to_surfel_map(surfel_map_to_cloud(SurfelMap.empty()))
    assert len(back) == 0 and back.means.shape == (0, 3)


def test_fields_are_found_by_name_not_position() -> None:
    m = _random_map(5, 0, seed=1)
    msg = surfel_map_to_cloud(m)
    msg.fields = list(reversed(msg.fields))  # same offsets, listed in another order
    assert torch.equal(cloud_to_surfel_map(msg).means, m.means)


def test_bad_clouds_name_the_problem() -> None:
    good = surfel_map_to_cloud(_random_map(4, 0, seed=2))

    def variant(**changes: object) -> object:
        msg = surfel_map_to_cloud(_random_map(4, 0, seed=2))
        for k, v in changes.items():
            setattr(msg, k, v)
        return msg

    with pytest.raises(InputError, match=r"missing field.*opacity_logit"):
        cloud_to_surfel_map(variant(fields=[f for f in good.fields if f.name != "opacity_logit"]))
    bad_type = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=1) for f in good.fields]
    bad_type[0].datatype = PointField.FLOAT64
    with pytest.raises(InputError, match=r"field x.*FLOAT32"):
        cloud_to_surfel_map(variant(fields=bad_type))
    with pytest.raises(InputError, match=r"data has .* bytes"):
        cloud_to_surfel_map(variant(data=bytes(good.data)[:-4], row_step=good.row_step))
    with pytest.raises(InputError, match="row_step"):
        cloud_to_surfel_map(variant(row_step=good.row_step + 4))
    data = np.frombuffer(bytes(good.data), "<f4").copy().reshape(4, -1)
    data[2, BASE_FIELDS.index("log_scale_v")] = np.nan
    with pytest.raises(InputError, match=r"field log_scales.*1 surfel"):
        cloud_to_surfel_map(variant(data=data.tobytes()))
    data = np.frombuffer(bytes(good.data), "<f4").copy().reshape(4, -1)
    data[1, 3:7] = 0.0
    with pytest.raises(InputError, match="zero-length rotation"):
        cloud_to_surfel_map(variant(data=data.tobytes()))
    with pytest.raises(InputError, match="big-endian"):
        cloud_to_surfel_map(variant(is_bigendian=True))


def test_poses_round_trip_and_bad_quaternion() -> None:
    poses = synth_trajectory(seed=4, n_frames=6)
    msg = poses_to_array(poses, 5, "map")
    np.testing.assert_allclose(array_to_poses(msg), poses, atol=1e-12)
    one = pose_stamped(poses[2], 7)
    assert one.header.frame_id == "map" and one.header.stamp.nanosec == 7
    msg.poses[3].orientation.w += 0.5  # no longer a unit quaternion
    with pytest.raises(InputError, match=r"poses\[3\].*unit quaternion"):
        array_to_poses(msg, "poses")
    msg.poses[3].orientation.w = float("nan")
    with pytest.raises(InputError, match=r"poses\[3\]"):
        array_to_poses(msg, "poses")
    assert array_to_poses(poses_to_array(np.zeros((0, 4, 4)), 0)).shape == (0, 4, 4)


def test_mesh_marker_lists_triangle_corners() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    m = mesh_marker(v, tri, np.full((4, 3), 0.5), 3)
    assert m.type == m.TRIANGLE_LIST and len(m.points) == 6 and len(m.colors) == 6
    assert [(p.x, p.y, p.z) for p in m.points[3:]] == [(0, 0, 0), (0, 1, 0), (0, 0, 1)]


@pytest.mark.parametrize("frame_id", ["m", "map", "odom_frm", "a_longer_frame_name"])
def test_mesh_marker_bytes_equal_the_object_marker(frame_id: str) -> None:
    """The bulk-built CDR bytes deserialize to exactly the marker built point by point (all paddings)."""
    from rclpy.serialization import deserialize_message, serialize_message
    from visualization_msgs.msg import Marker

    rng = np.random.default_rng(1)
    v = rng.normal(size=(60, 3))
    tri = rng.integers(0, 60, size=(45, 3))
    for colours in (rng.random((60, 3)), None):
        raw = mesh_marker_cdr(v, tri, colours, 1_700_000_000_000_000_123, frame_id)
        want = deserialize_message(
            serialize_message(mesh_marker(v, tri, colours, 1_700_000_000_000_000_123, frame_id)), Marker
        )
        got = deserialize_message(raw, Marker)
        assert got == want and len(got.points) == 135 and len(got.colors) == (135 if colours is not None else 0)
    empty = deserialize_message(mesh_marker_cdr(v, np.zeros((0, 3), int), None, 5, frame_id), Marker)
    assert empty.points == [] and empty.header.frame_id == frame_id
    with pytest.raises(InputError, match="mesh triangles"):
        mesh_marker_cdr(v, np.array([[0, 1, 60]]), None, 5, frame_id)


def test_cloud_carries_the_training_fisher() -> None:
    m = _random_map(33, 0)
    g = torch.Generator().manual_seed(3)
    h = {k: torch.rand(*getattr(m, k).shape, generator=g) for k in ("means", "quats", "log_scales", "opacity_logits")}
    msg = surfel_map_to_cloud(m, 7, h_train=h, fisher_outputs=("color", "depth"))
    assert "htrain_color+depth__means_2" in [f.name for f in msg.fields]
    outputs, back = cloud_h_train(msg)
    assert outputs == ("color", "depth") and set(back) == set(h)
    for k, t in h.items():
        assert torch.equal(back[k], t.float()), k
    assert len(cloud_to_surfel_map(msg)) == 33  # the extra fields do not disturb the map
    assert cloud_h_train(surfel_map_to_cloud(m, 7)) is None
    bad = {**h, "means": -h["means"]}
    with pytest.raises(InputError, match=fisher_field_names(("color",), "means")[0]):
        cloud_h_train(surfel_map_to_cloud(m, 7, h_train=bad, fisher_outputs=("color",)))
    with pytest.raises(ValueError, match="rows"):
        surfel_map_to_cloud(m, 7, h_train={"means": torch.zeros(5, 3)}, fisher_outputs=("color",))


def test_camera_info_of_the_nodes_and_of_the_bags_carry_the_same_intrinsics() -> None:
    """The mapper's ``/roigsf/map_camera_info`` (an rclpy message) and the bags' camera info (a rosbags one) are built
    from one set of fields; each reads back to the intrinsics it was made of, and the bag's survives a CDR round trip.
    """
    from roigsf_ros.core.camera import Intrinsics
    from roigsf_ros.data.bags import CAMERA_INFO_TYPE, TYPESTORE, camera_info_msg, camera_info_to_intrinsics
    from roigsf_ros.nodes.map_msgs import intrinsics_to_camera_info

    intr = Intrinsics(width=160, height=120, fx=151.25, fy=149.5, cx=79.25, cy=60.75)
    node_msg = intrinsics_to_camera_info(intr, 5, "map")
    bag_msg = TYPESTORE.deserialize_cdr(TYPESTORE.serialize_cdr(camera_info_msg(5, intr), CAMERA_INFO_TYPE),
                                        CAMERA_INFO_TYPE)  # fmt: skip
    for msg in (node_msg, bag_msg):
        assert camera_info_to_intrinsics(msg) == intr
        assert (msg.width, msg.height, msg.distortion_model) == (160, 120, "plumb_bob")
    for name in ("d", "k", "r", "p"):
        assert np.array_equal(np.asarray(getattr(node_msg, name)), np.asarray(getattr(bag_msg, name))), name
    assert np.asarray(node_msg.p).reshape(3, 4)[:, 3].tolist() == [0.0, 0.0, 0.0]
