"""A camera bag rewritten as a robot records it: the pose on TF, compressed images, RealSense topic names.

The robot settings of the nodes and of ``roigsf map`` (``pose_source: tf``, compressed transports, RealSense
topic names) can then be tried on any bag of this package, without a robot. The frame tree is a mobile
robot's (REP 105 / REP 103)::

    map -> odom                                   static (/tf_static)
    odom -> base_link                             moving (/tf), one transform per frame, recorded tf_lag_s late
    base_link -> camera_link -> <optical frame>   static (/tf_static); camera_link in body axes, optical in OpenCV axes

so the camera's pose is found only by composing four transforms, one of them interpolated in time. Colour is
``sensor_msgs/CompressedImage`` (PNG, lossless, or JPEG) on ``<ns>/color/image_raw/compressed``, depth a 16-bit
PNG of millimetres (as a RealSense gives it) on ``<ns>/aligned_depth_to_color/image_raw/compressedDepth`` (or
``/compressed``), camera info on ``<ns>/color/camera_info``: the topics :func:`~roigsf_ros.data.bags.realsense_topics`
names.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.interfaces import QosDurability
from rosbags.rosbag2 import StoragePlugin, Writer
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from roigsf_ros.core.camera import matrix_to_quat_xyzw
from roigsf_ros.core.errors import InputError
from roigsf_ros.data import bags
from roigsf_ros.data.tf import TF_MESSAGE_TYPE, TF_STATIC_TOPIC, TF_TOPIC

ROBOT_DEPTH_TRANSPORTS = ("compressedDepth", "compressed")
"""Depth transports :func:`write_robot_bag` writes (both a 16-bit PNG of millimetres)."""
ROBOT_COLOR_FORMATS = ("png", "jpeg")
"""Colour formats :func:`write_robot_bag` writes (PNG keeps the pixels; JPEG is what most robots record)."""
ODOM_FRAME_ID = "odom"
BASE_FRAME_ID = "base_link"
CAMERA_LINK_FRAME_ID = "camera_link"


def _rigid(rotvec: tuple[float, float, float], t_m: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t_m
    return T


T_MAP_ODOM = _rigid((0.0, 0.0, 0.4), (1.0, -2.0, 0.0))
"""[4, 4] odom in map: a robot that started away from the map's origin, turned 0.4 rad."""
T_BASE_CAMERA_LINK = _rigid((0.0, 0.05, 0.0), (0.1, 0.0, 0.3))
"""[4, 4] camera_link in base_link: 0.1 m ahead, 0.3 m up, pitched 0.05 rad."""
T_CAMERA_LINK_OPTICAL = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)
"""[4, 4] the optical frame in camera_link: REP 103 body axes (x forward, z up) to OpenCV's (z forward, y down)."""

_QOS_TF_STATIC = bags.QOS_RELIABLE._replace(durability=QosDurability.TRANSIENT_LOCAL)


def _transform(parent: str, child: str, T: np.ndarray, stamp_ns: int) -> Any:
    t = bags.TYPESTORE.types
    qx, qy, qz, qw = (float(v) for v in matrix_to_quat_xyzw(T[:3, :3]))
    return t["geometry_msgs/msg/TransformStamped"](
        header=bags.header_msg(stamp_ns, parent),
        child_frame_id=child,
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            rotation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        ),
    )


def _tf_message(*transforms: Any) -> Any:
    return bags.TYPESTORE.types[TF_MESSAGE_TYPE](transforms=list(transforms))


def _compressed(stamp_ns: int, fmt: str, data: bytes) -> Any:
    return bags.TYPESTORE.types[bags.COMPRESSED_IMAGE_TYPE](
        header=bags.header_msg(stamp_ns, bags.CAMERA_FRAME_ID), format=fmt, data=np.frombuffer(data, np.uint8)
    )


def base_link_in_odom(T_wc: np.ndarray) -> np.ndarray:
    """[4, 4] odom -> base_link of a camera pose ``T_wc`` (optical frame in map) in this module's frame tree."""
    return np.linalg.inv(T_MAP_ODOM) @ T_wc @ np.linalg.inv(T_BASE_CAMERA_LINK @ T_CAMERA_LINK_OPTICAL)


def robot_node_parameters(namespace: str = "/camera", depth_transport: str = "compressedDepth") -> dict[str, str]:
    """The camera nodes' parameters that read a bag :func:`write_robot_bag` wrote (names as the nodes declare them)."""
    t = bags.realsense_topics(namespace, color_transport="compressed", depth_transport=depth_transport)
    return {
        "pose_source": t.pose_source,
        "color_transport": t.color_transport,
        "depth_transport": t.depth_transport,
        "color_topic": t.color,
        "depth_topic": t.depth,
        "camera_info_topic": t.camera_info,
    }


_ROS_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def check_namespace(namespace: str) -> str:
    """``namespace`` as ``/a/b`` (``/`` for none) when every part of it is a ROS name token (letters, digits and
    ``_``, not starting with a digit), else an InputError naming ``namespace``: a bag written under ``/a b`` reads
    back here but cannot be published (rcl refuses the name). The rule is written out here, not taken from rclpy's
    validator, so that this module stays importable without ROS.
    """
    parts = namespace.strip("/").split("/") if namespace.strip("/") else []
    bad = [part for part in parts if not _ROS_TOKEN.fullmatch(part)]
    if bad:
        raise InputError(
            "namespace", f"{namespace!r} is no ROS namespace: {bad[0]!r} is not letters, digits and '_' (not "
            "starting with a digit), so no ROS node could publish or subscribe to its topics"
        )  # fmt: skip
    return "/" + "/".join(parts)


