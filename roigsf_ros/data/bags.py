"""Replica sequences as ROS 2 bags (rosbag2 folder, MCAP storage) and back, with rosbags only (no rclpy).

One bag frame is four messages that carry the identical header stamp (the bag's record time equals it):

    /camera/color/image_raw   sensor_msgs/msg/Image            rgb8
    /camera/depth/image_raw   sensor_msgs/msg/Image            32FC1 metres (or 16UC1 millimetres)
    /camera/camera_info       sensor_msgs/msg/CameraInfo       K, P, R = I, plumb_bob with zero distortion
    /camera/pose              geometry_msgs/msg/PoseStamped    T_wc of the optical frame in "map"

Images and camera info use frame_id ``camera_color_optical_frame`` (OpenCV axes: x right, y down,
z forward); the pose is that frame in ``map``, i.e. the ``traj.txt`` matrix as position + xyzw.

The message converters (:func:`image_to_rgb`, :func:`image_to_depth_m`, :func:`camera_info_to_intrinsics`,
:func:`pose_to_matrix`) accept any object with the message's fields, so rosbags messages and rclpy
messages both work, and ROS nodes reuse them.
"""

from __future__ import annotations

import contextlib
import logging
import math
import shutil
import struct
from collections import Counter, deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import cv2
import numpy as np
from numpy.typing import DTypeLike
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from tqdm import tqdm

from roigsf_ros.core.camera import Intrinsics, load_pose, matrix_to_quat_xyzw, pose_from_position_quat
from roigsf_ros.core.errors import InputError, warn_once
from roigsf_ros.core.fileio import atomic_dir
from roigsf_ros.core.frame import Frame, resize_frame
from roigsf_ros.core.package_files import package_path, package_path_places
from roigsf_ros.data.replica import PNG_SIGNATURE, ReplicaSequence, scene_gt_mesh
from roigsf_ros.data.sync import StampMatcher
from roigsf_ros.data.tf import (
    DEFAULT_TOLERANCE_S,
    TF_MESSAGE_TYPE,
    TF_STATIC_TOPIC,
    TF_TOPIC,
    TransformBuffer,
    TransformUnavailableError,
)

COLOR_TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/depth/image_raw"
CAMERA_INFO_TOPIC = "/camera/camera_info"
POSE_TOPIC = "/camera/pose"
CAMERA_FRAME_ID = "camera_color_optical_frame"
MAP_FRAME_ID = "map"

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"

DEPTH_ENCODINGS = ("32FC1", "16UC1")
"""Depth encodings :func:`write_bag` writes: float metres, or uint16 millimetres (0 = invalid)."""
COLOR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8")
"""Colour encodings :func:`image_to_rgb` reads."""

DEFAULT_RATE_HZ = 10.0
"""Default frame rate of written bags; the player's ``rate`` factor scales it at playback."""
DEFAULT_T0_NS = 1_700_000_000 * 10**9
"""Stamp of frame 0 in written bags (2023-11-14 22:13:20 UTC): fixed, so bags are reproducible."""
MAX_PENDING_STAMPS = 64
"""The reader holds at most this many incomplete frames while it waits for their other messages."""

SAMPLE_BAG = "bags/synth_room"
"""The shipped sample bag (bags/README.md), relative to the checkout or to the installed package's share folder."""
BAG_MARKS = ("metadata.yaml",)
"""The file of a rosbag2 bag folder: ``--overwrite`` replaces a folder holding it, or an empty one, and no other."""
SAMPLE_GT_MESH = "bags/synth_room_mesh.ply"
"""The sample bag's ground-truth mesh, relative as :data:`SAMPLE_BAG`."""


def sample_path(relative: str = SAMPLE_BAG) -> Path:
    """The shipped :data:`SAMPLE_BAG` (or :data:`SAMPLE_GT_MESH`): the checkout's when this runs from one, else the
    installed copy (setup.py puts bags/ into share/roigsf_ros/), so the defaults work from any folder.
    """
    path = package_path(relative, lambda p: p.is_file() or (p / "metadata.yaml").is_file())
    if path is None:
        raise InputError(relative, f"the package's sample is not installed (looked in {package_path_places(relative)})")
    return path


_LOG = logging.getLogger(__name__)
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
QOS_RELIABLE = Qos(
    history=QosHistory.KEEP_LAST,
    depth=10,
    reliability=QosReliability.RELIABLE,
    durability=QosDurability.VOLATILE,
    deadline=QosTime(0, 0),
    lifespan=QosTime(0, 0),
    liveliness=QosLiveliness.AUTOMATIC,
    liveliness_lease_duration=QosTime(0, 0),
    avoid_ros_namespace_conventions=False,
)


POSE_SOURCES = ("topic", "tf")
"""Where a frame's pose comes from: a PoseStamped topic, or the TF tree (``/tf`` + ``/tf_static``)."""
COLOR_TRANSPORTS = ("raw", "compressed")
DEPTH_TRANSPORTS = ("raw", "compressed", "compressedDepth")
"""image_transport names: ``raw`` (sensor_msgs/Image), ``compressed`` (JPEG/PNG), ``compressedDepth`` (header + PNG)."""
AUTO = "auto"
"""A transport read from the topic's type in a bag (not for live topics: the nodes need it named)."""


def transport_topic(topic: str, transport: str) -> str:
    """The topic a transport is published on, as image_transport names it: ``<base>/<transport>`` (raw: ``<base>``).

    A topic that already ends with ``/<transport>`` is kept as it is, so either the base name or the
    full name may be given.
    """
    if transport in ("raw", AUTO) or topic.endswith(f"/{transport}"):
        return topic
    return f"{topic.rstrip('/')}/{transport}"


