"""Playing a bag into ``active_mapping`` no faster than its nodes take it, and telling when they are done with it.

:class:`Lockstep` is the bag player's ``pace`` for ``roigsf demo --rate 0``; :func:`selector_took` and
:func:`system_busy` say, from the nodes' status, when the end of a stream may be declared: the selector has the last
frame, and no planner request, held frame or named keyframe is still in flight.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from roigsf_ros.nodes.active_mapping import ActiveMapping
    from roigsf_ros.nodes.bag_player import BagPlayer


KEYFRAMES_NOT_MAPPED = ("keyframes_dropped_overflow", "keyframes_missing", "keyframes_no_depth", "keyframes_failed")
"""The mapper's ``~/status`` counters of keyframes named to it that never reached the map; with ``keyframes_inserted``
and ``keyframes_duplicate`` every keyframe message ends in one of them."""


def system_busy(status: dict[str, Any]) -> bool:
    """Whether the nodes still work on what they received: a planner request or a window waiting for one, frames
    held until the map catches up (gaus-slam), or keyframes named and not yet inserted, dropped or refused.
    """
    sel, mp = status["selector"], status["mapper"]
    handled = mp["keyframes_inserted"] + mp["keyframes_duplicate"] + sum(mp[k] for k in KEYFRAMES_NOT_MAPPED)
    return bool(
        sel["planner_pending"]
        or sel["planner_window_waiting"]
        or mp["pending_keyframes"]
        or mp["waiting_keyframes"]
        or sel["frames_held_for_map"]
        or handled < mp["keyframe_msgs"]
        or mp["keyframe_msgs"] < sel["keyframes_published"]
    )


def selector_took(system: ActiveMapping, n_frames: int) -> bool:
    """Whether the selector has taken ``n_frames`` frames, the last one's callback returned (its ``frames`` count
    comes before the frame reaches the policy: ``finish`` called in between decided without the last frame).
    """
    cam = system.selector.camera.stats()
    return cam["frames"] >= n_frames and cam["in_callback"] == 0


class Lockstep:
    """The player's ``pace`` at ``--rate 0``: as fast as the nodes can go without losing anything.

    A frame's first message (on ``frame_topic``, the colour topic) waits until both camera nodes received and
    handled every message published before it, and until going on would lose work: while a window already waits
    behind a planner request (the next one would go to the fallback), while the window asked waits for the planner's
    first map or may have to (asked while the map has no keyframe: the next window would send it to the fallback),
    while gaus-slam holds frames for the map,
    or while the mapper has more than one keyframe to insert (its queue and frame buffer would overflow). The nodes'
    work otherwise overlaps the stream, as in real time. When nothing in the nodes' status moves for ``stall_s``
    while a frame waits (a message lost on a best-effort subscription, a stuck node), it goes anyway and
    ``stalls`` counts it. ``waited_s``: the playback thread's time in here.
    """

    def __init__(self, system: ActiveMapping, frame_topic: str, stall_s: float = 30.0, poll_s: float = 0.005) -> None:
        self.system = system
        self.frame_topic = frame_topic
        self.stall_s = stall_s
        self.poll_s = poll_s
        self.player: BagPlayer | None = None
        """The player paced (set once it is made): waiting ends when it is ``stopping``."""
        self.stalls = 0
        self.waited_s = 0.0

    def ready(self, published: Mapping[str, int]) -> tuple[bool, object]:
        """(the nodes can take the next frame without loss, their counters of work done, to tell progress by)."""
        cams = [self.system.mapper.camera.stats(), self.system.selector.camera.stats()]
        sel, mp = self.system.selector.status(), self.system.mapper.status()  # not the planner's: polled often
        delivered = all(
            cam["in_callback"] == 0 and all(cam["received"].get(t, n) >= n for t, n in published.items())
            for cam in cams
        )
        free = not (
            sel["planner_window_waiting"]
            or sel["planner_waits_for_map"]
            or (sel["planner_pending"] and mp["keyframes"] == 0)
            or sel["frames_held_for_map"]
            or mp["pending_keyframes"] + mp["waiting_keyframes"] > 1
        )
        progress = [sel[k] for k in ("frames", "keyframes_published", "planner_answers", "planner_failures")]
        progress += [sel[k] for k in ("planner_timeouts", "fallbacks", "frames_held_for_map", "planner_not_ready")]
        progress += [mp[k] for k in ("keyframe_msgs", "pending_keyframes", "waiting_keyframes", "keyframes")]
        return delivered and free, ([cam["received"] for cam in cams], progress)

    def __call__(self, topic: str, published: Mapping[str, int]) -> None:
        """Return once the nodes are ready for a message on ``topic`` (at once unless it starts a frame)."""
        if topic != self.frame_topic:
            return
        t0 = time.monotonic()
        moved_at, last = t0, None
        while self.player is None or not self.player.stopping:
            ok, snapshot = self.ready(dict(published))
            if ok:
                break
            now = time.monotonic()
            if snapshot != last:
                moved_at, last = now, snapshot
            elif now - moved_at > self.stall_s:
                self.stalls += 1
                break
            time.sleep(self.poll_s)
        self.waited_s += time.monotonic() - t0
