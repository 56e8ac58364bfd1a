"""Work an NBV scorer can keep between calls on a growing map (ROS-free; the planner node holds one of each).

- :class:`TrainFisherCache`: H_train over a growing set of keyframe poses, each pose's Fisher added once
  under the map of that moment, the rows carried over to a newer map by :func:`match_surfels` /
  :func:`carry_rows` (the approximation the Mapper's own running ``h_train`` makes).
- :class:`PreparedScorer`: an :class:`~roigsf_ros.nbv.scorer.NBVScorer` given the near-surface voxels of a TSDF
  already extracted, so repeated scoring against an unchanged TSDF does not extract them again.
- :class:`ScoringState`: everything scoring keeps between calls on a growing map, shared by the stream
  policies and the planner node: the scoring TSDF fused incrementally from the map's rendered depth at each
  keyframe pose (rebuilt when the keyframe set is not an extension of the fused one), its near-surface
  voxels (re-extracted only when a keyframe is fused), the close-front memory W_f (each new keyframe folded
  in once, or with ``NBVConfig.close_front_exact`` re-evaluated from every keyframe), and the choice of H_train.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.mapping.observed_space import ObservedSpace
from roigsf_ros.mapping.tsdf import SurfaceVoxels, TSDFVolume
from roigsf_ros.nbv.close_front import CloseFrontMemory
from roigsf_ros.nbv.config import ROI_MODES, NBVConfig
from roigsf_ros.nbv.scorer import NBVResult, NBVScorer, downsampled
from roigsf_ros.nbv.stop import ShouldStop, check_stop
from roigsf_ros.nbv.unseen import carve_depths, unseen_box
from roigsf_ros.render.surfels import SurfelMap

if TYPE_CHECKING:
    from roigsf_ros.mapping.mapper import Mapper, MapperConfig


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

    def get(
        self, surfel_map: SurfelMap, poses: np.ndarray, intr: Intrinsics, mode: str, should_stop: ShouldStop = None
    ) -> dict[str, torch.Tensor]:
        """H_train of ``mode`` for ``poses`` under ``surfel_map`` (incremental where the poses extend the last).

        ``should_stop`` is checked before each pose's Fisher; a stop keeps the cache as it was.
        """
        kind = "fisherrf" if mode == "fisherrf" else "fisher"
        keys = pose_keys(poses)
        means = surfel_map.means.detach().cpu().numpy().astype(np.float64)
        scorer = NBVScorer(self.config)
        entry = self._entries.get(kind)
        stale = entry is not None and self.refresh_every > 0 and entry[3] >= self.refresh_every
        if entry is None or keys[: len(entry[0])] != entry[0] or stale:
            h = scorer.train_fisher(surfel_map, poses, intr, mode, should_stop)
            self.full_computations += 1
            self._entries[kind] = (keys, h, means, 0)
            return h
        old_keys, h, old_means, added = entry
        if len(old_means) != len(means) or not np.array_equal(old_means, means):
            h = carry_rows(h, match_surfels(old_means, means, self.match_tol_m))
        if len(keys) > len(old_keys):
            new = scorer.train_fisher(surfel_map, np.asarray(poses)[len(old_keys) :], intr, mode, should_stop)
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


RenderRGBD = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""The map's own RGB-D at a pose ``T_wc`` [4, 4]: (depth_m [H, W] float32, 0 = no surface; rgb [H, W, 3] uint8)."""

SCORING_TSDF_BLOCKS = 2000
"""Initial block-map capacity of the scoring TSDF (blocks of 16^3 voxels: 66 MB without colour, less than the 82 MB
of the 1000 coloured blocks it started with before). Growing it holds Python's GIL for the whole copy (open3d),
stalling every thread of the process; the synthetic room's 1200-1300 blocks at 2 cm never need a growth."""
SCORING_TSDF_MAX_FILL = 0.75
"""The scoring TSDF's block map is grown between requests once more than this share of it is used."""
CLOSE_FRONT_MODES = ("roi-gsurfisher", "close-front")
"""Modes that need the close-front memory W_f."""