@dataclass(frozen=True)
class CameraTopics:
    """How one RGB-D camera with its pose is read: topic names, image transports, pose source and TF frames.

    The defaults are what :func:`write_bag` writes. With ``pose_source="tf"`` the pose of
    ``tf_child_frame`` in ``tf_parent_frame`` is looked up on ``tf_topic`` / ``tf_static_topic`` at each
    frame's stamp (:class:`roigsf_ros.data.tf.TransformBuffer`, ``tf_tolerance_s``) instead of ``pose``.
    ``color`` and ``depth`` are base topics: a compressed transport reads ``<topic>/compressed`` (or
    ``/compressedDepth``) as image_transport does, unless the name already ends so (:meth:`resolved`).
    """

    color: str = COLOR_TOPIC
    depth: str = DEPTH_TOPIC
    camera_info: str = CAMERA_INFO_TOPIC
    pose: str = POSE_TOPIC
    pose_source: str = "topic"
    tf_parent_frame: str = MAP_FRAME_ID
    tf_child_frame: str = CAMERA_FRAME_ID
    tf_topic: str = TF_TOPIC
    tf_static_topic: str = TF_STATIC_TOPIC
    tf_tolerance_s: float = DEFAULT_TOLERANCE_S
    color_transport: str = "raw"
    depth_transport: str = "raw"

    def __post_init__(self) -> None:
        """Refuse unknown choices and empty names, naming the field (a parameter or option of the same name)."""
        checks = (
            ("pose_source", self.pose_source, POSE_SOURCES),
            ("color_transport", self.color_transport, (*COLOR_TRANSPORTS, AUTO)),
            ("depth_transport", self.depth_transport, (*DEPTH_TRANSPORTS, AUTO)),
        )
        for name, value, choices in checks:
            if value not in choices:
                raise InputError(name, f"'{value}' is not one of {', '.join(choices)}")
        names = {"color": self.color, "depth": self.depth, "camera_info": self.camera_info}
        names |= {"pose": self.pose} if self.pose_source == "topic" else {}
        if self.pose_source == "tf":
            names |= {"tf_topic": self.tf_topic, "tf_parent_frame": self.tf_parent_frame}
            names |= {"tf_child_frame": self.tf_child_frame}
        for name, value in names.items():
            if not str(value).strip("/ "):
                raise InputError(name, "must not be empty")
        if not (math.isfinite(self.tf_tolerance_s) and self.tf_tolerance_s >= 0):
            raise InputError("tf_tolerance_s", f"must be a number of seconds >= 0, got {self.tf_tolerance_s}")

    def record(self) -> dict[str, Any]:
        """The fields that say how the bag was read, for a run's JSON: the pose topic only when the pose comes from it,
        the TF frames, topics and tolerance only when it comes from TF (a record of a TF read named ``/camera/pose``).
        """
        unused = ("tf_parent_frame", "tf_child_frame", "tf_topic", "tf_static_topic", "tf_tolerance_s")
        unused = unused if not self.uses_tf else ("pose",)
        return {k: v for k, v in asdict(self).items() if k not in unused}

    @property
    def uses_tf(self) -> bool:
        """True when poses come from the TF tree."""
        return self.pose_source == "tf"

    def resolved(self) -> CameraTopics:
        """The same with ``color`` and ``depth`` naming the topics their transports are published on."""
        return replace(
            self,
            color=transport_topic(self.color, self.color_transport),
            depth=transport_topic(self.depth, self.depth_transport),
        )

    def types(self) -> dict[str, str]:
        """Topic name -> expected message type, for the messages matched by stamp into a frame.

        Colour, depth and camera info, and the pose topic unless poses come from TF. Call on
        :meth:`resolved` topics (transport ``auto`` counts as raw here).
        """
        color_type = COMPRESSED_IMAGE_TYPE if self.color_transport == "compressed" else IMAGE_TYPE
        depth_type = COMPRESSED_IMAGE_TYPE if self.depth_transport in ("compressed", "compressedDepth") else IMAGE_TYPE
        types = {self.color: color_type, self.depth: depth_type, self.camera_info: CAMERA_INFO_TYPE}
        if not self.uses_tf:
            types[self.pose] = POSE_TYPE
        return types

    def tf_types(self) -> dict[str, str]:
        """The TF topics read (none unless poses come from TF)."""
        if not self.uses_tf:
            return {}
        return {self.tf_topic: TF_MESSAGE_TYPE, self.tf_static_topic: TF_MESSAGE_TYPE}

    def in_bag(self, present: dict[str, str], where: str | Path) -> CameraTopics:
        """These topics resolved against a bag's ``{topic: type}``: ``auto`` transports from the types found.

        With transport ``auto`` the topic is read as given if the bag has it, else ``<topic>/compressed``
        (depth: also ``<topic>/compressedDepth``); its type then says raw or compressed. InputError names
        the bag and the topic when a topic is missing or of the wrong type (the first of :meth:`against`'s).
        """
        topics, problems = self.against(present)
        if problems:
            topic, problem, missing = problems[0]
            have = ", ".join(sorted(present)) or "no topics"
            if missing:
                raise InputError(where, f"{problem} (it has {have})")
            raise InputError(f"{where}:{topic}", problem)
        return topics

    def against(self, present: dict[str, str]) -> tuple[CameraTopics, list[tuple[str, str, bool]]]:
        """These topics resolved as far as a bag's ``{topic: type}`` has them, and every problem :meth:`in_bag`
        refuses, in its order: ``(topic, what is wrong, True if it is missing / False if of another type)``.
        """
        fields: dict[str, str] = {}
        problems: list[tuple[str, str, bool]] = []
        reported: set[str] = set()
        for stream, suffixes in (("color", ("compressed",)), ("depth", ("compressedDepth", "compressed"))):
            topic, transport = getattr(self, stream), getattr(self, f"{stream}_transport")
            if transport != AUTO:
                continue
            candidates = [topic, *(transport_topic(topic, s) for s in suffixes)]
            found = next((c for c in candidates if c in present), None)
            if found is None:
                problems.append((topic, f"{stream} topic {topic} (or {', '.join(candidates[1:])}) is missing", True))
                reported.add(topic)
                continue
            if present[found] == COMPRESSED_IMAGE_TYPE:
                fields[f"{stream}_transport"] = (
                    "compressedDepth" if found.endswith("/compressedDepth") else "compressed"
                )
            elif present[found] == IMAGE_TYPE:
                fields[f"{stream}_transport"] = "raw"
            else:
                problems.append(
                    (found, f"has type {present[found]}, expected {IMAGE_TYPE} or {COMPRESSED_IMAGE_TYPE}", False)
                )
                reported.add(found)
            fields[stream] = found
        topics = replace(self, **fields).resolved()
        for topic, typ in topics.types().items():
            if topic in reported:
                continue
            if topic not in present:
                problems.append((topic, f"topic {topic} ({typ}) is missing from the bag", True))
            elif present[topic] != typ:
                problems.append((topic, f"has type {present[topic]}, expected {typ}", False))
        if topics.uses_tf:
            if topics.tf_topic not in present and topics.tf_static_topic not in present:
                problems.append(
                    (topics.tf_topic, f"pose_source is tf but the bag has neither {topics.tf_topic} nor "
                     f"{topics.tf_static_topic}", True)
                )  # fmt: skip
            for topic in (topics.tf_topic, topics.tf_static_topic):
                if topic in present and present[topic] != TF_MESSAGE_TYPE:
                    problems.append((topic, f"has type {present[topic]}, expected {TF_MESSAGE_TYPE}", False))
        return topics, problems


def realsense_topics(namespace: str = "/camera", **overrides: Any) -> CameraTopics:
    """The topics of a RealSense camera (realsense2_camera, depth aligned to colour) with the pose on TF.

    ``namespace`` is the camera's (``/camera``; newer drivers publish under ``/camera/camera``).
    """
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    fields: dict[str, Any] = {
        "color": f"{ns}/color/image_raw",
        "depth": f"{ns}/aligned_depth_to_color/image_raw",
        "camera_info": f"{ns}/color/camera_info",
        "pose_source": "tf",
        "tf_child_frame": CAMERA_FRAME_ID,
    }
    return CameraTopics(**(fields | overrides))


@dataclass
class BagFrame:
    """One RGB-D frame read back from a bag: four messages matched by header stamp."""

    stamp_ns: int
    rgb: np.ndarray  # [H, W, 3] uint8
    depth_m: np.ndarray  # [H, W] float32 metres, 0 where invalid
    T_wc: np.ndarray  # [4, 4] float64 camera-to-world (optical frame in map)
    intrinsics: Intrinsics


def resized_frame(bf: BagFrame, intr: Intrinsics) -> BagFrame:
    """``bf`` at ``intr``'s image size (colour by area, depth nearest with pixel centres aligned: :func:`resize_frame`),
    as the camera nodes take a frame with ``input_width``/``input_height``; itself when the size is already that.
    """
    if (bf.intrinsics.width, bf.intrinsics.height) == (intr.width, intr.height):
        return bf
    small = resize_frame(Frame(index=bf.stamp_ns, rgb=bf.rgb, depth_m=bf.depth_m, T_wc=bf.T_wc), intr)
    return BagFrame(bf.stamp_ns, small.rgb, small.depth_m, bf.T_wc, intr)


# --------------------------------------------------------------------------------------------
# Message -> numpy (any object with the message's fields: rosbags or rclpy messages)
# --------------------------------------------------------------------------------------------


