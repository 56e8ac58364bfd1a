"""``keyframe_selector`` node: picks keyframes from the incoming frames and names them on ``/roigsf/keyframe``.

The first frame is always a keyframe. Then, by ``policy``:

- ``roi-gsurfisher``, ``roi-fisher``, ``close-front``, ``fisherrf`` (the planner policies): the stream
  setting of :class:`roigsf_ros.policies.stream.StreamNBVPolicy`. The node keeps the last ``window``
  frames that are not keyframes; every ``trigger_every`` frames (0 = ``window``) it sends their poses
  to the planner's service (asynchronously: ``call_async`` and a timer that checks the answer, never a
  blocking call in a callback) and names the winner. A window that comes while the previous one is still
  being answered waits for that answer (at most one waits: when a third comes, the older waiting window
  is decided by the fallback); such an answer is often only milliseconds late (a process-wide stall, such
  as open3d growing a TSDF's block map with Python's GIL held, delays its delivery behind the frames that
  trigger the next window). When the planner is not available, answers
  ``success: false`` or does not answer within ``planner_timeout_s``, the window is decided by
  ``fallback_policy`` instead (logged "planner ... did not answer ...: fallback ..."); the next window
  asks the planner again, so the selector resumes using it as soon as it answers. An answer "map not ready"
  (:data:`roigsf_ros.nodes.nbv_planner.MAP_NOT_READY`: no map yet) is not a failure: the window asks again every
  ``ASK_AGAIN_S`` for up to ``map_wait_s`` from its first ask, or until a newer window waits (``planner_not_ready``).
  In three processes the first windows came before the mapper had published its first keyframe's map, and all went
  to the fallback.
- ``random`` (a seeded pick from the window, as the library's stream baseline), ``every-n`` (``every_n``),
  ``gaus-slam`` (``tau_k``, ``alpha_threshold``: needs the map, the shared one or the mapper's ``/roigsf/map``),
  ``all`` and ``novelty`` (beyond the paper: per window the frame whose depth shows the most surface no keyframe's
  depth showed, :mod:`roigsf_ros.nbv.novelty`) decide alone with the library's policies, as does a policy added to the
  library (found by name, reading the map as ``gaus-slam`` does, given the node's parameters it takes and
  ``policy_params`` for its own; a frame it fails on is counted in ``policy_errors`` and not decided). ``gaus-slam``
  judges a frame only once the map holds every keyframe it named before (the shared map's keyframe ids, else the
  positions on ``/roigsf/keyframe_poses``), as GauS-SLAM judges each frame on a map with all earlier keyframes: judged
  at once on a map the mapper has not caught up with, nearly every frame rendered unmapped and became a keyframe, and
  the mapper's queue dropped most. A frame waits at most ``map_wait_s`` (then it is judged on the map as it is;
  ``map_waits_expired``), and at most ``map_wait_frames`` frames wait (the oldest beyond is skipped, not a keyframe;
  ``frames_skipped_map_lag``).

Beyond the paper, ``novelty_weight`` > 0 with a planner policy adds ``novelty_weight x z(N)`` to the planner's fused
scores before the pick (:func:`roigsf_ros.nbv.novelty.fuse_novelty`, as the library's stream policy does), N each
candidate's observed novelty against the depth of the keyframes published so far; the planner scores poses only,
the selector holds the frames. N is computed in a thread of the selector's own while the planner scores the window
(in the node's timer it held the frames back, which then came in bursts, and with them windows faster than any
planner answers); the same thread adds each keyframe's depth, in order, and an answer is taken once its window's N
is in, so no callback of the node waits for either. ``fallback_policy: novelty`` decides an unanswered window by N.
Depth counts within the mapper's depth range (the shared mapper's settings in ``active_mapping``, else the defaults,
0.1-10 m).
``lookahead`` > 0 (with policy ``novelty``, or a planner policy and ``novelty_weight`` > 0) decides each window once
the next ``lookahead`` frames are in, N becoming the lookahead novelty (the library's ``lookahead``); the planner
is asked about the window's frames only. A stream has no end a node could see, so the frames still held when the
input stops are decided when ``~/finish`` (``std_srvs/Trigger``) is called, as the library's ``finish`` decides them
(``roigsf demo`` calls it when the bag ends); without lookahead it does nothing.

In a process of its own the selector subscribes to the camera only once its keyframe topic has a subscriber (the
mapper) and, with a planner policy, the planner's service is there, or ``startup_wait_s`` after start-up (then
saying what is missing; 0 = at once; ``reading_camera`` in the status): a bag player that waits for its subscribers
then waits for the whole pipeline. With the shared map (one process) it subscribes at once (built by
``active_mapping``: right after the mapper). In three processes the mapper's discovery came 2.5-3 s late in about a
third of the runs, and the selector, reading frames already, held its first keyframe that long while its first
windows went to the fallback.

The published ``geometry_msgs/PoseStamped`` carries the chosen frame's header stamp (the mapper finds
the frame by it) and its pose. Keyframes named before any subscriber matched the topic are held and sent, in order,
``MATCH_GRACE_S`` after one has (``keyframes_unsent`` in the status; a warning after 5 s without one): in three
processes discovery had not matched the mapper when the first keyframes were named, and they were lost without a
word. ``~/status`` (``std_msgs/String`` JSON) counts frames, keyframes,
planner calls, failures, timeouts, windows that waited for the previous answer (``planner_waited``) and
fallbacks, and gives the longest wait for an answer to a window of the stream (``max_answer_s``), the slowest
novelty computation (``max_novelty_s``) and the longest gap between two frames reaching the selector
(``max_frame_gap_s``; many frame periods: something held the frames back, and windows then came in a burst);
``window`` lists the candidate window (stamps in ns; the planner path's or the deciding policy's own): the last
``window`` frames not chosen, those that lost a selection too until newer frames push them out (with ``trigger_every``
< ``window`` a later selection can still pick them).

    keyframe_selector --ros-args -p policy:=gaus-slam -p tau_k:=0.02
"""

from __future__ import annotations

import collections
import concurrent.futures
import json
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseArray, PoseStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.task import Future
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from std_srvs.srv import Trigger