def pose_keys(poses: np.ndarray) -> list[bytes]:
    """One hashable key per [4, 4] pose (its float64 bytes): identifies the keyframe set fused or summed."""
    return [np.ascontiguousarray(T, dtype=np.float64).tobytes() for T in np.asarray(poses).reshape(-1, 4, 4)]


class CarvedSpaceMemory:
    """The unseen term's carved grid kept between scoring calls (``NBVConfig.unseen_carve_rerender`` false): the
    map's depth rendered at each keyframe pose once, when first seen (:func:`~roigsf_ros.nbv.unseen.carve_depths`),
    and the grid carved incrementally from those depths (:meth:`ObservedSpace.carve_more`). Carving is a per-cell OR,
    so the kept grid is, cell for cell, the one :meth:`ObservedSpace.carve` makes of all the kept depths at once; a
    new box (the surface grew) carves the kept depths again, without rendering. ROS-free, not thread-safe.
    """

    def __init__(self) -> None:
        self._keys: list[bytes] = []
        self._depth: list[np.ndarray] = []
        self._settings: tuple | None = None
        self._space: ObservedSpace | None = None
        self._box: tuple[np.ndarray, np.ndarray] | None = None
        self._n_carved = 0
        self.renders = 0
        """Keyframe poses rendered so far (each once, unless the keyframe set or the settings changed)."""
        self.carves = 0
        """Keyframe depths carved so far (a new box carves the kept ones again)."""

    def space(
        self,
        surfel_map: SurfelMap,
        poses: np.ndarray,
        intr: Intrinsics,
        box: tuple[np.ndarray, np.ndarray],
        config: NBVConfig,
        should_stop: ShouldStop = None,
    ) -> ObservedSpace:
        """The grid of ``box`` (lo, hi) carved by every keyframe of ``poses`` [K, 4, 4] at ``intr``: the ones not
        seen before rendered from ``surfel_map`` now. A keyframe set that does not extend the kept one (a loaded
        map), other intrinsics or other carving settings start afresh.
        """
        pose_arr = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        keys = pose_keys(pose_arr)
        settings = (intr, config.unseen_alpha, config.near_m, config.far_m, config.unseen_voxel_m)
        if settings != self._settings or keys[: len(self._keys)] != self._keys:
            self._keys, self._depth, self._settings, self._space, self._box = [], [], settings, None, None
        if len(keys) > len(self._keys):
            new = pose_arr[len(self._keys) :]
            self._depth.extend(carve_depths(surfel_map, new, intr, config, should_stop))
            self._keys.extend(keys[len(self._keys) :])
            self.renders += len(new)
        lo, hi = (np.asarray(b, dtype=np.float64).reshape(3) for b in box)
        if self._space is None or self._box is None or not all(map(np.array_equal, self._box, (lo, hi))):
            self._space, self._box, self._n_carved = ObservedSpace.empty(lo, hi, config.unseen_voxel_m), (lo, hi), 0
        n = len(self._keys)
        if self._n_carved < n:
            k = self._n_carved
            self._space.carve_more(pose_arr[k:n], np.stack(self._depth[k:n]), intr, config.far_m)
            self.carves += n - k
            self._n_carved = n
        return self._space


def running_h_train_fits(
    h_train: dict[str, torch.Tensor] | None, map_fisher_outputs: tuple[str, ...], config: NBVConfig, mode: str
) -> bool:
    """Whether a running H_train is what ``mode`` scores against (same outputs and parameters, no pixel weights).

    The mapper sums an unweighted (``sigma_p`` = 1) Fisher of ``map_fisher_outputs`` over the geometric
    parameters; FisherRF's H_train covers other parameters and outputs, so it is never the running one.
    """
    return (
        h_train is not None
        and mode != "fisherrf"
        and config.sigma_p == 1.0
        and tuple(map_fisher_outputs) == tuple(config.fisher_outputs)
        and all(p in h_train for p in config.fisher_params if p != "sh_rest")
    )