def stamp_to_ns(stamp: Any) -> int:
    """Nanoseconds of a ``builtin_interfaces/Time`` (``sec``, ``nanosec``)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _image_array(msg: Any, where: str, dtype: DTypeLike, channels: int) -> np.ndarray:
    """Pixels of an Image as a fresh [H, W] or [H, W, C] array of ``dtype``, after size/step checks."""
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    dtype = np.dtype(dtype)
    if height <= 0 or width <= 0:
        raise InputError(where, f"image size is {width}x{height}")
    row_bytes = width * channels * dtype.itemsize
    if step < row_bytes:
        raise InputError(where, f"step {step} is less than width*channels*bytes = {row_bytes} ({msg.encoding})")
    data = msg.data
    if isinstance(data, np.ndarray):
        buf = data.view(np.uint8).reshape(-1)
    else:
        try:
            buf = np.frombuffer(data, dtype=np.uint8)
        except TypeError:
            buf = np.asarray(data, dtype=np.uint8).reshape(-1)
    if buf.size != step * height:
        raise InputError(where, f"data has {buf.size} bytes, expected step*height = {step}*{height} = {step * height}")
    rows = buf.reshape(height, step)[:, :row_bytes]
    order = ">" if int(msg.is_bigendian) else "<"
    pixels = np.ascontiguousarray(rows).view(dtype.newbyteorder(order) if dtype.itemsize > 1 else dtype)
    shape = (height, width, channels) if channels > 1 else (height, width)
    return pixels.reshape(shape).astype(dtype, copy=True)


def image_to_rgb(msg: Any, where: str = COLOR_TOPIC) -> np.ndarray:
    """A colour ``sensor_msgs/Image`` (rgb8, bgr8, rgba8, bgra8) or ``CompressedImage`` as [H, W, 3] uint8 RGB."""
    if is_compressed(msg):
        return compressed_to_rgb(msg, where)
    enc = str(msg.encoding)
    if enc not in COLOR_ENCODINGS:
        raise InputError(where, f"unsupported colour encoding '{enc}' (supported: {', '.join(COLOR_ENCODINGS)})")
    px = _image_array(msg, where, np.uint8, 4 if enc.endswith("a8") else 3)
    if enc.startswith("bgr"):
        px = px[..., 2::-1]
    return np.ascontiguousarray(px[..., :3])


def image_to_depth_m(msg: Any, where: str = DEPTH_TOPIC) -> np.ndarray:
    """A depth ``sensor_msgs/Image`` (32FC1 metres, 16UC1/mono16 mm) or ``CompressedImage`` as [H, W] float32 metres.

    Invalid depth (0, NaN, inf or negative) becomes 0, the library's convention.
    """
    if is_compressed(msg):
        return compressed_to_depth_m(msg, where)
    enc = str(msg.encoding)
    if enc == "32FC1":
        depth_m = _image_array(msg, where, np.float32, 1)
        depth_m[~np.isfinite(depth_m) | (depth_m < 0)] = 0.0
        return depth_m
    if enc in ("16UC1", "mono16"):
        return _image_array(msg, where, np.uint16, 1).astype(np.float32) / np.float32(1000.0)
    raise InputError(where, f"unsupported depth encoding '{enc}' (supported: 32FC1 metres, 16UC1 millimetres)")


# --------------------------------------------------------------------------------------------
# sensor_msgs/CompressedImage (image_transport's "compressed" and "compressedDepth") -> numpy
# --------------------------------------------------------------------------------------------

COMPRESSED_DEPTH_HEADER_BYTES = 12
"""compressedDepth prepends a 12-byte ConfigHeader to the PNG: int32 format, float32 depthParam[2] (little-endian)."""


def is_compressed(msg: Any) -> bool:
    """True for a ``sensor_msgs/CompressedImage`` (a ``format`` and no ``encoding``), False for an ``Image``."""
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


def _compressed_bytes(msg: Any, where: str) -> np.ndarray:
    data = msg.data
    buf = data.view(np.uint8).reshape(-1) if isinstance(data, np.ndarray) else np.frombuffer(bytes(data), np.uint8)
    if buf.size == 0:
        raise InputError(where, f"compressed image ('{msg.format}') has no data")
    return buf


def _decode(buf: np.ndarray, flags: int, where: str, fmt: str) -> np.ndarray:
    """cv2.imdecode, refusing what it cannot decode (truncated, corrupt, not an image) with the topic named."""
    if buf.size >= 2 and buf[0] == 0xFF and buf[1] == 0xD8 and not bytes(buf[-16:]).rstrip(b"\0").endswith(b"\xff\xd9"):
        raise InputError(
            where, f"compressed image ('{fmt}', {buf.size} bytes) is truncated: JPEG without its end marker"
        )
    try:
        img = cv2.imdecode(buf, flags)
    except cv2.error as exc:
        raise InputError(where, f"cannot decode compressed image ('{fmt}', {buf.size} bytes): {exc}") from None
    if img is None or img.size == 0:
        raise InputError(
            where, f"cannot decode compressed image ('{fmt}', {buf.size} bytes): truncated or not JPEG/PNG"
        )
    return img


def compressed_to_rgb(msg: Any, where: str = COLOR_TOPIC) -> np.ndarray:
    """A colour ``CompressedImage`` (JPEG or PNG, as image_transport's ``compressed``) as [H, W, 3] uint8 RGB.

    OpenCV decodes to BGR (what compressed_image_transport encodes from), so the channels are swapped.
    """
    fmt = str(msg.format)
    if "compresseddepth" in fmt.lower():
        raise InputError(where, f"format '{fmt}' is a depth image, not colour")
    bgr = _decode(_compressed_bytes(msg, where), cv2.IMREAD_COLOR, where, fmt)
    return np.ascontiguousarray(bgr[..., ::-1])


def compressed_to_depth_m(msg: Any, where: str = DEPTH_TOPIC) -> np.ndarray:
    """A depth ``CompressedImage`` as [H, W] float32 metres (0 = invalid).

    Two layouts: image_transport's ``compressedDepth`` (format ``"16UC1; compressedDepth png"``: a
    12-byte config header, then a 16-bit PNG of millimetres; or ``"32FC1; compressedDepth png"``: the
    PNG holds quantised inverse depth ``q = A / depth + B`` with A, B in the header), and a plain 16-bit
    PNG of millimetres (``compressed`` transport, format e.g. ``"16UC1; png compressed"`` or ``"png"``).
    RVL-coded compressedDepth is not supported (refused naming the format).
    """
    fmt = str(msg.format)
    buf = _compressed_bytes(msg, where)
    encoding = fmt.split(";", 1)[0].strip()
    if "compresseddepth" in fmt.lower():
        if "rvl" in fmt.lower():
            raise InputError(where, f"compressedDepth format '{fmt}' (RVL) is not supported; use png")
        if buf.size <= COMPRESSED_DEPTH_HEADER_BYTES:
            raise InputError(where, f"compressedDepth data has {buf.size} bytes: no room for the header and a PNG")
        if bytes(buf[:8]) == PNG_SIGNATURE:  # a plain PNG where the header should be
            raise InputError(where, f"compressedDepth message ('{fmt}') starts with a PNG, not the 12-byte header "
                             "image_transport's compressedDepth puts before it: a plain 16-bit PNG is what "
                             "depth_transport: compressed reads")  # fmt: skip
        quant_a, quant_b = struct.unpack_from("<ff", bytes(buf[4:COMPRESSED_DEPTH_HEADER_BYTES]))
        px = _decode(buf[COMPRESSED_DEPTH_HEADER_BYTES:], cv2.IMREAD_UNCHANGED, where, fmt)
        if px.dtype != np.uint16 or px.ndim != 2:
            raise InputError(
                where, f"compressedDepth PNG is {px.dtype} with shape {px.shape}, expected 16-bit single-channel"
            )
        if encoding == "32FC1":
            if not (math.isfinite(quant_a) and math.isfinite(quant_b) and quant_a > 0):
                raise InputError(where, f"compressedDepth header has invalid quantisation A={quant_a}, B={quant_b}")
            q = px.astype(np.float32)
            with np.errstate(divide="ignore"):
                depth_m = np.where(px > 0, np.float32(quant_a) / (q - np.float32(quant_b)), np.float32(0.0))
            depth_m[~np.isfinite(depth_m) | (depth_m < 0)] = 0.0
            return depth_m.astype(np.float32)
        if encoding not in ("16UC1", "mono16"):
            raise InputError(where, f"unsupported compressedDepth encoding '{encoding}' (supported: 16UC1, 32FC1)")
        return px.astype(np.float32) / np.float32(1000.0)
    if encoding == "32FC1":
        raise InputError(where, f"format '{fmt}': float depth cannot be a plain PNG/JPEG; use compressedDepth")
    if bytes(buf[COMPRESSED_DEPTH_HEADER_BYTES : COMPRESSED_DEPTH_HEADER_BYTES + 8]) == PNG_SIGNATURE:
        raise InputError(where, f"format '{fmt}' names a plain PNG, but the data holds a 12-byte header before its "
                         "PNG, as image_transport's compressedDepth sends it: the publisher's format should read "
                         "'16UC1; compressedDepth png' (or '32FC1; ...' for quantised float depth)")  # fmt: skip
    px = _decode(buf, cv2.IMREAD_UNCHANGED, where, fmt)
    if px.dtype != np.uint16 or px.ndim != 2:
        raise InputError(
            where,
            f"compressed depth ('{fmt}') decodes to {px.dtype} with shape {px.shape}; expected a 16-bit PNG in mm",
        )
    return px.astype(np.float32) / np.float32(1000.0)


def encode_compressed_rgb(rgb: np.ndarray, fmt: str = "jpeg", jpeg_quality: int = 95) -> tuple[str, bytes]:
    """(format, data) of a ``CompressedImage`` of [H, W, 3] uint8 RGB as compressed_image_transport sends it."""
    if fmt not in ("jpeg", "png"):
        raise InputError("format", f"'{fmt}' is not jpeg or png")
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if fmt == "jpeg" else []
    ok, data = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", np.ascontiguousarray(rgb[..., ::-1]), params)
    if not ok:
        raise InputError("image", f"cannot encode a {rgb.shape} image as {fmt}")
    return f"rgb8; {fmt} compressed bgr8", data.tobytes()


def encode_compressed_depth(depth_m: np.ndarray, transport: str = "compressedDepth") -> tuple[str, bytes]:
    """(format, data) of a depth ``CompressedImage``: 16-bit PNG of millimetres, with compressedDepth's header or not.

    Depth is rounded to millimetres as for a 16UC1 ``Image`` (:func:`depth_to_image_data`).
    """
    if transport not in ("compressed", "compressedDepth"):
        raise InputError("depth transport", f"'{transport}' is not compressed or compressedDepth")
    ok, png = cv2.imencode(".png", depth_to_image_data(depth_m, "16UC1"))
    if not ok:
        raise InputError("depth", f"cannot encode a {depth_m.shape} depth image as PNG")
    if transport == "compressed":
        return "16UC1; png compressed", png.tobytes()
    header = struct.pack("<iff", 0, 0.0, 0.0)  # format INV_DEPTH; the quantisation is unused for 16UC1
    return "16UC1; compressedDepth png", header + png.tobytes()


def camera_info_to_intrinsics(msg: Any, where: str = CAMERA_INFO_TOPIC) -> Intrinsics:
    """Pinhole intrinsics from a ``sensor_msgs/CameraInfo`` (its K and width/height; images assumed rectified).

    Non-zero distortion coefficients are not applied: said once per topic, since unrectified images then map with
    bent edges (a camera's rectified stream, or image_proc's, is what to feed).
    """
    d = np.asarray(getattr(msg, "d", ()), dtype=np.float64).reshape(-1)
    if d.size and np.any(d[np.isfinite(d)] != 0):
        model = getattr(msg, "distortion_model", "") or "unnamed model"
        topic = where.split(" @ ")[0]
        text = (f"{topic}: distortion coefficients ({model}, D={d.tolist()}) are not applied: the images are mapped "
                "as if rectified; feed the camera's rectified images")  # fmt: skip
        warn_once(_LOG, topic, "distortion", text)
    k = np.asarray(msg.k, dtype=np.float64).reshape(-1)
    width, height = int(msg.width), int(msg.height)
    if k.size != 9 or not np.all(np.isfinite(k)):
        raise InputError(where, f"K must be 9 finite numbers, got {k.tolist()}")
    if width <= 0 or height <= 0 or k[0] <= 0 or k[4] <= 0:
        raise InputError(where, f"invalid camera info: {width}x{height}, fx={k[0]}, fy={k[4]}")
    return Intrinsics(width=width, height=height, fx=float(k[0]), fy=float(k[4]), cx=float(k[2]), cy=float(k[5]))


def pose_to_matrix(msg: Any, where: str = POSE_TOPIC, source: str | None = None) -> np.ndarray:
    """[4, 4] float64 T_wc of a ``geometry_msgs/PoseStamped`` (or a bare ``Pose``); must be finite and rigid.

    Checked by :func:`roigsf_ros.core.camera.load_pose` like every loaded pose; ``source`` (the topic,
    default ``where``) is what its once-only warning names. A header frame other than :data:`MAP_FRAME_ID` is said
    once per topic: the pose is taken as the camera's pose in the map as it is (no transform applied).
    """
    frame_id = getattr(getattr(msg, "header", None), "frame_id", "")
    if frame_id not in ("", MAP_FRAME_ID):
        topic = (source or where).split(" @ ")[0]
        text = (f"{topic}: poses in frame '{frame_id}', not '{MAP_FRAME_ID}', are taken as the camera's pose in the "
                f"map as they are (no transform applied); publish them in '{MAP_FRAME_ID}', or read the pose from TF "
                "(pose_source tf), which transforms it")  # fmt: skip
        warn_once(_LOG, topic, f"frame {frame_id}", text)
    pose = msg.pose if hasattr(msg, "pose") else msg
    p, q = pose.position, pose.orientation
    T = pose_from_position_quat(np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w]), where)
    return load_pose(T, where, source)


def header_stamp_ns(rawdata: bytes | memoryview) -> int:
    """Header stamp of a CDR-serialized message whose first field is ``std_msgs/Header``.

    CDR: 4-byte encapsulation (byte 1 = little-endian flag), then stamp.sec int32, stamp.nanosec uint32.
    """
    sec, nanosec = struct.unpack_from("<iI" if rawdata[1] else ">iI", rawdata, 4)
    return sec * 1_000_000_000 + nanosec


def refusal_summary(reasons: Counter[str], most: int = 5) -> str:
    """``"3 x TOPIC: problem; 1 x TOPIC: problem"``, the most frequent first, at most ``most`` (then how many other
    reasons there were); "" for none.
    """
    ranked = reasons.most_common()
    text = "; ".join(f"{n} x {reason}" for reason, n in ranked[:most])
    if len(ranked) > most:
        text += f"; and {len(ranked) - most} other reason(s) for {sum(n for _, n in ranked[most:])} frame(s)"
    return text


def header_frame_id(rawdata: bytes | memoryview) -> str:
    """Header frame id of a CDR-serialized message whose first field is ``std_msgs/Header`` ("" if cut short).

    CDR: after the stamp (offset 4, 8 bytes) a uint32 length (with the NUL) and the characters.
    """
    try:
        (n,) = struct.unpack_from("<I" if rawdata[1] else ">I", rawdata, 12)
        return bytes(rawdata[16 : 16 + max(0, n - 1)]).decode("utf-8", "replace")
    except (struct.error, IndexError):
        return ""


CHILD_FRAME_TOLERANCE = (1e-3, 0.1)
"""(metres, degrees): how far TF's ``tf_child_frame`` may sit from the images' own frame before
:func:`child_frame_mismatch` says so (a frame published twice under two names is no mistake)."""


def child_frame_mismatch(
    tf: TransformBuffer, parent: str, child: str, image_frame_id: str, stamp_ns: int, T_child: np.ndarray
) -> str:
    """What is wrong when the images' frame is another TF frame than ``child`` and sits apart from it, else "".

    ``T_child``: ``child``'s pose in ``parent`` at ``stamp_ns``. With ``--tf-child-frame camera_link`` on a RealSense
    bag whose images are in ``camera_color_optical_frame``, every image was placed at the link's pose (axes turned
    90 degrees): F@5cm 0.000 and no word. An images' frame TF does not know is no mistake: ``tf_child_frame`` then
    stands in for it, which is what it is for.
    """
    image = image_frame_id.lstrip("/")
    if not image or image == child.lstrip("/"):
        return ""
    try:
        T_image = tf.lookup(parent, image, stamp_ns)
    except (TransformUnavailableError, InputError):
        return ""
    rel = np.linalg.inv(T_child) @ T_image
    dist = float(np.linalg.norm(rel[:3, 3]))
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(rel[:3, :3])) - 1.0) / 2.0))))
    if dist <= CHILD_FRAME_TOLERANCE[0] and angle <= CHILD_FRAME_TOLERANCE[1]:
        return ""
    return (
        f"the poses are TF frame '{child.lstrip('/')}', but the images are in '{image}', {dist:.3f} m and "
        f"{angle:.1f} deg from it: every image is placed at the wrong pose (set tf_child_frame / --tf-child-frame to "
        f"'{image}')"
    )


def child_frame_hint(image_frame_id: str, tf_child_frame: str) -> str:
    """The hint after an unknown child frame's TF error: the frame the images are in, when it is another one."""
    image_frame_id = image_frame_id.lstrip("/")
    if not image_frame_id or image_frame_id == tf_child_frame.lstrip("/"):
        return ""
    return f"; the images are in frame '{image_frame_id}': set tf_child_frame / --tf-child-frame to it"


