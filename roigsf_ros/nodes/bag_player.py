"""``bag_player``: publish a rosbag2 bag's messages at their recorded timing (a stand-in for ``ros2 bag play``).

Messages are published as their serialized CDR bytes, never deserialized, so any message type whose
Python package is installed can be played. Run it as::

    ros2 run roigsf_ros bag_player --ros-args -p bag:=office0.bag -p rate:=1.0
    bag_player --ros-args -p bag:=office0.bag -p rate:=0.0        # as fast as possible

Parameters: ``bag`` (path to a rosbag2 folder or .mcap), ``rate`` (factor on recorded timing; <= 0
publishes as fast as possible), ``loop``, ``wait_for_subscribers`` and ``wait_timeout_s`` (see below),
``start_delay_s`` (a pause after that wait), ``topics`` (string list, unset = all), ``progress_period_s``,
``qos_depth``, ``ack_timeout_s``.

At rate <= 0 the player does not know how fast its subscribers take messages (``ros2 bag play`` does not either):
a subscriber slower than the bag loses what overflows its queue. A caller in the same process can pass ``pace``, a
callable run before each message that returns once the subscribers are ready for it; ``roigsf demo --rate 0``
plays in lockstep with its nodes that way.

Before the first message the player waits until every topic it plays has ``wait_for_subscribers``
(default 1; 0 = no wait) matched subscriptions, at most ``wait_timeout_s`` (default 10 s); latched topics
(``/tf_static``) are not waited for, a later subscriber gets them anyway. Without the
wait, a player started in a process of its own published before DDS discovery had matched it with
the subscribers, and those first messages were lost: a 20-frame bag played at rate 1 into a running
``active_mapping`` gave no keyframe at all. On timeout it logs the topics still short of subscribers
and plays anyway (as ``ros2 bag play`` would): a subscriber that matches later still gets the rest,
and playing into no subscriber at all is a legitimate use (a recorder started later, a smoke test).
"""

from __future__ import annotations

import importlib
import math
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from roigsf_ros.core.errors import InputError
from roigsf_ros.data.bags import open_any_reader
from roigsf_ros.data.tf import TF_MESSAGE_TYPE
from roigsf_ros.nodes.node_params import check_parameter_overrides, declare, parameter_error, read_at_start
from roigsf_ros.nodes.node_process import init_ros, script_args


def message_class(type_name: str, where: str = "message type") -> type:
    """The rclpy message class of a ROS 2 type name, e.g. ``sensor_msgs/msg/Image`` -> ``sensor_msgs.msg.Image``."""
    parts = type_name.split("/")
    if len(parts) != 3 or not all(parts):
        raise InputError(where, f"'{type_name}' is not a ROS 2 type name of the form package/msg/Name")
    package, kind, name = parts
    try:
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ImportError, AttributeError):
        problem = f"message type {type_name} is not installed (no Python class {package}.{kind}.{name})"
        raise InputError(where, problem) from None


