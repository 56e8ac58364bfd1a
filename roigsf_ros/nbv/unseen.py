"""The unseen term U (beyond the paper; ``NBVConfig.unseen_*``): how much of a candidate view looks into space the
map has not observed, which nothing in Eq. 7-16 pulls towards (the ROI and the Fisher see only mapped surface).

Two sources (``unseen_source``): the map rendered from the candidate ("map": pixels where its alpha stays below
``unseen_alpha``, optionally with the back of mapped surface, ``unseen_backfaces``), or a grid of unknown / free /
occupied cells carved by the map's depth rendered at the keyframes ("carved": pixels whose ray enters unknown space,
:func:`carved_space`, :func:`carved_unseen`). Counted as a fraction of the pixels, in m^2, in frontier cells or in
unknown cells per ray (carved only) (``unseen_measure``), within a box around the mapped surface
(``unseen_bbox_margin_m``), and optionally planned over a few views (``unseen_plan_views``) or weighed by how few
candidates look into the same unseen space (``unseen_rarity``) (:mod:`roigsf_ros.nbv.plan`). :class:`UnseenTerm` is
what the scorer builds once per call and measures per candidate; the scorer z-scores U into the fused score with
``unseen_weight``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from roigsf_ros.core.camera import Intrinsics, depth_points_w
from roigsf_ros.mapping.observed_space import ObservedSpace
from roigsf_ros.mapping.tsdf import SurfaceVoxels
from roigsf_ros.nbv.close_front import voxel_keys
from roigsf_ros.nbv.config import NBVConfig
from roigsf_ros.nbv.plan import UnseenCells, planned_unseen, rarity_weighted
from roigsf_ros.nbv.stop import ShouldStop, check_stop
from roigsf_ros.render.rasterize import render_map
from roigsf_ros.render.surfels import SurfelMap, quat_to_rotmat


def surfels_facing(surfel_map: SurfelMap, T_wc: np.ndarray) -> Tensor:
    """Bool [N]: the surfels whose normal (the third axis of their rotation, which faces the camera that seeded them)
    faces the camera at ``T_wc``; the others show it their back.
    """
    m = surfel_map
    normal = quat_to_rotmat(m.quats.detach())[:, :, 2]
    centre = torch.as_tensor(np.asarray(T_wc, dtype=np.float64)[:3, 3], dtype=m.dtype, device=m.device)
    return ((centre - m.means.detach()) * normal).sum(-1) > 0


@dataclass
class KeyframeDepths:
    """The map's median depth rendered at each keyframe pose, for ``NBVConfig.unseen_backfaces="unconfirmed"``
    (:meth:`confirmed`): which back pixels of a candidate a keyframe already saw from the candidate's side.

    Why: the mapper seeds no surfel where a keyframe's depth lies within ``densify_depth_margin_m`` of the rendered
    surface, so a shell thinner than that (a 1 cm bowl) seen from inside stays mapped by the outside's surfels, whose
    backs the keyframe's depth confirmed; the surfel test alone calls its inside unseen however often it is seen.
    """

    poses: np.ndarray
    """[K, 4, 4] camera-to-world keyframe poses."""
    depth_m: np.ndarray
    """[K, H, W] the map's median depth at each pose (camera z, metres; 0 where nothing renders)."""
    intr: Intrinsics
    """Intrinsics of the renders, and of the candidate images :meth:`confirmed` takes."""
    margin_m: float
    """A point is unoccluded in a keyframe's render when that render's depth there lies within this of the point's."""

    @classmethod
    def render(
        cls,
        surfel_map: SurfelMap,
        poses: Sequence[np.ndarray] | np.ndarray,
        intr: Intrinsics,
        margin_m: float,
        near_m: float,
        far_m: float,
        should_stop: ShouldStop = None,
    ) -> KeyframeDepths:
        """Render ``surfel_map``'s median depth at every pose of ``poses`` ([K, 4, 4]); ``should_stop`` is checked
        before each render.
        """
        pose_arr = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        depth, _alpha = _keyframe_renders(surfel_map, pose_arr, intr, near_m, far_m, should_stop)
        return cls(pose_arr, depth, intr, float(margin_m))

    def confirmed(self, T_wc: np.ndarray, depth_m: np.ndarray, normal_cam: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Bool [H, W]: the ``mask`` pixels of the camera at ``T_wc`` (at :attr:`intr`) whose point, at camera-z
        ``depth_m`` [H, W], some keyframe saw from the same side of the surface and unoccluded: the keyframe's centre
        lies in front of the pixel's ``normal_cam`` [H, W, 3] (the render's normal, camera frame, facing the camera)
        and the keyframe's rendered depth at the point's projection is within :attr:`margin_m` of the point's depth.
        """
        z = np.asarray(depth_m, dtype=np.float64)
        out = np.zeros(z.shape, dtype=bool)
        v, u = np.nonzero(np.asarray(mask, dtype=bool) & (z > 0))
        if len(v) == 0 or len(self.poses) == 0:
            return out
        T = np.asarray(T_wc, dtype=np.float64)
        intr = self.intr
        p = depth_points_w(z, T, intr, np.asarray(mask, dtype=bool) & (z > 0))  # in the order of (v, u)
        n = np.asarray(normal_cam, dtype=np.float64)[v, u] @ T[:3, :3].T
        hit = np.zeros(len(v), dtype=bool)
        for Tk, dk in zip(self.poses, self.depth_m, strict=True):
            same_side = np.einsum("ij,ij->i", n, Tk[:3, 3] - p) > 0.0
            pc = (p - Tk[:3, 3]) @ Tk[:3, :3]  # the points in the keyframe's camera frame
            zc = pc[:, 2]
            ok = same_side & ~hit & (zc > 0)
            uk = np.rint(np.where(ok, pc[:, 0] / np.where(ok, zc, 1.0), 0.0) * intr.fx + intr.cx).astype(np.int64)
            vk = np.rint(np.where(ok, pc[:, 1] / np.where(ok, zc, 1.0), 0.0) * intr.fy + intr.cy).astype(np.int64)
            ok &= (uk >= 0) & (uk < intr.width) & (vk >= 0) & (vk < intr.height)
            j = np.flatnonzero(ok)
            dj = dk[vk[j], uk[j]]
            hit[j[(dj > 0) & (np.abs(dj - zc[j]) <= self.margin_m)]] = True
        out[v, u] = hit
        return out


@dataclass
class SurfaceFacing:
    """The TSDF surface voxels' outward normals, indexed by grid cell (:meth:`build`), for the back-face test of
    ``NBVConfig.unseen_backfaces="tsdf"`` (:meth:`backfacing`).
    """

    origin_m: np.ndarray
    """[3] a voxel centre: positions are keyed relative to it, so a point's key is its nearest centre's (metres)."""
    voxel_size_m: float
    keys: np.ndarray
    """[M] sorted :func:`~roigsf_ros.nbv.close_front.voxel_keys` of the surface voxels (relative to ``origin_m``)."""
    normals: np.ndarray
    """[M, 3] outward normals (toward the free space the fused views saw) in the order of ``keys``."""

    @classmethod
    def build(cls, voxels: SurfaceVoxels, voxel_size_m: float) -> SurfaceFacing:
        """Index ``voxels`` (centres on the TSDF's grid) by their cell."""
        c = np.asarray(voxels.centres_m, dtype=np.float64).reshape(-1, 3)
        origin = c.min(0) if len(c) else np.zeros(3)
        keys = voxel_keys(c - origin, voxel_size_m)
        order = np.argsort(keys, kind="stable")
        normals = np.asarray(voxels.normals, dtype=np.float64).reshape(-1, 3)[order]
        return cls(origin, float(voxel_size_m), keys[order], normals)

    def backfacing(self, T_wc: np.ndarray, intr: Intrinsics, depth_m: np.ndarray) -> np.ndarray:
        """Bool [H, W]: pixels whose point at camera-z ``depth_m`` [H, W] (0: none) lies in the cell of a surface
        voxel whose outward normal faces away from the camera at ``T_wc`` (the back of the mapped surface).
        """
        z = np.asarray(depth_m, dtype=np.float64)
        out = np.zeros(z.shape, dtype=bool)
        v, u = np.nonzero(z > 0)
        if len(self.keys) == 0 or len(v) == 0:
            return out
        T = np.asarray(T_wc, dtype=np.float64)
        p = depth_points_w(z, T, intr, z > 0)
        keys = voxel_keys(p - self.origin_m, self.voxel_size_m)
        j = np.clip(np.searchsorted(self.keys, keys), 0, len(self.keys) - 1)
        found = self.keys[j] == keys
        away = np.einsum("ij,ij->i", self.normals[j], T[:3, 3] - p) < 0.0
        out[v, u] = found & away
        return out


@dataclass
class UnseenTerm:
    """The unseen term U of one scoring call: what it builds once (the box, the carved grid, the back-face tests) and
    how it measures each candidate.
    """

    cfg: NBVConfig
    box: tuple[np.ndarray, np.ndarray] | None
    """The surface voxels' bounds grown by ``unseen_bbox_margin_m`` (None: no voxels, or an infinite margin)."""
    facing: SurfaceFacing | None
    """``unseen_backfaces="tsdf"``: the TSDF's normals, to count the pixels that render the back of the surface."""
    seen_by: KeyframeDepths | None
    """``unseen_backfaces="unconfirmed"``: spares the back pixels a keyframe saw from this side."""
    space: ObservedSpace | None
    """``unseen_source="carved"``: the carved grid, in place of the map's render."""
    plan: dict[int, UnseenCells] | None
    """``unseen_plan_views`` > 1 or ``unseen_rarity`` > 0: receives each candidate's unseen pixels by entry cell,
    weighed and planned over once every candidate is in (:meth:`finish`)."""

    @classmethod
    def build(
        cls,
        cfg: NBVConfig,
        surfel_map: SurfelMap,
        vox: SurfaceVoxels | None,
        voxel_size_m: float,
        poses: Sequence[np.ndarray],
        intr_f: Intrinsics,
        should_stop: ShouldStop = None,
        kept_space: ObservedSpace | None = None,
    ) -> UnseenTerm:
        """What one scoring call builds once, not per candidate: the box, the carved grid of the keyframes ``poses``
        (``unseen_source="carved"``), the back-face tests (``unseen_backfaces``) and the plan (``unseen_plan_views``,
        ``unseen_rarity``); ``vox`` the TSDF's surface voxels (None: none), ``intr_f`` the scoring resolution.
        ``kept_space``: the carved grid of this box kept by the caller (``unseen_carve_rerender`` false,
        :class:`~roigsf_ros.nbv.state.CarvedSpaceMemory`) in place of one carved here from the map's renders.
        """
        empty_map = len(surfel_map) == 0
        use_facing = cfg.unseen_source == "map" and cfg.unseen_backfaces == "tsdf" and vox is not None
        facing = SurfaceFacing.build(vox, voxel_size_m) if use_facing else None
        box = unseen_box(vox, cfg) if vox is not None and np.isfinite(cfg.unseen_bbox_margin_m) else None
        carved = cfg.unseen_source == "carved"
        space = None  # the space the keyframes' rendered depth observed
        if carved and box is not None and not empty_map:
            space = kept_space
            if space is None:
                space = carved_space(surfel_map, poses, intr_f, *box, cfg, should_stop)
        # each candidate's unseen pixels by entry cell, weighed and planned over once all are in
        grouped = cfg.unseen_plan_views > 1 or cfg.unseen_rarity > 0
        plan: dict[int, UnseenCells] | None = {} if space is not None and grouped else None
        seen_by = None  # unseen_backfaces="unconfirmed": the map as each keyframe sees it
        if not carved and cfg.unseen_backfaces == "unconfirmed" and not empty_map and len(poses):
            seen_by = KeyframeDepths.render(
                surfel_map, poses, intr_f, cfg.unseen_confirm_margin_m, cfg.near_m, cfg.far_m, should_stop
            )
        return cls(cfg, box, facing, seen_by, space, plan)

    def measure(self, surfel_map: SurfelMap, T: np.ndarray, i: int, intr_f: Intrinsics) -> float | None:
        """U of candidate ``i`` at ``T`` (``unseen_measure``: a pixel fraction or m^2), or None where it is left as
        it is: planned once every candidate is in (``plan``), or nothing to measure it on (an empty map; no carved
        grid).
        """
        cfg, space, box = self.cfg, self.space, self.box
        if space is not None:
            if cfg.unseen_measure == "cells":  # m^2 of frontier, each cell once
                _, cells = space.unseen_frontier(T, intr_f, cfg.near_m, cfg.far_m)
                return len(cells) * space.voxel_m**2
            if self.plan is not None:  # its pixels by entry cell; U is written by finish once every candidate is in
                meets = rays_meet_box(T, intr_f, *box)
                enter, leave, cell = space.unseen_rays(T, intr_f, cfg.near_m, cfg.far_m)
                weight = (leave - enter) / space.voxel_m if cfg.unseen_measure == "rays" else None
                self.plan[i] = UnseenCells.from_pixels(cell, meets, weight)
                return None
            hole, enter, leave = carved_unseen(space, T, intr_f, box, cfg)
            if cfg.unseen_measure == "area":  # m^2: footprints where the unknown stretch ends (the farthest)
                return float((leave[hole] ** 2).sum() / (intr_f.fx * intr_f.fy))
            meets = rays_meet_box(T, intr_f, *box)
            if cfg.unseen_measure == "rays":  # unknown cells each counted ray crosses, per counted pixel
                return float((leave - enter)[hole & meets].sum() / space.voxel_m / max(int(meets.sum()), 1))
            return float((hole & meets).sum() / max(int(meets.sum()), 1))
        if cfg.unseen_source != "map" or len(surfel_map) == 0:
            return None
        m = surfel_map.detach()
        # With the surfel back-face test the render composites which surfels face this camera; else nothing but
        # alpha and depth (no feature channel). Culled to the frustum: the same images, the view's surfels projected.
        by_side = cfg.unseen_backfaces in ("surfels", "unconfirmed")
        feats = surfels_facing(m, T)[:, None].to(m.dtype) if by_side else m.means.new_zeros((len(m), 0))
        with torch.no_grad():
            out = render_map(m, T, intr_f, features=feats, near=cfg.near_m, far=cfg.far_m, with_distortion=False,
                             cull=True)  # fmt: skip
        seen = (out.alpha >= cfg.unseen_alpha).cpu().numpy()
        hole = ~seen
        if self.facing is not None:  # the back of the mapped surface: what is in front of it is unseen
            hole |= self.facing.backfacing(T, intr_f, np.where(seen, out.median_depth.cpu().numpy(), 0.0))
        if by_side:  # most of the pixel's alpha from surfels that face away: their back
            back = seen & (out.features[..., 0] < 0.5 * out.alpha).cpu().numpy()
            if self.seen_by is not None and back.any():
                back &= ~self.seen_by.confirmed(T, out.median_depth.cpu().numpy(), out.normal.cpu().numpy(), back)
            hole |= back
        exit_m = None  # where each ray leaves the box of the mapped region (0: it never meets it)
        if box is not None:
            exit_m = box_exit_depth(T, intr_f, *box)
        if cfg.unseen_measure == "area":  # m^2 the unseen pixels can show: footprints at the farthest depth
            far = np.full(hole.shape, cfg.far_m) if exit_m is None else np.minimum(exit_m, cfg.far_m)
            z = np.where(seen, out.median_depth.cpu().numpy(), far)  # seen holes: the back face's depth
            return float((np.where(hole, z, 0.0) ** 2).sum() / (intr_f.fx * intr_f.fy))
        if exit_m is not None:
            meets = exit_m > 0
            return float((hole & meets).sum() / max(int(meets.sum()), 1))
        return float(hole.mean())

    def finish(self, unseen: np.ndarray, should_stop: ShouldStop = None) -> None:
        """With a plan (``unseen_plan_views`` > 1 or ``unseen_rarity`` > 0), write into ``unseen`` [M] the U of the
        candidates :meth:`measure` left as they were: their cells weighed by rarity among them, then planned over;
        else nothing to do.
        """
        if self.plan and self.space is not None:
            order = sorted(self.plan)
            views = rarity_weighted([self.plan[i] for i in order], self.cfg.unseen_rarity,
                                    rarity_blocks(self.space, self.cfg.unseen_rarity_block_m))  # fmt: skip
            unseen[order] = planned_unseen(views, self.cfg.unseen_plan_views, lambda: check_stop(should_stop))


def rarity_blocks(space: ObservedSpace, block_m: float) -> Callable[[np.ndarray], np.ndarray]:
    """Maps [C] flat cell indices of ``space``'s grid to [C] ids of cubic blocks of ``block_m`` (rounded to whole
    cells, at least one) (``unseen_rarity_block_m``): rays into the same unseen pocket from two viewpoints enter it
    at different cells, so the rarity counts the candidates looking into each block.
    """
    b = max(round(block_m / space.voxel_m), 1)
    dims = np.asarray(space.state.shape, dtype=np.int64)
    blocks = tuple(int(d) for d in -(-dims // b))

    def block_of(cells: np.ndarray) -> np.ndarray:
        ijk = np.unravel_index(np.asarray(cells, dtype=np.int64), space.state.shape)
        return np.ravel_multi_index(tuple(a // b for a in ijk), blocks).astype(np.int64)

    return block_of


def unseen_box(vox: SurfaceVoxels, cfg: NBVConfig) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of the unseen term's box: the surface voxels' bounding box grown by ``unseen_bbox_margin_m``."""
    return vox.centres_m.min(0) - cfg.unseen_bbox_margin_m, vox.centres_m.max(0) + cfg.unseen_bbox_margin_m


def carved_space(
    surfel_map: SurfelMap,
    poses: Sequence[np.ndarray] | np.ndarray,
    intr: Intrinsics,
    lo_m: np.ndarray,
    hi_m: np.ndarray,
    cfg: NBVConfig,
    should_stop: ShouldStop = None,
) -> ObservedSpace:
    """The box [lo_m, hi_m] carved by the map's median depth rendered at every keyframe pose of ``poses``
    ([K, 4, 4]) where the map's alpha reaches ``unseen_alpha``, and free up to ``far_m`` where it does not (the map,
    trained on that keyframe, holds nothing along the ray) (``unseen_source="carved"``); cells of ``unseen_voxel_m``.
    The planner knows the map, not the frames it was trained on, so it carves what the map shows at the keyframes,
    as its TSDF fuses it.
    """
    pose_arr = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    depth = carve_depths(surfel_map, pose_arr, intr, cfg, should_stop)
    return ObservedSpace.carve(lo_m, hi_m, cfg.unseen_voxel_m, pose_arr, depth, intr, cfg.far_m)


def carve_depths(
    surfel_map: SurfelMap, poses: np.ndarray, intr: Intrinsics, cfg: NBVConfig, should_stop: ShouldStop = None
) -> np.ndarray:
    """[K, H, W] what the carved grid takes from the map at each pose of ``poses`` [K, 4, 4]: its median depth
    (camera z, metres) where its alpha reaches ``unseen_alpha``, inf (free up to ``far_m``) where it does not.
    """
    depth, alpha = _keyframe_renders(surfel_map, poses, intr, cfg.near_m, cfg.far_m, should_stop)
    return np.where(alpha >= cfg.unseen_alpha, depth, np.inf)


def carved_unseen(
    space: ObservedSpace, T_wc: np.ndarray, intr: Intrinsics, box: tuple[np.ndarray, np.ndarray], cfg: NBVConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """([H, W] bool, [H, W], [H, W]) the pixels the carved grid calls unseen from ``T_wc``, and where each pixel's last
    unknown stretch begins and ends (camera z, m; 0, 0: none, as ``ObservedSpace.unseen_depths``). With
    ``cfg.unseen_min_stretch_m`` > 0 a stretch counts only when at least that long or when it begins where the ray
    enters ``box`` (it goes on outside the box, so its length is unknown): observed surface seen from a new angle
    often lies behind a cell or a few of uncarved space, new surface behind long stretches.
    """
    enter, leave = space.unseen_depths(T_wc, intr, cfg.near_m, cfg.far_m)
    hole = enter > 0
    if cfg.unseen_min_stretch_m > 0:
        from_side = enter <= box_depths(T_wc, intr, *box)[0] + space.voxel_m
        hole &= (leave - enter >= cfg.unseen_min_stretch_m) | from_side
    return hole, enter, leave


def _keyframe_renders(
    surfel_map: SurfelMap,
    poses: np.ndarray,
    intr: Intrinsics,
    near_m: float,
    far_m: float,
    should_stop: ShouldStop = None,
) -> tuple[np.ndarray, np.ndarray]:
    """([K, H, W], [K, H, W]) the map's median depth (camera z, metres; 0 where nothing renders) and alpha rendered
    at each pose of ``poses`` [K, 4, 4]; zeros for an empty map. ``should_stop`` is checked before each render.
    """
    depth = np.zeros((len(poses), intr.height, intr.width))
    alpha = np.zeros_like(depth)
    if len(surfel_map):
        m = surfel_map.detach()
        none = m.means.new_zeros((len(m), 0))  # depth and alpha only: no feature channel
        with torch.no_grad():
            for k, T in enumerate(poses):
                check_stop(should_stop)
                out = render_map(m, T, intr, features=none, near=near_m, far=far_m, with_distortion=False, cull=True)
                depth[k] = out.median_depth.cpu().numpy()
                alpha[k] = out.alpha.cpu().numpy()
    return depth, alpha


def rays_meet_box(T_wc: np.ndarray, intr: Intrinsics, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Bool [H, W]: pixels whose viewing ray (from the camera centre, forward) meets the box [lo, hi] (slab test)."""
    return box_exit_depth(T_wc, intr, lo, hi) > 0


def box_exit_depth(T_wc: np.ndarray, intr: Intrinsics, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """[H, W] depth (m, along the camera's z) at which each pixel's forward ray leaves the box [lo, hi] (slab test);
    0 where the ray never meets it. Inside a room's box, where the ray meets its walls.
    """
    return box_depths(T_wc, intr, lo, hi)[1]


def box_depths(T_wc: np.ndarray, intr: Intrinsics, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """([H, W], [H, W]) depths (m, along the camera's z) at which each pixel's forward ray enters and leaves the box
    [lo, hi] (slab test; entry 0 for a camera inside it); both 0 where the ray never meets it.
    """
    u, v = np.meshgrid(np.arange(intr.width, dtype=np.float64), np.arange(intr.height, dtype=np.float64))
    d_cam = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], -1)  # z = 1: t is depth
    d = d_cam @ np.asarray(T_wc)[:3, :3].T
    o = np.asarray(T_wc)[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (np.asarray(lo) - o) / d, (np.asarray(hi) - o) / d
    t1, t2 = np.nan_to_num(t1, nan=-np.inf), np.nan_to_num(t2, nan=np.inf)
    t_near = np.maximum(np.minimum(t1, t2).max(-1), 0.0)
    t_far = np.maximum(t1, t2).min(-1)
    meets = t_far >= t_near
    return np.where(meets, t_near, 0.0), np.where(meets, np.maximum(t_far, 0.0), 0.0)


__all__ = [
    "KeyframeDepths",
    "SurfaceFacing",
    "UnseenTerm",
    "box_depths",
    "box_exit_depth",
    "carve_depths",
    "carved_space",
    "carved_unseen",
    "rarity_blocks",
    "rays_meet_box",
    "surfels_facing",
    "unseen_box",
]