# --------------------------------------------------------------------------------------------
# numpy -> messages (rosbags types) and the bag writer
# --------------------------------------------------------------------------------------------


def header_msg(stamp_ns: int, frame_id: str) -> Any:
    """A ``std_msgs/Header`` (rosbags type) of a stamp in ns and a frame id."""
    t = TYPESTORE.types
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id)


def _image_msg(stamp_ns: int, pixels: np.ndarray, encoding: str) -> Any:
    pixels = np.ascontiguousarray(pixels)
    height, width = pixels.shape[:2]
    return TYPESTORE.types[IMAGE_TYPE](
        header=header_msg(stamp_ns, CAMERA_FRAME_ID),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=pixels.nbytes // height,
        data=pixels.reshape(-1).view(np.uint8),
    )


def depth_to_image_data(depth_m: np.ndarray, encoding: str) -> np.ndarray:
    """[H, W] depth in the pixel type of ``encoding``: float32 metres (32FC1) or uint16 mm (16UC1).

    For 16UC1, millimetres are rounded; non-finite, non-positive or > 65.535 m depth becomes 0 (invalid).
    """
    if encoding == "32FC1":
        return np.ascontiguousarray(depth_m, dtype=np.float32)
    if encoding == "16UC1":
        mm = np.round(np.nan_to_num(depth_m.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0) * 1000.0)
        return np.where((mm > 0) & (mm <= 65535), mm, 0).astype(np.uint16)
    raise InputError("depth_encoding", f"'{encoding}' is not one of {', '.join(DEPTH_ENCODINGS)}")