def reliable_qos(depth: int) -> QoSProfile:
    """Reliable, volatile, keep-last ``depth``: what the player offers and its test subscribers use."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def progress_line(published: int, loops_completed: int, per_loop: int, looping: bool) -> str:
    """The player's progress log line: share of the current loop played, and messages published in all.

    Between a loop's last message and the end of playback (the closing delay) the loop is reported complete,
    not as the next loop at 0 %.
    """
    in_loop = published - loops_completed * per_loop
    loop_no = loops_completed + 1
    if in_loop == 0 and loops_completed > 0:
        in_loop, loop_no = per_loop, loops_completed
    pct = 100.0 * in_loop / max(1, per_loop)
    loop = f", loop {loop_no}" if looping else ""
    return f"{pct:5.1f}% ({in_loop}/{per_loop} messages{loop}), {published} published"


class BagPlayer(Node):
    """Publishes a bag's messages on their topics, timed against a monotonic clock relative to the start.

    Playback runs in a thread of its own that starts once the subscribers matched (``wait_for_subscribers``,
    ``wait_timeout_s``) and ``start_delay_s`` passed; the node's executor
    only runs the progress timer. ``done`` turns true when playback ends (never with ``loop``, unless
    stopped); :meth:`destroy_node` stops the thread and joins it. ``published`` (``published_by_topic``),
    ``loops_completed`` and ``play_duration_s`` (start of the latest loop to its latest publish) report progress.

    ``pace`` (rate <= 0 only): called in the playback thread before each message with its topic and the messages
    published so far per topic; it returns when the subscribers are ready for that message, and promptly once
    :attr:`stopping` is true.
    """

    def __init__(
        self,
        *,
        context: Context | None = None,
        parameter_overrides: list[Parameter] | None = None,
        node_name: str = "bag_player",
        pace: Callable[[str, Mapping[str, int]], None] | None = None,
    ) -> None:
        super().__init__(node_name, context=context, parameter_overrides=parameter_overrides)
        self._pace = pace
        try:
            self._setup(node_name)
        except BaseException as exc:
            error = parameter_error(self, exc)  # worded as the other nodes', naming the params file that set it
            super().destroy_node()
            if error is exc:
                raise
            raise error from None
        try:  # an unknown name in parameter_overrides raises, one in a params file or -p is logged
            check_parameter_overrides(self, parameter_overrides)
        except BaseException:
            self.destroy_node()
            raise

    def _setup(self, node_name: str) -> None:
        """Declare and check parameters, open the bag, create publishers, start the playback thread."""
        # declare(): a value of the wrong type is an error in the other nodes' words (the params file named)
        declare(self, "bag", "", "rosbag2 folder or .mcap file to play")
        declare(self, "rate", 1.0, "factor on recorded timing; 1.0 real time, <= 0 as fast as possible")
        declare(self, "loop", False, "restart from the beginning at the end")
        declare(self, "wait_for_subscribers", 1, "matched subscriptions every topic needs before playback; 0 = no wait")
        declare(self, "wait_timeout_s", 10.0, "seconds to wait for them; then a warning and playback anyway")
        declare(self, "start_delay_s", 0.5, "seconds to pause after the subscribers matched (their side of discovery)")
        topics_param = self.declare_parameter(
            "topics", Parameter.Type.STRING_ARRAY, read_at_start("topics to play; unset = all")
        )
        declare(self, "progress_period_s", 2.0, "seconds between progress lines; <= 0 = none")
        declare(self, "qos_depth", 100, "keep-last depth of the publishers")
        declare(self, "ack_timeout_s", 5.0, "at the end, seconds to wait for reliable subscribers to acknowledge")

        bag = str(self.get_parameter("bag").value)
        self.rate = float(self.get_parameter("rate").value)
        self.loop = bool(self.get_parameter("loop").value)
        start_delay_s = float(self.get_parameter("start_delay_s").value)
        self.wait_for_subscribers = int(self.get_parameter("wait_for_subscribers").value)
        self.wait_timeout_s = float(self.get_parameter("wait_timeout_s").value)
        wanted = topics_param.value  # None when unset (an empty list cannot be typed as a string array)
        progress_period_s = float(self.get_parameter("progress_period_s").value)
        qos_depth = int(self.get_parameter("qos_depth").value)
        ack_timeout_s = float(self.get_parameter("ack_timeout_s").value)
        # nan/inf: max(0, nan) is 0 and nan <= 0 is false: they passed as "no delay" or "as fast as possible"
        for name, value in (
            ("rate", self.rate),
            ("start_delay_s", start_delay_s),
            ("progress_period_s", progress_period_s),
            ("ack_timeout_s", ack_timeout_s),
        ):
            if not math.isfinite(value):
                raise InputError(f"parameter '{name}'", f"must be a finite number, got {value}")
        self.start_delay_s = max(0.0, start_delay_s)
        self.ack_timeout_s = max(0.0, ack_timeout_s)
        if not bag:
            raise InputError("parameter 'bag'", "no bag given (use --ros-args -p bag:=PATH)")
        if qos_depth < 1:
            raise InputError("parameter 'qos_depth'", f"must be >= 1, got {qos_depth}")
        if self.wait_for_subscribers < 0:
            raise InputError("parameter 'wait_for_subscribers'", f"must be >= 0, got {self.wait_for_subscribers}")
        if not self.wait_timeout_s >= 0:
            raise InputError("parameter 'wait_timeout_s'", f"must be >= 0, got {self.wait_timeout_s}")
        self.bag_path = Path(bag)

        reader = open_any_reader(self.bag_path)
        try:
            reader.open()
            connections = list(reader.connections)
            reader.close()
        except InputError:
            raise
        except Exception as exc:
            raise InputError(self.bag_path, f"cannot open bag: {exc}") from None
        types: dict[str, str] = {}
        counts: dict[str, int] = {}
        for c in connections:
            if types.setdefault(c.topic, c.msgtype) != c.msgtype:
                problem = f"has two message types, {types[c.topic]} and {c.msgtype}"
                raise InputError(f"{self.bag_path}:{c.topic}", problem)
            counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
        if wanted:
            missing = [t for t in wanted if t not in types]
            if missing:
                have = ", ".join(sorted(types)) or "no topics"
                raise InputError(self.bag_path, f"topic(s) {', '.join(missing)} not in the bag (it has {have})")
            types = {t: types[t] for t in wanted}
        if not types:
            raise InputError(self.bag_path, "bag has no topics to play")

        qos = reliable_qos(qos_depth)
        latched = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=qos_depth,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        # Static transforms are latched, as tf2's static broadcaster offers them (a listener asks for it).
        self._latched_topics = {t for t, typ in types.items() if typ == TF_MESSAGE_TYPE and t.endswith("tf_static")}
        self._publishers_by_topic: dict[str, Publisher] = {
            topic: self.create_publisher(
                message_class(typ, f"{self.bag_path}:{topic}"),
                topic,
                latched if topic in self._latched_topics else qos,
            )
            for topic, typ in types.items()
        }
        self.total_per_loop = sum(counts[t] for t in types)
        self.published = 0
        self.published_by_topic: Counter[str] = Counter()
        self.loops_completed = 0
        self.play_duration_s = 0.0
        self.subscriber_wait_s = 0.0
        """Seconds playback waited for subscribers to match."""
        self.subscribers_matched: bool | None = None
        """Whether every topic had its ``wait_for_subscribers`` when playback began (None: no wait asked)."""
        self.error: BaseException | None = None
        self._t_first_publish: float | None = None
        self._stop = threading.Event()
        self._done = threading.Event()
        self._progress_timer = (
            self.create_timer(progress_period_s, self._report_progress) if progress_period_s > 0 else None
        )
        mode = f"at rate x{self.rate:g}"
        if self.rate <= 0:
            mode = "as fast as the subscribers take them" if self._pace is not None else "as fast as possible"
        n = self.wait_for_subscribers
        start = f"{n} subscriber(s) on every topic (at most {self.wait_timeout_s:g} s), then " if n > 0 else ""
        self.get_logger().info(
            f"playing {self.bag_path}: {self.total_per_loop} messages on {len(types)} topics {mode}"
            f"{' in a loop' if self.loop else ''}, starting after {start}{self.start_delay_s:g} s; topics as published "
            f"(remapped): {', '.join(sorted(p.topic_name for p in self._publishers_by_topic.values()))}"
        )
        self._thread = threading.Thread(target=self._run, name=f"{node_name}_playback", daemon=True)
        self._thread.start()

    @property
    def stopping(self) -> bool:
        """True once :meth:`stop` was called: a ``pace`` callable returns at once."""
        return self._stop.is_set()

    @property
    def done(self) -> bool:
        """True once playback has ended (finished, stopped, or failed)."""
        return self._done.is_set()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Block until playback ends or ``timeout_s`` passes; True if it ended."""
        return self._done.wait(timeout_s)

    def stop(self) -> None:
        """Ask playback to stop and wait for its thread."""
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join()

    def destroy_node(self) -> None:
        """Stop playback, join its thread, then destroy the node."""
        self.stop()
        super().destroy_node()

    def summary(self) -> dict[str, Any]:
        """Counts and timing of the playback so far."""
        return {
            "bag": str(self.bag_path),
            "topics": sorted(self._publishers_by_topic),
            "published": self.published,
            "published_by_topic": dict(self.published_by_topic),
            "messages_per_loop": self.total_per_loop,
            "loops_completed": self.loops_completed,
            "play_duration_s": self.play_duration_s,
            "rate": self.rate,
            "subscriber_wait_s": self.subscriber_wait_s,
            "subscribers_matched": self.subscribers_matched,
            "error": None if self.error is None else str(self.error),
        }

    def _report_progress(self) -> None:
        if self.done or self._t_first_publish is None:
            return
        self.get_logger().info(progress_line(self.published, self.loops_completed, self.total_per_loop, self.loop))

    def _subscribers_short(self) -> dict[str, int]:
        """Topics with fewer than ``wait_for_subscribers`` matched subscriptions, and how many they have.

        Latched topics (``/tf_static``) are not waited for: a subscriber that comes later still gets them.
        """
        counts = {
            t: pub.get_subscription_count()
            for t, pub in self._publishers_by_topic.items()
            if t not in self._latched_topics
        }
        return {t: c for t, c in counts.items() if c < self.wait_for_subscribers}

    def _wait_for_subscribers(self) -> bool:
        """Wait (``wait_timeout_s`` at most) until every topic has its subscribers; False if stopped meanwhile."""
        if self.wait_for_subscribers <= 0:
            return True
        t0 = time.monotonic()
        short = self._subscribers_short()
        while short and time.monotonic() - t0 < self.wait_timeout_s:
            if self._stop.wait(0.02):
                return False
            short = self._subscribers_short()
        self.subscriber_wait_s = time.monotonic() - t0
        self.subscribers_matched = not short
        if short:
            have = ", ".join(f"{t} ({c})" for t, c in sorted(short.items()))
            self.get_logger().warning(
                f"after {self.wait_timeout_s:g} s (wait_timeout_s), topics still short of the "
                f"{self.wait_for_subscribers} subscriber(s) wait_for_subscribers asks for: {have}; playing anyway "
                "(nodes still starting, on a loaded machine: wait longer with -p wait_timeout_s:=30.0; else play only "
                "the topics a node reads with -p topics:=[...], or -p wait_for_subscribers:=0)"
            )
        else:
            self.get_logger().info(
                f"{self.wait_for_subscribers} subscriber(s) matched on every topic after {self.subscriber_wait_s:.2f} s"
            )
        return True

    def _run(self) -> None:
        try:
            if not self._wait_for_subscribers() or self._stop.wait(self.start_delay_s):
                return
            while not self._stop.is_set():
                if not self._play_once():
                    break
                self.loops_completed += 1
                if not self.loop:
                    break
            if not self._stop.is_set():
                self._wait_for_acks()
                self.get_logger().info(
                    f"finished: published {self.published} messages on {len(self._publishers_by_topic)} topics "
                    f"in {self.play_duration_s:.3f} s ({self.loops_completed} loop(s), rate "
                    f"{'max' if self.rate <= 0 else f'x{self.rate:g}'})"
                )
        except Exception as exc:  # the context shut down under us, or the bag broke mid-way
            if not self._stop.is_set() and self.context.ok():
                self.error = exc
                self.get_logger().error(f"playback failed: {exc}")
        finally:
            self._done.set()

    def _play_once(self) -> bool:
        """Publish the bag once; False if stopped part-way."""
        reader = open_any_reader(self.bag_path)
        with reader:
            conns = [c for c in reader.connections if c.topic in self._publishers_by_topic]
            t_start = time.monotonic()
            first_ns: int | None = None
            for conn, stamp_ns, raw in reader.messages(connections=conns):
                if first_ns is None:
                    first_ns = stamp_ns
                if self.rate > 0:
                    delay_s = t_start + (stamp_ns - first_ns) / 1e9 / self.rate - time.monotonic()
                    if delay_s > 0 and self._stop.wait(delay_s):
                        return False
                else:
                    if self._pace is not None:
                        self._pace(conn.topic, self.published_by_topic)
                    if self._stop.is_set():
                        return False
                self._publishers_by_topic[conn.topic].publish(raw if isinstance(raw, bytes) else bytes(raw))
                now = time.monotonic()
                if self._t_first_publish is None:
                    self._t_first_publish = now
                self.published += 1
                self.published_by_topic[conn.topic] += 1
                self.play_duration_s = now - t_start
        return True

    def _wait_for_acks(self) -> None:
        deadline = time.monotonic() + self.ack_timeout_s
        for pub in self._publishers_by_topic.values():
            left = max(0.0, deadline - time.monotonic())
            if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
                self.get_logger().warning(
                    f"{pub.topic_name}: not all messages acknowledged within {self.ack_timeout_s:g} s"
                )


def main(args: list[str] | None = None) -> int:
    """Console script ``bag_player [BAG]``: play, then exit 0 (also on Ctrl-C), 2 on bad input, 1 if playback failed."""
    args = script_args("bag_player", __doc__, args, bag=True)
    try:
        init_ros(args)
    except InputError as exc:  # a bad ROIGSF_GIL_SWITCH_INTERVAL_S
        print(f"bag_player: error: {exc}", file=sys.stderr)
        return 2
    try:
        node = BagPlayer()
    except (InputError, InvalidParameterTypeException, InvalidParameterValueException) as exc:  # as run_nodes does
        print(f"bag_player: error: {parameter_error(None, exc)}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    try:
        while rclpy.ok() and not node.done:
            rclpy.spin_once(node, timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        interrupted = not node.done
        node.stop()  # join the playback thread first: the count is then final (it may publish one more)
        if interrupted:  # printed, not logged: the line that tools and tests read
            print(f"bag_player: stopped after {node.published} messages", file=sys.stderr)
        node.destroy_node()
        rclpy.try_shutdown()
    return 1 if node.error is not None else 0


if __name__ == "__main__":
    sys.exit(main())
