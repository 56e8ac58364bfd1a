"""Camera input shared by the nodes: the camera's topics matched by stamp into validated, downscaled frames.

Colour and depth come as ``sensor_msgs/Image`` or ``CompressedImage`` (image_transport's ``compressed``
and ``compressedDepth``), and the pose as a ``geometry_msgs/PoseStamped`` or from TF (``/tf`` +
``/tf_static``, :class:`roigsf_ros.data.tf.TransformBuffer`) at the frame's stamp
(:class:`roigsf_ros.data.bags.CameraTopics` says which). Messages are converted with the library's
converters (:mod:`roigsf_ros.data.bags`) and matched with :class:`roigsf_ros.data.sync.FrameLedger`,
which accounts for every frame sent exactly once in bounded counters. Each frame is downscaled on
arrival to ``input_size`` (intrinsics scaled with pixel centres kept aligned), so a 640x480 30 Hz
camera costs the nodes only the mapping resolution in memory and work.

Bad messages (unsupported encoding, size mismatch with the camera info, NaN pose, truncated JPEG, ...)
are dropped with a throttled warning and counted by a short reason category; frames that never
complete (e.g. depth without colour) are dropped and counted once the bounded queue overflows; repeated
stamps and stamps gone back are counted, not delivered, with a throttled warning too; frames that never
arrived at all (every message overwritten in a full middleware queue, which the middleware does not
report) are estimated from gaps in the stamps (:class:`roigsf_ros.data.sync.StampGapCounter`). With
poses from TF, a complete frame waits (at most ``tf_wait_frames`` frames, at most ``tf_wait_s``) until TF
gives its pose, else it is dropped and counted as ``no_tf``.

A topic that delivers nothing is named in a warning with what the ROS graph suggests instead (the topic under
another transport, ``/tf`` for a pose topic, a publisher whose QoS does not match), so a wrong transport, a typo
or a best-effort camera (``camera_reliability``) is not a silent node.
"""

from __future__ import annotations

import importlib
import math
import re
import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.callback_groups import CallbackGroup
from rclpy.event_handler import QoSRequestedIncompatibleQoSInfo, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSPolicyKind, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from roigsf_ros.core.camera import Intrinsics, load_pose
from roigsf_ros.core.errors import InputError
from roigsf_ros.data.bags import (
    AUTO,
    CAMERA_INFO_TYPE,
    COLOR_TRANSPORTS,
    COMPRESSED_IMAGE_TYPE,
    DEPTH_TRANSPORTS,
    IMAGE_TYPE,
    POSE_TYPE,
    BagFrame,
    CameraTopics,
    assemble_frame,
    assemble_images,
    child_frame_hint,
    child_frame_mismatch,
    resized_frame,
    stamp_to_ns,
    transport_topic,
)
from roigsf_ros.data.sync import FrameLedger, StampGapCounter
from roigsf_ros.data.tf import DEFAULT_CACHE_S, TransformBuffer, TransformUnavailableError

WARN_THROTTLE_S = 5.0
"""At most one dropped-frame warning in this many seconds (counters keep every drop)."""


class ThrottleByKind:
    """At most one warning per ``WARN_THROTTLE_S`` for each kind of fault: one throttle for all hid a second fault
    behind the first (a bad pose after a bad encoding, a NaN pose after an empty candidate list). Not locked: callers
    ask under their own lock.
    """

    def __init__(self, period_s: float = WARN_THROTTLE_S) -> None:
        self.period_s = period_s
        self._last: dict[str, float] = {}  # kind -> when it was last said

    def due(self, kind: str) -> bool:
        """Whether a warning of ``kind`` may be said now (and if so, note that it is)."""
        now = time.monotonic()
        if now - self._last.get(kind, -math.inf) < self.period_s:
            return False
        self._last[kind] = now
        return True


def parameter_words(text: object) -> str:
    """A data-layer message in a node's words: "set tf_child_frame / --tf-child-frame to ..." names the parameter
    only, as a node has parameters, not the command line's options (the library's TF messages name both).
    """
    return re.sub(r" / --[a-z][a-z-]*", "", str(text))


