"""A small ROS-free TF buffer: camera poses from ``/tf`` and ``/tf_static`` (tf2 is not on PyPI).

Robots publish the camera pose as a tree of transforms (``map -> odom -> base_link -> camera_link ->
camera_color_optical_frame``), not as a ``PoseStamped``. tf2 and tf2_ros are not on PyPI, so this module
does the part of tf2's buffer the mapper needs, in plain numpy: transforms are stored per edge (child
frame -> its parent) with their stamps, static ones (``/tf_static``) without; :meth:`TransformBuffer.lookup`
composes the chain between two frames through their nearest common ancestor, each dynamic edge taken
at the stamp exactly or interpolated between the two samples around it (slerp for the rotation,
linear for the translation) when both lie within ``tolerance_s`` of it. There is no extrapolation: a
stamp after an edge's newest sample is "not yet" (:attr:`TransformUnavailableError.retry`), one before its
oldest (or in a gap longer than the tolerance) never will be. History is bounded by time
(``cache_s``, as tf2's 10 s) and by count per edge, and the number of frames is bounded.

The messages are the standard ones, as a full ROS install has them: ``tf2_msgs/msg/TFMessage`` (a list
of ``geometry_msgs/msg/TransformStamped``: ``header.frame_id`` the parent, ``child_frame_id`` the child,
``transform`` the child's pose in the parent). :meth:`TransformBuffer.add_message` reads any object
with those fields (rosbags or rclpy messages). Frame names are compared without a leading ``/`` (as tf2).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from roigsf_ros.core.camera import quat_xyzw_to_matrix
from roigsf_ros.core.errors import InputError

TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
TF_MESSAGE_TYPE = "tf2_msgs/msg/TFMessage"
DEFAULT_CACHE_S = 10.0
"""Seconds of history kept per dynamic edge (behind its newest sample): tf2's default buffer length."""
DEFAULT_TOLERANCE_S = 0.1
"""A dynamic edge is interpolated at a stamp only when both samples around it lie within this many seconds."""
DEFAULT_MAX_HISTORY = 4096
"""At most this many samples per dynamic edge (a 400 Hz transform over tf2's 10 s)."""
DEFAULT_MAX_FRAMES = 1024
"""At most this many frames (child edges): a source inventing frame names cannot grow memory without bound."""


class TransformUnavailableError(InputError):
    """No transform between two frames at a stamp; ``retry`` tells whether later messages may provide it."""

    def __init__(self, where: str, problem: str, retry: bool) -> None:
        super().__init__(where, problem)
        self.retry = retry


def frame_name(name: str) -> str:
    """A frame id as tf2 compares it: without a leading ``/``."""
    return str(name).lstrip("/")