class ScoringState:
    """What NBV scoring keeps between calls on a growing map (see the module docstring). ROS-free, not thread-safe.

    ``voxel_size_m``/``sdf_trunc_m``/``depth_max_m``: the scoring TSDF. ``cache_h_train``: when the running
    H_train does not fit, keep one with :class:`TrainFisherCache` (incremental, approximate; the planner) or,
    False, let the scorer recompute it exactly from the keyframe poses at every call (the offline policies).
    ``should_stop``: checked between units of work (a fused keyframe, a training view, a candidate); when it
    turns true the call raises :class:`~roigsf_ros.nbv.stop.ScoringStoppedError` (what was fused so far is kept).
    """

    def __init__(
        self,
        config: NBVConfig,
        voxel_size_m: float,
        sdf_trunc_m: float,
        depth_max_m: float,
        cache_h_train: bool = False,
        match_tol_m: float = 0.01,
        refresh_every: int = 0,
        should_stop: ShouldStop = None,
    ) -> None:
        self.config = config = NBVConfig.given(config)
        self.should_stop = should_stop
        self.voxel_size_m = float(voxel_size_m)
        self.sdf_trunc_m = float(sdf_trunc_m)
        self.depth_max_m = float(depth_max_m)
        self.train_fisher_cache = TrainFisherCache(config, match_tol_m, refresh_every) if cache_h_train else None
        self.tsdf: TSDFVolume | None = None
        """The scoring TSDF; None until a keyframe is fused."""
        self._fused: list[bytes] = []
        self._surface: SurfaceVoxels | None = None
        self._close_front: CloseFrontMemory | None = None
        self._close_front_fresh = False  # W_f matches the current surface voxels (exact mode)
        self.surface_extractions = 0
        self.close_front_builds = 0
        """Close-front memories built from every keyframe pose (once, or at each TSDF update when exact)."""
        self.close_front_views_added = 0
        """Keyframes folded into the kept close-front memory one at a time (not exact mode)."""
        keep_grid = config.unseen_source == "carved" and not config.unseen_carve_rerender
        self.carved = CarvedSpaceMemory() if keep_grid else None
        """The unseen term's carved grid, kept (``unseen_carve_rerender`` false), else None: carved at each call."""
        self._kept_space: ObservedSpace | None = None

    @classmethod
    def for_map(
        cls,
        mapper_config: MapperConfig,
        config: NBVConfig | None = None,
        voxel_size_m: float | None = None,
        sdf_trunc_m: float | None = None,
        **kwargs: Any,
    ) -> ScoringState:
        """A state whose scoring TSDF has a map's mesh settings, as :func:`score_views` and the stream policies make it:
        ``mesh_voxel_size_m``, ``mesh_sdf_trunc_m`` (at least a voxel) and ``max_depth_m`` of ``mapper_config``;
        ``voxel_size_m`` / ``sdf_trunc_m`` override the first two; ``config`` None is the paper's score; ``kwargs``
        as the constructor's (``cache_h_train``, ``should_stop``, ...).
        """
        voxel = mapper_config.mesh_voxel_size_m if voxel_size_m is None else float(voxel_size_m)
        trunc = max(mapper_config.mesh_sdf_trunc_m, voxel) if sdf_trunc_m is None else float(sdf_trunc_m)
        return cls(NBVConfig.given(config), voxel, trunc, mapper_config.max_depth_m, **kwargs)

    @property
    def n_fused(self) -> int:
        """Keyframe poses fused into the scoring TSDF."""
        return len(self._fused)

    def reset(self) -> None:
        """Forget the TSDF and what derives from it (the H_train cache is kept: it checks its own poses)."""
        self.tsdf, self._fused, self._surface, self._close_front = None, [], None, None
        self._close_front_fresh = False

    def sync(self, render_rgbd: RenderRGBD, poses: np.ndarray, intr: Intrinsics) -> int:
        """Fuse the map's rendered RGB-D at every keyframe pose not fused yet; returns how many were fused now.

        A keyframe set that does not extend the fused one (a loaded map) starts a new TSDF.
        """
        keys = pose_keys(poses)
        if keys[: len(self._fused)] != self._fused:
            self.reset()
        new = range(len(self._fused), len(keys))
        if not new:
            return 0
        if self.tsdf is None:  # geometry only: the scorer reads no TSDF colour (texture comes from the surfels)
            self.tsdf = TSDFVolume(self.voxel_size_m, self.sdf_trunc_m, self.depth_max_m,
                                   block_count=SCORING_TSDF_BLOCKS, with_color=False)  # fmt: skip
        for i in new:
            check_stop(self.should_stop)
            T = np.asarray(poses)[i]
            depth, _ = render_rgbd(T)
            self.tsdf.integrate(depth, T, intr)
            self._fused.append(keys[i])
            self._surface = None
            self._close_front_fresh = False
        return len(new)

    def reserve_ahead(self) -> bool:
        """Grow the TSDF's block map ahead of need (:meth:`TSDFVolume.reserve_ahead`); call between requests."""
        return self.tsdf is not None and self.tsdf.reserve_ahead(SCORING_TSDF_MAX_FILL)

    def products(
        self, poses: np.ndarray, intr: Intrinsics, close_front: bool
    ) -> tuple[SurfaceVoxels | None, CloseFrontMemory | None]:
        """Near-surface voxels of the TSDF and (``close_front``) W_f of the fused ``poses`` (see the module docstring).

        By default the first call with a surface builds W_f from every fused pose and later ones fold in only the
        poses fused since (one visibility pass each, on the surface after their fusion); with
        ``close_front_exact`` every TSDF update rebuilds it from every fused pose.
        """
        if self.tsdf is None:
            return None, None
        if self._surface is None:
            self._surface = NBVScorer(self.config).surface(self.tsdf)
            self.surface_extractions += 1
        if not close_front or len(self._surface.centres_m) == 0:
            return self._surface, self._close_front if close_front else None
        fused = np.asarray(poses).reshape(-1, 4, 4)[: self.n_fused]
        mem = self._close_front
        rebuild = mem is None or (self.config.close_front_exact and not self._close_front_fresh)
        if rebuild:
            mem = CloseFrontMemory.from_poses(self._surface, fused, intr, self.tsdf.voxel_size_m, self.config)
            self.close_front_builds += 1
        else:
            for T in fused[len(mem.poses) :]:
                mem.add_view(self._surface, T, intr)
                self.close_front_views_added += 1
        self._close_front, self._close_front_fresh = mem, True
        return self._surface, self._close_front

    def h_train(
        self,
        surfel_map: SurfelMap,
        running: dict[str, torch.Tensor] | None,
        map_fisher_outputs: tuple[str, ...],
        poses: np.ndarray,
        intr: Intrinsics,
        mode: str,
    ) -> dict[str, torch.Tensor] | None:
        """H_train for ``mode``: the running one when it fits, else the cache's (None: the scorer recomputes it)."""
        if running_h_train_fits(running, map_fisher_outputs, self.config, mode):
            return running
        if self.train_fisher_cache is None:
            return None
        return self.train_fisher_cache.get(surfel_map, poses, intr, mode, self.should_stop)

    def update(
        self,
        surfel_map: SurfelMap,
        running: dict[str, torch.Tensor] | None,
        map_fisher_outputs: tuple[str, ...],
        poses: np.ndarray,
        intr: Intrinsics,
        render_rgbd: RenderRGBD,
        mode: str | None = None,
    ) -> tuple[SurfaceVoxels | None, CloseFrontMemory | None, dict[str, torch.Tensor] | None]:
        """Bring everything ``mode`` (default: the config's) scores against up to date: TSDF, its products, H_train."""
        mode = mode or self.config.mode
        voxels = close_front = h = None
        self._kept_space = None
        if mode != "fisherrf" and len(surfel_map) > 0:
            self.sync(render_rgbd, poses, intr)
            voxels, close_front = self.products(poses, intr, close_front=mode in CLOSE_FRONT_MODES)
            cfg = self.config
            unseen = self.carved is not None and cfg.unseen_weight > 0 and mode in ROI_MODES
            if unseen and voxels is not None and len(voxels.centres_m):  # the scorer's box, at its resolution
                intr_f = downsampled(intr, cfg.fisher_downsample)
                box = unseen_box(voxels, cfg)
                self._kept_space = self.carved.space(surfel_map, poses, intr_f, box, cfg, self.should_stop)
        if self.config.uses_fisher(mode):
            h = self.h_train(surfel_map, running, map_fisher_outputs, poses, intr, mode)
        return voxels, close_front, h

    def score(
        self,
        surfel_map: SurfelMap,
        running: dict[str, torch.Tensor] | None,
        map_fisher_outputs: tuple[str, ...],
        poses: np.ndarray,
        candidates: list[np.ndarray] | np.ndarray,
        intr: Intrinsics,
        render_rgbd: RenderRGBD,
        mode: str | None = None,
        top_k: int | None = None,
    ) -> NBVResult:
        """Score ``candidates`` [N, 4, 4] against the map with keyframe ``poses``; the best is ``result.best_index``."""
        mode = mode or self.config.mode
        voxels, close_front, h = self.update(surfel_map, running, map_fisher_outputs, poses, intr, render_rgbd, mode)
        cfg = replace(self.config, mode=mode, top_k=self.config.top_k if top_k is None else top_k)  # 0 refused
        tsdf = self.tsdf if mode != "fisherrf" else None
        scorer = PreparedScorer(cfg, tsdf, voxels)
        return scorer.score(
            surfel_map, h, tsdf, poses, candidates, intr, mode=mode, close_front_memory=close_front,
            should_stop=self.should_stop, kept_space=self._kept_space,
        )  # fmt: skip