def tf_fault_kind(exc: InputError) -> str:
    """What kind of fault a refused transform has: its problem without the frame names and numbers in it."""
    return re.sub(r"'[^']*'|\[[^\]]*\]|-?\d[\d.e+-]*|nan|inf", "#", exc.problem)


REMEMBERED_REJECTIONS = 256
"""How many refused frames' stamps the input remembers with their reason (:meth:`CameraInput.rejection_of`)."""
TF_EXPIRE_PERIOD_S = 0.1
"""How often frames waiting for their pose on TF are checked against ``tf_wait_s``."""
INPUT_CHECK_PERIOD_S = 5.0
"""How often the input looks for subscribed topics that delivered nothing (:meth:`CameraInput.silent_topics`)."""
SILENT_WARN_S = 30.0
"""At most one warning about silent topics in this many seconds."""
FLOW_GRACE_S = 3.0
"""A topic with a publisher is "silent" only this long after another of the input's topics first delivered: a
robot's bag starts its /tf 0.2 s before its images, and the check that came between said the images never arrived."""
CAMERA_RELIABILITIES = ("reliable", "best_effort")
"""``camera_reliability``: what the camera subscriptions ask for. A reliable one never matches a best-effort
publisher (many camera drivers publish sensor data best effort); a best-effort one matches both, but may lose
frames under load."""
_MESSAGE_CLASSES: dict[str, type] = {
    IMAGE_TYPE: Image,
    COMPRESSED_IMAGE_TYPE: CompressedImage,
    CAMERA_INFO_TYPE: CameraInfo,
    POSE_TYPE: PoseStamped,
}


def reject_reason(exc: InputError, topics: CameraTopics) -> str:
    """The short, bounded category of a frame's conversion error (counters are keyed by it, not by its text)."""
    if isinstance(exc, TransformUnavailableError):
        return "no_tf"
    problem = exc.problem
    if "encoding" in problem:
        return "bad_encoding"
    if "sizes disagree" in problem:
        return "size_mismatch"
    source = exc.where.split(" @ ", 1)[0]  # errors name "<topic> @ <stamp> ns"
    reasons = {topics.color: "bad_image", topics.depth: "bad_image", topics.camera_info: "bad_camera_info"}
    reasons |= {topics.pose: "bad_pose", topics.tf_topic: "bad_pose"}
    if source in reasons:
        return reasons[source]
    return "other"


def tf_message_class() -> type:
    """``tf2_msgs.msg.TFMessage``; InputError saying how to get it when it is not installed."""
    try:
        return importlib.import_module("tf2_msgs.msg").TFMessage
    except (ImportError, AttributeError):
        raise InputError(
            "parameter 'pose_source'",
            "tf needs the tf2_msgs message package: run scripts/setup.sh (it builds vendor/tf2_msgs when "
            "a full ROS install does not provide it)",
        ) from None


def tf_static_qos() -> QoSProfile:
    """What tf2's static listener asks for: reliable, transient local (latched), keep-last 100."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=100,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def tf_qos() -> QoSProfile:
    """What tf2's listener asks for on ``/tf``: reliable, volatile, keep-last 100."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=100,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def camera_qos(depth: int, reliability: str = "reliable") -> QoSProfile:
    """The camera subscriptions' QoS: keep-last ``depth``, volatile, ``reliability`` (one of CAMERA_RELIABILITIES)."""
    if reliability not in CAMERA_RELIABILITIES:
        raise InputError("parameter 'camera_reliability'", f"'{reliability}' is not one of reliable, best_effort")
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE,
    )


_TOPIC_FIELDS = ("color", "depth", "camera_info", "pose", "tf_topic", "tf_static_topic")


def remapped_topics(node: Node, topics: CameraTopics) -> CameraTopics:
    """``topics`` as ``node`` reads them: expanded in its namespace and remapped (``-r /camera/color/image_raw:=...``),
    so that its logs, status and graph checks name the topics it subscribes to (they named the parameters' values).
    """
    return replace(
        topics, **{f: node.resolve_topic_name(getattr(topics, f)) for f in _TOPIC_FIELDS if getattr(topics, f)}
    )


