"""``nbv_planner`` node: scores candidate views against the current map on request (ROI-GSurFisher and ablations).

Holds the map: with ``shared`` (in-process) it snapshots the SharedMapper; otherwise it reads the
mapper's ``/roigsf/map`` cloud, ``/roigsf/keyframe_poses`` and the intrinsics: the map's, which the mapper publishes
on ``/roigsf/map_camera_info`` (``map_camera_info_topic``), else the camera's (``camera_info_topic``, scaled to
``input_width``/``input_height``). A map loaded by the mapper is thus scored before any camera publishes (with the
camera's only, every request answered "map not ready" until one did). It keeps
the scoring TSDF, fused (as in the paper and :class:`roigsf_ros.policies.stream.StreamNBVPolicy`) from the
map's rendered depth at each keyframe pose, incrementally: each keyframe is fused once, when first
seen (a timer every ``tsdf_sync_period_s`` and every request); a keyframe set that is no longer an
extension of the fused one (a loaded map) rebuilds it. What the scorer derives from the TSDF alone, its
near-surface voxels and the close-front memory W_f over the fused poses (exact: every pose on the
current voxels), is kept with it and rebuilt only when a keyframe is fused, not at every request: with a
loaded map (the whole room, 20+ keyframes) it was ~2/3 of the scorer's set-up, 1-4 s per request.
The timer also brings H_train up to date between requests, so the one-time catch-up of a loaded map
(its keyframes' Fisher: the mapper has no images of them) starts at load, not at the first request.

H_train: the mapper's running training Fisher when it fits the mode (in-process: from the snapshot;
from another process: the ``htrain_`` fields of the map cloud), as the mapper keeps it: each
keyframe's Fisher is added once, at insertion, under the map of that moment; densified surfels start
at zero, pruned ones drop out. Otherwise (FisherRF's parameters, ``sigma_p`` != 1, a loaded map whose
keyframes the mapper has no images of) :class:`TrainFisherCache` keeps the same approximation here:
the Fisher of each keyframe pose not seen before is added under the current map, the rows carried
over to the current surfels (:func:`match_surfels`); recomputed from scratch only when the keyframe
set is not an extension of the one summed (a loaded map) or every ``h_train_refresh_every`` new poses.

A request carries at most ``max_candidates`` poses (default 64, 8x the selector's window): scoring costs
about 0.1 s per candidate on 2 cores, and one request of 10,000 held the service (and every request queued
behind it) for minutes; a longer list is refused, ``success: false``, before any work. Scoring checks
between candidates (and between keyframes fused, training views summed) whether the node is stopping, so
Ctrl-C during a long request exits within one candidate's work (the request answers ``success: false``).

At start-up (``warm_up``, default true) the planner runs mapping and scoring once on a tiny scene
(:func:`roigsf_ros.nbv.warmup.warm_up_once`): the numba kernels compile on first use, 15-60 s with a cold
cache, and on a fresh machine the first windows of the demo then found the planner busy compiling and
were decided by the fallback. With a warm cache it takes about a second.

Requests older than ``max_request_age_s`` (their ``candidates.header.stamp``; 0 = unstamped, always
served) are refused before scoring, "stale request": the selector has given up on them by then, and
scoring them would only delay the next window's request. A stamp ahead of the planner's clock is served up to the
same bound (two machines' clocks differ a little without anything being wrong); beyond it the request is refused
naming the clocks (a sender an hour ahead used to pass the age check unseen, and a sender as far behind is refused as
stale anyway). An empty ``frame_id`` means the map frame.

Service ``~/get_next_best_view`` (``roigsf_interfaces/srv/GetNextBestView``) runs in a callback group of
its own, so a multi-threaded executor keeps serving the node's other callbacks while it scores. It
answers ``success: false`` with a reason for an empty candidate list, an unknown mode or frame, a bad
pose (non-unit quaternion, NaN), or a map that is not ready; scores are always finite. After each
success it publishes ``~/best_view`` (PoseStamped), ``~/candidate_scores`` (MarkerArray: an arrow per
candidate coloured by its fused score, best in green and larger, and its score as text) and
``~/uncertainty`` (32FC1 Image: Eq. 17's pixel uncertainty of the chosen view). ``~/status``
(``std_msgs/String`` JSON, ``status_rate_hz``) carries :meth:`NBVPlannerNode.status`: requests, answers, the
longest scoring, and where the last and the slowest request's time went, so a planner in its own process says
why a selector's windows went to the fallback.

    nbv_planner --ros-args --params-file config/nbv.yaml -p mode:=roi-fisher
"""

