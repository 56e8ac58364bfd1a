"""Camera input shared by the nodes: four subscriptions matched by stamp into validated frames.

Messages are converted with the library's converters (:mod:`roigsf_ros.data.bags`) and matched with
:class:`roigsf_ros.data.sync.FrameLedger`, which accounts for every frame sent exactly once in bounded
counters. Bad messages (unsupported encoding, size mismatch with the camera info, NaN pose, ...) are
dropped with a throttled warning and counted by a short reason category; frames that never complete
(e.g. depth without colour) are dropped and counted once the bounded queue overflows; repeated stamps
and stamps gone back are counted, not delivered; frames that never arrived at all (every message
overwritten in a full middleware queue, which the middleware does not report) are estimated from gaps
in the stamps (:class:`roigsf_ros.data.sync.StampGapCounter`).
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Callable
from typing import Any

from geometry_msgs.msg import PoseStamped
from rclpy.callback_groups import CallbackGroup
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import CameraInfo, Image

from roigsf_ros.core.errors import InputError
from roigsf_ros.data.bags import BagFrame, CameraTopics, assemble_frame, stamp_to_ns
from roigsf_ros.data.sync import FrameLedger, StampGapCounter

WARN_THROTTLE_S = 5.0
"""At most one dropped-frame warning in this many seconds (counters keep every drop)."""


def reject_reason(exc: InputError, topics: CameraTopics) -> str:
    """The short, bounded category of a frame's conversion error (counters are keyed by it, not by its text)."""
    problem = exc.problem
    if "encoding" in problem:
        return "bad_encoding"
    if "sizes disagree" in problem:
        return "size_mismatch"
    for topic, reason in ((topics.pose, "bad_pose"), (topics.camera_info, "bad_camera_info")):
        if exc.where.startswith(topic):
            return reason
    if exc.where.startswith((topics.color, topics.depth)):
        return "bad_image"
    return "other"


class CameraInput:
    """Subscribes ``node`` to an RGB-D camera's topics and calls ``on_frame`` with each complete frame."""

    def __init__(
        self,
        node: Node,
        on_frame: Callable[[BagFrame], None],
        qos: QoSProfile,
        topics: CameraTopics | None = None,
        max_pending: int = 16,
        callback_group: CallbackGroup | None = None,
    ) -> None:
        self.node = node
        self.on_frame = on_frame
        self.topics = topics or CameraTopics()
        self.received: Counter[str] = Counter()
        """Messages received per topic."""
        self.last_rejection = ""
        """The full text of the last frame's conversion error (the counters hold only its category)."""
        self._ledger: FrameLedger[Any] = FrameLedger(self.topics.types(), max_pending)
        self._gaps = {topic: StampGapCounter() for topic in self.topics.types()}
        self._lock = threading.Lock()
        t = self.topics
        for topic, msg_type in ((t.color, Image), (t.depth, Image), (t.camera_info, CameraInfo), (t.pose, PoseStamped)):
            node.create_subscription(msg_type, topic, self._callback_for(topic), qos, callback_group=callback_group)

    @property
    def frames(self) -> int:
        """Frames delivered to ``on_frame``."""
        with self._lock:
            return self._ledger.frames

    @property
    def dropped_incomplete(self) -> int:
        """Stamps given up because one of the four messages never came."""
        with self._lock:
            return self._ledger.dropped_incomplete

    def stats(self) -> dict[str, Any]:
        """Counters for reports; every frame sent is in exactly one of the frame counters.

        Frames: ``frames`` (delivered), ``rejected`` (by reason category), ``dropped_incomplete``,
        ``pending``, ``duplicate_stamp``, ``out_of_order`` and ``frames_missed_estimate`` (none of its
        messages arrived: stamp gaps) -- see :class:`roigsf_ros.data.sync.FrameLedger`. Messages:
        ``received`` and ``missed_estimate`` (estimated lost before they arrived) per topic.
        """
        with self._lock:
            counts = self._ledger.counts()
            return {
                "received": dict(self.received),
                "frames": counts["frames"],
                "rejected": counts["rejected"],
                "dropped_incomplete": counts["dropped_incomplete"],
                "pending": counts["pending"],
                "duplicate_stamp": counts["duplicate_stamp"],
                "out_of_order": counts["out_of_order"],
                "frames_missed_estimate": counts["missed_estimate"],
                "missed_estimate": {topic: g.missed for topic, g in self._gaps.items()},
                "last_rejection": self.last_rejection,
            }

    def _callback_for(self, topic: str) -> Callable[[Any], None]:
        def callback(msg: Any) -> None:
            self._on_message(topic, msg)

        return callback

    def _on_message(self, topic: str, msg: Any) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        with self._lock:
            self.received[topic] += 1
            self._gaps[topic].add(stamp)
            parts = self._ledger.add(stamp, topic, msg)
        if parts is None:
            return
        t = self.topics
        try:
            frame = assemble_frame(
                stamp,
                parts[t.color],
                parts[t.depth],
                parts[t.camera_info],
                parts[t.pose],
                t,
                lambda name: f"{name} @ {stamp} ns",
            )
        except InputError as exc:
            with self._lock:
                self._ledger.reject(reject_reason(exc, t))
                self.last_rejection = str(exc)
            self.node.get_logger().warning(f"dropped frame: {exc}", throttle_duration_sec=WARN_THROTTLE_S)
            return
        self.on_frame(frame)