def describe_topics(topics: CameraTopics) -> str:
    """One line naming what a camera input reads: topics with their transports, and where the pose comes from."""
    t = topics.resolved()
    pose = (
        f"pose from TF {t.tf_parent_frame} -> {t.tf_child_frame} ({t.tf_topic}, {t.tf_static_topic})"
        if t.uses_tf
        else f"pose {t.pose}"
    )
    return (
        f"colour {t.color} ({t.color_transport}), depth {t.depth} ({t.depth_transport}), info {t.camera_info}, {pose}"
    )


@dataclass(frozen=True)
class CameraSettings:
    """How a node reads its camera: topics, transports and pose source, the mapping size, the TF wait."""

    topics: CameraTopics
    input_size: tuple[int | None, int | None] | None = None
    """(width, height) frames are downscaled to on arrival; None keeps the camera's size, one None its aspect."""
    tf_wait_s: float = 1.0
    """Seconds a complete frame waits for its pose on TF before it is dropped (``no_tf``)."""
    reliability: str = "reliable"
    """What the camera subscriptions ask for (CAMERA_RELIABILITIES; ``camera_reliability``)."""
    tf_wait_frames: int = 64
    """At most this many complete frames wait for their pose on TF (the oldest beyond is dropped, ``no_tf``): 64 are
    2.1 s at 30 Hz, so ``tf_wait_s`` (1 s) decides (16 were 0.53 s, and a robot whose TF came 0.7 s late lost every
    frame)."""
    tf_cache_s: float = DEFAULT_CACHE_S
    """Seconds of TF history kept behind the newest transform (tf2's cache time; a replay as fast as possible
    sends the whole bag's /tf before the images are decoded, so it needs the bag's length)."""
    pending_frames: int = 64
    """At most this many stamps wait for their other messages (the oldest beyond is dropped, counted incomplete): 64
    are 2.1 s at 30 Hz (a fixed 16 were 0.53 s, and a pose topic from a VIO node 20 frames behind the images lost 44
    of 60 frames)."""


@dataclass
class _AwaitingPose:
    """A converted frame waiting for its pose on TF."""

    stamp_ns: int
    rgb: np.ndarray  # [H, W, 3] uint8
    depth_m: np.ndarray  # [H, W] float32 metres
    intrinsics: Intrinsics
    since: float  # time.monotonic() when it completed
    image_frame: str = ""  # the colour image's header frame_id (child_frame_mismatch)


def camera_status(stats: dict[str, Any]) -> dict[str, Any]:
    """The fields of a camera node's ``~/status`` from :meth:`CameraInput.stats`: refusals, queues, stamps and TF (a TF
    child frame apart from the images', frames that changed parent, refused transforms, the last refusal), which the
    nodes logged but their status left out: a wrong ``tf_child_frame`` looked healthy there.
    """
    return {
        "frames_rejected": stats["rejected"],
        "frames_pending": stats["pending"],
        "messages_received": stats["received"],
        "qos_incompatible": stats["qos_incompatible"],
        "frames_awaiting_tf": stats["awaiting_tf"],
        "frames_dropped_incomplete": stats["dropped_incomplete"],
        "frames_duplicate_stamp": stats["duplicate_stamp"],
        "frames_out_of_order": stats["out_of_order"],
        "frames_missed_estimate": stats["frames_missed_estimate"],
        "tf_child_frame_note": stats["tf_child_frame_note"],
        "tf_reparented": stats["tf_reparented"],
        "tf_rejected": stats["tf_rejected"],
        "last_rejection": stats["last_rejection"],
    }