from __future__ import annotations

import contextlib
import json
import re
import sys
import threading
import time
from dataclasses import replace
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseArray, PoseStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import String
from visualization_msgs.msg import Marker, MarkerArray

from roigsf_interfaces.srv import GetNextBestView
from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.data.bags import CameraTopics, camera_info_to_intrinsics, stamp_to_ns
from roigsf_ros.mapping.mapper import DEPTH_MODES, MapperConfig
from roigsf_ros.nbv.config import MODES, NBVConfig
from roigsf_ros.nbv.scorer import NBVResult, NBVScorer
from roigsf_ros.nbv.state import ScoringState
from roigsf_ros.nbv.stop import ScoringStoppedError
from roigsf_ros.nbv.warmup import warm_up_once
from roigsf_ros.nodes.bag_player import reliable_qos
from roigsf_ros.nodes.camera_input import WARN_THROTTLE_S, ThrottleByKind, camera_qos, tf_fault_kind
from roigsf_ros.nodes.map_msgs import (
    array_to_poses,
    cloud_h_train,
    cloud_to_surfel_map,
    header,
    matrix_to_pose,
    pose_stamped,
)
from roigsf_ros.nodes.mapper import KEYFRAME_POSES_TOPIC, MAP_CAMERA_INFO_TOPIC, MAP_TOPIC, latched_qos
from roigsf_ros.nodes.node_params import (
    SystemNode,
    changed_parameters,
    check_frame_id,
    check_input_size,
    check_positive,
    declare,
    declare_config,
    settings_text,
)
from roigsf_ros.nodes.node_process import run_nodes
from roigsf_ros.nodes.shared_map import MapSnapshot, SharedMapper, view_mapper

_MAPPER_DEFAULTS = MapperConfig()
SERVICE_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE
)
"""The planner's service: every request kept while others are scored (rclpy's services default keeps the last 10)."""
MAP_NOT_READY = "map: not ready"
"""How the message of an answer starts when the planner has no map to score yet (nothing received, or no keyframe):
not a fault of the request, so a client may ask again shortly (the keyframe selector does, for ``map_wait_s``)."""


def map_not_ready(why: str) -> InputError:
    """The refusal of a request that came before the map did; its message starts with :data:`MAP_NOT_READY`."""
    return InputError("map", f"not ready: {why}")


