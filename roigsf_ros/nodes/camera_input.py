"""Camera input shared by the nodes: four subscriptions matched by stamp into validated frames.

Messages are converted with the library's converters (:mod:`roigsf_ros.data.bags`) and matched with
:class:`roigsf_ros.data.sync.StampMatcher`. Bad messages (unsupported encoding, size mismatch with the
camera info, NaN pose, ...) are dropped with a throttled warning and counted by reason; frames that
never complete (e.g. depth without colour) are dropped and counted once the bounded queue overflows;
frames that never arrived at all (every message overwritten in a full middleware queue, which the
middleware does not report) are estimated from gaps in each topic's stamps
(:class:`roigsf_ros.data.sync.StampGapCounter`).
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
from roigsf_ros.data.sync import StampGapCounter, StampMatcher

WARN_THROTTLE_S = 5.0
"""At most one dropped-frame warning in this many seconds (counters keep every drop)."""


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
        self.rejected: Counter[str] = Counter()
        """Frames dropped because a message was bad, by reason."""
        self.frames = 0
        self._matcher: StampMatcher[Any] = StampMatcher(self.topics.types(), max_pending)
        self._gaps = {topic: StampGapCounter() for topic in self.topics.types()}
        self._lock = threading.Lock()
        t = self.topics
        for topic, msg_type in ((t.color, Image), (t.depth, Image), (t.camera_info, CameraInfo), (t.pose, PoseStamped)):
            node.create_subscription(msg_type, topic, self._callback_for(topic), qos, callback_group=callback_group)

    @property
    def dropped_incomplete(self) -> int:
        """Stamps given up because one of the four messages never came."""
        return self._matcher.dropped

    def stats(self) -> dict[str, Any]:
        """Counters for reports: messages per topic, frames, rejected by reason, incomplete dropped, missed.

        ``missed_estimate``: messages per topic estimated lost before they arrived (stamp gaps);
        ``frames_missed_estimate``: frames none of whose messages arrived, the least of those (a frame
        missing on some topics only is counted in ``dropped_incomplete`` instead).
        """
        with self._lock:
            missed = {topic: g.missed for topic, g in self._gaps.items()}
            return {
                "received": dict(self.received),
                "frames": self.frames,
                "rejected": dict(self.rejected),
                "dropped_incomplete": self._matcher.dropped,
                "pending": self._matcher.pending,
                "missed_estimate": missed,
                "frames_missed_estimate": min(missed.values()),
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
            parts = self._matcher.add(stamp, topic, msg)
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
            reason = exc.problem.split(" (")[0].split(":")[0]
            with self._lock:
                self.rejected[reason] += 1
            self.node.get_logger().warning(f"dropped frame: {exc}", throttle_duration_sec=WARN_THROTTLE_S)
            return
        with self._lock:
            self.frames += 1
        self.on_frame(frame)