class CameraInput:
    """Subscribes ``node`` to an RGB-D camera's topics and calls ``on_frame`` with each complete frame."""

    def __init__(
        self,
        node: Node,
        on_frame: Callable[[BagFrame], None],
        qos: QoSProfile,
        topics: CameraTopics | None = None,
        max_pending: int = 64,
        callback_group: CallbackGroup | None = None,
        input_size: tuple[int | None, int | None] | None = None,
        tf_wait_s: float = 1.0,
        tf_cache_s: float = DEFAULT_CACHE_S,
        tf_wait_frames: int = 64,
        subscribe: bool = True,
    ) -> None:
        self.node = node
        self.on_frame = on_frame
        requested = topics or CameraTopics()
        for name in ("color_transport", "depth_transport"):
            if getattr(requested, name) == AUTO:
                raise InputError(f"parameter '{name}'", "'auto' is for bags; name the transport of a live topic")
        given = requested.resolved()
        self.topics = remapped_topics(node, given)
        self._given_names = {getattr(self.topics, f): getattr(given, f) for f in _TOPIC_FIELDS if getattr(given, f)}
        """Each topic as subscribed -> as the parameter gives it: the subscriptions are created with the parameter's
        name, which rcl remaps once; created with the remapped name, a chain of rules (``a:=b b:=c``) went a step
        further than ROS goes."""
        self.input_size = input_size
        self.tf_wait_s = float(tf_wait_s)
        self.max_pending = int(max_pending)
        self.tf_wait_frames = int(tf_wait_frames)
        self._started = time.monotonic()
        self.received: Counter[str] = Counter()
        """Messages received per topic (every subscribed topic listed, 0 until its first message)."""
        self._in_callback = 0  # messages received whose callback (and the frame it completed) is still running
        self.tf_rejected = 0
        """Transforms refused on the TF topics (bad values); the rest of their messages is kept."""
        self.child_frame_note = ""
        """Why the poses are not the images' (``tf_child_frame`` another frame than theirs), from the first posed frame;
        warned once and kept in :meth:`stats`."""
        self._child_checked = False
        self._child_warned = False
        self.last_rejection = ""
        """The full text of the last frame's conversion error (the counters hold only its category)."""
        self._ledger: FrameLedger[Any] = FrameLedger(self.topics.types(), max_pending)
        self._gaps = {topic: StampGapCounter() for topic in self.topics.types()}
        self.qos_incompatible: Counter[str] = Counter()
        """Publishers per topic this input could not match for their QoS (rclpy's incompatible-QoS event)."""
        self._lock = threading.Lock()
        self._tf: TransformBuffer | None = None
        self._awaiting: deque[_AwaitingPose] = deque()
        self._last_silent_warning = -float("inf")
        self._first_flow: float | None = None
        """When a message first came on any of the input's topics (:data:`FLOW_GRACE_S`)."""
        self._reject_warnings = ThrottleByKind()  # by reason category
        self._tf_warnings = ThrottleByKind()  # by kind of refused transform (tf_fault_kind)
        self._rejections: OrderedDict[int, str] = OrderedDict()  # stamp -> why, the newest REMEMBERED_REJECTIONS
        self._qos = qos
        self._group = callback_group
        self._tf_cache_s = tf_cache_s
        self.subscribed = False
        """Whether the subscriptions exist (``subscribe=False`` defers them to :meth:`subscribe`)."""
        if subscribe:
            self.subscribe()

    @classmethod
    def of_settings(
        cls,
        node: Node,
        on_frame: Callable[[BagFrame], None],
        settings: CameraSettings,
        qos_depth: int,
        callback_group: CallbackGroup | None = None,
        subscribe: bool = True,
    ) -> CameraInput:
        """A node's camera input as its camera parameters say (``settings``, from ``camera_params``): topics, QoS
        (keep-last ``qos_depth``, the settings' reliability), mapping size and TF wait.
        """
        return cls(
            node,
            on_frame,
            camera_qos(qos_depth, settings.reliability),
            settings.topics,
            callback_group=callback_group,
            input_size=settings.input_size,
            tf_wait_s=settings.tf_wait_s,
            tf_cache_s=settings.tf_cache_s,
            tf_wait_frames=settings.tf_wait_frames,
            max_pending=settings.pending_frames,
            subscribe=subscribe,
        )

    def subscribe(self) -> None:
        """Create the camera's subscriptions (once): a node that must not read frames before its outputs are
        connected (the keyframe selector) creates the input with ``subscribe=False`` and calls this later.
        """
        if self.subscribed:
            return
        self.subscribed = True
        self._started = time.monotonic()
        node, qos, callback_group = self.node, self._qos, self._group
        t = self.topics
        for topic, type_name in t.types().items():
            cls = _MESSAGE_CLASSES[type_name]
            events = SubscriptionEventCallbacks(incompatible_qos=self._incompatible_callback_for(topic, qos))
            node.create_subscription(
                cls,
                self._given_names.get(topic, topic),
                self._callback_for(topic),
                qos,
                callback_group=callback_group,
                event_callbacks=events,
            )
        if t.uses_tf:
            tf_cls = tf_message_class()
            self._tf = TransformBuffer(cache_s=self._tf_cache_s, tolerance_s=t.tf_tolerance_s)
            for topic, static, tqos in ((t.tf_topic, False, tf_qos()), (t.tf_static_topic, True, tf_static_qos())):
                node.create_subscription(
                    tf_cls,
                    self._given_names.get(topic, topic),
                    self._tf_callback_for(topic, static),
                    tqos,
                    callback_group=callback_group,
                )
            expire = lambda: self._counted(self._expire_awaiting)  # noqa: E731 - it delivers frames: counted too
            node.create_timer(TF_EXPIRE_PERIOD_S, expire, callback_group=callback_group)
        with self._lock:
            self.received.update(dict.fromkeys(self.subscribed_topics(), 0))
        node.create_timer(INPUT_CHECK_PERIOD_S, self._check_inputs, callback_group=callback_group)

    @property
    def frames(self) -> int:
        """Frames delivered to ``on_frame``."""
        with self._lock:
            return self._ledger.frames - len(self._awaiting)

    @property
    def dropped_incomplete(self) -> int:
        """Stamps given up because one of their messages never came."""
        with self._lock:
            return self._ledger.dropped_incomplete

    def stats(self) -> dict[str, Any]:
        """Counters for reports; every frame sent is in exactly one of the frame counters.

        Frames: ``frames`` (delivered), ``rejected`` (by reason category, ``no_tf`` included),
        ``awaiting_tf`` (complete, waiting for their pose on TF), ``dropped_incomplete``, ``pending``,
        ``duplicate_stamp``, ``out_of_order`` and ``frames_missed_estimate`` (none of its messages
        arrived: stamp gaps) -- see :class:`roigsf_ros.data.sync.FrameLedger`. Messages: ``received``
        and ``missed_estimate`` (estimated lost before they arrived) per topic; ``tf_rejected``; ``tf_reparented``
        (TF frames that changed parent: the poses through them moved); ``tf_child_frame_note`` (the poses are another
        frame's than the images', :func:`~roigsf_ros.data.bags.child_frame_mismatch`); ``in_callback``,
        callbacks still running that may deliver a frame (a message's, counted in ``received`` first, or the TF
        expiry timer's), with the ``on_frame`` calls they make.
        """
        with self._lock:
            counts = self._ledger.counts()
            awaiting = len(self._awaiting)
            return {
                "received": dict(self.received),
                "in_callback": self._in_callback,
                "frames": counts["frames"] - awaiting,
                "rejected": counts["rejected"],
                "awaiting_tf": awaiting,
                "dropped_incomplete": counts["dropped_incomplete"],
                "pending": counts["pending"],
                "duplicate_stamp": counts["duplicate_stamp"],
                "out_of_order": counts["out_of_order"],
                "frames_missed_estimate": counts["missed_estimate"],
                "missed_estimate": {topic: g.missed for topic, g in self._gaps.items()},
                "tf_rejected": self.tf_rejected,
                "tf_reparented": 0 if self._tf is None else self._tf.reparented,
                "tf_child_frame_note": self.child_frame_note,
                "last_rejection": self.last_rejection,
                "qos_incompatible": dict(self.qos_incompatible),
            }

    def subscribed_topics(self) -> list[str]:
        """The topics a frame needs messages from: colour, depth, camera info, and the pose topic or /tf."""
        t = self.topics
        return [*t.types(), *([t.tf_topic] if t.uses_tf else [])]

    def silent_topics(self) -> dict[str, str]:
        """Each subscribed topic that delivered nothing yet -> why, as far as the ROS graph tells, with the fix.

        At once where the graph says something is off: another of the camera's topics delivers, a publisher is on
        the topic but its messages do not come (QoS), or the topic's stream is published under another name
        this input could read (another transport; ``/tf`` beside a pose topic); a topic with no publisher and
        nothing better to read only once the input has waited SILENT_WARN_S (a camera starting up).
        """
        with self._lock:
            received = Counter(self.received)
            incompatible = Counter(self.qos_incompatible)
            flow_started = math.inf if self._first_flow is None else self._first_flow
        silent = [topic for topic in self.subscribed_topics() if received[topic] == 0]
        if not silent:
            return {}
        published = {name: types for name, types in self.node.get_topic_names_and_types()}
        flowing = sorted(topic for topic in self.subscribed_topics() if received[topic] > 0)
        t = self.topics
        out: dict[str, str] = {}
        for topic in silent:
            publishers = self.node.count_publishers(topic)
            if incompatible[topic]:
                why = (f"{incompatible[topic]} publisher(s) with a QoS this subscription cannot match (most often a "
                       "best-effort camera: set camera_reliability: best_effort)")  # fmt: skip
            elif publishers:
                if not flowing or time.monotonic() - flow_started < FLOW_GRACE_S:
                    continue  # the publisher may not have started sending (a player waiting for subscribers)
                why = f"{publishers} publisher(s) on it, but no message has arrived"
            else:
                why = "no publisher"
                hint = self._elsewhere(topic, published)
                if hint:
                    why += f"; {hint}"
                elif not flowing and time.monotonic() - self._started < SILENT_WARN_S:
                    continue  # nothing at all yet, and nothing better to read: the camera may not have started
            if flowing and topic != t.tf_topic:
                why += f" (while {', '.join(flowing)} delivered)"
            out[topic] = why
        return out

    def _elsewhere(self, topic: str, published: dict[str, list[str]]) -> str:
        """Where the stream of a silent ``topic`` seems to be published instead, with the parameter to set; or ""."""
        t = self.topics
        for stream, transports in (("color", COLOR_TRANSPORTS), ("depth", DEPTH_TRANSPORTS)):
            if topic != getattr(t, stream):
                continue
            base = topic
            for suffix in ("/compressed", "/compressedDepth"):
                base = base.removesuffix(suffix)
            for transport in transports:
                other = transport_topic(base, transport)
                if other != topic and other in published and self.node.count_publishers(other):
                    return f"{other} is published: set {stream}_transport: {transport}"
        if topic == t.pose and t.tf_topic in published and self.node.count_publishers(t.tf_topic):
            return f"{t.tf_topic} is published: set pose_source: tf (with tf_parent_frame and tf_child_frame)"
        return ""

    def _check_inputs(self) -> None:
        """Warn (throttled) about subscribed topics that deliver nothing, naming why and what to set."""
        now = time.monotonic()
        if now - self._last_silent_warning < SILENT_WARN_S:
            return
        silent = self.silent_topics()
        if silent:
            self._last_silent_warning = now
            listed = "; ".join(f"{topic}: {why}" for topic, why in silent.items())
            self.node.get_logger().warning(f"nothing received on {listed}")

    def _incompatible_callback_for(self, topic: str, qos: QoSProfile) -> Callable[[Any], None]:
        def callback(info: QoSRequestedIncompatibleQoSInfo) -> None:
            with self._lock:
                self.qos_incompatible[topic] = info.total_count
            policy = QoSPolicyKind(info.last_policy_kind).name
            asked = qos.reliability.name.lower()
            self.node.get_logger().warning(
                f"{topic}: a publisher's QoS does not match this subscription ({policy}; it asks {asked}): its "
                "messages never arrive; a best-effort camera needs camera_reliability: best_effort",
                throttle_duration_sec=WARN_THROTTLE_S,
            )

        return callback

    def _callback_for(self, topic: str) -> Callable[[Any], None]:
        def callback(msg: Any) -> None:
            self._counted(self._on_message, topic, msg)

        return callback

    def _tf_callback_for(self, topic: str, static: bool) -> Callable[[Any], None]:
        def callback(msg: Any) -> None:
            self._counted(self._on_tf, topic, static, msg)

        return callback

    def _counted(self, handler: Callable[..., None], *args: Any) -> None:
        """Run a handler (a message's, or the timer's that delivers frames TF posed late), counted in ``in_callback``
        from before its ``received`` count to its end (with the ``on_frame`` calls it makes).
        """
        with self._lock:
            self._in_callback += 1
        try:
            handler(*args)
        finally:
            with self._lock:
                self._in_callback -= 1

    def _on_message(self, topic: str, msg: Any) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        with self._lock:
            self.received[topic] += 1
            self._first_flow = self._first_flow or time.monotonic()
            self._gaps[topic].add(stamp)
            dropped_before = self._ledger.dropped_incomplete
            stamps_before = (self._ledger.duplicate_stamp, self._ledger.out_of_order)
            parts = self._ledger.add(stamp, topic, msg)
            dropped = self._ledger.dropped_incomplete
            repeated, back = self._ledger.duplicate_stamp, self._ledger.out_of_order
        # Counted in ~/status; said once in a while, as other drops are (one call each: throttled apart).
        when = f"{stamp // 1_000_000_000}.{stamp % 1_000_000_000:09d}" if (repeated, back) != stamps_before else ""
        if repeated != stamps_before[0]:
            self.node.get_logger().warning(
                f"dropped frame at stamp {when} s on {topic}: it repeats the stamp of a frame already "
                f"received ({repeated} so far; complete or not: each stamp is read once, so a bag played again into "
                "a running node repeats every stamp)",
                throttle_duration_sec=WARN_THROTTLE_S,
            )
        if back != stamps_before[1]:
            self.node.get_logger().warning(
                f"dropped frame at stamp {when} s on {topic}: it is older than a frame already "
                f"delivered, the stamps went back ({back} so far)",
                throttle_duration_sec=WARN_THROTTLE_S,
            )
        if dropped > dropped_before:  # rare: only then look for the topics that never delivered
            with self._lock:
                missing = [name for name in self.topics.types() if self.received[name] == 0]
            why = f"nothing ever received on {', '.join(missing)}" if missing else "one of their messages never came"
            self.node.get_logger().warning(
                f"{dropped} incomplete frame(s) dropped so far (more than {self.max_pending} waiting, pending_frames): "
                f"{why}",
                throttle_duration_sec=WARN_THROTTLE_S,
            )
        if parts is None:
            return
        t = self.topics

        def where(name: str) -> str:
            return f"{name} @ {stamp} ns"

        try:
            if self._tf is None:
                frame = self._downscale(
                    assemble_frame(stamp, parts[t.color], parts[t.depth], parts[t.camera_info], parts[t.pose], t, where)
                )
            else:
                rgb, depth_m, intr = assemble_images(parts[t.color], parts[t.depth], parts[t.camera_info], t, where)
                small = self._downscale(BagFrame(stamp, rgb, depth_m, np.eye(4), intr))
                awaiting = _AwaitingPose(stamp, small.rgb, small.depth_m, small.intrinsics, time.monotonic(),
                                         str(parts[t.color].header.frame_id))  # fmt: skip
        except InputError as exc:
            self._reject(exc, stamp)
            return
        if self._tf is None:
            self.on_frame(frame)
            return
        with self._lock:
            self._awaiting.append(awaiting)
            if self._tf.child_hint is None:  # once: an unknown tf_child_frame's error names the images' frame
                self._tf.child_hint = child_frame_hint(parts[t.color].header.frame_id, t.tf_child_frame)
        self._deliver_posed()

    def _on_tf(self, topic: str, static: bool, msg: Any) -> None:
        assert self._tf is not None
        with self._lock:
            self.received[topic] += 1
            self._first_flow = self._first_flow or time.monotonic()
            before = self._tf.reparented
            errors = self._tf.add_message(msg, static, topic)
            self.tf_rejected += len(errors)
            reparented = self._tf.reparented
            # one throttle per kind of fault: a NaN translation hid a zero quaternion and a zero stamp behind it
            said = [e for e in errors if self._tf_warnings.due(tf_fault_kind(e))]
        for error in said:
            self.node.get_logger().warning(f"ignored transform: {parameter_words(error)}")
        if reparented > before:  # two publishers of one frame: every pose through it moves, and nothing else says so
            self.node.get_logger().warning(
                f"TF: {self._tf.reparent_note} ({reparented} change(s) of parent so far)",
                throttle_duration_sec=WARN_THROTTLE_S,
            )
        self._deliver_posed()

    def _expire_awaiting(self) -> None:
        self._deliver_posed(now=time.monotonic())

    def _deliver_posed(self, now: float | None = None) -> None:
        """Deliver the waiting frames (oldest first) whose pose TF gives; drop those it will not give in time."""
        assert self._tf is not None
        t = self.topics
        ready: list[BagFrame] = []
        dropped: list[InputError] = []
        with self._lock:
            while self._awaiting:
                a = self._awaiting[0]
                try:
                    T = self._tf.lookup(t.tf_parent_frame, t.tf_child_frame, a.stamp_ns)
                    T_wc = load_pose(T, f"{t.tf_topic} @ {a.stamp_ns} ns", t.tf_topic)
                except TransformUnavailableError as exc:
                    expired = now is not None and now - a.since > self.tf_wait_s
                    if exc.retry and not expired and len(self._awaiting) <= self.tf_wait_frames:
                        break
                    self._awaiting.popleft()
                    if exc.retry:
                        n = self.tf_wait_frames
                        why = "in time (tf_wait_s)" if expired else f"before {n} newer frames were (tf_wait_frames)"
                        exc = TransformUnavailableError(exc.where, f"{exc.problem} (no pose {why})", retry=False)
                    self._remember_rejection(a.stamp_ns, "no_tf", exc)
                    dropped.append(exc)
                    continue
                except InputError as exc:  # a composed pose that is not rigid
                    self._awaiting.popleft()
                    self._remember_rejection(a.stamp_ns, "bad_pose", exc)
                    dropped.append(exc)
                    continue
                self._awaiting.popleft()
                if not self._child_checked:  # once: the first posed frame's images against the frame TF gave
                    self._child_checked = True
                    note = child_frame_mismatch(self._tf, t.tf_parent_frame, t.tf_child_frame, a.image_frame,
                                                a.stamp_ns, T_wc)  # fmt: skip
                    self.child_frame_note = parameter_words(note)
                ready.append(BagFrame(a.stamp_ns, a.rgb, a.depth_m, T_wc, a.intrinsics))
        if ready and self.child_frame_note and not self._child_warned:
            self._child_warned = True
            self.node.get_logger().warning(f"TF: {self.child_frame_note}")
        if dropped:
            with self._lock:
                total = sum(self._ledger.counts()["rejected"].values())  # type: ignore[union-attr]
            self.node.get_logger().warning(
                f"dropped {len(dropped)} frame(s) ({total} refused so far): {parameter_words(dropped[-1])}",
                throttle_duration_sec=WARN_THROTTLE_S,
            )
        for frame in ready:
            self.on_frame(frame)

    def rejection_of(self, stamp_ns: int) -> str | None:
        """Why the frame of ``stamp_ns`` was refused (``no_tf: ...``), if it was one of the last ones refused."""
        with self._lock:
            return self._rejections.get(int(stamp_ns))

    def _remember_rejection(self, stamp_ns: int, reason: str, exc: InputError) -> None:
        """Count a refused frame and keep why (the caller holds the lock)."""
        self._ledger.reject(reason)
        self.last_rejection = parameter_words(exc)
        self._rejections[int(stamp_ns)] = f"{reason}: {self.last_rejection}"
        while len(self._rejections) > REMEMBERED_REJECTIONS:
            self._rejections.popitem(last=False)

    def _reject(self, exc: InputError, stamp_ns: int) -> None:
        """Count and keep why a frame was refused; log it, at most once per WARN_THROTTLE_S for each reason category
        (one throttle for all hid a second fault behind the first: a bad pose after a bad encoding went unsaid).
        """
        reason = reject_reason(exc, self.topics)
        with self._lock:
            self._remember_rejection(stamp_ns, reason, exc)
            due = self._reject_warnings.due(reason)
        if due:
            self.node.get_logger().warning(f"dropped frame: {parameter_words(exc)}")

    def _downscale(self, bf: BagFrame) -> BagFrame:
        """The frame at ``input_size`` (colour by area, depth nearest with centres aligned, intrinsics scaled)."""
        if self.input_size is None:
            return bf
        return resized_frame(bf, bf.intrinsics.resized(*self.input_size))