class NBVPlannerNode(SystemNode):
    """The NBV planner; see the module docstring. ``shared`` given: score the in-process map."""

    default_name = "nbv_planner"

    # ------------------------------------------------------------------------------ set-up
    def _setup(self, shared: SharedMapper | None) -> None:
        self.nbv = NBVConfig(**declare_config(self, NBVConfig))
        d = _MAPPER_DEFAULTS
        self.voxel_size_m = float(declare(self, "voxel_size_m", d.mesh_voxel_size_m, "voxel of the scoring TSDF (m)"))
        self.sdf_trunc_m = float(declare(self, "sdf_trunc_m", d.mesh_sdf_trunc_m, "truncation of the scoring TSDF (m)"))
        self.min_alpha = float(
            declare(self, "min_alpha", d.mesh_min_alpha, "rendered depth is fused where alpha >= this")
        )
        self.render_depth = str(declare(self, "render_depth", d.mesh_depth, "rendered depth fused: median or expected"))
        self.max_depth_m = float(declare(self, "max_depth_m", d.max_depth_m, "depth range of the scoring TSDF (m)"))
        self.render_near_m = float(declare(self, "render_near_m", d.near_m, "near plane of the renders (topic mode)"))
        map_topic = declare(self, "map_topic", MAP_TOPIC, "map cloud of the mapper (used without a shared map)")
        poses_topic = declare(self, "keyframe_poses_topic", KEYFRAME_POSES_TOPIC, "keyframe poses (PoseArray)")
        info_topic = declare(
            self, "camera_info_topic", CameraTopics().camera_info, "camera info (intrinsics, topic mode)"
        )
        map_info_topic = declare(self, "map_camera_info_topic", MAP_CAMERA_INFO_TOPIC, "the map's intrinsics, from "
                                 "the mapper (topic mode; preferred to camera_info_topic)")  # fmt: skip
        info_qos = camera_qos(10, str(declare(self, "camera_reliability", "reliable", "reliable | best_effort")))
        in_w = int(declare(self, "input_width", 0, "camera info scaled to the mapper's input_width (0 = as sent)"))
        in_h = int(declare(self, "input_height", 0, "camera info scaled to the mapper's input_height (0 = as sent)"))
        self.input_size = check_input_size(in_w, in_h)
        self.frame_id = check_frame_id(
            "frame_id", str(declare(self, "frame_id", "map", "frame of candidate poses and outputs"))
        )
        sync_s = float(declare(self, "tsdf_sync_period_s", 1.0, "seconds between TSDF updates (0 = at requests only)"))
        self.publish_uncertainty = bool(declare(self, "publish_uncertainty", True, "publish Eq. 17 of the best view"))
        self.max_request_age_s = float(
            declare(self, "max_request_age_s", 10.0, "refuse requests stamped longer ago than this (0 = no limit)")
        )
        self.max_candidates = int(declare(self, "max_candidates", 64, "most candidate poses one request may carry"))
        warm_up = bool(declare(self, "warm_up", True, "compile the numba kernels at start-up (tiny scene)"))
        refresh = int(declare(self, "h_train_refresh_every", 0, "full H_train recompute every this many new poses"))
        match_tol = float(declare(self, "h_train_match_tol_m", 0.01, "surfel centre drift tolerated when carrying H"))
        status_hz = float(declare(self, "status_rate_hz", 1.0, "~/status publications per second (0 = none)"))
        check_positive("max_request_age_s", self.max_request_age_s, allow_zero=True)
        check_positive("max_candidates", self.max_candidates)
        check_positive("h_train_refresh_every", refresh, allow_zero=True)
        check_positive("h_train_match_tol_m", match_tol)
        check_positive("status_rate_hz", status_hz, allow_zero=True)
        check_positive("voxel_size_m", self.voxel_size_m)
        check_positive("max_depth_m", self.max_depth_m)
        check_positive("render_near_m", self.render_near_m)
        check_positive("tsdf_sync_period_s", sync_s, allow_zero=True)
        if self.sdf_trunc_m < self.voxel_size_m:
            raise InputError("parameter 'sdf_trunc_m'", f"must be >= voxel_size_m ({self.voxel_size_m})")
        if not 0.0 <= self.min_alpha <= 1.0:
            raise InputError("parameter 'min_alpha'", f"must be in [0, 1], got {self.min_alpha}")
        if self.render_depth not in DEPTH_MODES:
            raise InputError("parameter 'render_depth'", f"must be one of {', '.join(DEPTH_MODES)}")

        self.shared = shared
        self._stop = threading.Event()
        self._lock = threading.Lock()  # topic-mode map state and counters
        self._cloud: PointCloud2 | None = None
        self._cloud_version = 0
        self.map_publisher_gone = False
        """True once the map's last publisher left after a map came (the mapper stopped): answers use the last map."""
        self._poses = np.zeros((0, 4, 4))
        self._intr: Intrinsics | None = None
        """The camera's intrinsics (``camera_info_topic``), scaled to the input size."""
        self._map_intr: Intrinsics | None = None
        """The map's intrinsics (``map_camera_info_topic``): preferred, they are what the map was built with."""
        self._topic_snapshot: MapSnapshot | None = None
        self.state = ScoringState(
            self.nbv, self.voxel_size_m, self.sdf_trunc_m, self.max_depth_m, True, match_tol, refresh,
            should_stop=self.stopping,
        )  # fmt: skip
        """TSDF, its products and the H_train cache, kept between requests (ROS-free, one callback group)."""
        self.last_result: NBVResult | None = None
        self._refusal_warnings = ThrottleByKind()  # by the request field at fault
        self.counters: dict[str, Any] = dict.fromkeys(
            ("requests", "answered", "failed", "stale", "not_ready", "bad_map_msgs"), 0
        )
        self.counters["last_refusal"] = ""  # why the last request was not scored (the count alone said nothing)
        self.counters["last_scoring_s"] = 0.0
        self.counters["max_scoring_s"] = 0.0
        self.counters["max_request_wait_s"] = 0.0
        self.counters["max_sync_s"] = 0.0
        self.counters["warm_up_s"] = 0.0
        self._last_phases_s: dict[str, float] = {}
        self._slowest_phases_s: dict[str, float] = {}
        self._slowest_request_s = -1.0
        if warm_up:  # before the service exists: no request waits behind the compiler
            try:
                times = warm_up_once(self.nbv)
            except Exception as exc:  # the real calls compile on first use then; the node still serves
                self.get_logger().warning(f"kernel warm-up failed ({exc}): kernels compile at the first request")
                times = None
            if times is not None:
                self.counters["warm_up_s"] = times["total_s"]
                self.get_logger().info(f"numba kernels ready in {times['total_s']:.1f} s (warm-up on a tiny scene)")

        scoring = MutuallyExclusiveCallbackGroup()
        inputs = MutuallyExclusiveCallbackGroup()
        if shared is None:  # the parameters' names: rcl remaps them once (a remapped name would be remapped again)
            self.create_subscription(PointCloud2, map_topic, self._on_cloud, latched_qos(), callback_group=inputs)
            self.create_subscription(PoseArray, poses_topic, self._on_poses, latched_qos(), callback_group=inputs)
            self.create_subscription(CameraInfo, info_topic, self._on_info, info_qos, callback_group=inputs)
            self.create_subscription(
                CameraInfo, map_info_topic, self._on_map_info, latched_qos(), callback_group=inputs
            )
        # as subscribed (namespace, remapping): the graph checks and logs named the parameters' values, so a remapped
        # map read "no node publishes the map (the mapper stopped?)" while it came
        map_topic, info_topic, map_info_topic, poses_topic = (
            self.resolve_topic_name(name) for name in (map_topic, info_topic, map_info_topic, poses_topic)
        )
        self._map_topic, self._info_topic, self._map_info_topic = map_topic, info_topic, map_info_topic
        self._best_pub = self.create_publisher(PoseStamped, "~/best_view", latched_qos())
        self._markers_pub = self.create_publisher(MarkerArray, "~/candidate_scores", latched_qos())
        self._uncertainty_pub = self.create_publisher(Image, "~/uncertainty", latched_qos())
        # Requests wait in the service's queue while one is scored: keep every one. With the services' default
        # (keep the last 10) a burst of 30 lost 19 without an answer, and a client without a timeout hung.
        self.create_service(
            GetNextBestView, "~/get_next_best_view", self._on_request, qos_profile=SERVICE_QOS, callback_group=scoring
        )
        self._status_pub = self.create_publisher(String, "~/status", reliable_qos(10))
        if status_hz > 0:  # its own group: published while a request is being scored
            self.create_timer(1.0 / status_hz, self.publish_status, callback_group=MutuallyExclusiveCallbackGroup())
        if sync_s > 0:
            self.create_timer(sync_s, self._sync_timer, callback_group=scoring)
        if shared is None:
            self.create_timer(1.0, self._watch_map_publisher, callback_group=inputs)
        source = (
            "the shared in-process map"
            if shared is not None
            else f"{map_topic} + {poses_topic} + {map_info_topic} (else {info_topic})"
        )
        changed = {k: v for k, v in self.nbv.changed().items() if k != "mode"}
        changed |= changed_parameters(self, exclude=(*self.nbv.to_dict(), "warm_up"))  # the node's own too
        self.get_logger().info(f"scoring ({self.nbv.mode}{settings_text(changed)}) against {source}")

    # ------------------------------------------------------------------------------ topic inputs
    def _watch_map_publisher(self) -> None:
        """Say once when the map's last publisher leaves after a map came (the mapper stopped: the planner goes on
        answering from the last map it received, which no longer grows), and when one is back.
        """
        live = self.count_publishers(self._map_topic) > 0
        with self._lock:
            had_map, was_gone = self._cloud is not None, self.map_publisher_gone
            self.map_publisher_gone = had_map and not live
        if self.map_publisher_gone and not was_gone:
            self.get_logger().warning(
                f"no node publishes the map on {self._map_topic} now (the mapper stopped?): requests are answered from "
                "the last map received, which no longer grows"
            )
        elif was_gone and live:
            self.get_logger().info(f"a node publishes the map on {self._map_topic} again")

    def _on_cloud(self, msg: PointCloud2) -> None:
        with self._lock:
            self._cloud = msg
            self._cloud_version += 1

    def _on_poses(self, msg: PoseArray) -> None:
        try:
            poses = array_to_poses(msg, "keyframe poses")
        except InputError as exc:
            with self._lock:
                self.counters["bad_map_msgs"] += 1
            self.get_logger().warning(f"ignored: {exc}", throttle_duration_sec=WARN_THROTTLE_S)
            return
        with self._lock:
            self._poses = poses
            self._cloud_version += 1

    def _on_info(self, msg: CameraInfo) -> None:
        try:
            intr = camera_info_to_intrinsics(msg)
            if self.input_size is not None:  # the mapper downscales frames on arrival: score at that size
                intr = intr.resized(*self.input_size)
        except InputError as exc:
            self.get_logger().warning(f"ignored: {exc}", throttle_duration_sec=WARN_THROTTLE_S)
            return
        with self._lock:
            self._intr = intr

    def _on_map_info(self, msg: CameraInfo) -> None:
        try:
            intr = camera_info_to_intrinsics(msg, self._map_info_topic)
        except InputError as exc:
            self.get_logger().warning(f"ignored: {exc}", throttle_duration_sec=WARN_THROTTLE_S)
            return
        with self._lock:
            if self._map_intr != intr:
                self._map_intr = intr
                self._cloud_version += 1

    # ------------------------------------------------------------------------------ map and TSDF
    def snapshot(self) -> MapSnapshot | None:
        """The map to score: a shared snapshot, or one built from the latest cloud/poses/intrinsics."""
        if self.shared is not None:
            return self.shared.snapshot()
        with self._lock:
            cloud, poses, version = self._cloud, self._poses, self._cloud_version
            intr = self._map_intr or self._intr
            cached = self._topic_snapshot
        if cloud is None or intr is None:
            return None
        if cached is not None and cached.version == version:
            return cached
        try:
            surfels = cloud_to_surfel_map(cloud)
            carried = cloud_h_train(cloud)
        except InputError as exc:
            with self._lock:
                self.counters["bad_map_msgs"] += 1
            self.get_logger().warning(f"ignored: {exc}", throttle_duration_sec=WARN_THROTTLE_S)
            return None
        cfg = MapperConfig(near_m=self.render_near_m, max_depth_m=self.max_depth_m, track_h_train=False)
        h = None
        if carried is not None:
            cfg = replace(cfg, fisher_outputs=carried[0])
            h = carried[1]
        snap = MapSnapshot(surfels, h, list(range(len(poses))), poses, intr, cfg, version)
        with self._lock:
            self._topic_snapshot = snap
        return snap

    def _waiting_for(self) -> str:
        """What the planner has not received yet, naming the topics (a shared map: the mapper's first keyframe)."""
        if self.shared is not None:
            return "no keyframe in the shared map yet"
        with self._lock:
            missing = [f"a map on {self._map_topic}"] if self._cloud is None else []
            if self._intr is None and self._map_intr is None:
                missing.append(f"camera info on {self._map_info_topic} (the mapper's) or {self._info_topic}")
        return "nothing received yet: " + " and ".join(missing) if missing else "the map is not readable"

    def _render(self, snap: MapSnapshot):
        """The snapshot's rendered RGB-D at a pose, as the scoring TSDF fuses it."""
        view = view_mapper(snap.surfel_map, snap.intrinsics, snap.config)
        return lambda T: view.rendered_rgbd(T, self.render_depth, self.min_alpha)

    def _update(self, snap: MapSnapshot, mode: str):
        """Bring the scoring state up to date with ``snap`` for ``mode`` (TSDF, its products, H_train)."""
        outputs = tuple(snap.config.fisher_outputs)
        return self.state.update(
            snap.surfel_map, snap.h_train, outputs, snap.keyframe_poses, snap.intrinsics, self._render(snap), mode
        )

    def _answering(self) -> contextlib.AbstractContextManager[None]:
        """The in-process mapper pauses its optimisation while this is held (its ``yield_to_planner_s``)."""
        return self.shared.answering() if self.shared is not None else contextlib.nullcontext()

    def stopping(self) -> bool:
        """True once :meth:`stop` was called or the context shut down: long scoring gives up."""
        return self._stop.is_set() or not self.context.ok()

    def stop(self) -> None:
        """Make scoring in progress give up within one candidate's work (returns at once)."""
        self._stop.set()

    def _sync_timer(self) -> None:
        """Between requests: fuse new keyframes, rebuild what derives from the TSDF, bring H_train up to date."""
        snap = self.snapshot()
        if snap is None or len(snap.keyframe_poses) == 0 or snap.n_surfels == 0 or self.stopping():
            return
        t0 = time.perf_counter()
        try:
            with self._answering():  # the next answer's work, done ahead
                self._update(snap, self.nbv.mode)
                self.state.reserve_ahead()  # a TSDF block-map rehash here, not inside a request
        except ScoringStoppedError:
            return
        except InputError as exc:
            self.get_logger().warning(f"map update failed: {exc}", throttle_duration_sec=WARN_THROTTLE_S)
        dt = time.perf_counter() - t0
        with self._lock:
            self.counters["max_sync_s"] = max(self.counters["max_sync_s"], dt)

    # ------------------------------------------------------------------------------ service
    def _on_request(self, req: GetNextBestView.Request, res: GetNextBestView.Response) -> GetNextBestView.Response:
        t0 = time.perf_counter()
        stamp_ns = stamp_to_ns(req.candidates.header.stamp)
        wait_s = (self.get_clock().now().nanoseconds - stamp_ns) * 1e-9 if stamp_ns > 0 else 0.0
        with self._lock:
            self.counters["requests"] += 1
            self.counters["max_request_wait_s"] = max(self.counters["max_request_wait_s"], wait_s)
        try:
            with self._answering():
                result, snap, cands = self.score_request(req)
        except ScoringStoppedError:
            res.success, res.message, res.best_index = False, "nbv_planner: shutting down, not scored", -1
            with self._lock:
                self.counters["failed"] += 1
            return res
        except InputError as exc:
            res.success, res.message, res.best_index = False, str(exc), -1
            # candidates[3] and candidates[7]: one kind of fault; a NaN position and one 1e6 m away: two (one kind per
            # field hid the second behind the first's throttle)
            field = re.sub(r"\[\d+\]", "[i]", str(exc.where))
            kind = f"{field}: {tf_fault_kind(exc)}"
            with self._lock:
                self.counters["failed"] += 1
                self.counters["stale"] += int(exc.where == "candidates.header.stamp")
                self.counters["not_ready"] += int(str(exc).startswith(MAP_NOT_READY))
                self.counters["last_refusal"] = str(exc)
                due = self._refusal_warnings.due(kind)  # each caller has its message; the log, each kind
            if due:
                self.get_logger().warning(f"get_next_best_view: {exc}")
            return res
        stamp = self.get_clock().now().nanoseconds
        best = int(result.best_index)
        res.success = True
        res.message = result.reason or f"scored {len(cands)} candidate{'s' if len(cands) != 1 else ''} ({result.mode})"
        res.best_index = best
        res.best_pose = pose_stamped(cands[best], stamp, self.frame_id)
        res.top_k_indices = [int(i) for i in result.top_k]
        res.fused_scores = [float(v) for v in result.fused]
        res.fisher_scores = [float(v) for v in result.fisher]
        res.close_front_scores = [float(v) for v in result.close_front]
        self.last_result = result
        self._best_pub.publish(res.best_pose)
        self._markers_pub.publish(self.score_markers(cands, result, stamp))
        if self.publish_uncertainty:
            self._publish_uncertainty(snap, result.mode, cands[best], stamp)
        with self._lock:
            self.counters["answered"] += 1
            self.counters["last_scoring_s"] = time.perf_counter() - t0
            self.counters["max_scoring_s"] = max(self.counters["max_scoring_s"], self.counters["last_scoring_s"])
        return res

    def score_request(self, req: GetNextBestView.Request) -> tuple[NBVResult, MapSnapshot, np.ndarray]:
        """Validate a request and score it; InputError with the reason for every refusal."""
        mode = req.mode or self.nbv.mode
        if mode not in MODES:
            raise InputError("mode", f"unknown score mode '{mode}' (choose from {', '.join(MODES)})")
        if not req.candidates.poses:
            raise InputError("candidates", "empty candidate list")
        if len(req.candidates.poses) > self.max_candidates:
            raise InputError(
                "candidates",
                f"{len(req.candidates.poses)} poses, more than max_candidates ({self.max_candidates}); "
                "send at most that many per request (or raise the parameter)",
            )
        frame = req.candidates.header.frame_id
        if frame and frame.lstrip("/") != self.frame_id.lstrip("/"):  # "/map" is "map", as TF reads it
            raise InputError("candidates.header.frame_id", f"'{frame}' is not the map frame '{self.frame_id}'")
        cands = array_to_poses(req.candidates, "candidates")
        self._check_age(req)
        snap = self.snapshot()
        if snap is None:
            raise map_not_ready(self._waiting_for())
        if len(snap.keyframe_poses) == 0 or snap.n_surfels == 0:
            k, n = len(snap.keyframe_poses), snap.n_surfels
            raise map_not_ready(f"{k} keyframes, {n} surfels")
        t_update = time.perf_counter()
        self._update(snap, mode)  # the map work (kept for the next request) may take a while: check the age again
        update_s = time.perf_counter() - t_update
        self._check_age(req)
        top_k = int(req.top_k) if req.top_k > 0 else len(cands)
        outputs = tuple(snap.config.fisher_outputs)
        t_score = time.perf_counter()
        result = self.state.score(
            snap.surfel_map, snap.h_train, outputs, snap.keyframe_poses, cands, snap.intrinsics,
            self._render(snap), mode=mode, top_k=top_k,
        )  # fmt: skip
        score_s = time.perf_counter() - t_score
        parts = {k: v for k, v in result.timings_s.items() if not k.endswith("_cpu") and k != "roi_close_front"}
        phases = {"map_update": update_s, "scoring": score_s, **parts}
        with self._lock:
            self._last_phases_s = phases
            if update_s + score_s > self._slowest_request_s:
                self._slowest_request_s, self._slowest_phases_s = update_s + score_s, phases
        return result, snap, cands

    def _check_age(self, req: GetNextBestView.Request) -> None:
        """InputError "stale request" when the candidates' stamp is older than ``max_request_age_s``, and one naming the
        clocks when it is that far in the future (a sender whose clock runs ahead got past the age check unseen).
        """
        stamp_ns = stamp_to_ns(req.candidates.header.stamp)
        if stamp_ns <= 0 or self.max_request_age_s <= 0:
            return
        now_ns = self.get_clock().now().nanoseconds
        age_s = (now_ns - stamp_ns) * 1e-9
        sim = ""
        if self.get_parameter("use_sim_time").value:  # the usual cause of a clock apart: a sender on wall time
            sim = f" (the planner runs on /clock, use_sim_time, which reads {now_ns * 1e-9:.1f} s)"
        if age_s > self.max_request_age_s:
            raise InputError(
                "candidates.header.stamp",
                f"stale request: sent {age_s:.1f} s ago (max_request_age_s {self.max_request_age_s:g}){sim}; not "
                "scored",
            )
        if -age_s > self.max_request_age_s:
            raise InputError(
                "candidates.header.stamp",
                f"request stamped {-age_s:.1f} s in the future: the sender's clock and the planner's differ by more "
                f"than max_request_age_s ({self.max_request_age_s:g}, which bounds both ways){sim}; not scored",
            )

    def score_markers(self, cands: np.ndarray, result: NBVResult, stamp_ns: int) -> MarkerArray:
        """An arrow per candidate (optical axis) coloured red (worst) to green (best), and its fused score as text."""
        f = result.fused
        span = float(f.max() - f.min()) if len(f) else 0.0
        out = MarkerArray()
        clear = Marker(header=header(stamp_ns, self.frame_id), action=Marker.DELETEALL)
        out.markers.append(clear)
        for i, T in enumerate(cands):
            s = (float(f[i]) - float(f.min())) / span if span > 0 else 1.0
            best = i == result.best_index
            arrow = Marker(header=header(stamp_ns, self.frame_id), ns="nbv_candidates", id=i, type=Marker.ARROW)
            arrow.pose = matrix_to_pose(T @ _Z_TO_X)
            arrow.scale.x, arrow.scale.y, arrow.scale.z = (0.3, 0.04, 0.04) if best else (0.2, 0.02, 0.02)
            arrow.color.r, arrow.color.g, arrow.color.b, arrow.color.a = 1.0 - s, s, 0.0, 1.0
            text = Marker(header=header(stamp_ns, self.frame_id), ns="nbv_scores", id=i, type=Marker.TEXT_VIEW_FACING)
            text.pose = matrix_to_pose(T)
            text.pose.position.z += 0.1
            text.scale.z = 0.05
            text.color.r = text.color.g = text.color.b = text.color.a = 1.0
            text.text = f"{i}: {float(f[i]):+.2f}"
            out.markers += [arrow, text]
        return out

    def _publish_uncertainty(self, snap: MapSnapshot, mode: str, T_wc: np.ndarray, stamp_ns: int) -> None:
        try:
            h_mode = mode if mode != "fisherrf" else "roi-fisher"
            outputs = tuple(snap.config.fisher_outputs)
            h = self.state.h_train(snap.surfel_map, snap.h_train, outputs, snap.keyframe_poses, snap.intrinsics, h_mode)
            u = NBVScorer(self.nbv).uncertainty(snap.surfel_map, h or {}, T_wc, snap.intrinsics, None).u
        except InputError as exc:
            self.get_logger().warning(f"no uncertainty image: {exc}", throttle_duration_sec=WARN_THROTTLE_S)
            return
        img = Image(header=header(stamp_ns, "camera_color_optical_frame"))
        img.height, img.width = u.shape
        img.encoding, img.is_bigendian, img.step = "32FC1", 0, 4 * u.shape[1]
        img.data = np.ascontiguousarray(u, dtype="<f4").tobytes()
        self._uncertainty_pub.publish(img)

    def publish_status(self) -> None:
        """Publish :meth:`status` as JSON on ``~/status``."""
        self._status_pub.publish(String(data=json.dumps(self.status())))

    def status(self) -> dict[str, Any]:
        """Counters: requests, answered, failed (of which ``stale`` and ``not_ready``: before the map came), the last
        refusal's message (``last_refusal``), scoring times, TSDF work, H_train work;
        ``map_publisher_gone``: the map's publisher left after a map came (answers use the last map).

        ``max_request_wait_s``: the longest time from a request's stamp to the start of its handling (for the
        selector, which stamps at sending: the transport and the wait behind the planner's other work);
        ``max_sync_s``: the longest run of the sync timer (keyframes fused, TSDF products, H_train, block map grown);
        ``carved_renders`` / ``carved_carves``: keyframes rendered for and carved into the unseen term's kept grid
        (``unseen_carve_rerender`` false; 0 otherwise, where every request renders and carves them all);
        ``last_phases_s`` / ``slowest_phases_s``: where the last and the slowest scored request's time went, wall
        seconds: ``map_update`` (keyframes fused, H_train), ``scoring`` (the scorer's call) and its phases
        (:attr:`~roigsf_ros.nbv.scorer.NBVResult.timings_s`), to tell which part makes a planner late for its windows.
        """
        st, c = self.state, self.state.train_fisher_cache
        assert c is not None  # the planner always keeps one
        with self._lock:
            return {
                **self.counters,
                "surface_extractions": st.surface_extractions,
                "close_front_builds": st.close_front_builds,
                "close_front_views_added": st.close_front_views_added,
                "tsdf_frames": st.n_fused,
                "h_train_full": c.full_computations,
                "h_train_poses_added": c.poses_added,
                "carved_renders": st.carved.renders if st.carved is not None else 0,
                "carved_carves": st.carved.carves if st.carved is not None else 0,
                "last_phases_s": dict(self._last_phases_s),
                "slowest_phases_s": dict(self._slowest_phases_s),
                "map_publisher_gone": self.map_publisher_gone,
            }


_Z_TO_X = np.array([[0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
"""Rotation taking a marker's x axis (RViz arrows point along x) onto the camera's optical z axis."""


def main(args: list[str] | None = None) -> int:
    """Console script ``nbv_planner``: serve until Ctrl-C; exit 2 on a bad parameter."""
    return run_nodes("nbv_planner", lambda: [NBVPlannerNode()], args, description=__doc__)


if __name__ == "__main__":
    sys.exit(main())
