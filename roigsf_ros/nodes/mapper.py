"""``mapper`` node: builds the surfel map from the keyframes the selector names, in a background thread.

Subscribes to the camera topics (:class:`~roigsf_ros.nodes.camera_input.CameraInput`) and keeps the
most recent ``frame_buffer_size`` frames by stamp; a ``geometry_msgs/PoseStamped`` on ``keyframe_topic``
names a frame by its header stamp, and that frame joins a bounded queue of keyframes to insert. A
keyframe whose frame has not arrived yet waits up to ``keyframe_wait_s``; one whose frame was evicted
or never received is counted and warned about. A worker thread inserts each keyframe
(:meth:`Mapper.add_keyframe`: densify, then ``iters_per_keyframe`` steps), then spends up to
``idle_iters_per_keyframe`` further steps over random keyframes while no keyframe waits, always in
slices of ``optimise_slice_iters`` steps under the shared lock, so readers never wait long. Between two
slices it pauses (at most ``yield_to_planner_s``) while an in-process planner answers a request or prepares
the next one: the answer is what the robot waits for, the optimisation can lag and catch up.

Keyframe ids are the frames' header stamps in nanoseconds: unique across processes and restarts.

At start-up (``warm_up``, default true), before it subscribes to anything, the node maps a tiny scene once
(:func:`roigsf_ros.nbv.warmup.warm_up_once` with ``scoring=False``; nothing when an in-process planner warmed up
already): a process's first 640x480 keyframe took 1.1 s against 0.5 s for the next while the kernels loaded, and a
planner in another process waited that long for its first map. With a warm cache it takes about half a second.

Outputs: the map as ``sensor_msgs/PointCloud2`` (:mod:`~roigsf_ros.nodes.map_msgs` layout, transient
local, at most ``map_publish_rate_hz``), the keyframe poses as ``geometry_msgs/PoseArray`` and the intrinsics the
map is built with (after ``input_width``/``input_height``) as ``sensor_msgs/CameraInfo`` on ``map_camera_info_topic``
(same QoS; a planner in another process scores with them: with a loaded map it had none until a camera published);
``~/status`` (``std_msgs/String`` JSON counters); services ``~/save_map``, ``~/load_map``
(``roigsf_interfaces/srv/SaveMap``, ``LoadMap``) and ``~/publish_mesh`` (``std_srvs/Trigger``: the
mesh, decimated to at most ``mesh_marker_max_triangles``, as a ``visualization_msgs/Marker`` on
``~/mesh``, sent as serialized bytes built in bulk). ``load_map`` at start resumes a saved map.
With ``map_with_h_train`` the cloud also carries the mapper's running training Fisher (``htrain_``
fields), so a planner in another process scores like an in-process one, with no Fisher pass of its own.

Long service work (the mesh) runs in a helper thread that the callback waits for while watching
:meth:`MapperNode.stop` and the context, so Ctrl-C never waits for it (a callback still running
in the executor's thread pool would hold the process at exit).

    mapper --ros-args --params-file config/mapper.yaml -p iters_per_keyframe:=20
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseArray, PoseStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, PointCloud2
from std_msgs.msg import String
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker

from roigsf_interfaces.srv import LoadMap, SaveMap
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import check_writable
from roigsf_ros.core.frame import Frame
from roigsf_ros.data.bags import BagFrame, CameraTopics, stamp_to_ns
from roigsf_ros.data.tf import DEFAULT_CACHE_S
from roigsf_ros.mapping.mapper import MapperConfig
from roigsf_ros.nbv.warmup import warm_up_once
from roigsf_ros.nodes.bag_player import reliable_qos
from roigsf_ros.nodes.camera_input import (
    WARN_THROTTLE_S,
    CameraInput,
    CameraSettings,
    camera_qos,
    camera_status,
    describe_topics,
)
from roigsf_ros.nodes.map_msgs import intrinsics_to_camera_info, mesh_marker_cdr, poses_to_array, surfel_map_to_cloud
from roigsf_ros.nodes.node_params import (
    SystemNode,
    changed_parameters,
    check_frame_id,
    check_input_size,
    check_positive,
    declare,
    declare_config,
    node_label,
    settings_text,
)
from roigsf_ros.nodes.node_process import run_nodes
from roigsf_ros.nodes.shared_map import (
    SharedMapper,
    check_replaceable_map,
    decimate_mesh,
    is_saved_map,
    same_camera,
)

KEYFRAME_TOPIC = "roigsf/keyframe"
MAP_TOPIC = "roigsf/map"
KEYFRAME_POSES_TOPIC = "roigsf/keyframe_poses"
MAP_CAMERA_INFO_TOPIC = "roigsf/map_camera_info"
MISSING_AFTER_NEWER_FRAMES = 3
"""A keyframe waiting for its frame is given up once this many newer frames arrived (or after keyframe_wait_s)."""


def latched_qos(depth: int = 1) -> QoSProfile:
    """Reliable, transient-local, keep-last ``depth``: a late joiner gets the latest map at once."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def camera_params(node: Node) -> CameraSettings:
    """Declare the camera input's parameters (topics, transports, pose source and TF, input size); their settings.

    ``color_topic`` / ``depth_topic`` are base topics: a compressed transport subscribes to
    ``<topic>/compressed`` (``/compressedDepth``) as image_transport does, unless the name already ends so.
    """
    d = CameraTopics()
    fields = {
        "color": declare(node, "color_topic", d.color, "colour image topic (base name; see color_transport)"),
        "depth": declare(node, "depth_topic", d.depth, "depth image topic (base name; see depth_transport)"),
        "camera_info": declare(node, "camera_info_topic", d.camera_info, "camera info topic (sensor_msgs/CameraInfo)"),
        "pose": declare(
            node, "pose_topic", d.pose, "camera pose topic (PoseStamped of the optical frame; pose_source topic)"
        ),
        "color_transport": declare(
            node, "color_transport", d.color_transport, "raw (Image rgb8/bgr8/rgba8/bgra8) | compressed (JPEG/PNG)"
        ),
        "depth_transport": declare(
            node,
            "depth_transport",
            d.depth_transport,
            "raw (32FC1 m, 16UC1 mm) | compressed (16-bit PNG) | compressedDepth",
        ),
        "pose_source": declare(
            node, "pose_source", d.pose_source, "topic (pose_topic) | tf (tf_topic + tf_static_topic)"
        ),
        "tf_parent_frame": declare(node, "tf_parent_frame", d.tf_parent_frame, "tf: the world frame of the poses"),
        "tf_child_frame": declare(node, "tf_child_frame", d.tf_child_frame, "tf: the camera's optical frame"),
        "tf_topic": declare(node, "tf_topic", d.tf_topic, "tf: transforms (tf2_msgs/TFMessage)"),
        "tf_static_topic": declare(node, "tf_static_topic", d.tf_static_topic, "tf: static transforms (latched)"),
        "tf_tolerance_s": declare(
            node, "tf_tolerance_s", d.tf_tolerance_s, "tf: interpolate only between samples this close to the stamp"
        ),
    }
    tf_wait_s = float(declare(node, "tf_wait_s", 1.0, "tf: seconds a frame waits for its pose, then dropped (no_tf)"))
    reliability = str(
        declare(node, "camera_reliability", "reliable", "reliable | best_effort (what the camera publishes)")
    )
    tf_cache_s = float(declare(node, "tf_cache_s", DEFAULT_CACHE_S, "tf: seconds of history behind the newest"))
    tf_wait_frames = int(declare(node, "tf_wait_frames", 64, "tf: at most this many frames wait for their pose"))
    pending_frames = int(declare(node, "pending_frames", 64, "at most this many stamps wait for their other messages"))
    check_positive("tf_cache_s", tf_cache_s)
    check_positive("tf_wait_frames", tf_wait_frames)
    check_positive("pending_frames", pending_frames)
    width = int(declare(node, "input_width", 0, "frames resized on arrival to this width (0 = camera's)"))
    height = int(declare(node, "input_height", 0, "frames resized on arrival to this height (0 = camera's)"))
    check_positive("tf_wait_s", tf_wait_s, allow_zero=True)
    size = check_input_size(width, height)
    try:
        topics = CameraTopics(**fields)
    except InputError as exc:
        name = {
            "color": "color_topic",
            "depth": "depth_topic",
            "camera_info": "camera_info_topic",
            "pose": "pose_topic",
        }
        raise InputError(f"parameter '{name.get(exc.where, exc.where)}'", exc.problem) from None
    camera_qos(1, reliability)  # an unknown value: an error naming the parameter
    return CameraSettings(topics, size, tf_wait_s, reliability, tf_wait_frames, tf_cache_s, pending_frames)