from roigsf_interfaces.srv import GetNextBestView
from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame
from roigsf_ros.data.bags import BagFrame
from roigsf_ros.mapping.mapper import Mapper, MapperConfig
from roigsf_ros.nbv.config import MODES
from roigsf_ros.nbv.novelty import (
    NOVELTY_RADIUS_M,
    NOVELTY_VOXEL_M,
    ObservedSurface,
    check_novelty_settings,
    fuse_novelty,
)
from roigsf_ros.nodes.bag_player import reliable_qos
from roigsf_ros.nodes.camera_input import WARN_THROTTLE_S, CameraInput, camera_status, describe_topics
from roigsf_ros.nodes.map_msgs import cloud_to_surfel_map, pose_stamped, poses_to_array
from roigsf_ros.nodes.mapper import (
    KEYFRAME_POSES_TOPIC,
    KEYFRAME_TOPIC,
    MAP_TOPIC,
    camera_params,
    frame_of,
    latched_qos,
)
from roigsf_ros.nodes.nbv_planner import MAP_NOT_READY
from roigsf_ros.nodes.node_params import (
    SystemNode,
    changed_parameters,
    check_frame_id,
    check_positive,
    declare,
    settings_text,
)
from roigsf_ros.nodes.node_process import run_nodes
from roigsf_ros.nodes.shared_map import SharedMapper, view_mapper
from roigsf_ros.policies.base import (
    KeyframePolicy,
    checked_keyframes,
    make_policy,
    parse_params,
    policy_names,
    policy_parameters,
    unknown_policy,
)
from roigsf_ros.policies.stream import CandidateWindow, StreamNBVPolicy, split_lookahead
from roigsf_ros.render.surfels import SurfelMap

PLANNER_POLICIES = MODES
"""Policies whose keyframes the NBV planner chooses (its score modes)."""
FALLBACK_POLICIES = ("random", "every-n", "gaus-slam", "all", "novelty")
"""The built-in policies that decide without the planner: the baselines, and the fallbacks."""


def alone_policies() -> tuple[str, ...]:
    """Every registered policy that decides without the planner: the built-in ones, then any added (sorted)."""
    added = sorted(set(policy_names()) - set(PLANNER_POLICIES) - set(FALLBACK_POLICIES))
    return (*FALLBACK_POLICIES, *added)


PLANNER_SERVICE = "nbv_planner/get_next_best_view"
"""The planner's ``~/get_next_best_view``, relative: in the selector's namespace, where the planner's private service
is when both run under one (``-r __ns:=/robot1``; an absolute default asked ``/nbv_planner/...``, which was not there,
and every window went to the fallback)."""
MATCH_GRACE_S = 0.5
"""Seconds after the keyframe topic's first subscriber matched before keyframes go out: the subscriber's side of
discovery (as the bag player's ``start_delay_s``)."""
MAX_UNSENT = 10_000
"""Keyframes held at most while no subscriber has matched (the oldest are dropped and counted beyond)."""
HOLD_WARN_S = 5.0
"""Seconds of holding keyframes without a subscriber before the selector warns."""
ASK_AGAIN_S = 0.25
"""Seconds between two asks of a window while the planner answers that its map is not ready (within ``map_wait_s``)."""


@dataclass
class PlannerAsk:
    """A window sent to the planner, from its first ask until its answer is taken or it falls back."""

    candidates: list[Frame]
    intr: Intrinsics
    ahead: list[Frame]
    """The newer frames that judge its novelty (``lookahead``)."""
    in_stream: bool
    """False: the frames held at the end of the stream (:meth:`KeyframeSelectorNode.finish`)."""
    first_s: float
    """Monotonic time of the first ask: the window waits for the planner's map at most ``map_wait_s`` from it."""
    future: Future | None = None
    """The call in flight; None while the window waits to ask again (the map was not ready)."""
    sent_s: float = 0.0
    """Monotonic time of the call in flight (``planner_timeout_s`` counts from it)."""
    ask_at: float = 0.0
    """Monotonic time of the next ask, while ``future`` is None."""
    not_ready: str = ""
    """The planner's last "map not ready" answer about it."""
    novelty: concurrent.futures.Future | None = None
    """The window's novelty, computed by the selector's novelty thread while the planner scores."""