def camera_info_fields(intr: Intrinsics) -> dict[str, Any]:
    """The ``sensor_msgs/CameraInfo`` fields of pinhole intrinsics: the size, ``plumb_bob`` with no distortion, K,
    R = I and P = [K | 0] (float64 arrays), for the bags' (rosbags) message class and the nodes' (rclpy) alike;
    :func:`camera_info_to_intrinsics` reads them back.
    """
    p = np.zeros((3, 4))
    p[:, :3] = intr.K
    return {
        "height": int(intr.height),
        "width": int(intr.width),
        "distortion_model": "plumb_bob",
        "d": np.zeros(5),
        "k": intr.K.reshape(-1),
        "r": np.eye(3).reshape(-1),
        "p": p.reshape(-1),
    }


def camera_info_msg(stamp_ns: int, intr: Intrinsics) -> Any:
    """A ``sensor_msgs/CameraInfo`` (rosbags type) of pinhole intrinsics, no distortion, in the optical frame."""
    t = TYPESTORE.types
    roi = t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return t[CAMERA_INFO_TYPE](
        header=header_msg(stamp_ns, CAMERA_FRAME_ID), **camera_info_fields(intr), binning_x=0, binning_y=0, roi=roi
    )


def _pose_msg(stamp_ns: int, T_wc: np.ndarray) -> Any:
    t = TYPESTORE.types
    x, y, z = (float(v) for v in T_wc[:3, 3])
    qx, qy, qz, qw = (float(v) for v in matrix_to_quat_xyzw(T_wc[:3, :3]))
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
    )
    return t[POSE_TYPE](header=header_msg(stamp_ns, MAP_FRAME_ID), pose=pose)


@contextlib.contextmanager
def staged_bag(
    out: Path, gt_mesh: Path | None = None, overwrite: bool = False, inputs: Sequence[str | Path] = ()
) -> Iterator[Path]:
    """The folder a rosbags ``Writer`` writes the bag ``out`` into, which becomes ``out`` only once complete.

    rosbags names the storage file after its folder, so the bag is written into ``<tmp>/<name>`` and moved up into the
    temporary folder at the end; ``gt_mesh`` is copied in as ``mesh.ply`` (InputError now if it is missing), where
    :func:`roigsf_ros.data.replica.scene_gt_mesh` finds it. An exception in the block leaves nothing at ``out``;
    ``overwrite`` replaces an earlier bag only, never a folder holding ``inputs`` (what the bag is made from).
    """
    if gt_mesh is not None and not Path(gt_mesh).is_file():
        raise InputError(gt_mesh, "ground-truth mesh not found")
    out = Path(out)
    reads = [*inputs, *([gt_mesh] if gt_mesh is not None else [])]
    with atomic_dir(out, overwrite, marks=BAG_MARKS, what="a bag", inputs=reads) as tmp:
        staging = tmp / out.name
        yield staging
        for item in staging.iterdir():
            item.rename(tmp / item.name)
        staging.rmdir()
        if gt_mesh is not None:
            shutil.copyfile(gt_mesh, tmp / "mesh.ply")


def frame_stamp_ns(k: int, rate_hz: float, t0_ns: int = DEFAULT_T0_NS) -> int:
    """Stamp of the ``k``-th written frame: ``t0 + k / rate_hz`` in integer nanoseconds."""
    return int(t0_ns) + round(k * 1e9 / rate_hz)


def write_bag(
    seq: ReplicaSequence,
    out: str | Path,
    rate_hz: float = DEFAULT_RATE_HZ,
    depth_encoding: str = "32FC1",
    stride: int = 1,
    max_frames: int | None = None,
    overwrite: bool = False,
    progress: bool = True,
    t0_ns: int = DEFAULT_T0_NS,
    gt_mesh: Path | None = None,
) -> int:
    """Write every ``stride``-th frame of ``seq`` (at most ``max_frames``) as a rosbag2 MCAP bag folder.

    ``gt_mesh``: a ground-truth mesh copied into the folder as ``mesh.ply``, where ``roigsf map``, ``roigsf bench`` and
    ``roigsf demo`` find it (:func:`roigsf_ros.data.replica.scene_gt_mesh`); a bag's readers open the files its
    ``metadata.yaml`` lists only. Returns the number of frames written. The bag appears under
    ``out`` only once complete.
    """
    out = Path(out)
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise InputError("rate_hz", f"must be a positive number of frames per second, got {rate_hz}")
    if depth_encoding not in DEPTH_ENCODINGS:
        raise InputError("depth_encoding", f"'{depth_encoding}' is not one of {', '.join(DEPTH_ENCODINGS)}")
    if stride < 1:
        raise InputError("stride", f"must be >= 1, got {stride}")
    if max_frames is not None and max_frames < 1:
        raise InputError("max_frames", f"must be >= 1, got {max_frames}")
    ks = list(range(0, len(seq), stride))[:max_frames]
    intr = seq.intrinsics
    with (
        staged_bag(out, gt_mesh, overwrite, [seq.root]) as staging,
        Writer(staging, version=9, storage_plugin=StoragePlugin.MCAP) as writer,
    ):
        conns = {
            topic: writer.add_connection(topic, typ, typestore=TYPESTORE, offered_qos_profiles=[QOS_RELIABLE])
            for topic, typ in CameraTopics().types().items()
        }
        for n, k in enumerate(tqdm(ks, desc=f"bag {out.name}", unit="frame", disable=not progress)):
            frame = seq.frame(k)
            stamp = frame_stamp_ns(n, rate_hz, t0_ns)
            depth_px = depth_to_image_data(frame.depth_m, depth_encoding)
            msgs = (
                (COLOR_TOPIC, _image_msg(stamp, frame.rgb, "rgb8")),
                (DEPTH_TOPIC, _image_msg(stamp, depth_px, depth_encoding)),
                (CAMERA_INFO_TOPIC, camera_info_msg(stamp, intr)),
                (POSE_TOPIC, _pose_msg(stamp, frame.T_wc)),
            )
            for topic, msg in msgs:
                writer.write(conns[topic], stamp, TYPESTORE.serialize_cdr(msg, msg.__msgtype__))
    return len(ks)


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


def open_any_reader(path: str | Path) -> AnyReader:
    """An unopened rosbags ``AnyReader`` of a rosbag2 folder or a bare ``.mcap``; InputError if unreadable."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "bag not found")
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        mcaps = sorted(path.glob("*.mcap"))
        if len(mcaps) != 1:
            raise InputError(path, "not a rosbag2 folder (no metadata.yaml) and not holding exactly one .mcap file")
        path = mcaps[0]
    try:
        return AnyReader([path])
    except (AnyReaderError, OSError, ValueError) as exc:
        raise InputError(path, f"cannot open bag: {exc}{_cut_short_hint(exc)}") from None


def _cut_short_hint(exc: Exception) -> str:
    """A hint after rosbags' error for an MCAP file cut short (a copy or a recording that never closed its file)."""
    text = str(exc).lower()
    if "magic" in text or "truncated" in text or "unexpected end" in text:
        return (" (the .mcap file is cut short or not MCAP: a copy stopped early, or a recording that never closed "
                "its file; `mcap recover` from the mcap CLI rewrites what it holds)")  # fmt: skip
    return ""