def write_robot_bag(
    src: str | Path,
    out: str | Path,
    *,
    namespace: str = "/camera",
    color_format: str = "png",
    depth_transport: str = "compressedDepth",
    tf_lag_s: float = 0.001,
    keep_tf: Callable[[int], bool] | None = None,
    overwrite: bool = False,
    progress: bool = False,
    gt_mesh: Path | None = None,
) -> int:
    """Rewrite the camera bag ``src`` (this package's layout, :func:`~roigsf_ros.data.bags.write_bag`) at ``out``
    as a robot records it (module docstring); returns the number of frames written. ``out`` appears only once
    complete.

    Frame k's odom -> base_link is stamped with its images' stamp and recorded ``tf_lag_s`` after them (TF
    lags the camera on a robot), unless ``keep_tf(k)`` is False (a lost transform, for tests). Depth is
    rounded to millimetres (what a RealSense gives), so a 32FC1 source reads back within 0.5 mm. ``gt_mesh``: copied
    into the bag folder as ``mesh.ply``, as :func:`~roigsf_ros.data.bags.write_bag` does (the poses keep the source's
    world frame, ``map``, so the source's ground truth holds).
    """
    if color_format not in ROBOT_COLOR_FORMATS:
        raise InputError("color_format", f"'{color_format}' is not one of {', '.join(ROBOT_COLOR_FORMATS)}")
    if depth_transport not in ROBOT_DEPTH_TRANSPORTS:
        raise InputError("depth_transport", f"'{depth_transport}' is not one of {', '.join(ROBOT_DEPTH_TRANSPORTS)}")
    if not (np.isfinite(tf_lag_s) and tf_lag_s >= 0):
        raise InputError("tf_lag_s", f"must be a number of seconds >= 0, got {tf_lag_s}")
    if Path(out).resolve() == Path(src).resolve():
        raise InputError(out, "is the bag being rewritten: write the robot's bag elsewhere")
    check_namespace(namespace)
    topics = bags.realsense_topics(namespace, color_transport="compressed", depth_transport=depth_transport)
    resolved = topics.resolved()
    types = resolved.types() | {TF_TOPIC: TF_MESSAGE_TYPE, TF_STATIC_TOPIC: TF_MESSAGE_TYPE}
    lag_ns = round(tf_lag_s * 1e9)
    out = Path(out)
    n = 0
    source_topics = bags.CameraTopics(color_transport=bags.AUTO, depth_transport=bags.AUTO)
    with bags.BagReader(src, source_topics) as reader, bags.staged_bag(out, gt_mesh, overwrite, [src]) as staging:
        with Writer(staging, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            conns = {
                topic: writer.add_connection(
                    topic,
                    typ,
                    typestore=bags.TYPESTORE,
                    offered_qos_profiles=[_QOS_TF_STATIC if topic == TF_STATIC_TOPIC else bags.QOS_RELIABLE],
                )
                for topic, typ in types.items()
            }

            def write(topic: str, record_ns: int, msg: Any) -> None:
                writer.write(conns[topic], record_ns, bags.TYPESTORE.serialize_cdr(msg, types[topic]))

            pending_tf: list[tuple[int, Any]] = []  # (record time, message): written in record-time order
            total = reader.message_count() // max(1, len(reader.topics.types()))
            for frame in tqdm(reader.frames(), total=total, desc=f"bag {out.name}", unit="frame", disable=not progress):
                stamp = frame.stamp_ns
                if n == 0:
                    static = _tf_message(
                        _transform(bags.MAP_FRAME_ID, ODOM_FRAME_ID, T_MAP_ODOM, stamp),
                        _transform(BASE_FRAME_ID, CAMERA_LINK_FRAME_ID, T_BASE_CAMERA_LINK, stamp),
                        _transform(CAMERA_LINK_FRAME_ID, topics.tf_child_frame, T_CAMERA_LINK_OPTICAL, stamp),
                    )
                    write(TF_STATIC_TOPIC, stamp - 1, static)
                while pending_tf and pending_tf[0][0] <= stamp:
                    write(TF_TOPIC, *pending_tf.pop(0))
                fmt, data = bags.encode_compressed_rgb(frame.rgb, color_format)
                write(resolved.color, stamp, _compressed(stamp, fmt, data))
                fmt, data = bags.encode_compressed_depth(frame.depth_m, depth_transport)
                write(resolved.depth, stamp, _compressed(stamp, fmt, data))
                write(resolved.camera_info, stamp, bags.camera_info_msg(stamp, frame.intrinsics))
                if keep_tf is None or keep_tf(n):
                    odom_base = _transform(ODOM_FRAME_ID, BASE_FRAME_ID, base_link_in_odom(frame.T_wc), stamp)
                    pending_tf.append((stamp + lag_ns, _tf_message(odom_base)))
                n += 1
            for record_ns, msg in pending_tf:
                write(TF_TOPIC, record_ns, msg)
        if n == 0:
            raise InputError(src, "no complete frame to rewrite")
    return n


__all__ = [
    "BASE_FRAME_ID",
    "CAMERA_LINK_FRAME_ID",
    "ODOM_FRAME_ID",
    "ROBOT_COLOR_FORMATS",
    "ROBOT_DEPTH_TRANSPORTS",
    "T_BASE_CAMERA_LINK",
    "T_CAMERA_LINK_OPTICAL",
    "T_MAP_ODOM",
    "base_link_in_odom",
    "check_namespace",
    "robot_node_parameters",
    "write_robot_bag",
]