class KeyframeSelectorNode(SystemNode):
    """The keyframe selector; see the module docstring. ``shared`` given: gaus-slam reads the in-process map."""

    default_name = "keyframe_selector"

    def __init__(self, *, defer_camera: bool = False, **kw: Any) -> None:
        """``defer_camera``: no camera subscription until the caller calls ``self.camera.subscribe()`` (one process
        builds the selector first, so a mistyped policy is refused before the planner warms up, and subscribes it
        with the mapper's: :func:`roigsf_ros.nodes.active_mapping.build_nodes`). ``kw``: :class:`SystemNode`'s.
        """
        self._defer_camera = defer_camera
        super().__init__(**kw)

    # ------------------------------------------------------------------------------ set-up
    def _setup(self, shared: SharedMapper | None) -> None:
        names = (*PLANNER_POLICIES, *alone_policies())
        self.policy = str(declare(self, "policy", "roi-gsurfisher", f"keyframe policy: {', '.join(names)}"))
        policy_params = str(declare(self, "policy_params", "", "NAME=VALUE pairs, ':'-separated: parameters of a "
                                    "policy that decides alone which the node does not declare (a policy added "
                                    "to the library)"))  # fmt: skip
        self.window = int(declare(self, "window", 8, "candidate frames kept (the most recent non-keyframes)"))
        trigger = int(declare(self, "trigger_every", 0, "frames between two selections (0 = window)"))
        self.seed = int(declare(self, "seed", 0, "seed of the random pick (policy or fallback random)"))
        self.every_n = int(declare(self, "every_n", 5, "every-n: every n-th frame is a keyframe"))
        self.tau_k = float(declare(self, "tau_k", 0.01, "gaus-slam: keyframe when this fraction renders unmapped"))
        self.alpha_threshold = float(declare(self, "alpha_threshold", 0.5, "gaus-slam: alpha below this is unmapped"))
        self.service_name = str(declare(self, "planner_service", PLANNER_SERVICE, "the planner's service"))
        self.timeout_s = float(declare(self, "planner_timeout_s", 10.0, "seconds to wait for the planner's answer"))
        self.fallback = str(declare(self, "fallback_policy", "random", "decides when the planner does not answer"))
        self.novelty_weight = float(declare(self, "novelty_weight", 0.0, "weight of z(observed novelty) (0 = off)"))
        self.novelty_voxel_m = float(declare(self, "novelty_voxel_m", NOVELTY_VOXEL_M, "novelty's voxel (m)"))
        self.novelty_radius_m = float(declare(self, "novelty_radius_m", NOVELTY_RADIUS_M, "observed within this (m)"))
        self.novelty_measure = str(declare(self, "novelty_measure", "area", "novelty counts: area | pixels"))
        self.lookahead = int(declare(self, "lookahead", 0, "newer frames that judge a window's novelty (0 = off)"))
        self.map_wait_s = float(declare(self, "map_wait_s", 5.0, "seconds a decision waits for the map: gaus-slam's "
                                        "frame for the keyframes named before it, a planner policy's window for the "
                                        "planner's first map (0 = decide at once)"))  # fmt: skip
        self.map_wait_frames = int(declare(self, "map_wait_frames", 32, "gaus-slam: frames held meanwhile (beyond: "
                                           "the oldest is skipped, not a keyframe)"))  # fmt: skip
        poses_topic = declare(self, "keyframe_poses_topic", KEYFRAME_POSES_TOPIC, "the map's keyframe poses "
                              "(gaus-slam without a shared map)")  # fmt: skip
        camera = camera_params(self)
        keyframe_topic = declare(self, "keyframe_topic", KEYFRAME_TOPIC, "keyframes output (PoseStamped)")
        map_topic = declare(self, "map_topic", MAP_TOPIC, "map cloud (gaus-slam without a shared map)")
        self.frame_id = check_frame_id(
            "frame_id", str(declare(self, "frame_id", "map", "frame of the published poses"))
        )
        qos_depth = int(declare(self, "qos_depth", 100, "keep-last depth of the camera subscriptions"))
        status_hz = float(declare(self, "status_rate_hz", 1.0, "~/status publications per second (0 = none)"))
        self.startup_wait_s = float(declare(self, "startup_wait_s", 10.0, "seconds the camera subscriptions wait at "
                                            "start-up for a keyframe subscriber (the mapper; not a hidden node's) "
                                            "and, with a planner policy, the planner's service (0 = subscribe at "
                                            "once)"))  # fmt: skip
        if self.policy not in names:
            raise unknown_policy(self.policy, names, "parameter 'policy'")
        self.policy_params = self._parse_policy_params(policy_params)
        if self.fallback not in FALLBACK_POLICIES:
            if self.fallback not in names:  # a typo: said as one, with the closest names
                raise unknown_policy(self.fallback, FALLBACK_POLICIES, "parameter 'fallback_policy'")
            choices = ", ".join(FALLBACK_POLICIES)
            raise InputError("parameter 'fallback_policy'", f"'{self.fallback}' must decide alone: one of {choices}")
        check_positive("window", self.window)
        check_positive("novelty_weight", self.novelty_weight, allow_zero=True)
        if self.novelty_weight > 0 and self.policy not in PLANNER_POLICIES:
            raise InputError("parameter 'novelty_weight'", f"is added to the planner's scores: policy '{self.policy}' "
                             "does not ask the planner (policy novelty ranks by it alone)")  # fmt: skip
        check_positive("lookahead", self.lookahead, allow_zero=True)
        judged = self.policy == "novelty" or (self.policy in PLANNER_POLICIES and self.novelty_weight > 0)
        if self.lookahead and not judged:
            raise InputError("parameter 'lookahead'", "judges the observed novelty: it needs policy novelty, or a "
                             "planner policy with novelty_weight > 0")  # fmt: skip
        try:  # checked even where nothing counts the novelty, as the stream policies do
            check_novelty_settings(self.novelty_voxel_m, self.novelty_radius_m, self.novelty_measure)
        except InputError as exc:
            raise InputError(f"parameter '{exc.where}'", exc.problem) from None
        counted = judged or (self.policy in PLANNER_POLICIES and self.fallback == "novelty")
        if self.novelty_measure != "area" and not counted:
            raise InputError("parameter 'novelty_measure'", "counts the observed novelty: it needs policy novelty, "
                             "a planner policy with novelty_weight > 0, or fallback_policy novelty")  # fmt: skip
        check_positive("trigger_every", trigger, allow_zero=True)
        check_positive("planner_timeout_s", self.timeout_s)
        check_positive("qos_depth", qos_depth)
        check_positive("map_wait_s", self.map_wait_s, allow_zero=True)
        check_positive("map_wait_frames", self.map_wait_frames)
        check_positive("status_rate_hz", status_hz, allow_zero=True)
        check_positive("startup_wait_s", self.startup_wait_s, allow_zero=True)
        self.trigger_every = trigger or self.window
        self.uses_planner = self.policy in PLANNER_POLICIES
        self._alone = self._make_alone(self.policy) if not self.uses_planner else None
        self._fallback = self._make_alone(self.fallback)
        self._fallback_rng = np.random.default_rng(self.seed)
        needs = self.uses_planner and (self.novelty_weight > 0 or self.fallback == "novelty")
        self._observed = (
            ObservedSurface(self.novelty_voxel_m, self.novelty_radius_m, self.novelty_measure) if needs else None
        )
        """The keyframes' observed surface, for the planner policies' novelty term or fallback."""

        self.shared = shared
        self._lock = threading.RLock()
        self._cloud: PointCloud2 | None = None
        self._cloud_version = 0
        self._view: tuple[int, Mapper] | None = None
        self._window = CandidateWindow(self.window + self.lookahead, self.trigger_every)
        self._seen = 0
        self._request: PlannerAsk | None = None
        """The window the planner is asked about (one at a time)."""
        self._novelty_pool = (
            concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="selector_novelty")
            if self._observed is not None
            else None
        )
        """One thread that does all the work on ``_observed``, in the order it was asked for: a keyframe's depth is
        added before any later window's novelty is counted, and the node never waits for either while holding its
        lock (frames keep coming)."""
        self._observed_lock = threading.Lock()
        """Held around every read and write of ``_observed`` (the pool's thread, and the node's after a shutdown)."""
        self._waiting: tuple[list[Frame], Intrinsics, list[Frame], bool] | None = None
        """A window that came while ``_request`` was in flight: sent when its answer is in."""
        self._planner_down = False
        self._last_intr: Intrinsics | None = None
        self.keyframe_ids: list[int] = []
        """Stamps (ns) of the keyframes published, in order."""
        self.counters: dict[str, int] = dict.fromkeys(
            ("planner_calls", "planner_answers", "planner_failures", "planner_timeouts", "planner_waited", "fallbacks"),
            0,
        )
        self.counters["planner_not_ready"] = 0
        """Answers "map not ready" after which the window asked again (``map_wait_s``)."""
        self.counters |= {"frames_skipped_map_lag": 0, "map_waits_expired": 0, "keyframes_dropped_unsent": 0}
        self.counters["policy_errors"] = 0
        """Frames a policy deciding alone failed on (it raised, or returned no list of new frames): not decided."""
        self._named: set[int] = set()
        """The frames a policy deciding alone named (checked_keyframes: none twice)."""
        self.reads_map = any(p is not None and p.reads_map for p in (self._alone, self._fallback))
        """Whether a policy deciding alone reads the map (:attr:`KeyframePolicy.reads_map`): gaus-slam, and a policy
        added to the library unless it says it does not."""
        self.waits_for_map = self.policy == "gaus-slam" and self.map_wait_s > 0
        """GauS-SLAM's rule judges a frame against a map holding every keyframe named before it, as GauS-SLAM does;
        live, the mapper inserts them later, and judged at once nearly every frame would render unmapped."""
        self._unmapped: dict[int, tuple[float, tuple[float, ...]]] = {}
        """Keyframes named that the map does not hold yet: stamp -> (monotonic time named, camera position)."""
        self._held_for_map: collections.deque[tuple[Frame, Intrinsics, bool]] = collections.deque()
        """Frames waiting for the map (frame, intrinsics, whether it is the first frame), oldest first."""
        self._map_positions: set[tuple[float, ...]] = set()
        """Without a shared map: the positions of the map's keyframes, from its latest keyframe poses."""
        self.slowest_s = {"answer": 0.0, "novelty": 0.0, "frame_gap": 0.0}
        """Wall seconds of the longest wait for a planner's answer to a window of the stream (the held frames sent
        by :meth:`finish` left out: nothing comes after them), of the slowest novelty computation and of the longest
        gap between two frames reaching the selector (many frame periods: frames came in a burst, and windows with
        them)."""
        self._last_frame_t: float | None = None

        inputs = MutuallyExclusiveCallbackGroup()
        planner = MutuallyExclusiveCallbackGroup()
        self.camera = CameraInput.of_settings(
            self,
            self._on_frame,
            camera,
            qos_depth,
            callback_group=inputs,
            # In one process (the shared map) mapper and planner are there already (or, deferred, the process
            # subscribes it with the mapper's), and a player waiting for one subscriber must find the mapper's and the
            # selector's together; else once they are: _start_camera.
            subscribe=(self.startup_wait_s == 0 or shared is not None) and not self._defer_camera,
        )
        self._pub = self.create_publisher(PoseStamped, keyframe_topic, reliable_qos(100))
        self._unsent: collections.deque[PoseStamped] = collections.deque()  # named, not yet sent (_send_unsent)
        self._matched_at: float | None = None
        self._holding_since: float | None = None
        self._status_pub = self.create_publisher(String, "~/status", reliable_qos(10))
        self._client = self.create_client(GetNextBestView, self.service_name, callback_group=planner)
        self.service_name = self._client.service_name  # resolved in the node's namespace, as the logs name it
        self.create_service(Trigger, "~/finish", self._on_finish, callback_group=planner)
        self.create_timer(0.05, self._check_request, callback_group=planner)
        self.create_timer(0.05, self._send_unsent, callback_group=inputs)
        self._created_at = time.monotonic()
        if not self.camera.subscribed and not self._defer_camera:
            self._startup_timer = self.create_timer(0.05, self._start_camera, callback_group=inputs)
        if status_hz > 0:
            self.create_timer(1.0 / status_hz, self.publish_status, callback_group=planner)
        self._map_topic = self.resolve_topic_name(map_topic)  # as subscribed (namespace, remapping), for the logs
        if shared is None and self.reads_map:  # the parameter's name: rcl remaps it once
            self.create_subscription(PointCloud2, map_topic, self._on_cloud, latched_qos(), callback_group=inputs)
        if self.waits_for_map:
            if shared is None:
                self.create_subscription(
                    PoseArray, poses_topic, self._on_map_poses, latched_qos(), callback_group=inputs
                )
            self.create_timer(0.05, self._judge_held, callback_group=inputs)
        how = f"asking {self.service_name} (fallback {self.fallback})" if self.uses_planner else "deciding alone"
        window = f"window {self.window}" + (f", lookahead {self.lookahead}" if self.lookahead else "")
        window += f", novelty_weight {self.novelty_weight:g}" if self.novelty_weight else ""
        if self.policy not in (*PLANNER_POLICIES, *FALLBACK_POLICIES) and self._alone is not None:  # added: its own
            window = ", ".join(f"{k} {v}" for k, v in self._alone.params().items()) or "no parameters"
        shown = ("policy", "policy_params", "window", "lookahead", "novelty_weight", "fallback_policy")
        shown += tuple(self._alone.params()) if self._alone is not None else ()
        own = changed_parameters(self, exclude=shown)  # its other settings off their defaults (qos_depth=10, ...)
        self.get_logger().info(
            f"policy {self.policy} ({window}{settings_text(own)}): {how}; keyframes on "
            f"{self.resolve_topic_name(keyframe_topic)}; camera: "
            f"{describe_topics(self.camera.topics)}, {camera.reliability}"
        )

    def outputs_missing(self) -> list[str]:
        """What the selector's decisions would not reach yet: the keyframe topic's subscriber, the planner's service.

        A subscriber of a hidden node (name starting with '_', as the ros2 CLI names its own, e.g. for ``ros2 topic
        echo``) is not the mapper: the matched subscriptions must outnumber the hidden nodes' ones.
        """
        missing = []
        subscribers = self.get_subscriptions_info_by_topic(self._pub.topic_name)
        hidden = sum(info.node_name.startswith("_") for info in subscribers)
        if self._pub.get_subscription_count() <= hidden:
            missing.append(f"subscriber on {self._pub.topic_name} (the mapper)")
        if self.uses_planner and not self._client.service_is_ready():
            missing.append(f"planner service {self.service_name}")
        return missing

    def _start_camera(self) -> None:
        """Read the camera once the outputs are connected, or ``startup_wait_s`` after start-up (module docstring)."""
        missing = self.outputs_missing()
        waited = time.monotonic() - self._created_at
        if missing and waited < self.startup_wait_s:
            return
        self._startup_timer.cancel()
        if self.camera.subscribed:
            return
        if missing:
            then = "keyframes are held until a subscriber matches"  # a policy deciding alone has no planner to wait for
            then += "; windows go to the fallback until the planner answers" if self.uses_planner else ""
            self.get_logger().warning(
                f"still no {' and no '.join(missing)} after {waited:.1f} s (startup_wait_s): reading the camera anyway "
                f"({then})"
            )
        else:
            self.get_logger().info(f"keyframe subscriber{' and planner' if self.uses_planner else ''} found after "
                                   f"{waited:.1f} s: reading the camera")  # fmt: skip
        self.camera.subscribe()

    def _parse_policy_params(self, text: str) -> dict[str, Any]:
        """``policy_params`` as a dict (values as ``roigsf bench``'s policy specs read them); only for a policy that
        decides alone.
        """
        params = parse_params(text.split(":"), "parameter 'policy_params'", "expected NAME=VALUE pairs split by ':'")
        for key in params:
            if self.has_parameter(key):  # one setting, one place: the node's parameter
                raise InputError("parameter 'policy_params'", f"{key} is a parameter of the node itself: set it as "
                                 f"{key}:=VALUE")  # fmt: skip
        if params and self.policy in PLANNER_POLICIES:
            raise InputError("parameter 'policy_params'", f"is for a policy that decides alone: policy '{self.policy}' "
                             "asks the planner, whose own parameters set its score")  # fmt: skip
        return params

    def _make_alone(self, name: str) -> KeyframePolicy:
        """Policy ``name`` made from the node's parameters (and, for the node's own policy, ``policy_params``)."""
        node_values: dict[str, Any] = {
            "window": self.window,
            "trigger_every": self.trigger_every,
            "seed": self.seed,
            "every_n": self.every_n,
            "tau_k": self.tau_k,
            "alpha_threshold": self.alpha_threshold,
            "novelty_voxel_m": self.novelty_voxel_m,
            "novelty_radius_m": self.novelty_radius_m,
            "novelty_measure": self.novelty_measure,
            "lookahead": self.lookahead,
        }
        built_in = {  # the node parameters each built-in policy gets
            "random": ("window", "trigger_every", "seed"),
            "novelty": (
                "window",
                "trigger_every",
                "novelty_voxel_m",
                "novelty_radius_m",
                "novelty_measure",
                "lookahead",
            ),
            "every-n": ("every_n",),
            "gaus-slam": ("tau_k", "alpha_threshold"),
            "all": (),
        }
        takes = built_in[name] if name in built_in else policy_parameters(name)  # added: those it takes
        params = {k: node_values[k] for k in takes if k in node_values}
        if name == self.policy:
            params = params | self.policy_params
        try:
            return make_policy(name, **params)
        except InputError as exc:  # the library names its field: name it as the node's parameter
            where = "policy_params" if exc.where == f"policy {name!r}" else exc.where  # a name the policy does not take
            raise InputError(f"parameter '{where}'", exc.problem) from None

    # ------------------------------------------------------------------------------ map (gaus-slam)
    def _on_cloud(self, msg: PointCloud2) -> None:
        with self._lock:
            self._cloud = msg
            self._cloud_version += 1

    def _on_map_poses(self, msg: PoseArray) -> None:
        with self._lock:
            self._map_positions = {_position_key(p.position.x, p.position.y, p.position.z) for p in msg.poses}

    def _map_lags(self) -> bool:
        """Whether a keyframe named less than ``map_wait_s`` ago is not in the map yet (forgets those that are)."""
        if not self._unmapped:
            return False
        if self.shared is not None:
            held = set(self.shared.keyframe_ids())
            mapped = [k for k in self._unmapped if k in held]
        else:
            mapped = [k for k, (_, pos) in self._unmapped.items() if pos in self._map_positions]
        now = time.monotonic()
        expired = [k for k, (t, _) in self._unmapped.items() if k not in mapped and now - t > self.map_wait_s]
        self.counters["map_waits_expired"] += len(expired)  # dropped by the mapper, or it is slower than the wait
        for k in (*mapped, *expired):
            del self._unmapped[k]
        return bool(self._unmapped)

    def _map_lag_hint(self) -> str:
        """Why the frames wait, and what judges more of them; or that no mapper publishes the map any more."""
        if self.shared is None and self.count_publishers(self._map_topic) == 0:
            return f"no node publishes the map on {self._map_topic} now: the mapper stopped?"
        trip = "its insertion" if self.shared is not None else "its insertion and the map's next publication"
        return (f"a frame is judged only on a map holding every keyframe named before it, so each keyframe holds the "
                f"frames after it for {trip}: a slower playback rate, or a larger map_wait_frames (judged later; "
                "the mapper's frame_buffer_size must still hold them), judges more")  # fmt: skip

    def _judge_held(self) -> None:
        """Judge the frames held for the map, oldest first, while the map holds every keyframe named before them."""
        with self._lock:
            while self._held_for_map and not self._map_lags():
                frame, intr, first = self._held_for_map.popleft()
                self._decide_alone(self._alone, [frame], intr, force_first=first)

    def _map_view(self, intr: Intrinsics) -> Mapper:
        """A Mapper holding the current map to render (an empty one before any map arrives)."""
        if self.shared is not None:
            snap = self.shared.snapshot(with_h_train=False)
            if snap is None:
                return view_mapper(SurfelMap.empty(), intr)
            with self._lock:
                if self._view is None or self._view[0] != snap.version:
                    self._view = (snap.version, view_mapper(snap.surfel_map, snap.intrinsics, snap.config))
                return self._view[1]
        with self._lock:
            if self._view is None or self._view[0] != self._cloud_version:
                surfels = SurfelMap.empty()
                if self._cloud is not None:
                    try:
                        surfels = cloud_to_surfel_map(self._cloud)
                    except InputError as exc:
                        self.get_logger().warning(f"ignored map: {exc}", throttle_duration_sec=WARN_THROTTLE_S)
                self._view = (self._cloud_version, view_mapper(surfels, intr))
            return self._view[1]

    # ------------------------------------------------------------------------------ frames
    def _on_frame(self, bf: BagFrame) -> None:
        frame = frame_of(bf)
        with self._lock:
            now = time.monotonic()
            if self._last_frame_t is not None:
                self.slowest_s["frame_gap"] = max(self.slowest_s["frame_gap"], now - self._last_frame_t)
            self._last_frame_t = now
            self._last_intr = bf.intrinsics
            first = self._seen == 0
            self._seen += 1
            if self.waits_for_map:  # judged once the map holds the keyframes named before it
                self._held_for_map.append((frame, bf.intrinsics, first))
                while len(self._held_for_map) > self.map_wait_frames:  # the mapper is that far behind: skip
                    self._held_for_map.popleft()
                    self.counters["frames_skipped_map_lag"] += 1
                    self.get_logger().warning(  # counted only in ~/status, two thirds of a bag went unsaid
                        f"{self.counters['frames_skipped_map_lag']} frame(s) skipped so far, not judged: the map lags "
                        f"more than map_wait_frames ({self.map_wait_frames}) frames behind the camera "
                        f"({self._map_lag_hint()})",
                        throttle_duration_sec=WARN_THROTTLE_S,
                    )
                self._judge_held()
                return
            if not self.uses_planner:
                self._decide_alone(self._alone, [frame], bf.intrinsics, force_first=first)
                return
            held, first = self._window.push(frame)  # the library's stream window and trigger
            if first:
                self._publish(frame, bf.intrinsics)
                return
            candidates, ahead = split_lookahead(held, self.lookahead)
            if not candidates:  # nothing due, or (lookahead) every frame held is still ahead
                return
        self._ask_planner(candidates, bf.intrinsics, ahead)

    def _decide_alone(
        self, policy: KeyframePolicy, frames: list[Frame], intr: Intrinsics, force_first: bool = False
    ) -> None:
        """Run a library policy over ``frames`` and publish the keyframes it names (the first frame always)."""
        for frame in frames:
            if policy.name == "novelty":
                view = self._depth_view(intr)
            elif policy.name in ("random", "every-n", "all"):
                view = None  # they read no map
            else:  # gaus-slam, and a policy added to the library
                view = self._map_view(intr)
            try:  # a policy added to the library may fail: the node says so and goes on with the next frame
                chosen = checked_keyframes(policy, policy.observe(frame, view), self._named)  # type: ignore[arg-type]
            except Exception as exc:
                self.counters["policy_errors"] += 1
                self.get_logger().error(f"frame {frame.index} not decided: {type(exc).__name__}: {exc}",
                                        throttle_duration_sec=WARN_THROTTLE_S)  # fmt: skip
                chosen = []
            if force_first and not any(f is frame for f in chosen):
                chosen = [frame, *chosen]
                self._named.add(int(frame.index))
            force_first = False
            for f in chosen:
                self._publish(f, intr)

    def finish(self) -> int:
        """End of the stream: with ``lookahead``, decide the frames still held (nothing is ahead of them now), once.

        Policy novelty: the library policy's ``finish``; a planner policy: the held frames go to the planner as one
        more window (its fallback when it does not answer). Returns how many frames were decided among (0: none).
        """
        with self._lock:
            intr = self._last_intr
            if not self.lookahead or intr is None:
                return 0
            if not self.uses_planner:
                policy = self._alone
                assert isinstance(policy, StreamNBVPolicy)  # lookahead needs policy novelty (checked at start)
                n_held = len(policy.candidates.held())
                for f in policy.finish(self._depth_view(intr)):
                    self._publish(f, intr)
                return n_held
            held = self._window.held()
            for f in held:
                self._window.remove(f)  # decided now: never a candidate again
        if held:
            self._ask_planner(held, intr, [], in_stream=False)
        return len(held)

    def _on_finish(self, req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        n = self.finish()
        res.success = True
        if n:
            res.message = f"decided among {n} held frames"
        elif self.waits_for_map:  # no window: its own words, not a window's
            with self._lock:
                waiting = len(self._held_for_map)
            res.message = (f"nothing to decide: {self.policy} judges each frame as it comes ({waiting} still wait for "
                           "a map holding the keyframes named before them, and are judged then)")  # fmt: skip
        elif not self.lookahead:  # the window's frames are no debt: each window was decided at its trigger
            res.message = (f"nothing to decide: with lookahead 0 every window was decided at its trigger (the "
                           f"{len(self._window_ids())} frames in ~/status' window are candidates of later triggers "
                           "only)")  # fmt: skip
        else:
            res.message = "nothing held (no frames since the last decision, or finish was called already)"
        return res

    # ------------------------------------------------------------------------------ planner
    def _ask_planner(
        self, candidates: list[Frame], intr: Intrinsics, ahead: list[Frame], in_stream: bool = True
    ) -> None:
        self._check_request()  # an answer that came since the last timer tick (50 ms) is taken, not called busy
        with self._lock:
            if self._request is not None:  # wait for the answer in flight; at most one window waits
                if self._waiting is not None:
                    older, older_intr, older_ahead, _ = self._waiting
                    self._fall_back(older, older_intr, "is still busy with two windows before this one", older_ahead)
                self._waiting = (candidates, intr, ahead, in_stream)
                self.counters["planner_waited"] += 1
                return
            self._send(candidates, intr, ahead, in_stream)

    def _send(self, candidates: list[Frame], intr: Intrinsics, ahead: list[Frame], in_stream: bool = True) -> None:
        """Send a window's poses to the planner (call with the lock held and no request in flight); ``ahead``: the
        newer frames that judge its novelty (``lookahead``); ``in_stream`` false: the frames held at the end.
        """
        with self._lock:
            ask = PlannerAsk(candidates, intr, ahead, in_stream, first_s=time.monotonic())
            if not self._call(ask):
                return
            # The window's novelty (against the keyframes published so far, all windows before it being decided)
            # is computed while the planner scores, off the executor: frames keep coming meanwhile.
            if self._novelty_pool is not None and self.novelty_weight > 0:
                try:
                    ask.novelty = self._novelty_pool.submit(self._novelty, candidates, intr, ahead)
                except RuntimeError:  # the pool is shut down (the node is being destroyed): computed on the answer
                    ask.novelty = None

    def _call(self, ask: PlannerAsk) -> bool:
        """Ask the planner about ``ask``'s window (call with the lock held): it is the request in flight. False when
        the planner is not available: the window went to the fallback and no request is in flight.
        """
        if not self._client.service_is_ready():
            self._request = None
            self._fall_back(ask.candidates, ask.intr, "is not available", ask.ahead)
            return False
        req = GetNextBestView.Request(mode=self.policy, top_k=0)
        req.candidates = poses_to_array([f.T_wc for f in ask.candidates], self.get_clock().now().nanoseconds)
        req.candidates.header.frame_id = self.frame_id
        self.counters["planner_calls"] += 1
        ask.future, ask.sent_s = self._client.call_async(req), time.monotonic()
        self._request = ask
        return True

    def _check_request(self) -> None:
        """Timer: take the planner's answer when it came, or fall back once ``planner_timeout_s`` passed.

        Once the request in flight is settled either way, a window that waited for it is sent.
        """
        with self._lock:
            self._settle_request()
            if self._request is None and self._waiting is not None:
                candidates, intr, ahead, in_stream = self._waiting
                self._waiting = None
                self._send(candidates, intr, ahead, in_stream)

    def _settle_request(self) -> None:
        """Take the answer of the request in flight, or fall back on a timeout (call with the lock held).

        An answer "map not ready" (the planner has no map yet: the first windows of a run in several processes) is
        not a failure: the window asks again every ``ASK_AGAIN_S`` until ``map_wait_s`` from its first ask has passed,
        or until a newer window waits (then the older goes to the fallback and the newer is asked: waiting on, the
        older would only hold the newer back, and a third window would send the newer to the fallback instead).
        """
        with self._lock:
            ask = self._request
            if ask is None:
                return
            now = time.monotonic()
            if ask.future is None:  # waiting to ask again
                if self._waiting is not None:
                    self._request = None
                    self.counters["planner_failures"] += 1
                    self._fall_back(
                        ask.candidates,
                        ask.intr,
                        f"answered success=false ({ask.not_ready}) and a newer window waits",
                        ask.ahead,
                    )
                    return
                if now >= ask.ask_at:
                    self._call(ask)
                return
            future = ask.future
            if future.done():
                res = future.result() if future.exception() is None else None
                if (
                    res is not None
                    and not res.success
                    and res.message.startswith(MAP_NOT_READY)
                    and now + ASK_AGAIN_S - ask.first_s <= self.map_wait_s
                    and self._waiting is None
                ):
                    self.counters["planner_not_ready"] += 1
                    if self.counters["planner_not_ready"] == 1:
                        self.get_logger().info(f"planner {self.service_name}: {res.message}; the window asks again "
                                               f"for up to {self.map_wait_s:g} s (map_wait_s)")  # fmt: skip
                    ask.future, ask.ask_at, ask.not_ready = None, now + ASK_AGAIN_S, res.message
                    return
                if ask.novelty is not None and not ask.novelty.done():
                    return  # its novelty is still being counted: taken on a later tick, the node not held meanwhile
                self._request = None
                if res is None or not res.success:
                    self.counters["planner_failures"] += 1
                    why = "no answer" if res is None else res.message
                    self._fall_back(ask.candidates, ask.intr, f"answered success=false ({why})", ask.ahead)
                    return
                if not 0 <= res.best_index < len(ask.candidates):
                    self.counters["planner_failures"] += 1
                    self._fall_back(
                        ask.candidates, ask.intr, f"answered an invalid best_index {res.best_index}", ask.ahead
                    )
                    return
                self.counters["planner_answers"] += 1
                if ask.in_stream:
                    self.slowest_s["answer"] = max(self.slowest_s["answer"], now - ask.first_s)
                if self._planner_down:
                    self._planner_down = False
                    self.get_logger().info(f"planner {self.service_name} answers again: using it")
                best = res.best_index
                if self.novelty_weight > 0:
                    best = self._with_novelty(ask.candidates, ask.intr, res.fused_scores, best, ask.ahead, ask.novelty)
                winner = ask.candidates[best]
                self._window.remove(winner)
                self._publish(winner, ask.intr)
            elif now - ask.sent_s > self.timeout_s:
                self._request = None
                self._client.remove_pending_request(future)
                future.cancel()
                self.counters["planner_timeouts"] += 1
                self._fall_back(ask.candidates, ask.intr, f"did not answer within {self.timeout_s:g} s", ask.ahead)

    def _fall_back(self, candidates: list[Frame], intr: Intrinsics, why: str, ahead: list[Frame]) -> None:
        """Decide a window with ``fallback_policy`` (call with the lock held); logs the first of a run of them."""
        self.counters["fallbacks"] += 1
        gone = "not available" not in why and not self._client.service_is_ready()
        why += "; no node serves it now (the planner stopped?)" if gone else ""
        msg = f"planner {self.service_name} {why}: fallback {self.fallback} ({self.counters['fallbacks']} so far)"
        if not self._planner_down:
            self.get_logger().warning(msg)
        else:
            self.get_logger().warning(msg, throttle_duration_sec=WARN_THROTTLE_S)
        self._planner_down = True
        if self.fallback in ("random", "novelty"):
            if self.fallback == "random":
                winner = candidates[int(self._fallback_rng.integers(len(candidates)))]
            else:
                winner = candidates[int(np.argmax(self._novelty_in_order(candidates, intr, ahead)))]  # ties: oldest
            self._window.remove(winner)
            self._publish(winner, intr)
            return
        for f in candidates:
            self._window.remove(f)
        self._decide_alone(self._fallback, candidates, intr)

    # ------------------------------------------------------------------------------ novelty
    def _mapper_config(self) -> MapperConfig:
        """The mapper's settings: the shared mapper's in-process, else the defaults."""
        return self.shared.config if self.shared is not None else MapperConfig()

    def _depth_view(self, intr: Intrinsics) -> Mapper:
        """An empty map with the mapper's settings: what the novelty policy reads (the camera and depth range)."""
        return view_mapper(SurfelMap.empty(), intr, self._mapper_config())

    def _novelty_in_order(self, candidates: list[Frame], intr: Intrinsics, ahead: list[Frame]) -> np.ndarray:
        """:meth:`_novelty` counted after every keyframe asked of ``_novelty_pool`` so far has been added (waits)."""
        if self._novelty_pool is not None:
            try:
                return self._novelty_pool.submit(self._novelty, candidates, intr, ahead).result()
            except RuntimeError:  # the pool is shut down (the node is being destroyed)
                pass
        return self._novelty(candidates, intr, ahead)

    def _add_observed(self, frame: Frame, intr: Intrinsics) -> None:
        """Add a keyframe's depth to ``_observed`` (what it shows no longer counts as new); a bad one is logged."""
        assert self._observed is not None
        try:
            with self._observed_lock:
                self._observed.add_frame(frame, intr, self._mapper_config())
        except InputError as exc:  # in the pool's thread nobody would see it raised
            self.get_logger().warning(f"keyframe {frame.index}: its depth is not counted as observed: {exc}")

    def _novelty(self, candidates: list[Frame], intr: Intrinsics, ahead: list[Frame]) -> np.ndarray:
        """[M] observed novelty (``novelty_measure``: m^2 or pixels) of the candidates against the keyframes
        published so far (``ahead``: the lookahead novelty).
        """
        assert self._observed is not None
        with self._observed_lock:  # not the node's lock: a thread holding that may wait for this one's result
            t0 = time.monotonic()
            novelty = self._observed.frames_novelty(candidates, intr, self._mapper_config(), ahead)
            self.slowest_s["novelty"] = max(self.slowest_s["novelty"], time.monotonic() - t0)
        return novelty

    def _with_novelty(
        self,
        candidates: list[Frame],
        intr: Intrinsics,
        fused: Any,
        best: int,
        ahead: list[Frame],
        novelty: concurrent.futures.Future | None = None,
    ) -> int:
        """The pick of ``fused + novelty_weight z(N)``; the planner's own ``best`` when its scores do not fit.

        ``novelty``: the candidates' novelty computed meanwhile (:meth:`_send`); None computes it now.
        """
        if len(fused) != len(candidates):
            self.get_logger().warning(f"planner answered {len(fused)} fused scores for {len(candidates)} candidates: "
                                      "its pick is taken without the novelty term")  # fmt: skip
            return best
        values = novelty.result() if novelty is not None else self._novelty_in_order(candidates, intr, ahead)
        return int(np.argmax(fuse_novelty(np.asarray(fused), values, self.novelty_weight)))

    # ------------------------------------------------------------------------------ outputs
    def _publish(self, frame: Frame, intr: Intrinsics) -> None:
        self.keyframe_ids.append(int(frame.index))
        if self.waits_for_map:
            self._unmapped[int(frame.index)] = (time.monotonic(), _position_key(*frame.T_wc[:3, 3]))
        self._unsent.append(pose_stamped(frame.T_wc, int(frame.index), self.frame_id))
        self._send_unsent()
        if self._observed is None:
            return
        if self._novelty_pool is not None:  # in the pool's thread, before any novelty asked of it later
            try:
                self._novelty_pool.submit(self._add_observed, frame, intr)
                return
            except RuntimeError:  # the pool is shut down (the node is being destroyed)
                pass
        self._add_observed(frame, intr)

    def _send_unsent(self) -> None:
        """Publish the keyframes named so far, once a subscriber (the mapper) has matched for ``MATCH_GRACE_S``.

        In three processes the first keyframes were named before discovery had matched the mapper's subscription,
        and a volatile topic drops what it publishes then: every-n lost frames 0, 5 and 10, with no counter saying
        so. They are held instead (at most ``MAX_UNSENT``, the oldest dropped and counted) and sent in order.
        """
        with self._lock:
            now = time.monotonic()
            if self._matched_at is None and self._pub.get_subscription_count() > 0:
                self._matched_at = now  # the reader's side of discovery may still be under way: a grace period
            if not self._unsent:
                return
            if self._matched_at is None:
                self._holding_since = self._holding_since or now
                while len(self._unsent) > MAX_UNSENT:
                    self._unsent.popleft()
                    self.counters["keyframes_dropped_unsent"] += 1
                if now - self._holding_since > HOLD_WARN_S:
                    self.get_logger().warning(
                        f"no subscriber on {self._pub.topic_name} yet (is the mapper running?): holding "
                        f"{len(self._unsent)} keyframe(s) until one matches",
                        throttle_duration_sec=WARN_THROTTLE_S,
                    )
                return
            if now - self._matched_at < MATCH_GRACE_S:
                return
            while self._unsent:
                self._pub.publish(self._unsent.popleft())

    def status(self) -> dict[str, Any]:
        """Counters: frames, keyframes published (stamps in ns), planner calls/answers/failures/timeouts, fallbacks."""
        cam = self.camera.stats()
        with self._lock:
            return {
                "policy": self.policy,
                "policy_params": {} if self._alone is None else dict(self._alone.params()),
                "reading_camera": self.camera.subscribed,
                "frames": cam["frames"],
                **camera_status(cam),
                "keyframes_published": len(self.keyframe_ids),
                "keyframes_unsent": len(self._unsent),
                "keyframe_ids": list(self.keyframe_ids),
                "window": self._window_ids(),
                "planner_pending": self._request is not None,
                "frames_held_for_map": len(self._held_for_map),
                "planner_window_waiting": self._waiting is not None,
                "planner_waits_for_map": self._request is not None and bool(self._request.not_ready),
                **self.counters,
                "max_answer_s": self.slowest_s["answer"],
                "max_novelty_s": self.slowest_s["novelty"],
                "max_frame_gap_s": self.slowest_s["frame_gap"],
            }

    def _window_ids(self) -> list[int]:
        """The candidate window's frame ids (stamps, ns): the planner path's, or the deciding policy's own."""
        with self._lock:
            return self._window.pending_ids if self._alone is None else list(self._alone.pending_ids)

    def publish_status(self) -> None:
        """Publish :meth:`status` as JSON on ``~/status``."""
        self._status_pub.publish(String(data=json.dumps(self.status())))

    def destroy_node(self) -> None:
        """Drop a planner request still in flight (and a window waiting for it), join the novelty thread, then destroy
        the node.
        """
        with self._lock:
            self._waiting = None
            if self._request is not None and self._request.future is not None:
                self._client.remove_pending_request(self._request.future)
                self._request.future.cancel()
            self._request = None
        if self._novelty_pool is not None:
            self._novelty_pool.shutdown(wait=True, cancel_futures=True)
        super().destroy_node()


def _position_key(x: float, y: float, z: float) -> tuple[float, ...]:
    """A camera position (m) as a set key: a keyframe's pose is the frame's, so the mapper's equals ours."""
    return (round(float(x), 6), round(float(y), 6), round(float(z), 6))


def main(args: list[str] | None = None) -> int:
    """Console script ``keyframe_selector``: run until Ctrl-C; exit 2 on a bad parameter."""
    return run_nodes("keyframe_selector", lambda: [KeyframeSelectorNode()], args, description=__doc__)


if __name__ == "__main__":
    sys.exit(main())
