"""Which space a set of depth maps has observed: a dense voxel grid of unknown, free and occupied cells.

The NBV's unseen term with ``NBVConfig.unseen_source="carved"`` asks, for each pixel of a candidate view, whether its
ray reaches observed surface (or the box's side) through space no keyframe has observed: there a new view may show new
surface; with ``unseen_measure="cells"`` it counts the distinct cells where those unknown stretches begin (the
frontier the view looks at). The TSDF cannot answer it: open3d's voxel-block grid allocates blocks only within the
truncation band of observed surfaces, so free space far from a surface and space never seen look the same
(unallocated). OctoMap is the field's library for such a grid, but it is not among this project's dependencies, and
the grid needed here is small: one box, three states, rebuilt from the keyframes' depth at each scoring call, carved by
straight ray marching in two numba kernels.

Carving is deterministic whatever the thread schedule: every keyframe's rays first mark the cells in front of their
depth FREE (only cells still UNKNOWN), then every keyframe's rays mark the cells from their depth to one voxel behind
it OCCUPIED, so a cell some keyframe saw as surface stays occupied whichever order the rays ran in (and the free pass
can run right up to each depth). The band behind the surface keeps candidate rays from slipping between sampled hits;
the space behind it stays unknown, so a ray from behind a surface seen from one side meets unknown space first: its
far side counts as unseen.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.render.numba_setup import KERNEL_LOCK, Kernels, numba_available, prange

UNKNOWN, FREE, OCCUPIED = 0, 1, 2
"""Cell states of :attr:`ObservedSpace.state`."""


def _ray(T: np.ndarray, fx: float, fy: float, cx: float, cy: float, u: float, v: float) -> tuple:
    """World origin and direction (camera z = 1, so the ray parameter is the camera-z depth) of pixel (u, v)."""
    a = (u - cx) / fx
    b = (v - cy) / fy
    dx = T[0, 0] * a + T[0, 1] * b + T[0, 2]
    dy = T[1, 0] * a + T[1, 1] * b + T[1, 2]
    dz = T[2, 0] * a + T[2, 1] * b + T[2, 2]
    return T[0, 3], T[1, 3], T[2, 3], dx, dy, dz


def _slab(ox: float, oy: float, oz: float, dx: float, dy: float, dz: float, hi: np.ndarray) -> tuple:
    """(t_in, t_out) of the ray o + t d through the box [0, hi] (grid coordinates); t_in > t_out when it misses."""
    t_in = -np.inf
    t_out = np.inf
    for o, d, h in ((ox, dx, hi[0]), (oy, dy, hi[1]), (oz, dz, hi[2])):
        if d == 0.0:
            if o < 0.0 or o > h:
                return 1.0, 0.0
        else:
            t1 = (0.0 - o) / d
            t2 = (h - o) / d
            if t1 > t2:
                t1, t2 = t2, t1
            t_in = max(t_in, t1)
            t_out = min(t_out, t2)
    return t_in, t_out


def _k_carve(grid: np.ndarray, poses: np.ndarray, depth: np.ndarray, lo: np.ndarray, voxel: float, fx: float,
             fy: float, cx: float, cy: float, far: float, occupied: bool) -> None:  # fmt: skip
    """Mark cells along each keyframe pixel's ray: FREE before its depth (cells still UNKNOWN), or with ``occupied``
    OCCUPIED from its depth to one voxel behind it. ``grid`` [X, Y, Z] uint8; ``poses`` [K, 4, 4] camera-to-world;
    ``depth`` [K, H, W] camera-z metres (<= 0 or nan: no observation; inf: nothing up to ``far``, all free);
    ``lo`` the grid's corner (metres).
    """
    nx, ny, nz = grid.shape
    hi = np.array([nx, ny, nz], dtype=np.float64)
    n_k, h, w = depth.shape
    for r in prange(n_k * h):
        k = r // h
        v = r % h
        T = poses[k]
        for u in range(w):
            z = depth[k, v, u]
            if not z > 0.0 or (occupied and not z <= far):
                continue
            ox, oy, oz, dx, dy, dz = _ray(T, fx, fy, cx, cy, float(u), float(v))
            norm = np.sqrt(dx * dx + dy * dy + dz * dz)
            # grid coordinates: cell (i, j, k) spans [i, i + 1) voxels from lo
            gx, gy, gz = (ox - lo[0]) / voxel, (oy - lo[1]) / voxel, (oz - lo[2]) / voxel
            ex, ey, ez = dx / voxel, dy / voxel, dz / voxel
            t_in, t_out = _slab(gx, gy, gz, ex, ey, ez, hi)
            step = 0.5 * voxel / norm  # half a voxel along the ray, in depth units
            if occupied:
                t0 = max(z, t_in, 0.0)
                t1 = min(z + voxel / norm, t_out)
                value = 2
            else:  # up to the depth: the cell holding the surface point is marked OCCUPIED in the second pass
                t0 = max(t_in, 0.0)
                t1 = min(z - 1e-6, far, t_out)
                value = 1
            n = int((t1 - t0) / step) + 1 if t1 >= t0 else 0
            for s in range(n + 1):
                t = min(t0 + s * step, t1)
                i = int(gx + t * ex)
                j = int(gy + t * ey)
                q = int(gz + t * ez)
                if 0 <= i < nx and 0 <= j < ny and 0 <= q < nz and (occupied or grid[i, j, q] == 0):
                    grid[i, j, q] = value


def _k_unseen(grid: np.ndarray, T: np.ndarray, lo: np.ndarray, voxel: float, fx: float, fy: float, cx: float,
              cy: float, near: float, far: float, enter: np.ndarray, leave: np.ndarray,
              cell: np.ndarray) -> None:  # fmt: skip
    """Per pixel of ``enter`` [H, W]: the camera-z depth where the last stretch of the ray, before its first OCCUPIED
    cell (or where it leaves the grid or passes ``far``), begins when that stretch is UNKNOWN (0 when it is FREE), in
    ``leave`` where it ends, and in ``cell`` the flat index of the stretch's first cell (-1 when FREE). Unknown cells
    the ray crosses before observed free space do not count: the space near a camera no keyframe looked through says
    nothing about the surface the ray ends on.
    """
    nx, ny, nz = grid.shape
    hi = np.array([nx, ny, nz], dtype=np.float64)
    h, w = enter.shape
    for r in prange(h):
        for u in range(w):
            enter[r, u] = 0.0
            leave[r, u] = 0.0
            cell[r, u] = -1
            ox, oy, oz, dx, dy, dz = _ray(T, fx, fy, cx, cy, float(u), float(r))
            norm = np.sqrt(dx * dx + dy * dy + dz * dz)
            gx, gy, gz = (ox - lo[0]) / voxel, (oy - lo[1]) / voxel, (oz - lo[2]) / voxel
            ex, ey, ez = dx / voxel, dy / voxel, dz / voxel
            t_in, t_out = _slab(gx, gy, gz, ex, ey, ez, hi)
            t0 = max(t_in, near)
            t1 = min(t_out, far)
            step = 0.5 * voxel / norm
            n = int((t1 - t0) / step) + 1 if t1 >= t0 else 0
            found = False
            t = t0
            for s in range(n + 1):
                t = min(t0 + s * step, t1)
                i = int(gx + t * ex)
                j = int(gy + t * ey)
                q = int(gz + t * ez)
                if 0 <= i < nx and 0 <= j < ny and 0 <= q < nz:
                    c = grid[i, j, q]
                    if c == 2:
                        break
                    if c == 1:  # observed free space: unknown space crossed before it does not count
                        found = False
                    elif not found:
                        enter[r, u] = t
                        cell[r, u] = (i * ny + j) * nz + q
                        found = True
            if found:
                leave[r, u] = t
            else:
                enter[r, u] = 0.0
                cell[r, u] = -1


_KERNELS = Kernels(helpers=(_ray, _slab), carve=_k_carve, unseen=_k_unseen)


@dataclass
class ObservedSpace:
    """A box of space cut into cubic cells, each UNKNOWN, FREE or OCCUPIED as a set of depth maps observed it."""

    lo_m: np.ndarray
    """[3] the grid's corner (world metres): cell (i, j, k) spans lo + [i, i + 1) voxel along each axis."""
    voxel_m: float
    state: np.ndarray
    """[X, Y, Z] uint8 cell states (:data:`UNKNOWN`, :data:`FREE`, :data:`OCCUPIED`)."""

    @classmethod
    def empty(cls, lo_m: np.ndarray, hi_m: np.ndarray, voxel_m: float) -> ObservedSpace:
        """The box [lo_m, hi_m] in cells of ``voxel_m``, every cell UNKNOWN (nothing observed yet)."""
        lo = np.asarray(lo_m, dtype=np.float64).reshape(3)
        hi = np.asarray(hi_m, dtype=np.float64).reshape(3)
        if not (voxel_m > 0 and np.isfinite(voxel_m)):
            raise InputError("voxel_m", f"must be a positive size in metres, got {voxel_m}")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi > lo)):
            raise InputError("box", f"needs finite corners with hi > lo, got {lo} .. {hi}")
        dims = np.maximum(np.ceil((hi - lo) / voxel_m).astype(np.int64), 1)
        if int(np.prod(dims)) > 256_000_000:
            raise InputError("voxel_m", f"{voxel_m} m cells make a {dims.tolist()} grid of the box: too many")
        return cls(lo, float(voxel_m), np.zeros(tuple(int(d) for d in dims), dtype=np.uint8))

    @classmethod
    def carve(
        cls,
        lo_m: np.ndarray,
        hi_m: np.ndarray,
        voxel_m: float,
        poses: Sequence[np.ndarray] | np.ndarray,
        depth_m: np.ndarray,
        intr: Intrinsics,
        far_m: float = np.inf,
    ) -> ObservedSpace:
        """The box [lo_m, hi_m] as the depth maps ``depth_m`` [K, H, W] (camera z, metres; 0 or nan: no observation;
        inf: the ray met nothing up to ``far_m``, so all it crossed is free) seen from ``poses`` [K, 4, 4]
        (camera-to-world) at ``intr`` observed it; depths beyond ``far_m`` carve free space up to it only.
        """
        space = cls.empty(lo_m, hi_m, voxel_m)
        space.carve_more(poses, depth_m, intr, far_m)
        return space

    def carve_more(
        self,
        poses: Sequence[np.ndarray] | np.ndarray,
        depth_m: np.ndarray,
        intr: Intrinsics,
        far_m: float = np.inf,
    ) -> None:
        """Carve more depth maps into this grid, in place (arguments as :meth:`carve`'s). A cell ends OCCUPIED where
        any ray ended in it, else FREE where any ray passed, else UNKNOWN, so carving in parts gives the grid carving
        all at once gives, cell for cell (a planner adds each new keyframe without carving the old ones again).
        """
        pose_arr = np.ascontiguousarray(np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4))
        depth = np.ascontiguousarray(np.asarray(depth_m, dtype=np.float64))
        if depth.ndim != 3 or len(depth) != len(pose_arr) or depth.shape[1:] != (intr.height, intr.width):
            raise InputError(
                "depth_m", f"expected [{len(pose_arr)}, {intr.height}, {intr.width}] (one per pose), got {depth.shape}"
            )
        if len(pose_arr):
            for occupied in (False, True):
                self._launch("carve", self.state, pose_arr, depth, self.lo_m, self.voxel_m, intr.fx, intr.fy,
                             intr.cx, intr.cy, float(far_m), occupied)  # fmt: skip

    def unseen_depths(
        self, T_wc: np.ndarray, intr: Intrinsics, near_m: float = 0.0, far_m: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray]:
        """([H, W], [H, W]) camera-z depths where each pixel's ray from ``T_wc`` enters the unknown space it crosses
        last, right before it meets observed surface or leaves the box, and where that stretch ends (0, 0: the ray
        reaches observed surface or the box's side through observed free space); only the part of the ray between
        ``near_m`` and ``far_m`` counts.
        """
        enter, leave, _ = self.unseen_rays(T_wc, intr, near_m, far_m)
        return enter, leave

    def unseen_frontier(
        self, T_wc: np.ndarray, intr: Intrinsics, near_m: float = 0.0, far_m: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`unseen_depths`, but where the second array is [F] int64: the distinct flat indices (into
        :attr:`state`) of the unknown cells where the pixels' unseen stretches begin, each once: the part of the
        boundary between observed free space and unseen space that the view looks at, whatever its distance
        (``NBVConfig.unseen_measure="cells"``); from a camera inside unknown space, the few cells its rays start in.
        """
        enter, _, cell = self.unseen_rays(T_wc, intr, near_m, far_m)
        return enter, np.unique(cell[cell >= 0])

    def unseen_cells(
        self, T_wc: np.ndarray, intr: Intrinsics, near_m: float = 0.0, far_m: float = np.inf
    ) -> np.ndarray:
        """[H, W] int64: the flat index (into :attr:`state`) of the unknown cell where each pixel's last unknown
        stretch begins, as in :meth:`unseen_depths`, or -1 where the ray crosses none (``unseen_plan_views``).
        """
        return self.unseen_rays(T_wc, intr, near_m, far_m)[2]

    def unseen_rays(
        self, T_wc: np.ndarray, intr: Intrinsics, near_m: float = 0.0, far_m: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """([H, W] enter depth, [H, W] leave depth, [H, W] int64 first cell or -1) of each pixel's unseen stretch: the
        three of :meth:`unseen_depths` and :meth:`unseen_cells` from one pass (``NBVConfig.unseen_rarity``).
        """
        enter = np.zeros((intr.height, intr.width))
        leave = np.zeros((intr.height, intr.width))
        cell = np.full((intr.height, intr.width), -1, dtype=np.int64)
        T = np.ascontiguousarray(np.asarray(T_wc, dtype=np.float64))
        self._launch("unseen", self.state, T, self.lo_m, self.voxel_m, intr.fx, intr.fy, intr.cx, intr.cy,
                     float(near_m), float(far_m), enter, leave, cell)  # fmt: skip
        return enter, leave, cell

    def counts(self) -> dict[str, int]:
        """Cells per state, for logs and tests."""
        n = np.bincount(self.state.reshape(-1), minlength=3)
        return {"unknown": int(n[UNKNOWN]), "free": int(n[FREE]), "occupied": int(n[OCCUPIED])}

    @staticmethod
    def _launch(name: str, *args: object) -> None:
        """Run kernel ``name`` compiled (numba) or, without numba, as plain Python (slow; numba is a dependency)."""
        if numba_available():
            with KERNEL_LOCK:
                _KERNELS[name](*args)
        else:
            {"carve": _k_carve, "unseen": _k_unseen}[name](*args)


__all__ = ["FREE", "OCCUPIED", "UNKNOWN", "ObservedSpace"]
