"""Work an NBV scorer can keep between calls on a growing map (ROS-free; the planner node holds one of each).

- :class:`TrainFisherCache`: H_train over a growing set of keyframe poses, each pose's Fisher added once
  under the map of that moment, the rows carried over to a newer map by :func:`match_surfels` /
  :func:`carry_rows` (the approximation the Mapper's own running ``h_train`` makes).
- :class:`PreparedScorer`: an :class:`~roigsf_ros.nbv.NBVScorer` given the near-surface voxels of a TSDF
  already extracted, so repeated scoring against an unchanged TSDF does not extract them again.
"""

from __future__ import annotations

import numpy as np
import torch

from roigsf_ros.camera import Intrinsics
from roigsf_ros.nbv import NBVConfig, NBVScorer
from roigsf_ros.surfels import SurfelMap
from roigsf_ros.tsdf import SurfaceVoxels, TSDFVolume


def match_surfels(old_means: np.ndarray, new_means: np.ndarray, tol_m: float) -> np.ndarray:
    """For each surfel of a newer map, the row of the older map it continues (-1: a surfel added since).

    The Mapper keeps surviving surfels in order and appends new ones, so the longest common prefix
    (centres within ``tol_m``) is matched as is; each later surfel takes the nearest older one within
    ``tol_m`` not taken yet (optimisation moves centres by far less than the surfel spacing).
    """
    from scipy.spatial import cKDTree

    old_means = np.asarray(old_means, dtype=np.float64).reshape(-1, 3)
    new_means = np.asarray(new_means, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(new_means), -1, dtype=np.int64)
    k = min(len(old_means), len(new_means))
    close = np.linalg.norm(old_means[:k] - new_means[:k], axis=1) <= tol_m
    prefix = k if bool(close.all()) else int(np.argmin(close))
    out[:prefix] = np.arange(prefix)
    rest_old = old_means[prefix:]
    if prefix == len(new_means) or len(rest_old) == 0:
        return out
    dist, idx = cKDTree(rest_old).query(new_means[prefix:], k=1, distance_upper_bound=tol_m)
    hit = np.flatnonzero(np.isfinite(dist))
    _, first = np.unique(idx[hit], return_index=True)  # one older surfel continues at most one newer
    hit = hit[first]
    out[prefix + hit] = prefix + idx[hit]
    return out


def carry_rows(h: dict[str, torch.Tensor], rows: np.ndarray) -> dict[str, torch.Tensor]:
    """``h`` re-indexed to a newer map: row i = h[rows[i]], zeros where rows[i] == -1."""
    sel = torch.as_tensor(rows)
    keep = sel >= 0
    out = {}
    for name, t in h.items():
        new = t.new_zeros((len(rows), *t.shape[1:]))
        new[keep] = t[sel[keep]]
        out[name] = new
    return out


class TrainFisherCache:
    """H_train over a growing set of keyframe poses, kept across map versions (see the module docstring).

    One entry per Fisher kind (``fisherrf`` or the ROI modes'): pose keys summed, the sum, and the
    surfel centres it is aligned with. ROS-free; not thread-safe (the planner calls it from one group).
    """

    def __init__(self, config: NBVConfig, match_tol_m: float = 0.01, refresh_every: int = 0) -> None:
        self.config = config
        self.match_tol_m = match_tol_m
        self.refresh_every = refresh_every
        self._entries: dict[str, tuple[list[bytes], dict[str, torch.Tensor], np.ndarray, int]] = {}
        self.full_computations = 0
        self.poses_added = 0

    def get(self, surfel_map: SurfelMap, poses: np.ndarray, intr: Intrinsics, mode: str) -> dict[str, torch.Tensor]:
        """H_train of ``mode`` for ``poses`` under ``surfel_map`` (incremental where the poses extend the last)."""
        kind = "fisherrf" if mode == "fisherrf" else "fisher"
        keys = [np.ascontiguousarray(T, dtype=np.float64).tobytes() for T in poses]
        means = surfel_map.means.detach().cpu().numpy().astype(np.float64)
        scorer = NBVScorer(self.config)
        entry = self._entries.get(kind)
        stale = entry is not None and self.refresh_every > 0 and entry[3] >= self.refresh_every
        if entry is None or keys[: len(entry[0])] != entry[0] or stale:
            h = scorer.train_fisher(surfel_map, poses, intr, mode)
            self.full_computations += 1
            self._entries[kind] = (keys, h, means, 0)
            return h
        old_keys, h, old_means, added = entry
        if len(old_means) != len(means) or not np.array_equal(old_means, means):
            h = carry_rows(h, match_surfels(old_means, means, self.match_tol_m))
        if len(keys) > len(old_keys):
            new = scorer.train_fisher(surfel_map, np.asarray(poses)[len(old_keys) :], intr, mode)
            h = {k: h[k] + new[k] for k in h}
            self.poses_added += len(keys) - len(old_keys)
            added += len(keys) - len(old_keys)
        self._entries[kind] = (keys, h, means, added)
        return h


class PreparedScorer(NBVScorer):
    """An :class:`NBVScorer` that takes the near-surface voxels of one TSDF as already extracted."""

    def __init__(self, config: NBVConfig, tsdf: TSDFVolume | None, voxels: SurfaceVoxels | None) -> None:
        super().__init__(config)
        self._tsdf = tsdf
        self._voxels = voxels

    def surface(self, tsdf: TSDFVolume | None) -> SurfaceVoxels | None:
        """The prepared voxels for the prepared TSDF (same config), else extracted as usual."""
        if tsdf is not None and tsdf is self._tsdf and self._voxels is not None:
            return self._voxels
        return super().surface(tsdf)


__all__ = ["PreparedScorer", "TrainFisherCache", "carry_rows", "match_surfels"]