def score_views(
    mapper: Mapper,
    candidates: list[np.ndarray] | np.ndarray,
    config: NBVConfig | None = None,
    mode: str | None = None,
    top_k: int | None = None,
) -> NBVResult:
    """Score candidate poses ([N, 4, 4] camera-to-world, a list of 4x4, or [N, 7] position + xyzw rows) against a
    mapper's map in one call, as the planner node does: the TSDF fused from the map rendered at every keyframe
    (:meth:`~roigsf_ros.mapping.mapper.Mapper.map_keyframes`, so a map from ``Mapper.load`` works too), with the
    mapper's mesh settings, and its running H_train where it covers every keyframe (else recomputed).

    ``config`` default: the paper's score; ``NBVConfig(**RECOMMENDED_UNSEEN)`` is the recommended variant. For many
    calls on a growing map keep a :class:`ScoringState` instead (it fuses only new keyframes).
    """
    cfg = mapper.config
    state = ScoringState.for_map(cfg, config)
    _, poses = mapper.map_keyframes()
    running = mapper.h_train if cfg.track_h_train and mapper.h_train_complete else None
    outputs = tuple(cfg.fisher_outputs)  # the map rendered as its mesh is fused: depth, and alpha threshold
    return state.score(mapper.map, running, outputs, poses, candidates, mapper.intr, mapper.rendered_rgbd,
                       mode=mode, top_k=top_k)  # fmt: skip


__all__ = [
    "CLOSE_FRONT_MODES",
    "CarvedSpaceMemory",
    "PreparedScorer",
    "RenderRGBD",
    "ScoringState",
    "TrainFisherCache",
    "carry_rows",
    "match_surfels",
    "pose_keys",
    "running_h_train_fits",
    "score_views",
]