@contextlib.contextmanager
def opened_bag(path: str | Path) -> Iterator[AnyReader]:
    """An open rosbags ``AnyReader`` of a bag, closed on exit; InputError naming the bag if it cannot be opened."""
    reader = open_any_reader(path)
    try:
        reader.open()
    except (AnyReaderError, OSError, ValueError) as exc:
        raise InputError(path, f"cannot open bag: {exc}{_cut_short_hint(exc)}") from None
    try:
        yield reader
    finally:
        reader.close()


def bag_topic_types(path: str | Path) -> dict[str, str]:
    """The bag's ``{topic: message type}``."""
    with opened_bag(path) as reader:
        return {c.topic: c.msgtype for c in reader.connections}


class BagReader:
    """Frames of an RGB-D bag, their messages matched by identical header stamp (no approximate sync).

    Use as a context manager and iterate :meth:`frames`. A stamp that lacks one of its messages is
    skipped and counted in ``skipped_frames`` (also when more than ``MAX_PENDING_STAMPS`` incomplete
    stamps pile up, the oldest is given up). A missing topic or a topic of the wrong type raises
    InputError naming the bag and the topic. Transports ``auto`` are read from the topics' types
    (:meth:`CameraTopics.in_bag`). With poses from TF, a complete frame waits (at most
    ``MAX_PENDING_STAMPS`` of them) until the TF messages read so far give its pose; one whose pose
    never comes is skipped and counted in ``no_tf`` (the reason in ``last_tf_error``). A complete, posed
    frame whose messages do not convert (a JPEG depth image, sizes that disagree, a pose that is no rotation)
    raises InputError naming the topic and stamp, or with ``skip_refused`` is skipped and its stamp kept in
    ``refused_stamps`` (the reason in ``last_refusal``). A frame whose stamp a frame read before it already had
    is skipped (``repeated_stamps``: a recorder's repeated stamp; the nodes skip it too), and one stamped before
    the frame read before it is read but counted (``stamps_back``, the first in ``first_back``), since frame ids
    (:class:`roigsf_ros.data.sources.BagFrameSource`) follow the stamps. :meth:`stamps` gives the frames' stamps
    undecoded.
    """

    def __init__(self, path: str | Path, topics: CameraTopics | None = None, skip_refused: bool = False) -> None:
        self.path = Path(path)
        self.requested = topics or CameraTopics()
        self.topics = self.requested
        """The topics read: ``requested`` resolved against the bag once it is open."""
        self.skip_refused = skip_refused
        self.refused_stamps: list[int] = []
        """Stamps of the complete, posed frames skipped because their messages did not convert (``skip_refused``)."""
        self.last_refusal = ""
        self._refusals: Counter[str] = Counter()
        """Refused frames by reason (the error without its stamp)."""
        self.skipped_frames = 0
        self.frames_read = 0
        self.no_tf = 0
        """Complete frames skipped because TF never gave their pose."""
        self.tf_rejected = 0
        """Transforms refused (bad values); the rest of their messages is kept."""
        self.last_tf_error = ""
        self.tf_reparented = 0
        """Times a frame of the TF tree changed parent (:attr:`roigsf_ros.data.tf.TransformBuffer.reparent_note`)."""
        self.tf_reparent_note = ""
        self.child_frame_note = ""
        """Set at the first posed frame when the images' frame is another TF frame than ``tf_child_frame``, apart from
        it (:func:`child_frame_mismatch`): the poses are then not the images'."""
        self._child_checked = False
        self.repeated_stamps: list[int] = []
        """Stamps of the complete, posed frames skipped because a frame read before had the same stamp."""
        self.stamps_back = 0
        """Frames read whose stamp is older than the frame read before them (the recording's order)."""
        self.first_back: tuple[int, int, int] | None = None
        """The first of those: (its place among the frames read, 0-based; its stamp; the stamp before it) in ns."""
        self._reader = open_any_reader(self.path)
        self._open = False

    def __enter__(self) -> Self:
        try:
            self._reader.open()
        except (AnyReaderError, OSError, ValueError) as exc:
            raise InputError(self.path, f"cannot open bag: {exc}{_cut_short_hint(exc)}") from None
        self._open = True
        try:
            present = {c.topic: c.msgtype for c in self._reader.connections}
            self.topics = self.requested.in_bag(present, self.path)
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close the underlying reader (idempotent)."""
        if self._open:
            self._reader.close()
            self._open = False

    def message_count(self) -> int:
        """Messages on the topics matched into frames (camera topics, and the pose topic unless from TF)."""
        wanted = set(self.topics.types())
        return sum(c.msgcount for c in self._reader.connections if c.topic in wanted)

    def frames(self) -> Iterator[BagFrame]:
        """Yield complete frames in the order they complete (stamp order for bags from :func:`write_bag`)."""
        for stamp, parts, T_wc in self._matched():
            try:
                frame = self._convert(stamp, parts, T_wc)
            except InputError as exc:
                if not self.skip_refused:
                    raise
                self.refused_stamps.append(stamp)
                self.last_refusal = str(exc)
                self._refusals[f"{exc.where.split(' @ ', 1)[0]}: {exc.problem}"] += 1
                continue
            self.frames_read += 1
            yield frame

    @property
    def refused(self) -> int:
        """How many frames were refused (``skip_refused``): :attr:`refused_stamps`."""
        return len(self.refused_stamps)

    @property
    def refusal_reasons(self) -> str:
        """Each distinct reason frames were refused for, with its count, the most frequent first ("" if none): a bag
        with five kinds of bad depth image said only the last one's.
        """
        return refusal_summary(self._refusals)

    def stamps(self) -> Iterator[int]:
        """The stamps of the frames :meth:`frames` would read (matched and posed), their images not decoded."""
        for stamp, _, _ in self._matched():
            yield stamp

    def _matched(self) -> Iterator[tuple[int, dict[str, tuple[Any, bytes]], np.ndarray | None]]:
        """:meth:`_completed` without the frames whose stamp was read before (counted), those going back counted."""
        seen: set[int] = set()
        last: int | None = None
        for stamp, parts, T_wc in self._completed():
            if stamp in seen:
                self.repeated_stamps.append(stamp)
                continue
            if last is not None and stamp < last:
                self.stamps_back += 1
                if self.first_back is None:
                    self.first_back = (len(seen), stamp, last)
            seen.add(stamp)
            last = stamp
            yield stamp, parts, T_wc

    def _completed(self) -> Iterator[tuple[int, dict[str, tuple[Any, bytes]], np.ndarray | None]]:
        """``(stamp, {topic: (connection, raw)}, T_wc or None)`` of each complete frame TF poses, as it completes."""
        if not self._open:
            raise RuntimeError("BagReader.frames() needs an open reader: use it in a `with` block")
        t = self.topics
        frame_topics, tf_topics = t.types(), t.tf_types()
        conns = [c for c in self._reader.connections if c.topic in frame_topics or c.topic in tf_topics]
        matcher: StampMatcher[tuple[Any, bytes]] = StampMatcher(frame_topics, MAX_PENDING_STAMPS)
        tf = TransformBuffer(tolerance_s=t.tf_tolerance_s) if t.uses_tf else None
        waiting: deque[tuple[int, dict[str, tuple[Any, bytes]]]] = deque()
        for conn, _, raw in self._reader.messages(connections=conns):
            if tf is not None and conn.topic in tf_topics:
                self._add_tf(tf, conn, raw)
                yield from self._posed(tf, waiting, final=False)
                continue
            try:
                stamp = header_stamp_ns(raw)
            except (struct.error, IndexError):
                raise InputError(f"{self.path}:{conn.topic}", "message too short to hold a header") from None
            parts = matcher.add(stamp, conn.topic, (conn, raw))
            self.skipped_frames = matcher.dropped
            if parts is None:
                continue
            if tf is None:
                yield stamp, parts, None
                continue
            waiting.append((stamp, parts))
            yield from self._posed(tf, waiting, final=False)
        if tf is not None:
            yield from self._posed(tf, waiting, final=True)
        matcher.flush()
        self.skipped_frames = matcher.dropped

    def _add_tf(self, tf: TransformBuffer, conn: Any, raw: bytes) -> None:
        where = f"{self.path}:{conn.topic}"
        try:
            msg = self._reader.deserialize(raw, conn.msgtype)
        except AnyReaderError as exc:
            raise InputError(where, f"cannot deserialize TF message: {exc}") from None
        errors = tf.add_message(msg, static=conn.topic == self.topics.tf_static_topic, where=where)
        self.tf_rejected += len(errors)
        if errors:
            self.last_tf_error = str(errors[-1])
        self.tf_reparented, self.tf_reparent_note = tf.reparented, tf.reparent_note

    def _posed(
        self, tf: TransformBuffer, waiting: deque[tuple[int, dict[str, tuple[Any, bytes]]]], final: bool
    ) -> Iterator[tuple[int, dict[str, tuple[Any, bytes]], np.ndarray]]:
        """Frames of ``waiting`` (oldest first) whose pose TF now gives; those it never will are counted and dropped."""
        t = self.topics
        while waiting:
            stamp, parts = waiting[0]
            if tf.child_hint is None:  # once: the first frame's header says the frame the images are in
                tf.child_hint = child_frame_hint(header_frame_id(parts[t.color][1]), t.tf_child_frame)
            try:
                T_wc = tf.lookup(t.tf_parent_frame, t.tf_child_frame, stamp)
            except TransformUnavailableError as exc:
                if exc.retry and not final and len(waiting) <= MAX_PENDING_STAMPS:
                    return
                waiting.popleft()
                self.no_tf += 1
                self.last_tf_error = str(exc)
                continue
            waiting.popleft()
            if not self._child_checked:  # once: the first posed frame's images against the frame TF gave
                self._child_checked = True
                image_frame = header_frame_id(parts[t.color][1])
                self.child_frame_note = child_frame_mismatch(
                    tf, t.tf_parent_frame, t.tf_child_frame, image_frame, stamp, T_wc
                )
            yield stamp, parts, T_wc

    def _convert(self, stamp: int, parts: dict[str, tuple[Any, bytes]], T_wc: np.ndarray | None) -> BagFrame:
        t = self.topics

        def msg(topic: str) -> Any:
            conn, raw = parts[topic]
            try:
                return self._reader.deserialize(raw, conn.msgtype)
            except AnyReaderError as exc:
                raise InputError(f"{self.path}:{topic}", f"cannot deserialize message at {stamp} ns: {exc}") from None

        def where(topic: str) -> str:
            return f"{self.path}:{topic} @ {stamp} ns"

        pose = T_wc if T_wc is not None else msg(t.pose)
        source = f"{self.path}:{t.tf_topic if T_wc is not None else t.pose}"
        return assemble_frame(stamp, msg(t.color), msg(t.depth), msg(t.camera_info), pose, t, where, source)


def assemble_images(
    color_msg: Any, depth_msg: Any, info_msg: Any, topics: CameraTopics | None = None, where: Callable[[str], str] = str
) -> tuple[np.ndarray, np.ndarray, Intrinsics]:
    """``(rgb [H, W, 3] uint8, depth_m [H, W] float32, intrinsics)`` of one stamp; InputError if sizes disagree."""
    t = topics or CameraTopics()
    rgb = image_to_rgb(color_msg, where(t.color))
    depth_m = image_to_depth_m(depth_msg, where(t.depth))
    intr = camera_info_to_intrinsics(info_msg, where(t.camera_info))
    h, w = depth_m.shape
    if rgb.shape[:2] != (h, w) or (intr.width, intr.height) != (w, h):
        sizes = f"colour {rgb.shape[1]}x{rgb.shape[0]}, depth {w}x{h}, camera info {intr.width}x{intr.height}"
        if rgb.shape[:2] == (h, w):  # the images agree: the camera info is the odd one out
            raise InputError(where(t.camera_info), f"sizes disagree: {sizes}; the camera info is another stream's or "
                             "resolution's: use the one recorded with these images")  # fmt: skip
        raise InputError(where(t.depth), f"sizes disagree: {sizes}; is the depth aligned to the colour (RealSense: "
                         "aligned_depth_to_color)?")  # fmt: skip
    return rgb, depth_m, intr


def assemble_frame(
    stamp_ns: int,
    color_msg: Any,
    depth_msg: Any,
    info_msg: Any,
    pose: Any,
    topics: CameraTopics | None = None,
    where: Callable[[str], str] = str,
    pose_source: str | None = None,
) -> BagFrame:
    """Convert the messages of one stamp into a :class:`BagFrame`, checking that sizes agree.

    ``pose`` is a ``PoseStamped`` (or ``Pose``) message, or the [4, 4] ``T_wc`` already looked up on TF.
    Shared by the bag reader and the ROS nodes; ``where(topic)`` names the source in errors,
    ``pose_source`` (default: the pose or TF topic) the stream in the once-only pose warning.
    """
    t = topics or CameraTopics()
    if isinstance(pose, np.ndarray):
        T_wc = load_pose(pose, where(t.tf_topic), pose_source if pose_source is not None else t.tf_topic)
    else:
        T_wc = pose_to_matrix(pose, where(t.pose), pose_source if pose_source is not None else t.pose)
    rgb, depth_m, intr = assemble_images(color_msg, depth_msg, info_msg, t, where)
    return BagFrame(stamp_ns=stamp_ns, rgb=rgb, depth_m=depth_m, T_wc=T_wc, intrinsics=intr)


def read_bag_frames(path: str | Path, topics: CameraTopics | None = None) -> tuple[list[BagFrame], int]:
    """All frames of a (small) bag in memory and the number of incomplete stamps skipped."""
    with BagReader(path, topics) as reader:
        frames = list(reader.frames())
        return frames, reader.skipped_frames


def bag_info(path: str | Path, topics: CameraTopics | None = None, decode: bool = True) -> dict[str, Any]:
    """Summary of a bag: topics with types and counts, time span, image size, encodings, frame count.

    ``frame_count`` counts the frames :class:`BagReader` reads with these topics (resolved against the bag
    when it has them): stamps carried by every topic matched into a frame, posed by the bag's TF messages
    when poses come from TF, and (``decode``) whose messages convert. ``frames_without_tf`` counts the
    complete stamps TF does not pose (None with poses from a topic), ``no_tf_reason`` says why (the last
    error); ``frames_refused`` the complete, posed frames whose messages do not convert (a JPEG depth image, sizes that
    disagree; None without ``decode``, whose count then includes them), ``refused_reason`` each distinct error with its
    count (:attr:`BagReader.refusal_reasons`); ``incomplete_stamps`` the other stamps. ``frames_repeating_stamp`` counts
    the frames skipped because a frame before them had their stamp; ``frames_stamped_back`` those stamped before the
    frame before them, ``first_stamped_back`` where the first is (both as :class:`BagReader` counts them).
    ``tf_reparented`` counts the TF frames that changed parent (None with poses from a topic; ``tf_reparent_note``
    says the first: two publishers of one frame move every pose through it, and nothing else shows it).
    ``frames_other_size`` counts the frames whose images are not the first frame's size, not in ``frame_count``
    (``roigsf map`` and the nodes refuse them; None without ``decode``), ``first_other_size`` names the first.
    ``missing_topics`` names each topic the bag lacks or holds with another type (empty when all are there; no
    frame is then complete, and the stamps of the topics it has count as incomplete); ``realsense_namespace``
    is then the namespace of a RealSense camera the bag does hold in full (:func:`realsense_topics`), else
    None. Image fields are None when the bag has no such topic; a compressed stream's encoding is its
    ``format``. ``gt_mesh``: the bag's ground-truth mesh (:func:`~roigsf_ros.data.replica.scene_gt_mesh`, what
    ``roigsf map``, ``bench`` and ``demo`` score against), else None.
    """
    requested = topics or CameraTopics()
    with opened_bag(path) as reader:
        conns = reader.connections
        counts: dict[str, dict[str, Any]] = {}
        for c in conns:
            entry = counts.setdefault(c.topic, {"type": c.msgtype, "count": 0})
            entry["count"] += c.msgcount
        present = {c.topic: c.msgtype for c in conns}
        t, missing = _topics_as_far_as_present(requested, present)  # counted as far as the bag has the topics
        frame_types = t.types()
        camera = [c for c in conns if c.topic in frame_types and c.msgtype == frame_types[c.topic]]
        first_msgs: dict[str, Any] = {}
        for c in camera:
            if c.msgtype in (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE) and c.topic not in first_msgs:
                for conn, _, raw in reader.messages(connections=[c]):
                    first_msgs[c.topic] = reader.deserialize(raw, conn.msgtype)
                    break
        any_message = sum(c.msgcount for c in conns) > 0
        first_ns = reader.start_time if any_message else None
        last_ns = reader.end_time - 1 if any_message else None  # rosbags' end is one past the last message
        if missing:  # no frame is complete: the stamps of the camera topics present are all incomplete
            # (none present: none; rosbags reads EVERY topic for an empty connection list, and /tf's TFMessages, which
            # have no header, counted as "166 incomplete stamps" of a 150-frame bag read with a wrong --realsense)
            stamps = reader.messages(connections=camera) if camera else ()
            incomplete = len({header_stamp_ns(raw) for _, _, raw in stamps})
    frames = refused = no_tf = repeated = back = reparented = 0
    reason = refusal = first_back = first_other = reparent_note = child_note = ""
    other: list[int] = []  # places (in the bag's order) of frames not at the first frame's size
    if not missing:
        with BagReader(path, requested, skip_refused=True) as frame_reader:
            if decode:
                read = [(f.intrinsics.width, f.intrinsics.height, f.stamp_ns) for f in frame_reader.frames()]
                other = [k for k, (w, h, _) in enumerate(read) if (w, h) != read[0][:2]]
                frames = len(read) - len(other)  # as roigsf map and the nodes count them
                if other:
                    (w0, h0, _), (w1, h1, stamp) = read[0], read[other[0]]
                    first_other = (
                        f"frame {other[0]} (in the bag's order) at {stamp / 1e9:.3f} s: {w1}x{h1}, not {w0}x{h0}"
                    )
            else:
                frames = sum(1 for _ in frame_reader.stamps())
            incomplete, no_tf, refused = frame_reader.skipped_frames, frame_reader.no_tf, frame_reader.refused
            reason, refusal = frame_reader.last_tf_error, frame_reader.refusal_reasons
            repeated, back = len(frame_reader.repeated_stamps), frame_reader.stamps_back
            reparented, reparent_note = frame_reader.tf_reparented, frame_reader.tf_reparent_note
            child_note = frame_reader.child_frame_note
            if frame_reader.first_back is not None:
                place, stamp, before = frame_reader.first_back
                first_back = f"frame {place} (in the bag's order) at {stamp / 1e9:.3f} s, after {before / 1e9:.3f} s"
    color, depth = first_msgs.get(t.color), first_msgs.get(t.depth)
    size = None
    for msg, convert, topic in ((color, image_to_rgb, t.color), (depth, image_to_depth_m, t.depth)):
        if msg is not None and size is None:
            if is_compressed(msg):
                try:
                    size = convert(msg, f"{path}:{topic}").shape[1::-1]
                except InputError:
                    size = None
            else:
                size = (int(msg.width), int(msg.height))
    mesh = scene_gt_mesh(Path(path))
    return {
        "path": str(path),
        "gt_mesh": None if mesh is None else str(mesh),
        "topics": counts,
        "message_count": sum(v["count"] for v in counts.values()),
        "start_ns": first_ns,
        "end_ns": last_ns,
        "duration_s": (last_ns - first_ns) / 1e9 if first_ns is not None and last_ns is not None else 0.0,
        "width": int(size[0]) if size is not None else None,
        "height": int(size[1]) if size is not None else None,
        "color_encoding": _encoding_of(color),
        "depth_encoding": _encoding_of(depth),
        "pose_source": t.pose_source,
        "frame_count": frames,
        "frames_without_tf": no_tf if t.uses_tf else None,
        "no_tf_reason": reason if t.uses_tf and no_tf else None,
        "tf_reparented": reparented if t.uses_tf else None,
        "tf_reparent_note": reparent_note or None,
        "tf_child_frame_note": child_note or None,
        "frames_refused": refused if decode else None,
        "refused_reason": refusal if decode and refused else None,
        "incomplete_stamps": incomplete,
        "frames_repeating_stamp": repeated,
        "frames_stamped_back": back,
        "first_stamped_back": first_back or None,
        "frames_other_size": len(other) if decode else None,
        "first_other_size": first_other or None,
        "missing_topics": missing,
        "realsense_namespace": _realsense_namespace(present) if missing else None,
    }


def _topics_as_far_as_present(requested: CameraTopics, present: dict[str, str]) -> tuple[CameraTopics, list[str]]:
    """``requested`` resolved against a bag's ``{topic: type}`` as far as it has the topics, and one line per
    topic it lacks or holds with another type (all that :meth:`CameraTopics.in_bag` refuses, not the first only),
    a missing one with the bag's similar topics.
    """

    def near(topic: str) -> str:
        similar = sorted(p for p in present if p.startswith(topic.rstrip("/") + "/") or topic.startswith(p + "/"))
        return f" (the bag has {', '.join(similar)})" if similar else ""

    topics, problems = requested.against(present)
    return topics, [text.removesuffix(" from the bag") + near(topic) if missing else f"{topic} {text}"
                    for topic, text, missing in problems]  # fmt: skip


def _realsense_namespace(present: dict[str, str]) -> str | None:
    """The namespace of a RealSense camera (:func:`realsense_topics`, auto transports) a bag's ``{topic: type}``
    holds in full, TF included, or None: what ``--realsense`` would read.
    """
    marker = "/aligned_depth_to_color/image_raw"
    for ns in sorted({topic.split(marker)[0] for topic in present if marker in topic}):
        try:
            realsense_topics(ns or "/", color_transport=AUTO, depth_transport=AUTO).in_bag(present, "bag")
        except InputError:
            continue
        return ns or "/"
    return None


def _encoding_of(msg: Any) -> str | None:
    if msg is None:
        return None
    return str(msg.format) if is_compressed(msg) else str(msg.encoding)


__all__ = [
    "AUTO",
    "BAG_MARKS",
    "CAMERA_FRAME_ID",
    "CAMERA_INFO_TOPIC",
    "CAMERA_INFO_TYPE",
    "CHILD_FRAME_TOLERANCE",
    "COLOR_ENCODINGS",
    "COLOR_TOPIC",
    "COLOR_TRANSPORTS",
    "COMPRESSED_DEPTH_HEADER_BYTES",
    "COMPRESSED_IMAGE_TYPE",
    "DEFAULT_RATE_HZ",
    "DEFAULT_T0_NS",
    "DEPTH_ENCODINGS",
    "DEPTH_TOPIC",
    "DEPTH_TRANSPORTS",
    "IMAGE_TYPE",
    "MAP_FRAME_ID",
    "MAX_PENDING_STAMPS",
    "POSE_SOURCES",
    "POSE_TOPIC",
    "POSE_TYPE",
    "QOS_RELIABLE",
    "SAMPLE_BAG",
    "SAMPLE_GT_MESH",
    "TYPESTORE",
    "BagFrame",
    "BagReader",
    "CameraTopics",
    "assemble_frame",
    "assemble_images",
    "bag_info",
    "bag_topic_types",
    "camera_info_fields",
    "camera_info_msg",
    "camera_info_to_intrinsics",
    "child_frame_hint",
    "child_frame_mismatch",
    "compressed_to_depth_m",
    "compressed_to_rgb",
    "depth_to_image_data",
    "encode_compressed_depth",
    "encode_compressed_rgb",
    "frame_stamp_ns",
    "header_frame_id",
    "header_msg",
    "header_stamp_ns",
    "image_to_depth_m",
    "image_to_rgb",
    "is_compressed",
    "open_any_reader",
    "opened_bag",
    "pose_to_matrix",
    "read_bag_frames",
    "realsense_topics",
    "refusal_summary",
    "resized_frame",
    "sample_path",
    "staged_bag",
    "stamp_to_ns",
    "transport_topic",
    "write_bag",
]
