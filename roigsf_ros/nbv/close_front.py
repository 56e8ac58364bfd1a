"""Close-front view scoring (ROI-GSurFisher Eq. 11-14): reward views closer to and more frontal on surfaces.

Each near-surface TSDF voxel l keeps its best training observation ``W_f(l) = max_r cos(theta_r) / z_r``
(Eq. 11-12) over the training views r that see it (front-facing, in the frustum, not occluded, as
:func:`roigsf_ros.nbv.roi.voxel_visibility` decides); a candidate x gains
``I_vis(x) = sum_l [cos(theta_x) / z_x - W_f(l)]_+`` (Eq. 13-14) over the voxels it sees. Units: 1/m.

Keeping W_f aligned with a growing TSDF (:class:`CloseFrontMemory`): values live in a table keyed by the
voxels' integer grid coordinates (packed into int64, sorted, looked up with ``searchsorted``), so voxels
may appear, disappear or be reordered between calls. ``add_view`` evaluates one new keyframe against the
current voxel set, O(V) per keyframe; call it after integrating that keyframe into the TSDF, so the
surface it observes is in the set. A voxel that only enters the surface band later keeps no value from
earlier views (it counts as unobserved by them, W_f = 0); :meth:`CloseFrontMemory.from_poses` recomputes
W_f exactly from all stored poses on the current voxel set, O(P V), for callers that prefer exactness.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from roigsf_ros.core.camera import Intrinsics, check_pose
from roigsf_ros.core.errors import InputError
from roigsf_ros.mapping.tsdf import SurfaceVoxels
from roigsf_ros.nbv.config import NBVConfig
from roigsf_ros.nbv.roi import VoxelView, voxel_visibility

_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


def voxel_keys(centres_m: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Int64 keys [M] of voxel centres [M, 3] (integer grid coordinates, 21 bits each, +-2^20 voxels)."""
    ijk = np.rint(np.asarray(centres_m, dtype=np.float64).reshape(-1, 3) / voxel_size_m).astype(np.int64)
    if ijk.size and (np.abs(ijk).max() >= _KEY_OFFSET):
        raise InputError("voxels", f"voxel coordinates beyond +-{_KEY_OFFSET} voxels cannot be keyed")
    ijk += _KEY_OFFSET
    return (ijk[:, 0] << (2 * _KEY_BITS)) | (ijk[:, 1] << _KEY_BITS) | ijk[:, 2]


def observation_weight(view: VoxelView) -> np.ndarray:
    """Eq. 11 / 13: ``cos(theta) / z`` [K] (1/m) of the voxels a camera sees."""
    return view.cos_incidence / view.z_m


def close_front_gain(view: VoxelView, fused_weight: np.ndarray) -> float:
    """Eq. 14: ``I_vis = sum [W_x - W_f]_+`` over the candidate's visible voxels; ``fused_weight`` [M] is W_f."""
    if len(view) == 0:
        return 0.0
    return float(np.maximum(observation_weight(view) - np.asarray(fused_weight)[view.index], 0.0).sum())


class CloseFrontMemory:
    """W_f of Eq. 12 per voxel, keyed by integer voxel coordinates, updated one training view at a time."""

    def __init__(self, voxel_size_m: float, cfg: NBVConfig) -> None:
        if not (np.isfinite(voxel_size_m) and voxel_size_m > 0):
            raise InputError("voxel_size_m", f"must be a positive number, got {voxel_size_m}")
        self.voxel_size_m = float(voxel_size_m)
        self.cfg = cfg
        self.keys = np.zeros(0, dtype=np.int64)
        """Sorted voxel keys [V] (see :func:`voxel_keys`)."""
        self.values = np.zeros(0, dtype=np.float64)
        """W_f [V] of the keys, 1/m."""
        self.poses: list[np.ndarray] = []
        """Training poses added so far (camera-to-world [4, 4])."""

    def __len__(self) -> int:
        return int(self.keys.shape[0])

    def add_view(self, voxels: SurfaceVoxels, T_wc: np.ndarray, intr: Intrinsics) -> int:
        """Fold one training view into W_f (max with cos/z of the voxels it sees); returns how many it sees."""
        T = check_pose(T_wc, "T_wc")
        self.poses.append(T.copy())
        if len(voxels.centres_m) == 0:
            return 0
        view = voxel_visibility(voxels, T, intr, self.voxel_size_m, self.cfg)
        if len(view) == 0:
            return 0
        self._merge(voxel_keys(np.asarray(voxels.centres_m)[view.index], self.voxel_size_m), observation_weight(view))
        return len(view)

    def _merge(self, keys: np.ndarray, values: np.ndarray) -> None:
        all_keys = np.concatenate([self.keys, keys])
        all_vals = np.concatenate([self.values, values])
        uniq, inv = np.unique(all_keys, return_inverse=True)
        merged = np.full(len(uniq), -np.inf)
        np.maximum.at(merged, inv, all_vals)
        self.keys, self.values = uniq, merged

    def fused_weight(self, voxels: SurfaceVoxels) -> np.ndarray:
        """W_f [M] of the given voxels (0 for voxels no added view has seen)."""
        keys = voxel_keys(voxels.centres_m, self.voxel_size_m)
        out = np.zeros(len(keys))
        if len(self.keys) == 0 or len(keys) == 0:
            return out
        pos = np.clip(np.searchsorted(self.keys, keys), 0, len(self.keys) - 1)
        hit = self.keys[pos] == keys
        out[hit] = self.values[pos[hit]]
        return out

    @classmethod
    def from_poses(
        cls,
        voxels: SurfaceVoxels,
        poses: Iterable[np.ndarray],
        intr: Intrinsics,
        voxel_size_m: float,
        cfg: NBVConfig,
    ) -> CloseFrontMemory:
        """A memory with every pose evaluated on the current voxel set (exact W_f; O(poses x voxels))."""
        mem = cls(voxel_size_m, cfg)
        for T in poses:
            mem.add_view(voxels, np.asarray(T), intr)
        return mem


__all__ = [
    "CloseFrontMemory",
    "close_front_gain",
    "observation_weight",
    "voxel_keys",
]