def slerp_xyzw(q0: np.ndarray, q1: np.ndarray, alpha: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (x, y, z, w) at ``alpha`` in [0, 1], shortest arc."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: the normalised linear blend is exact to ~1e-7 and avoids sin(0)
        q = q0 + alpha * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(min(1.0, dot))
    s = math.sin(theta)
    return (math.sin((1.0 - alpha) * theta) / s) * q0 + (math.sin(alpha * theta) / s) * q1


def _matrix(t_xyz: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_xyzw_to_matrix(q_xyzw)
    T[:3, 3] = t_xyz
    return T


@dataclass
class _Edge:
    """The transform of one child frame in its parent: one static sample, or stamped samples in stamp order."""

    parent: str
    static: bool
    where: str = ""
    """Where its transforms came from (a topic): said when another parent replaces this one."""
    stamps: list[int] = field(default_factory=list)
    translations: list[np.ndarray] = field(default_factory=list)  # each [3] metres
    rotations: list[np.ndarray] = field(default_factory=list)  # each [4] unit quaternion (x, y, z, w)


class TransformBuffer:
    """Stamped transforms of a frame tree; :meth:`lookup` gives a frame's pose in another at a stamp."""

    def __init__(
        self,
        cache_s: float = DEFAULT_CACHE_S,
        tolerance_s: float = DEFAULT_TOLERANCE_S,
        max_history: int = DEFAULT_MAX_HISTORY,
        max_frames: int = DEFAULT_MAX_FRAMES,
    ) -> None:
        if not (cache_s > 0 and tolerance_s >= 0 and max_history >= 2 and max_frames >= 1):
            raise InputError(
                "TransformBuffer",
                f"need cache_s > 0, tolerance_s >= 0, max_history >= 2, max_frames >= 1; got "
                f"{cache_s}, {tolerance_s}, {max_history}, {max_frames}",
            )
        self.cache_ns = round(cache_s * 1e9)
        self.tolerance_ns = round(tolerance_s * 1e9)
        self.max_history = int(max_history)
        self.max_frames = int(max_frames)
        self.reparented = 0
        """Times a child frame's parent changed (its history then starts afresh, as a new edge)."""
        self.reparent_note = ""
        """The first change of parent, said with both parents and where each came from ("" while none): a frame has
        one parent in a TF tree, and two publishers of one frame (a driver's ``odom -> base_link`` beside
        robot_state_publisher's) silently moved every pose through it."""
        self.frames_refused = 0
        """Transforms refused because ``max_frames`` frames were already known."""
        self.child_hint: str | None = None
        """Appended to an unknown child frame's error by a caller who knows more (the images' own frame id; None until
        a caller has looked, "" when it has nothing to add)."""
        self._edges: dict[str, _Edge] = {}

    # ------------------------------------------------------------------------------ adding
    def set_transform(
        self,
        parent: str,
        child: str,
        translation: np.ndarray,
        rotation_xyzw: np.ndarray,
        stamp_ns: int,
        static: bool = False,
        where: str = "tf",
    ) -> None:
        """Store ``child``'s pose in ``parent`` at ``stamp_ns`` (any stamp when ``static``); InputError if invalid."""
        parent, child = frame_name(parent), frame_name(child)
        if not parent or not child:
            raise InputError(where, f"transform with an empty frame id (parent '{parent}', child '{child}')")
        if parent == child:
            raise InputError(where, f"transform of frame '{child}' to itself")
        t = np.asarray(translation, dtype=np.float64).reshape(-1)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise InputError(where, f"translation {t.tolist()} of '{parent}' -> '{child}' is not 3 finite numbers")
        quat_xyzw_to_matrix(rotation_xyzw, f"{where}: rotation of '{parent}' -> '{child}'")  # checks it is unit
        q = np.asarray(rotation_xyzw, dtype=np.float64)
        q = q / np.linalg.norm(q)
        edge = self._edges.get(child)
        if edge is None or edge.parent != parent or edge.static != static:
            if edge is None and len(self._edges) >= self.max_frames:
                self.frames_refused += 1
                raise InputError(where, f"more than {self.max_frames} frames; transform to '{child}' ignored")
            if edge is not None and edge.parent != parent:
                self.reparented += 1
                if not self.reparent_note:
                    self.reparent_note = (
                        f"frame '{child}' changed parent: '{edge.parent}' ({edge.where}), then '{parent}' ({where}); a "
                        "frame has one parent in a TF tree (two publishers of it?): poses through it follow the newest"
                    )
            edge = self._edges[child] = _Edge(parent=parent, static=static, where=where)
        if static:
            edge.stamps, edge.translations, edge.rotations = [0], [t], [q]
            return
        stamp = int(stamp_ns)
        i = bisect.bisect_left(edge.stamps, stamp)
        if i < len(edge.stamps) and edge.stamps[i] == stamp:  # the same stamp again: the newer message wins
            edge.translations[i], edge.rotations[i] = t, q
            return
        edge.stamps.insert(i, stamp)
        edge.translations.insert(i, t)
        edge.rotations.insert(i, q)
        oldest_kept = edge.stamps[-1] - self.cache_ns
        n_old = bisect.bisect_left(edge.stamps, oldest_kept)
        n_drop = max(n_old, len(edge.stamps) - self.max_history)
        if n_drop > 0:
            del edge.stamps[:n_drop], edge.translations[:n_drop], edge.rotations[:n_drop]

    def add_message(self, msg: Any, static: bool = False, where: str = TF_TOPIC) -> list[InputError]:
        """Store every transform of a ``tf2_msgs/TFMessage``; returns the errors of those refused (others kept)."""
        errors: list[InputError] = []
        for ts in msg.transforms:
            tr, rot = ts.transform.translation, ts.transform.rotation
            try:
                self.set_transform(
                    ts.header.frame_id,
                    ts.child_frame_id,
                    np.array([tr.x, tr.y, tr.z], dtype=np.float64),
                    np.array([rot.x, rot.y, rot.z, rot.w], dtype=np.float64),
                    int(ts.header.stamp.sec) * 1_000_000_000 + int(ts.header.stamp.nanosec),
                    static,
                    where,
                )
            except InputError as exc:
                errors.append(exc)
        return errors

    # ------------------------------------------------------------------------------ queries
    def frames(self) -> list[str]:
        """Every frame named so far (children and parents), sorted."""
        return sorted(set(self._edges) | {e.parent for e in self._edges.values()})

    def history(self, child: str) -> int:
        """Samples held for ``child``'s edge (0 when unknown; 1 for a static one)."""
        edge = self._edges.get(frame_name(child))
        return 0 if edge is None else len(edge.stamps)

    def newest_stamp_ns(self, child: str) -> int | None:
        """The newest stamp of ``child``'s dynamic edge; None when unknown or static."""
        edge = self._edges.get(frame_name(child))
        return None if edge is None or edge.static else edge.stamps[-1]

    def lookup(self, parent: str, child: str, stamp_ns: int) -> np.ndarray:
        """[4, 4] float64 pose of ``child`` in ``parent`` at ``stamp_ns`` (maps child coordinates to parent's).

        Raises :class:`TransformUnavailableError` naming both frames and why: a frame unknown or not connected
        to the other (``retry``: its transforms may still come), the stamp after an edge's newest sample
        (``retry``), before its oldest or in a gap longer than the tolerance (no retry).
        """
        parent, child = frame_name(parent), frame_name(child)
        where = f"tf '{parent}' -> '{child}'"
        if parent == child:
            return np.eye(4)
        up_child, up_parent = self._chain(child, where), self._chain(parent, where)
        on_parent_chain = {f: k for k, f in enumerate(up_parent)}
        common = next((k for k, f in enumerate(up_child) if f in on_parent_chain), None)
        if common is None:
            known = ", ".join(self.frames()) or "none"
            for name in (child, parent):
                if name not in self._edges and all(e.parent != name for e in self._edges.values()):
                    if name == child:
                        hint = self.child_hint or ""
                    else:  # the frames without a parent: the one the poses are wanted in is likely among them
                        roots = sorted({e.parent for e in self._edges.values()} - set(self._edges))
                        hint = f"; roots of the trees: {', '.join(roots)} (tf_parent_frame / --tf-parent-frame)"
                    raise TransformUnavailableError(
                        where, f"frame '{name}' is unknown (frames known: {known}){hint}", retry=True
                    )
            raise TransformUnavailableError(
                where,
                f"frames '{parent}' and '{child}' are not connected: no transform with child '{up_child[-1]}' has "
                f"come yet (their trees have roots '{up_parent[-1]}' and '{up_child[-1]}'; frames known: {known})",
                retry=True,
            )
        T_common_child = self._compose(up_child[: common + 1], stamp_ns, where)
        T_common_parent = self._compose(up_parent[: on_parent_chain[up_child[common]] + 1], stamp_ns, where)
        R, t = T_common_parent[:3, :3], T_common_parent[:3, 3]
        inv = np.eye(4)
        inv[:3, :3], inv[:3, 3] = R.T, -R.T @ t
        return inv @ T_common_child

    def _chain(self, frame: str, where: str) -> list[str]:
        """``frame`` and its ancestors up to the root of its tree."""
        chain = [frame]
        while (edge := self._edges.get(chain[-1])) is not None:
            chain.append(edge.parent)
            if len(chain) > len(self._edges) + 1:
                raise TransformUnavailableError(
                    where, f"the transforms above '{frame}' form a loop: {chain}", retry=False
                )
        return chain

    def _compose(self, chain: list[str], stamp_ns: int, where: str) -> np.ndarray:
        """Pose of ``chain[0]`` in ``chain[-1]`` (``chain`` goes up the tree) at ``stamp_ns``."""
        T = np.eye(4)
        for frame in chain[:-1]:
            T = self._sample(frame, stamp_ns, where) @ T
        return T

    def _sample(self, child: str, stamp_ns: int, where: str) -> np.ndarray:
        """Pose of ``child`` in its parent at ``stamp_ns``: static, exact, or interpolated within the tolerance."""
        edge = self._edges[child]
        if edge.static:
            return _matrix(edge.translations[0], edge.rotations[0])
        stamps, t = edge.stamps, int(stamp_ns)
        i = bisect.bisect_left(stamps, t)
        if i < len(stamps) and stamps[i] == t:
            return _matrix(edge.translations[i], edge.rotations[i])
        link = f"'{edge.parent}' -> '{child}'"
        if i == len(stamps):
            raise TransformUnavailableError(
                where,
                f"stamp {t} ns is after the newest transform {link} ({stamps[-1]} ns, "
                f"{(t - stamps[-1]) / 1e9:.3f} s earlier): not yet received",
                retry=True,
            )
        if i == 0:
            raise TransformUnavailableError(
                where,
                f"stamp {t} ns is before the oldest transform {link} held ({stamps[0]} ns, "
                f"{(stamps[0] - t) / 1e9:.3f} s later; history is {self.cache_ns / 1e9:g} s)",
                retry=False,
            )
        s0, s1 = stamps[i - 1], stamps[i]
        if t - s0 > self.tolerance_ns or s1 - t > self.tolerance_ns:
            # tf2 interpolates across any gap; this buffer only within the tolerance (a lost stretch of odometry is
            # not a straight line): say how to widen it, and how often the edge is sampled
            period = float(np.median(np.diff(stamps))) / 1e9 if len(stamps) > 2 else (s1 - s0) / 1e9
            raise TransformUnavailableError(
                where,
                f"no transform {link} within {self.tolerance_ns / 1e9:g} s of stamp {t} ns (nearest at "
                f"{(t - s0) / 1e9:.3f} s before and {(s1 - t) / 1e9:.3f} s after; the edge comes every {period:.3g} s "
                "here: a larger TF tolerance, tf_tolerance_s / --tf-tolerance, interpolates across the gap)",
                retry=False,
            )
        alpha = (t - s0) / (s1 - s0)
        trans = (1.0 - alpha) * edge.translations[i - 1] + alpha * edge.translations[i]
        return _matrix(trans, slerp_xyzw(edge.rotations[i - 1], edge.rotations[i], alpha))


__all__ = [
    "DEFAULT_CACHE_S",
    "DEFAULT_MAX_FRAMES",
    "DEFAULT_MAX_HISTORY",
    "DEFAULT_TOLERANCE_S",
    "TF_MESSAGE_TYPE",
    "TF_STATIC_TOPIC",
    "TF_TOPIC",
    "TransformBuffer",
    "TransformUnavailableError",
    "frame_name",
    "slerp_xyzw",
]