def request_folder(directory: str) -> Path:
    """A service request's folder with ``~`` expanded, made absolute (a relative one is in the node's working folder),
    so that the reply says where the map went.
    """
    return Path(os.path.abspath(Path(directory).expanduser()))


def frame_of(bf: BagFrame) -> Frame:
    """The library frame of a received camera frame; its index is the stamp in nanoseconds."""
    return Frame(index=int(bf.stamp_ns), rgb=bf.rgb, depth_m=bf.depth_m, T_wc=bf.T_wc)


FIXED_BY_FIRST = (
    " (the map takes its camera from the first frame it receives, or a loaded map's: if that frame's camera_info "
    "was wrong, restart the mapper; another camera needs a map of its own)"
)
"""The end of a refused frame's reason when its intrinsics are not the map's: how the map's came to be, and the way
out (a wrong first camera_info fixed them for the whole run)."""


class MapperNode(SystemNode):
    """The mapper; see the module docstring. ``shared`` given: map into that in-process SharedMapper."""

    default_name = "mapper"
    _thread: threading.Thread | None = None

    # ------------------------------------------------------------------------------ set-up
    def _setup(self, shared: SharedMapper | None) -> None:
        self.config = MapperConfig(**declare_config(self, MapperConfig))
        camera = camera_params(self)
        keyframe_topic = declare(self, "keyframe_topic", KEYFRAME_TOPIC, "keyframes to insert (PoseStamped, stamp)")
        map_topic = declare(self, "map_topic", MAP_TOPIC, "map output (PointCloud2, transient local)")
        poses_topic = declare(self, "keyframe_poses_topic", KEYFRAME_POSES_TOPIC, "keyframe poses (PoseArray)")
        map_info_topic = declare(self, "map_camera_info_topic", MAP_CAMERA_INFO_TOPIC, "the map's intrinsics "
                                 "(CameraInfo, transient local)")  # fmt: skip
        self.frame_id = check_frame_id(
            "frame_id", declare(self, "frame_id", "map", "frame of the map, its cloud and the keyframe poses")
        )
        self.buffer_size = int(declare(self, "frame_buffer_size", 64, "recent frames kept to match keyframes"))
        self.max_pending = int(declare(self, "max_pending_keyframes", 16, "bound of the queue of keyframes"))
        self.wait_s = float(
            declare(self, "keyframe_wait_s", 10.0, "seconds a keyframe waits for its frame (unless a newer one came)")
        )
        self.slice_iters = int(declare(self, "optimise_slice_iters", 2, "optimiser steps per hold of the map lock"))
        self.yield_s = float(
            declare(self, "yield_to_planner_s", 2.0, "longest pause between slices while the in-process planner works")
        )
        self.idle_iters = int(
            declare(self, "idle_iters_per_keyframe", 10, "extra steps over random keyframes per keyframe, when idle")
        )
        publish_hz = float(declare(self, "map_publish_rate_hz", 1.0, "map cloud publications per second at most"))
        status_hz = float(declare(self, "status_rate_hz", 1.0, "~/status publications per second (0 = none)"))
        qos_depth = int(declare(self, "qos_depth", 100, "keep-last depth of the camera and keyframe subscriptions"))
        load_dir = str(declare(self, "load_map", "", "saved map folder to resume from at start ('' = none)"))
        self.autosave_dir = str(declare(self, "autosave_dir", "", "folder the map is saved to ('' = never)"))
        self.autosave_every = int(declare(self, "autosave_every", 0, "save to autosave_dir every this many keyframes"))
        autosave_overwrite = bool(declare(self, "autosave_overwrite", False, "replace a map an earlier run "
                                          "left in autosave_dir (else start-up refuses it unless load_map "
                                          "resumes it)"))  # fmt: skip
        self.mesh_max_triangles = int(
            declare(self, "mesh_marker_max_triangles", 100000, "~/mesh marker decimated to at most this many triangles")
        )
        self.map_with_h_train = bool(
            declare(self, "map_with_h_train", True, "map cloud carries the running training Fisher (htrain_)")
        )
        warm_up = bool(declare(self, "warm_up", True, "load the mapping kernels at start-up (tiny scene)"))
        for name, value in (("frame_buffer_size", self.buffer_size), ("max_pending_keyframes", self.max_pending)):
            check_positive(name, value)
        check_positive("optimise_slice_iters", self.slice_iters)
        check_positive("yield_to_planner_s", self.yield_s, allow_zero=True)
        check_positive("qos_depth", qos_depth)
        for name, value in (("keyframe_wait_s", self.wait_s), ("idle_iters_per_keyframe", self.idle_iters)):
            check_positive(name, value, allow_zero=True)
        check_positive("map_publish_rate_hz", publish_hz, allow_zero=True)
        check_positive("status_rate_hz", status_hz, allow_zero=True)
        check_positive("autosave_every", self.autosave_every, allow_zero=True)
        if self.autosave_dir:  # now, naming the parameter, not at the first autosave
            self.autosave_dir = str(request_folder(self.autosave_dir))
            try:
                check_writable(self.autosave_dir)
                check_replaceable_map(self.autosave_dir)
            except InputError as exc:
                raise InputError("parameter 'autosave_dir'", str(exc)) from None
            resumed = bool(load_dir) and request_folder(load_dir) == Path(self.autosave_dir)
            if is_saved_map(self.autosave_dir) and not (resumed or autosave_overwrite):
                raise InputError(  # a restart with the same parameters must not replace the last run's map
                    "parameter 'autosave_dir'",
                    f"{self.autosave_dir} holds a map an earlier run saved: resume it with load_map:="
                    f"{self.autosave_dir}, replace it with autosave_overwrite:=true, or choose another folder",
                )
        check_positive("mesh_marker_max_triangles", self.mesh_max_triangles, allow_zero=True)

        self.in_process = shared is not None
        if shared is None:
            shared = SharedMapper(self.config)
        elif shared.mapper is None:
            shared.config = self.config
        self.shared = shared
        if load_dir:
            try:
                loaded = shared.load(load_dir)
            except InputError as exc:  # named as the parameter that asked for it, as the other start-up errors are
                raise InputError(f"parameter '{node_label(self)}.load_map'", str(exc)) from None
            self.get_logger().info(
                f"resumed map {load_dir}: {len(loaded.loaded_keyframe_ids)} keyframes, {loaded.n_surfels} surfels"
            )

        self._lock = threading.Lock()  # node state below (not the map: that is shared.lock)
        self._wake = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._service_threads: list[threading.Thread] = []  # service work still running (_run_interruptible)
        self._intrinsics_refusals: OrderedDict[int, str] = OrderedDict()  # stamp -> why (the last buffer_size)
        self._frames: OrderedDict[int, Frame] = OrderedDict()
        self._pending: deque[Frame] = deque()
        self._waiting: dict[int, list[float]] = {}  # stamp -> [time received, newer frames seen since]
        self._queued_ids: set[int] = set(shared.keyframe_ids())
        self._idle_left = 0
        self._busy = False
        with shared.lock:
            self._intr = None if shared.mapper is None else shared.mapper.intr
        self.counters: dict[str, int] = dict.fromkeys(
            (
                "keyframe_msgs",
                "keyframes_inserted",
                "keyframes_missing",
                "keyframes_dropped_overflow",
                "keyframes_duplicate",
                "keyframes_no_depth",
                "keyframes_failed",
                "frames_evicted",
                "frames_bad_intrinsics",
                "map_publishes",
                "autosaves",
                "autosaves_failed",
            ),
            0,
        )
        self.counters["paused_for_planner_s"] = 0.0  # type: ignore[assignment]
        self.counters["warm_up_s"] = 0.0  # type: ignore[assignment]
        if warm_up:  # before any subscription: the first keyframe's map goes out as fast as the next ones'
            try:
                times = warm_up_once(scoring=False)
            except Exception as exc:  # a failed warm-up must not stop the node: the first keyframe compiles
                self.get_logger().warning(f"kernel warm-up failed ({exc}): kernels load at the first keyframe")
            else:
                if times is not None:
                    self.counters["warm_up_s"] = times["total_s"]  # type: ignore[assignment]
                    self.get_logger().info(f"mapping kernels ready in {times['total_s']:.1f} s (warm-up, tiny scene)")
        self.last_keyframe_drop = ""
        """Why the last keyframe named was dropped (the warnings are throttled; ``~/status`` keeps this)."""

        inputs = MutuallyExclusiveCallbackGroup()
        keyframes = MutuallyExclusiveCallbackGroup()
        outputs = MutuallyExclusiveCallbackGroup()
        services = MutuallyExclusiveCallbackGroup()
        self.camera = CameraInput.of_settings(self, self._on_frame, camera, qos_depth, callback_group=inputs)
        self.create_subscription(
            PoseStamped, keyframe_topic, self._on_keyframe, reliable_qos(qos_depth), callback_group=keyframes
        )
        self._map_pub = self.create_publisher(PointCloud2, map_topic, latched_qos())
        self._poses_pub = self.create_publisher(PoseArray, poses_topic, latched_qos())
        self._map_info_pub = self.create_publisher(CameraInfo, map_info_topic, latched_qos())
        self._mesh_pub = self.create_publisher(Marker, "~/mesh", latched_qos())
        self._status_pub = self.create_publisher(String, "~/status", reliable_qos(10))
        self._published_version = -1
        self._publish_lock = threading.Lock()  # the timer publishes, and the worker once: the first keyframe's map
        self._publishes_maps = publish_hz > 0
        if publish_hz > 0:
            self.create_timer(1.0 / publish_hz, self.publish_map, callback_group=outputs)
        if status_hz > 0:
            self.create_timer(1.0 / status_hz, self.publish_status, callback_group=outputs)
        self.create_timer(0.1, self._expire_waiting, callback_group=keyframes)
        self.create_service(SaveMap, "~/save_map", self._on_save, callback_group=services)
        self.create_service(LoadMap, "~/load_map", self._on_load, callback_group=services)
        self.create_service(Trigger, "~/publish_mesh", self._on_mesh, callback_group=services)
        self._thread = threading.Thread(target=self._work, name=f"{self.get_name()}_worker", daemon=True)
        self._thread.start()
        settings = self.config.changed() | changed_parameters(self, exclude=self.config.to_dict())  # the node's own too
        self.get_logger().info(
            f"mapping keyframes named on {self.resolve_topic_name(keyframe_topic)}; map on "
            f"{self.resolve_topic_name(map_topic)} "
            f"({'shared in-process' if self.in_process else 'own'} map{settings_text(settings)}); "
            f"camera: {describe_topics(self.camera.topics)}, {camera.reliability}"
        )

    # ------------------------------------------------------------------------------ inputs
    def _on_frame(self, bf: BagFrame) -> None:
        # Never wait for the map lock here (the worker holds it for whole insertions): the intrinsics are
        # checked against a node-local copy; only the very first frame creates the map.
        try:
            intr = self._intr
            if intr is None:
                self._intr = self.shared.ensure(bf.intrinsics).intr
            elif not same_camera(intr, bf.intrinsics):
                raise InputError(
                    "camera_info", f"intrinsics {bf.intrinsics} differ from the map's {intr}{FIXED_BY_FIRST}"
                )
        except InputError as exc:
            with self._lock:
                self.counters["frames_bad_intrinsics"] += 1
                self._intrinsics_refusals[bf.stamp_ns] = f"bad_intrinsics: {exc}"
                while len(self._intrinsics_refusals) > self.buffer_size:
                    self._intrinsics_refusals.popitem(last=False)
            self.get_logger().warning(f"dropped frame {bf.stamp_ns}: {exc}", throttle_duration_sec=WARN_THROTTLE_S)
            return
        frame = frame_of(bf)
        with self._wake:
            self._frames[frame.index] = frame
            while len(self._frames) > self.buffer_size:
                self._frames.popitem(last=False)
                self.counters["frames_evicted"] += 1
            if self._waiting.pop(frame.index, None) is not None:
                self._enqueue(frame)
            # A keyframe whose frame has not come while MISSING_AFTER_NEWER_FRAMES newer frames did is missing
            # (frames complete in stamp order up to a little reordering between the four topics).
            missing = []
            for s, entry in self._waiting.items():
                if s < frame.index:
                    entry[1] += 1
                    if entry[1] >= MISSING_AFTER_NEWER_FRAMES:
                        missing.append(s)
            for s in missing:
                del self._waiting[s]
            self.counters["keyframes_missing"] += len(missing)
        if missing:
            self.get_logger().warning(
                f"{len(missing)} keyframe(s) dropped: a newer frame arrived but not theirs",
                throttle_duration_sec=WARN_THROTTLE_S,
            )

    def _on_keyframe(self, msg: PoseStamped) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        warn = None
        with self._wake:
            self.counters["keyframe_msgs"] += 1
            if stamp in self._queued_ids or stamp in self._waiting:
                self.counters["keyframes_duplicate"] += 1
                warn = (f"keyframe {stamp}: named before (in the map or on its way), not inserted twice "
                        f"({self.counters['keyframes_duplicate']} so far; a looped or replayed bag repeats its "
                        "stamps)")  # fmt: skip
            elif stamp in self._intrinsics_refusals:  # its frame came, but not for this map
                self.counters["keyframes_missing"] += 1
                warn = f"keyframe {stamp}: its frame was refused ({self._intrinsics_refusals[stamp]}); dropped"
            elif stamp in self._frames:
                self._enqueue(self._frames[stamp])
            elif not self._frames or stamp > next(reversed(self._frames)):
                if len(self._waiting) >= self.max_pending:
                    self.counters["keyframes_dropped_overflow"] += 1
                    warn = f"keyframe {stamp}: too many keyframes wait for their frames; dropped"
                else:
                    self._waiting[stamp] = [time.monotonic(), 0]
            else:
                self.counters["keyframes_missing"] += 1
                refused = self.camera.rejection_of(stamp)
                oldest, newest = next(iter(self._frames)), next(reversed(self._frames))
                if refused:
                    why = f"refused ({refused})"
                elif stamp < oldest and len(self._frames) >= self.buffer_size:  # named later than the buffer holds
                    why = (f"already out of the buffer, which holds the last {len(self._frames)} frames "
                           f"({(newest - oldest) * 1e-9:.1f} s; named {(newest - stamp) * 1e-9:.1f} s after it): "
                           "raise frame_buffer_size")  # fmt: skip
                else:
                    why = "never received"
                warn = f"keyframe {stamp}: its frame was {why}; dropped"
            if warn:
                self.last_keyframe_drop = warn
        if warn:
            self.get_logger().warning(warn, throttle_duration_sec=WARN_THROTTLE_S)

    def _enqueue(self, frame: Frame) -> None:
        """Queue a keyframe for the worker (call with ``self._wake`` held); drops the oldest when full."""
        self._queued_ids.add(frame.index)
        self._pending.append(frame)
        if len(self._pending) > self.max_pending:
            old = self._pending.popleft()
            self._queued_ids.discard(old.index)
            self.counters["keyframes_dropped_overflow"] += 1
            self.get_logger().warning(
                f"keyframe queue full ({self.max_pending}): dropped keyframe {old.index}",
                throttle_duration_sec=WARN_THROTTLE_S,
            )
        self._wake.notify()

    def _expire_waiting(self) -> None:
        """Drop the keyframes that wait for a frame refused since they were named (at once, with the reason: they
        used to wait out ``keyframe_wait_s`` first), then those that waited longer than that.
        """
        with self._lock:
            refused_now = {
                s: why
                for s in self._waiting
                if (why := self.camera.rejection_of(s) or self._intrinsics_refusals.get(s))
            }
            for s in refused_now:
                del self._waiting[s]
            self.counters["keyframes_missing"] += len(refused_now)
            for s, why in refused_now.items():
                self.last_keyframe_drop = f"keyframe {s}: its frame was refused ({why}); dropped"
        for s, why in refused_now.items():
            self.get_logger().warning(f"keyframe {s}: its frame was refused ({why}); dropped")
        now = time.monotonic()
        with self._lock:
            expired = [s for s, (t, _) in self._waiting.items() if now - t > self.wait_s]
            for s in expired:
                del self._waiting[s]
            self.counters["keyframes_missing"] += len(expired)
        if expired:
            with self._lock:
                late_refusals = [self._intrinsics_refusals.get(s) for s in expired]
            refused = [
                why
                for s, late in zip(expired, late_refusals, strict=True)
                if (why := self.camera.rejection_of(s) or late)
            ]
            because = f" ({len(refused)} refused, the last: {refused[-1]})" if refused else ""
            with self._lock:
                total = self.counters["keyframes_missing"]
                warn = (f"{len(expired)} keyframe(s) dropped ({total} missing so far): their frames did not arrive "
                        f"within {self.wait_s:g} s{because}")  # fmt: skip
                self.last_keyframe_drop = warn
            self.get_logger().warning(warn, throttle_duration_sec=WARN_THROTTLE_S)

    # ------------------------------------------------------------------------------ worker
    def _work(self) -> None:
        while not self._stop.is_set():
            with self._wake:
                if not self._pending and self._idle_left <= 0:
                    self._busy = False
                    self._wake.wait(0.5)
                frame = self._pending.popleft() if self._pending else None
                self._busy = frame is not None or self._idle_left > 0
            try:
                if frame is not None:
                    self._insert(frame)
                elif self._idle_left > 0:
                    n = min(self.slice_iters, self._idle_left)
                    self._idle_left -= n
                    with self.shared.lock:
                        m = self.shared.mapper
                        if m is not None and m.keyframes:
                            m.optimise(n, newest=None)
                            self.shared.touch()
                    self._yield()
            except Exception as exc:  # keep mapping: one bad keyframe must not stop the node
                with self._lock:
                    self.counters["keyframes_failed"] += 1
                self.get_logger().error(f"mapping step failed: {exc}")

    def _yield(self) -> None:
        """Between two slices: let waiting readers take the lock, and pause while the in-process planner works."""
        self.shared.yield_to_readers()
        if self.yield_s > 0:
            paused = self.shared.yield_to_answers(self.yield_s, self._stop.is_set)
            if paused > 0.001:
                with self._lock:
                    self.counters["paused_for_planner_s"] += paused

    def _insert(self, frame: Frame) -> None:
        """Run the library's keyframe schedule, releasing the map lock between its slices (readers never wait long)."""
        self._yield()  # not even the densification starts while the planner works
        with self.shared.lock:
            m = self.shared.mapper
            if m is None:
                return
        if not m.valid_depth_mask(frame.depth_m).any():  # the sensor's, not a failed insertion: said with its topic
            warn = (f"keyframe {frame.index}: its depth image on {self.camera.topics.depth} has "
                    f"{m.no_depth_reason(frame.depth_m)}; not mapped")  # fmt: skip
            with self._lock:
                self.counters["keyframes_no_depth"] += 1
                self.last_keyframe_drop = warn
            self.get_logger().warning(warn, throttle_duration_sec=WARN_THROTTLE_S)
            return
        steps = m.keyframe_schedule(frame, self.slice_iters, flush_fisher=True)  # Fisher now: snapshots only clone
        ok = False
        while not self._stop.is_set():
            with self.shared.lock:
                if self.shared.mapper is not m:  # a map was loaded meanwhile
                    return
                try:
                    next(steps)
                except StopIteration as done:
                    ok = bool(done.value)
                    break
                except InputError as exc:
                    self.get_logger().warning(f"keyframe {frame.index} not inserted: {exc}")
                    break
                finally:
                    self.shared.touch()
                    n_kf = len(m.keyframes) + len(m.loaded_keyframe_ids)
            self._yield()
        if not ok:
            if not self._stop.is_set():
                with self._lock:
                    self.counters["keyframes_failed"] += 1
            return
        with self._lock:
            self.counters["keyframes_inserted"] += 1
            self._idle_left += self.idle_iters
        if n_kf == 1 and self._publishes_maps:
            # A planner in another process has nothing to score until a map with a keyframe comes: the first one
            # goes out now, not at the timer's next tick (up to 1 / map_publish_rate_hz later; the first windows of
            # a three-process run found no map and went to the fallback).
            self.publish_map()
        if self.autosave_dir and self.autosave_every and n_kf % self.autosave_every == 0:
            self.autosave()

    def autosave(self) -> bool:
        """Save the map to ``autosave_dir`` (replacing the last autosave); a failure is logged and counted as a failed
        autosave (``autosaves_failed``), not as a failed keyframe: the keyframe is mapped.
        """
        try:
            self.save(self.autosave_dir, overwrite=True)
        except (InputError, OSError) as exc:
            self.get_logger().error(f"autosave to {self.autosave_dir} (autosave_dir) failed: {exc}")
            with self._lock:
                self.counters["autosaves_failed"] += 1
            return False
        with self._lock:
            self.counters["autosaves"] += 1
        return True

    def wait_idle(self, timeout_s: float) -> bool:
        """Block until no keyframe is queued or waiting and the worker is idle; False on timeout."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if not self._pending and not self._waiting and not self._busy:
                    return True
            time.sleep(0.02)
        return False

    # ------------------------------------------------------------------------------ outputs
    def publish_map(self, force: bool = False) -> bool:
        """Publish the map cloud and keyframe poses if the map changed since the last time; True if published."""
        with self._publish_lock:
            if not force and self.shared.version == self._published_version:
                return False
            snap = self.shared.snapshot(with_h_train=self.map_with_h_train)
            if snap is None:
                return False
            stamp = self.get_clock().now().nanoseconds
            outputs = snap.config.fisher_outputs
            self._map_pub.publish(surfel_map_to_cloud(snap.surfel_map, stamp, self.frame_id, snap.h_train, outputs))
            self._poses_pub.publish(poses_to_array(snap.keyframe_poses, stamp, self.frame_id))
            self._map_info_pub.publish(intrinsics_to_camera_info(snap.intrinsics, stamp, self.frame_id))
            self._published_version = snap.version
        with self._lock:
            self.counters["map_publishes"] += 1
        return True

    def status(self) -> dict[str, Any]:
        """Counters: frames, keyframes (ids are stamps in ns), queue sizes, drops by reason, map size."""
        cam = self.camera.stats()
        # One read under the map lock, counters taken inside it: the worker counts an insertion only after
        # adding its keyframe, so ``keyframes`` is the loaded ones + ``keyframes_inserted`` (+1 in insertion).
        with self.shared.reading(), self._lock:
            m = self.shared.mapper
            snap_ids = self.shared.keyframe_ids()
            surfels = 0 if m is None else m.n_surfels
            stats = {} if m is None else dict(vars(m.stats))
            return {
                "frames_received": cam["frames"],
                **camera_status(cam),
                "keyframes": len(snap_ids),
                "keyframe_ids": snap_ids,
                "surfels": surfels,
                "pending_keyframes": len(self._pending),
                "waiting_keyframes": len(self._waiting),
                "buffered_frames": len(self._frames),
                "map_version": self.shared.version,
                "last_keyframe_drop": self.last_keyframe_drop,
                **self.counters,
                "mapper_stats": stats,
            }

    def publish_status(self) -> None:
        """Publish :meth:`status` as JSON on ``~/status``."""
        self._status_pub.publish(String(data=json.dumps(self.status())))

    def save(
        self, directory: str, with_mesh: bool = False, overwrite: bool = False, overwrite_hint: str | None = None
    ) -> tuple[int, int]:
        """Save the map (atomically) into ``directory``; returns (keyframes, surfels). ``overwrite_hint``: how the
        caller's user replaces an existing folder (:meth:`SharedMapper.save`).
        """
        snap = self.shared.save(directory, with_mesh=with_mesh, overwrite=overwrite, overwrite_hint=overwrite_hint)
        return len(snap.keyframe_ids), snap.n_surfels

    def _on_save(self, req: SaveMap.Request, res: SaveMap.Response) -> SaveMap.Response:
        try:
            if not req.directory:
                raise InputError("directory", "no folder given")
            directory = request_folder(req.directory)
            check_writable(directory)  # as the command line: a path under a file "is not a folder", not Errno 17
            # An existing folder's error names the request field, not the command line's --overwrite.
            hint = "set overwrite: true in the request"
            res.keyframes, res.surfels = self.save(str(directory), req.with_mesh, req.overwrite, overwrite_hint=hint)
            res.success = True
            res.message = f"saved {res.keyframes} keyframes, {res.surfels} surfels to {directory}"
            self.get_logger().info(res.message)
        except (InputError, OSError) as exc:
            res.success, res.message = False, str(exc)
            self.get_logger().warning(f"save_map failed: {exc}")
        except Exception as exc:  # a service callback that raises ends the node's executor: answer instead
            res.success, res.message = False, f"directory {req.directory!r}: {type(exc).__name__}: {exc}"
            self.get_logger().error(f"save_map failed: {res.message}")
        return res

    def _on_load(self, req: LoadMap.Request, res: LoadMap.Response) -> LoadMap.Response:
        try:
            if not req.directory:
                raise InputError("directory", "no folder given")
            with self.shared.lock:
                current = self.shared.mapper.intr if self.shared.mapper is not None else None
            directory = request_folder(req.directory)
            loaded = self.shared.load(directory, expect_intr=current)
            self._intr = loaded.intr
            ids = set(self.shared.keyframe_ids())  # map lock first, then node lock (as status does)
            with self._lock:
                self._queued_ids = ids
            res.success = True
            res.keyframes, res.surfels = len(loaded.loaded_keyframe_ids), loaded.n_surfels
            res.message = f"loaded {res.keyframes} keyframes, {res.surfels} surfels from {directory}"
            self.get_logger().info(res.message)
        except (InputError, OSError, ValueError, KeyError) as exc:
            res.success, res.message = False, str(exc)
            self.get_logger().warning(f"load_map failed: {exc}")
        except Exception as exc:  # a service callback that raises ends the node's executor: answer instead
            res.success, res.message = False, f"directory {req.directory!r}: {type(exc).__name__}: {exc}"
            self.get_logger().error(f"load_map failed: {res.message}")
        return res

    def _on_mesh(self, req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        try:
            res.message = self._run_interruptible(self.publish_mesh)
            res.success = True
        except InputError as exc:
            res.success, res.message = False, str(exc)
        return res

    def publish_mesh(self) -> str:
        """Build the TSDF mesh, decimate it for display and publish it on ``~/mesh``; returns what was sent."""
        mesh, snap = self.shared.mesh()
        n_full = len(mesh.triangles)
        mesh = decimate_mesh(mesh, self.mesh_max_triangles)
        colours = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None
        stamp = self.get_clock().now().nanoseconds
        self._mesh_pub.publish(
            mesh_marker_cdr(np.asarray(mesh.vertices), np.asarray(mesh.triangles), colours, stamp, self.frame_id)
        )
        shown = f"{len(mesh.triangles)} of {n_full}" if len(mesh.triangles) < n_full else f"{n_full}"
        return (
            f"mesh of {len(snap.keyframe_ids)} keyframes: {len(mesh.vertices)} vertices, "
            f"{shown} triangles on {self.resolve_topic_name('~/mesh')}"
        )

    def _run_interruptible(self, work: Callable[[], str], poll_s: float = 0.1) -> str:
        """Run ``work`` in a daemon thread and wait for it, giving up (InputError) when the node stops.

        The request is answered at once then, but the thread runs on (Open3D's mesh extraction cannot be cut short):
        :meth:`destroy_node` waits for it, as a process that exits with a thread inside Open3D aborted (rc 134).
        """
        box: dict[str, Any] = {}

        def target() -> None:
            try:
                box["value"] = work()
            except BaseException as exc:  # handed to the waiting callback
                box["error"] = exc

        thread = threading.Thread(target=target, name=f"{self.get_name()}_service_work", daemon=True)
        with self._lock:
            self._service_threads = [t for t in self._service_threads if t.is_alive()] + [thread]
        thread.start()
        while thread.is_alive():
            thread.join(poll_s)
            if self._stop.is_set() or not self.context.ok():
                raise InputError("service", "the node is shutting down; request abandoned")
        if "error" in box:
            raise box["error"]
        return box["value"]

    # ------------------------------------------------------------------------------ teardown
    def stop(self) -> None:
        """Ask the worker and any long service work to stop (returns at once; destroy_node joins the worker)."""
        self._stop.set()
        with self._wake:
            self._wake.notify_all()

    def destroy_node(self) -> None:
        """Stop and join the worker thread and any service work still running, then destroy the node."""
        self._stop_worker()
        with self._lock:
            service_threads, self._service_threads = self._service_threads, []
        for thread in service_threads:
            if thread is not threading.current_thread():
                thread.join()
        super().destroy_node()

    def _stop_worker(self) -> None:
        if self._thread is None:
            return
        self._stop.set()
        with self._wake:
            self._wake.notify_all()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join()


def main(args: list[str] | None = None) -> int:
    """Console script ``mapper``: run until Ctrl-C; exit 2 on a bad parameter."""
    return run_nodes("mapper", lambda: [MapperNode()], args, description=__doc__)


if __name__ == "__main__":
    sys.exit(main())
