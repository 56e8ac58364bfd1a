"""Observed novelty of a captured frame: how much surface its depth shows that no keyframe's depth has shown.

Beyond the paper, for the stream setting only (issue 10). There the candidates are frames the camera has already
captured, so their depth is known; the pose-only scores (Eq. 10, 14 and the unseen term) can only guess which of them
sees new surface. The mesh recall of a keyframe set is bounded, tightly, by how much of the surface its keyframes'
depth observes (``scripts/coverage_bound.py``), and a frame's novelty is that quantity measured on the frame's own
points instead of the ground truth: the area of its back-projected depth farther than ``radius_m`` from every point
the keyframes' depth observed.

Both sides are voxelised at ``voxel_m``: :class:`ObservedSurface` keeps the voxels within ``radius_m`` (plus half a
voxel: a point in either voxel may lie that close) of the keyframes' observed voxels in an open3d hash set, so a
frame costs one back-projection, one ``np.unique`` and one hash lookup of its voxels. Nothing here needs ROS.

Deciding a window late (the stream policies' ``lookahead``): :meth:`ObservedSurface.lookahead_new_voxels` scores a
candidate by the pair it makes with the best of the newer frames, so surface that a later frame shows anyway is left
to that frame (the coverage study's "one window late" scorer, with each frame's depth instead of the ground truth).
Which voxels ahead each candidate reaches is found for all candidates in one pass (:func:`unreached_by_each`: a bit mask
per voxel, from a binary search among packed int64 keys), 5.4x faster on the shipped bag than a k-d tree per candidate
(:func:`unreached_by_each_plain`, the reference; ``roigsf perf novelty``); the selector node computes it in a thread
of its own while the planner scores the window.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from roigsf_ros.core.camera import Intrinsics, depth_points_w
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame
from roigsf_ros.mapping.mapper import MapperConfig, valid_depth_mask
from roigsf_ros.nbv.scorer import zscore

NOVELTY_VOXEL_M = 0.025
"""Default voxel (m) of the observed surface: about the pixel spacing of a 240 px wide Replica view at 2 m."""
NOVELTY_RADIUS_M = 0.05
"""Default reach (m): a point within 5 cm of observed depth is observed, the threshold of the mesh recall R@5cm."""

NOVELTY_MEASURES = ("area", "pixels")
"""What a frame's novelty counts: the area of surface it shows first (the default), or the held frames' pixels
it brings within reach (:meth:`ObservedSurface.held_pixels_covered`)."""

HASH_CHUNK_ROWS = 1 << 16
"""Rows per call into open3d's hash set: a call holds Python's lock throughout (a keyframe's 1.4M reach keys took 84 ms
in one call, stalling every other thread of the node, the executor's among them), so large inserts and lookups go in
chunks of a few milliseconds each. The same set either way."""

HASH_CAPACITY = 1 << 21
"""Initial capacity of the observed-surface hash set: growing it rehashes every entry in one call that holds Python's
lock (0.07 s at 0.26M entries, 0.14 s at 0.5M on the shipped bag's keyframes), so it starts large enough that a room's
reach voxels (0.6M for the shipped bag) never make it grow; pages are touched only as it fills (4 MB at 1M empty)."""

_MAX_INDEX = 1 << 30
"""Voxel indices stay within int32 (+-2^30 voxels: far beyond any map; larger means a broken pose or depth)."""


def check_novelty_settings(voxel_m: float, radius_m: float, measure: str) -> None:
    """InputError naming the first of :class:`ObservedSurface`'s settings out of range (callers check them up front)."""
    if measure not in NOVELTY_MEASURES:
        raise InputError("novelty_measure", f"must be one of {', '.join(NOVELTY_MEASURES)}, got {measure!r}")
    if not (np.isfinite(voxel_m) and voxel_m > 0):
        raise InputError("novelty_voxel_m", f"must be a finite number > 0, got {voxel_m!r}")
    if not (np.isfinite(radius_m) and radius_m >= 0):
        raise InputError("novelty_radius_m", f"must be a finite number >= 0, got {radius_m!r}")


class ObservedSurface:
    """Voxels [``voxel_m``] within ``radius_m`` of some observed point; the novelty of a frame against them.

    ``add`` the depth of each keyframe as it is inserted; :meth:`new_area_m2` of a candidate is then the number of
    its own occupied voxels that are not within reach of an observed one, times ``voxel_m``^2 (the area of surface
    it shows for the first time, in m^2 up to the voxelisation). A voxel v is within reach of an observed voxel o
    when their centres are at most ``radius_m + voxel_m / 2`` apart. A pixel marks one voxel, so surface whose
    pixels are more than ``voxel_m`` apart (beyond ``fx x voxel_m``: 3 m at 240 px wide on Replica) counts less
    than its area: an estimate, biased towards near surface, as the mesh's own sampling is.
    """

    def __init__(
        self,
        voxel_m: float = NOVELTY_VOXEL_M,
        radius_m: float = NOVELTY_RADIUS_M,
        measure: str = "area",
        hash_capacity: int = HASH_CAPACITY,
        hash_chunk_rows: int = HASH_CHUNK_ROWS,
    ) -> None:
        check_novelty_settings(voxel_m, radius_m, measure)
        for name, value in (("hash_capacity", hash_capacity), ("hash_chunk_rows", hash_chunk_rows)):
            if int(value) < 1:
                raise InputError(name, f"must be at least 1, got {value}")
        self.hash_chunk_rows = int(hash_chunk_rows)
        """Rows per call into the hash set (:data:`HASH_CHUNK_ROWS`); the same counts whatever it is."""
        self.measure = measure
        """What :meth:`frames_novelty` counts: "area" (m^2 of new surface) or "pixels" (held frames' pixels)."""
        self.voxel_m = float(voxel_m)
        self.radius_m = float(radius_m)
        r = (self.radius_m + 0.5 * self.voxel_m) / self.voxel_m
        n = int(np.floor(r))
        grid = np.arange(-n, n + 1)
        offs = np.stack(np.meshgrid(grid, grid, grid, indexing="ij"), axis=-1).reshape(-1, 3)
        self._offsets = offs[(offs**2).sum(axis=1) <= r * r + 1e-9].astype(np.int64)
        """Integer voxel offsets within reach: [K, 3]."""
        try:
            self._reached = o3d.core.HashSet(int(hash_capacity), o3d.core.int32, [3], o3d.core.Device("CPU:0"))
        except RuntimeError as exc:  # open3d's "CPU malloc failed": the same as numpy's MemoryError, named
            if "malloc" not in str(exc):
                raise
            raise MemoryError(f"a hash set of hash_capacity {int(hash_capacity)} voxels: {exc}") from None
        self.n_added = 0
        """Frames added so far."""

    def _voxel_index(self, points_w: np.ndarray) -> np.ndarray:
        """The voxel index [N, 3] int32 of each point [N, 3] (world, metres; InputError when not finite or too far)."""
        pts = np.asarray(points_w, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(pts)):
            raise InputError("points_w", "non-finite points")
        ijk = np.floor(pts / self.voxel_m)
        if ijk.size and np.abs(ijk).max() >= _MAX_INDEX:
            raise InputError("points_w", f"points beyond {_MAX_INDEX * self.voxel_m:.3g} m from the origin")
        return ijk.astype(np.int32)

    def _voxels(self, points_w: np.ndarray) -> np.ndarray:
        """Distinct voxel indices [N, 3] int32 of the points [N, 3] (world, metres), in lexicographic order."""
        return unique_voxels(self._voxel_index(points_w))

    def add_points(self, points_w: np.ndarray) -> None:
        """Mark the voxels within reach of ``points_w`` [N, 3] (world, metres) as observed."""
        ijk = self._voxels(points_w)
        if len(ijk):  # open3d hashes the [3] keys itself (packing them into one int64 hashed badly: 100x slower)
            reached = np.ascontiguousarray((ijk[:, None, :] + self._offsets[None].astype(np.int32)).reshape(-1, 3))
            step = self.hash_chunk_rows
            for start in range(0, len(reached), step):  # Python's lock released between the chunks
                self._reached.insert(o3d.core.Tensor(reached[start : start + step]))
        self.n_added += 1

    def add(self, depth_m: np.ndarray, T_wc: np.ndarray, intr: Intrinsics, valid: np.ndarray) -> None:
        """Mark what a keyframe's depth [H, W] (its ``valid`` pixels) observes."""
        self.add_points(depth_points_w(depth_m, T_wc, intr, valid))

    def _unreached_mask(self, ijk: np.ndarray) -> np.ndarray:
        """[N] bool: which voxels of ``ijk`` [N, 3] int32 (distinct) no added observation reaches."""
        if len(ijk) == 0 or self.n_added == 0:
            return np.ones(len(ijk), dtype=bool)
        ijk, step = np.ascontiguousarray(ijk), self.hash_chunk_rows
        found = [
            self._reached.find(o3d.core.Tensor(ijk[start : start + step]))[1].numpy().astype(bool)
            for start in range(0, len(ijk), step)  # Python's lock released between the chunks
        ]
        return ~np.concatenate(found)

    def _unreached(self, ijk: np.ndarray) -> np.ndarray:
        """The voxels [N, 3] int32 of ``ijk`` (distinct) that no added observation reaches."""
        return ijk[self._unreached_mask(ijk)]

    def unreached_points(self, points_w: np.ndarray) -> int:
        """How many of ``points_w`` [N, 3] (world, metres; each counted, not per voxel) no added observation reaches."""
        voxels, inverse = np.unique(self._voxel_index(points_w), axis=0, return_inverse=True)
        return int(self._unreached_mask(voxels)[inverse.reshape(-1)].sum())

    def new_voxels(self, points_w: np.ndarray) -> int:
        """How many distinct voxels of ``points_w`` [N, 3] no added observation reaches."""
        return len(self._unreached(self._voxels(points_w)))

    def lookahead_new_voxels(self, candidates_w: list[np.ndarray], ahead_w: list[np.ndarray]) -> np.ndarray:
        """[M] int: each candidate's new voxels plus the most new voxels one frame ahead would still add after it.

        ``candidates_w`` and ``ahead_w`` hold each frame's points [N, 3] (world, metres). For candidate f, with
        V_f its voxels and B_g the new voxels of a frame g ahead: |new(f)| + max_g |{b in B_g: no voxel of V_f within
        reach}|, the voxels the pair (f, best g) shows first. Picking f by it leaves to the next pick the surface
        that a later frame also shows. With no frames ahead it is :meth:`new_voxels` of each candidate.
        """
        cand = [self._voxels(p) for p in candidates_w]
        own = np.array([len(self._unreached(v)) for v in cand], dtype=np.int64)
        ahead_new = [self._unreached(self._voxels(p)) for p in ahead_w]
        if not ahead_new or sum(len(b) for b in ahead_new) == 0:
            return own
        return own + unreached_by_each(cand, ahead_new, self._offsets).max(axis=1)

    def held_pixels_covered(self, candidates_w: list[np.ndarray], ahead_w: list[np.ndarray]) -> np.ndarray:
        """[M] int: pixels of the held frames each candidate (with the best frame ahead) would bring within reach.

        ``candidates_w`` and ``ahead_w`` hold each frame's points [N, 3] (world, metres), one per valid pixel. The
        held frames' pixels whose voxel no added observation reaches are the *uncovered* pixels, each voxel u
        weighing w(u), its number of such pixels over all held frames. For candidate f with voxels V_f and a frame
        g ahead: sum of w(u) over the u within reach of V_f, plus the most that one g reaches that f does not:
        the held frames' pixels the pair (f, best g) shows first. It is :meth:`lookahead_new_voxels` counted in
        the pixels of the frames around the candidate instead of the candidate's own voxels, so surface the
        trajectory looks at often, or from near, weighs more than surface one far frame shows.
        """
        index = [self._voxel_index(p) for p in (*candidates_w, *ahead_w)]  # one per pixel
        cand = [np.unique(i, axis=0) for i in index[: len(candidates_w)]]
        ahead = [np.unique(i, axis=0) for i in index[len(candidates_w) :]]
        every = np.concatenate(index) if index else np.zeros((0, 3), np.int32)
        voxels, weight = np.unique(every, axis=0, return_counts=True)
        keep = self._unreached_mask(voxels)
        uncovered, weight = voxels[keep].astype(np.float64), weight[keep]
        r = np.sqrt(((self.radius_m + 0.5 * self.voxel_m) / self.voxel_m) ** 2 + 1e-9)  # as the offsets' test

        def reached(v: np.ndarray) -> np.ndarray:
            if len(v) == 0 or len(uncovered) == 0:
                return np.zeros(len(uncovered), dtype=bool)
            d, _ = cKDTree(v.astype(np.float64)).query(uncovered, k=1, distance_upper_bound=r + 1.0)
            return d <= r  # inf (nothing within the bound) is not reached

        by_ahead = [reached(v) for v in ahead]
        out = np.empty(len(cand), dtype=np.int64)
        for i, v in enumerate(cand):
            mine = reached(v)
            after = max((int(weight[g & ~mine].sum()) for g in by_ahead), default=0)
            out[i] = int(weight[mine].sum()) + after
        return out

    def new_area_m2(self, depth_m: np.ndarray, T_wc: np.ndarray, intr: Intrinsics, valid: np.ndarray) -> float:
        """Novelty of a frame: its voxels no keyframe's observation reaches, as an area (count x ``voxel_m``^2)."""
        return self.new_voxels(depth_points_w(depth_m, T_wc, intr, valid)) * self.voxel_m**2

    def add_frame(self, frame: Frame, intr: Intrinsics, config: MapperConfig) -> None:
        """:meth:`add` a keyframe's depth within the mapper's depth range (``config``)."""
        self.add_points(frame_points(frame, intr, config))

    def frames_new_area_m2(
        self, frames: list[Frame], intr: Intrinsics, config: MapperConfig, ahead: list[Frame] | None = None
    ) -> np.ndarray:
        """[M] :meth:`new_area_m2` of each frame's depth within the mapper's depth range (``config``); with frames
        ``ahead``, the area of :meth:`lookahead_new_voxels` instead.
        """
        points = [frame_points(f, intr, config) for f in frames]
        if not ahead:
            return np.array([self.new_voxels(p) for p in points], dtype=np.float64) * self.voxel_m**2
        later = [frame_points(f, intr, config) for f in ahead]
        return self.lookahead_new_voxels(points, later).astype(np.float64) * self.voxel_m**2

    def frames_novelty(
        self, frames: list[Frame], intr: Intrinsics, config: MapperConfig, ahead: list[Frame] | None = None
    ) -> np.ndarray:
        """[M] the novelty of each of ``frames`` in this surface's :attr:`measure`: :meth:`frames_new_area_m2` (m^2)
        or :meth:`held_pixels_covered` (pixels of ``frames`` and ``ahead``, the frames held around them).
        """
        if self.measure == "area":
            return self.frames_new_area_m2(frames, intr, config, ahead)
        points = [frame_points(f, intr, config) for f in frames]
        later = [frame_points(f, intr, config) for f in ahead or []]
        return self.held_pixels_covered(points, later).astype(np.float64)


def unique_voxels(ijk: np.ndarray) -> np.ndarray:
    """The distinct rows of ``ijk`` [N, 3] (int voxel indices) in lexicographic order, as ``np.unique(ijk, axis=0)``
    returns them, as int32; each row packed into one int64 relative to the rows' own box (sorting rows is slower).
    """
    ijk = np.asarray(ijk).reshape(-1, 3)
    if len(ijk) == 0:
        return np.zeros((0, 3), np.int32)
    lo = ijk.min(axis=0).astype(np.int64)
    ext = ijk.max(axis=0).astype(np.int64) - lo + 1
    if float(ext[0]) * float(ext[1]) * float(ext[2]) >= 2.0**62:  # a box too large to pack: sort the rows
        return np.unique(ijk, axis=0).astype(np.int32)
    keys = np.unique(_pack(ijk, lo, ext))
    z, yx = keys % ext[2], keys // ext[2]
    return np.stack([yx // ext[1] + lo[0], yx % ext[1] + lo[1], z + lo[2]], axis=1).astype(np.int32)


def unreached_by_each(cand: list[np.ndarray], ahead: list[np.ndarray], offsets: np.ndarray) -> np.ndarray:
    """[M, G] int: for each candidate's voxels ``cand[f]`` and each frame ahead's voxels ``ahead[g]`` ([N, 3] int,
    distinct within each), how many voxels of ``ahead[g]`` no voxel of ``cand[f]`` reaches (lies at an offset of
    ``offsets`` [K, 3] from it: the lattice points of a ball about 0, :class:`ObservedSurface`'s reach).

    One pass for all candidates: each voxel of the frames ahead gathers, over the offsets, a bit mask of the
    candidates that reach it, found by binary search among every candidate's voxels packed into int64 keys (at most
    64 candidates a pass). The same counts as a nearest-neighbour query of each candidate's voxels.
    """
    m, g = len(cand), len(ahead)
    union = np.concatenate([np.asarray(b, dtype=np.int64).reshape(-1, 3) for b in ahead])
    group = np.repeat(np.arange(g), [len(b) for b in ahead])
    out = np.zeros((m, g), dtype=np.int64)
    if len(union) == 0:
        return out
    offs = np.asarray(offsets, dtype=np.int64).reshape(-1, 3)
    reach = int(np.abs(offs).max()) if len(offs) else 0
    lo = union.min(axis=0) - reach  # the box of every voxel the frames ahead can be reached from
    ext = union.max(axis=0) + reach - lo + 1
    if float(ext[0]) * float(ext[1]) * float(ext[2]) >= 2.0**62:  # too large a box to pack: the plain way
        return unreached_by_each_plain(cand, ahead, offs)
    keys, inverse = np.unique(_pack(union, lo, ext), return_inverse=True)
    inverse = inverse.reshape(-1)
    shifts = _pack(offs, np.zeros(3, np.int64), ext)  # a key plus a shift is the key of the voxel at that offset
    for first in range(0, m, 64):
        chunk = range(first, min(first + 64, m))
        packed, bits = [], []
        for f in chunk:
            v = np.asarray(cand[f], dtype=np.int64).reshape(-1, 3)
            v = v[np.all((v >= lo) & (v < lo + ext), axis=1)]  # outside the box it reaches nothing ahead
            packed.append(_pack(v, lo, ext))
            bits.append(np.full(len(v), 1 << (f - first), dtype=np.uint64))
        ck, cb = np.concatenate(packed), np.concatenate(bits)
        reached = np.zeros(len(keys), dtype=np.uint64)
        if len(ck):
            order = np.argsort(ck, kind="stable")
            ck, cb = ck[order], cb[order]
            starts = np.flatnonzero(np.r_[True, ck[1:] != ck[:-1]])
            ck, cb = ck[starts], np.bitwise_or.reduceat(cb, starts)  # one mask per distinct candidate voxel
            query = (keys[None, :] - shifts[:, None]).reshape(-1)
            pos = np.minimum(np.searchsorted(ck, query), len(ck) - 1)
            found = np.where(ck[pos] == query, cb[pos], np.uint64(0))
            reached = np.bitwise_or.reduce(found.reshape(len(shifts), -1), axis=0)
        per_voxel = reached[inverse]
        for f in chunk:
            left = (per_voxel >> np.uint64(f - first)) & np.uint64(1) == 0
            out[f] = np.bincount(group[left], minlength=g)
    return out


def unreached_by_each_plain(cand: list[np.ndarray], ahead: list[np.ndarray], offsets: np.ndarray) -> np.ndarray:
    """:func:`unreached_by_each` by a nearest-neighbour query of each candidate's voxels (a k-d tree per candidate):
    the plain reference the fast path is tested against, and its fallback for boxes too large to pack.
    """
    m, g = len(cand), len(ahead)
    union = np.concatenate([np.asarray(b, dtype=np.float64).reshape(-1, 3) for b in ahead])
    group = np.repeat(np.arange(g), [len(b) for b in ahead])
    r2 = float((np.asarray(offsets, dtype=np.float64) ** 2).sum(axis=1).max()) if len(offsets) else 0.0
    out = np.zeros((m, g), dtype=np.int64)
    for f, v in enumerate(cand):
        left = np.ones(len(union), dtype=bool)
        if len(v) and len(union):
            d, _ = cKDTree(np.asarray(v, dtype=np.float64)).query(union, k=1, distance_upper_bound=np.sqrt(r2) + 1.0)
            left = ~(d * d <= r2 + 1e-9)  # inf (nothing within the bound) stays unreached
        out[f] = np.bincount(group[left], minlength=g)
    return out


def _pack(ijk: np.ndarray, lo: np.ndarray, ext: np.ndarray) -> np.ndarray:
    """[N] int64 keys of voxel indices ``ijk`` [N, 3] within the box at ``lo`` [3] of ``ext`` [3] voxels (for
    offsets, ``lo`` 0: the key of a shift); keys keep the rows' lexicographic order.
    """
    v = np.asarray(ijk, dtype=np.int64).reshape(-1, 3) - lo
    return (v[:, 0] * ext[1] + v[:, 1]) * ext[2] + v[:, 2]


def lookahead_new_voxels_plain(
    surface: ObservedSurface, candidates_w: list[np.ndarray], ahead_w: list[np.ndarray]
) -> np.ndarray:
    """:meth:`ObservedSurface.lookahead_new_voxels` the plain way, as the package first computed it: distinct voxels
    by sorting rows, a k-d tree per candidate (:func:`unreached_by_each_plain`); the reference its fast path is
    checked and timed against (``roigsf perf novelty``).
    """
    cand = [np.unique(surface._voxel_index(p), axis=0) for p in candidates_w]
    own = np.array([len(surface._unreached(v)) for v in cand], dtype=np.int64)
    ahead = [surface._unreached(np.unique(surface._voxel_index(p), axis=0)) for p in ahead_w]
    if not ahead or sum(len(b) for b in ahead) == 0:
        return own
    return own + unreached_by_each_plain(cand, ahead, surface._offsets).max(axis=1)


def frame_points(frame: Frame, intr: Intrinsics, config: MapperConfig) -> np.ndarray:
    """World points [N, 3] of a frame's depth within the mapper's depth range (``config``)."""
    return depth_points_w(_depth_of(frame, intr), frame.T_wc, intr, valid_depth_mask(frame.depth_m, config))


def _depth_of(frame: Frame, intr: Intrinsics) -> np.ndarray:
    """The frame's depth [H, W], or InputError naming the frame when it has none of the camera's size."""
    if np.shape(frame.depth_m) != (intr.height, intr.width):
        raise InputError(f"frame {frame.index} depth_m", f"shape {np.shape(frame.depth_m)}: novelty needs the frame's "
                         "depth image (a pose-only candidate, as in the pool setting, has none)")  # fmt: skip
    return frame.depth_m


def fuse_novelty(fused: np.ndarray, novelty_m2: np.ndarray, weight: float) -> np.ndarray:
    """[M] ``fused + weight z(N)``: a scored mode's fused score (Eq. 15, plus any unseen term) and the novelty.

    A candidate the scorer flagged (no mapped surface in view) keeps its fused 0 and competes by its novelty.
    """
    fused = np.asarray(fused, dtype=np.float64).reshape(-1)
    novelty = np.asarray(novelty_m2, dtype=np.float64).reshape(-1)
    if fused.shape != novelty.shape:
        raise InputError("novelty_m2", f"{novelty.size} values for {fused.size} candidates")
    return fused + float(weight) * zscore(novelty)


__all__ = [
    "HASH_CAPACITY",
    "HASH_CHUNK_ROWS",
    "NOVELTY_MEASURES",
    "NOVELTY_RADIUS_M",
    "NOVELTY_VOXEL_M",
    "ObservedSurface",
    "check_novelty_settings",
    "frame_points",
    "fuse_novelty",
    "lookahead_new_voxels_plain",
    "unique_voxels",
    "unreached_by_each",
    "unreached_by_each_plain",
]
