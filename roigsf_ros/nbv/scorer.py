"""Next-best-view scoring: ROI-GSurFisher (Eq. 9-10, 15-16), its ablations, FisherRF, pixel uncertainty (Eq. 17-18).

Score modes (``NBVConfig.mode``):

- ``"roi-gsurfisher"``: ``eps z(F) + delta z(I_vis)`` (Eq. 15), F the ROI-weighted geometric Fisher gain
  (Eq. 9-10), I_vis the close-front gain (Eq. 14, :mod:`roigsf_ros.nbv.close_front`); z the z-score over the
  candidate set;
- ``"roi-fisher"``: F alone; ``"close-front"``: I_vis alone (the paper's ablations);
- ``"fisherrf"``: the FisherRF baseline, ``sum F_cand / (H_train + lambda)`` over every parameter, the
  whole colour image, no ROI, no close-front.

Eq. 10 as implemented: ``F(x) = sum_k F_diag_k(x) / (H_train_k + phi)``. Read literally,
``<F_diag, (H^-1 + phi)^-1>`` grows with H_train and would favour parameters that are already well
constrained, the opposite of what the paper says the normalisation is for; the sum of ratios is Eq. 5
(``tr(H_cand H_train^-1)`` with a diagonal H) and what every FisherRF implementation scores.

Eq. 15 as implemented: the z-scores are taken over the candidates that have scores; a flagged candidate
(sees no surface voxel, or gets no Fisher) gets 0 and ranks last, so it cannot shift the others' balance.

Audit (README, "Audit of Eq. 7-18"): the ROI and the Fisher see only surface that is already mapped
(the TSDF of rendered depth; no surfels elsewhere), so nothing in Eq. 7-16 pulls towards unseen space;
``NBVConfig.unseen_weight`` adds that as an option (the unseen term, :mod:`roigsf_ros.nbv.unseen`).
H_train (the mapper's) weights pixels by valid input depth with a 0.1 m near plane, the candidate Fisher
by the ROI with ``near_m``: equal on clean depth, a known mismatch with depth holes.

Eq. 17 as implemented: ``tr(G_i)`` is read as the trace of the surfel's *inverse* training information
(its parameter variance), ``sum_k 1 / (H_train_k + phi)`` over the surfel's geometric entries, so that the
rendered uncertainty is high where the training views constrain the geometry little.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import Tensor

from roigsf_ros.core.camera import Intrinsics, check_pose, pose_from_position_quat
from roigsf_ros.core.errors import InputError
from roigsf_ros.evaluation.metrics import ause
from roigsf_ros.mapping.observed_space import ObservedSpace
from roigsf_ros.mapping.tsdf import SurfaceVoxels, TSDFVolume
from roigsf_ros.nbv.close_front import CloseFrontMemory
from roigsf_ros.nbv.config import MODES, ROI_MODES, NBVConfig
from roigsf_ros.nbv.roi import ViewROI, batch_roi, frustum_union, view_roi, voxel_texture
from roigsf_ros.nbv.stop import ShouldStop, check_stop
from roigsf_ros.nbv.unseen import UnseenTerm
from roigsf_ros.render.fisher import fisher_diag, fisher_weighted_sum
from roigsf_ros.render.rasterize import camera_tensors, render_map
from roigsf_ros.render.surfels import SurfelMap

_ROI_CHUNK = 16
"""Candidates whose ROI one parallel pass computes (a stop request waits at most one chunk's pass)."""


# ------------------------------------------------------------------------------------ fusion
def zscore(x: np.ndarray, min_std: float = 0.0) -> np.ndarray:
    """Z-scores of a score vector [M]; a (numerically) constant vector gives zeros, never NaN. ``min_std`` floors the
    divisor: a spread below it counts as less than one standard unit (``NBVConfig.unseen_min_std``).
    """
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    if a.size == 0:
        return a.copy()
    if not np.all(np.isfinite(a)):
        raise InputError("scores", "non-finite score in z-score normalisation")
    spread = float(a.max() - a.min())
    if spread <= 1e-12 * max(float(np.abs(a).max()), 1e-300):
        return np.zeros_like(a)
    centred = a - a.mean()
    return centred / max(float(np.sqrt(np.mean(centred**2))), float(min_std))


def fuse_scores(
    fisher: np.ndarray,
    close_front: np.ndarray,
    epsilon: float = 0.4,
    delta: float = 0.6,
    close_front_min_std: float = 0.0,
) -> np.ndarray:
    """Eq. 15: ``epsilon z(F) + delta z(I_vis)`` [M]; ``close_front_min_std`` floors z(I_vis)'s divisor
    (``NBVConfig.close_front_min_std``).
    """
    return epsilon * zscore(fisher) + delta * zscore(close_front, close_front_min_std)


def rank_candidates(scores: np.ndarray, flagged: np.ndarray | None = None) -> np.ndarray:
    """Candidate indices [M], best first: descending score, flagged ones last, ties by ascending index."""
    s = np.asarray(scores, dtype=np.float64)
    f = np.zeros(s.shape, bool) if flagged is None else np.asarray(flagged, bool)
    return np.lexsort((np.arange(s.size), -s, f)).astype(np.int64)


# ------------------------------------------------------------------------------ Fisher scores
def information_gain(f_cand: dict[str, Tensor], h_train: dict[str, Tensor], prior: float) -> float:
    """Eq. 10 / Eq. 5 (FisherRF reading): ``sum_k F_cand_k / (H_train_k + prior)`` over ``f_cand``'s entries."""
    return gain_with(f_cand, inverse_denominators(h_train, {k: tuple(f.shape) for k, f in f_cand.items()}, prior))


def inverse_denominators(
    h_train: dict[str, Tensor], shapes: dict[str, tuple[int, ...]], prior: float
) -> dict[str, np.ndarray]:
    """``1 / (H_train_k + prior)`` (float64, flat) for each parameter of ``shapes``: Eq. 10's per-entry weights.

    Computed once per ``score()`` call, not once per candidate, and as numpy arrays: each candidate's sum
    (:func:`~roigsf_ros.render.fisher.fisher_weighted_sum`) then reads them at the surfels that reach its view.
    """
    _check_entries(h_train, shapes)
    return {k: 1.0 / (h_train[k].detach().to("cpu", torch.float64).numpy().reshape(-1) + prior) for k in shapes}


def gain_with(f_cand: dict[str, Tensor], inv: dict[str, np.ndarray]) -> float:
    """``sum_k F_cand_k * inv_k`` over ``f_cand``'s entries (``inv`` from :func:`inverse_denominators`)."""
    total = 0.0
    for name, f in f_cand.items():
        # Not np.dot: BLAS's own threads stalled next to the numba pool in a profiled score().
        total += float((f.detach().cpu().numpy().reshape(-1).astype(np.float64) * inv[name]).sum())
    return total


def train_fisher(
    surfel_map: SurfelMap,
    train_poses: Sequence[np.ndarray] | np.ndarray,
    intr: Intrinsics,
    outputs: Sequence[str],
    params: Sequence[str],
    pixel_weight: float = 1.0,
    near_m: float = 0.2,
    far_m: float = 100.0,
    should_stop: ShouldStop = None,
) -> dict[str, Tensor]:
    """H_train: the diagonal Fisher of ``outputs`` w.r.t. ``params`` summed over whole training views.

    ``pixel_weight`` multiplies every pixel (1 / sigma_p^2 keeps it in the units of Eq. 9). One exact
    Fisher pass per pose; the Mapper keeps the same sum incrementally (``Mapper.h_train``).
    ``should_stop`` is checked before each pose (:class:`ScoringStoppedError`).
    """
    poses = _as_pose_list(train_poses, "train_poses", allow_empty=True)
    names = [p for p in params if p != "sh_rest" or surfel_map.sh_rest is not None]
    out = {k: torch.zeros_like(getattr(surfel_map, k)).detach() for k in names}
    if len(surfel_map) == 0:
        return out
    w = torch.full((intr.height, intr.width), float(pixel_weight), dtype=surfel_map.dtype)
    for T in poses:
        check_stop(should_stop)
        f = fisher_diag(surfel_map, T, intr, outputs=outputs, params=names, pixel_weights=w, near=near_m, far=far_m)
        for k in out:
            out[k] += f[k]
    return out


# ------------------------------------------------------------------------------ pixel uncertainty
def surfel_variance(h_train: dict[str, Tensor], params: Sequence[str], prior: float) -> Tensor:
    """Per-surfel ``tr(G_i)`` of Eq. 17 as read here: ``sum_k 1 / (H_train_k + prior)`` [N] over ``params``."""
    parts = []
    for name in params:
        if name not in h_train:
            if name == "sh_rest":
                continue
            raise InputError("h_train", f"has no entry '{name}' (it covers {', '.join(h_train) or 'nothing'})")
        h = h_train[name].detach().double()
        parts.append((1.0 / (h + prior)).reshape(h.shape[0], -1).sum(-1))
    if not parts:
        raise InputError("params", "no parameters to take the uncertainty of")
    return torch.stack(parts).sum(0)


def render_surfel_scalar(
    surfel_map: SurfelMap, values: Tensor, T_wc: np.ndarray, intr: Intrinsics, near_m: float, far_m: float
) -> np.ndarray:
    """``sum_i T_i alpha_i values_i`` [H, W] (float64): a per-surfel scalar [N] alpha-composited from ``T_wc``."""
    if len(surfel_map) == 0:
        return np.zeros((intr.height, intr.width))
    m = surfel_map.detach()
    with torch.no_grad():
        feats = values.to(m.dtype)[:, None]
        out = render_map(m, T_wc, intr, features=feats, near=near_m, far=far_m, with_distortion=False, cull=True)
    return out.features[..., 0].double().cpu().numpy()


def depth_error_ause(
    uncertainty: np.ndarray | Tensor,
    depth_pred_m: np.ndarray | Tensor,
    depth_gt_m: np.ndarray | Tensor,
    n_ratios: int = 100,
    random_seed: int = 0,
) -> dict:
    """AUSE (:func:`roigsf_ros.evaluation.metrics.ause`) of an uncertainty map [H, W] against |depth_pred - depth_gt|.

    Only pixels where both depths are finite and > 0 count; no such pixel raises InputError. Keys:
    ``ause`` (normalised by the joint curve maximum, as FisherRF / Bayes' Rays report it), ``ause_raw``
    (metres), ``ause_random_raw`` (metres, a uniform-random pixel ordering seeded by ``random_seed``),
    ``spearman_rho`` (uncertainty vs |depth error|), ``n`` (pixels), and the curves. Report the raw
    numbers too: the normalisation rewards maps that rank pixels backwards (their curve peaks far above
    the mean error and the division shrinks their area), so a map with a low ``ause`` but ``ause_raw``
    above ``ause_random_raw`` and ``spearman_rho`` < 0 is worse than no information.
    """
    u, dp, dg = (np.asarray(t.detach().cpu() if isinstance(t, Tensor) else t, dtype=np.float64) for t in
                 (uncertainty, depth_pred_m, depth_gt_m))  # fmt: skip
    if not (u.shape == dp.shape == dg.shape):
        raise InputError("uncertainty", f"shapes differ: {u.shape}, {dp.shape}, {dg.shape}")
    ok = np.isfinite(dp) & np.isfinite(dg) & (dp > 0) & (dg > 0) & np.isfinite(u)
    if not ok.any():
        raise InputError("depth", "no pixel with a valid predicted and ground-truth depth")
    return ause(u[ok], np.abs(dp[ok] - dg[ok]), n_ratios=n_ratios, random_seed=random_seed)


@dataclass
class UncertaintyMaps:
    """Pixel uncertainty of one view: ``u`` [H, W] (Eq. 17), ``u_roi`` [H, W] (Eq. 18), ``roi`` [H, W] W_roi."""

    u: np.ndarray
    u_roi: np.ndarray
    roi: np.ndarray


# ---------------------------------------------------------------------------------------- scorer
@dataclass
class NBVResult:
    """Scores of M candidates; ``fused`` is what the mode ranks by (its z-score combination).

    ``fisher`` [M]: F of Eq. 10 (ROI modes) or the FisherRF score (``fisherrf``), 0 where not computed;
    ``close_front`` [M]: I_vis of Eq. 14, 0 where not computed; ``best_index``: the argmax (Eq. 16);
    ``ranking`` [M]: best first, flagged candidates last, ties by index; ``flagged`` [M]: candidates with nothing
    to score: they see no surface (behind or outside the map; their raw scores are 0) and, with the unseen term
    (``unseen_weight`` > 0), no unseen space either (on an empty map every candidate sees only unseen space, so
    none is flagged); ``reason``: why scores are
    degenerate ("" when they are not); diagnostics per candidate: ``n_roi_pixels``, ``roi_mass``,
    ``n_visible_voxels``; ``timings_s``: wall seconds per phase (``setup``, ``h_train``, ``roi`` (with close-front:
    one pass over all candidates), ``close_front`` (0, kept for callers), ``fisher``, ``unseen`` (the unseen term:
    its once-per-call build, e.g. the carved grid, and each candidate's measure); ``roi_close_front`` their ROI sum)
    and process CPU seconds (``<phase>_cpu``). ``n_skipped``: candidates whose frustum cannot meet the mapped region,
    flagged before any work.
    """

    mode: str
    fused: np.ndarray
    fisher: np.ndarray
    close_front: np.ndarray
    best_index: int
    ranking: np.ndarray
    top_k: np.ndarray
    flagged: np.ndarray
    n_roi_pixels: np.ndarray
    roi_mass: np.ndarray
    n_visible_voxels: np.ndarray
    reason: str = ""
    timings_s: dict[str, float] = field(default_factory=dict)
    unseen: np.ndarray | None = None
    """[M] U(x), the unseen pixels' fraction, their surface or frontier cells in m^2, or the unknown cells their rays
    cross per pixel (``unseen_measure``), when ``NBVConfig.unseen_weight`` > 0 in the ROI modes; else None."""
    n_skipped: int = 0


def downsampled(intr: Intrinsics, factor: int) -> Intrinsics:
    """Intrinsics of the image block-averaged by ``factor`` (the top-left ``W // f`` x ``H // f`` blocks)."""
    f = int(factor)
    if f == 1:
        return intr
    if intr.width < f or intr.height < f:
        raise InputError("fisher_downsample", f"{f} is larger than the {intr.width}x{intr.height} image")
    return replace(
        intr,
        width=intr.width // f,
        height=intr.height // f,
        fx=intr.fx / f,
        fy=intr.fy / f,
        cx=(intr.cx + 0.5) / f - 0.5,
        cy=(intr.cy + 0.5) / f - 0.5,
    )


def block_mean(img: np.ndarray, factor: int) -> np.ndarray:
    """Mean over ``factor`` x ``factor`` blocks of an [H, W] image (the remainder rows/columns dropped)."""
    f = int(factor)
    if f == 1:
        return img
    h, w = img.shape[0] // f, img.shape[1] // f
    return img[: h * f, : w * f].reshape(h, f, w, f).mean(axis=(1, 3))


def _as_pose_list(poses: object, where: str, allow_empty: bool = False) -> list[np.ndarray]:
    """Camera-to-world poses from [M, 4, 4], a list of 4x4, or [M, 7] (x, y, z, qx, qy, qz, qw) rows."""
    if poses is None:
        arr = np.zeros((0, 4, 4))
    else:
        try:
            arr = np.asarray(poses, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(where, f"cannot read poses: {exc}") from None
    if arr.size == 0:
        if allow_empty:
            return []
        raise InputError(where, "no candidate poses given")
    if arr.ndim == 2 and arr.shape == (4, 4):
        arr = arr[None]
    if arr.ndim == 2 and arr.shape[1] == 7:
        return [pose_from_position_quat(r[:3], r[3:], f"{where}[{i}]") for i, r in enumerate(arr)]
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise InputError(where, f"expected [M, 4, 4] matrices or [M, 7] position+quaternion rows, got {arr.shape}")
    return [check_pose(T, f"{where}[{i}]") for i, T in enumerate(arr)]


class NBVScorer:
    """Scores candidate views of a surfel map + TSDF for next-best-view selection (all modes)."""

    def __init__(self, config: NBVConfig | None = None) -> None:
        self.config = NBVConfig.given(config)

    # -------------------------------------------------------------------------------- parts
    def surface(self, tsdf: TSDFVolume | None) -> SurfaceVoxels | None:
        """The TSDF's near-surface voxels under this config (None without a TSDF)."""
        if tsdf is None:
            return None
        thr = self.config.roi_max_abs_tsdf_voxels * tsdf.voxel_size_m / tsdf.sdf_trunc_m
        return tsdf.surface_voxels(max_abs_tsdf=thr, min_weight=self.config.roi_min_weight)

    def roi(self, tsdf: TSDFVolume, T_wc: np.ndarray, intr: Intrinsics, surfel_map: SurfelMap | None = None) -> ViewROI:
        """The ROI of one view (Eq. 7-8); texture comes from ``surfel_map`` (None: all texture-poor)."""
        vox = self.surface(tsdf)
        tex = voxel_texture(vox.centres_m, surfel_map, tsdf.voxel_size_m, self.config)
        return view_roi(vox, tsdf.voxel_size_m, check_pose(T_wc, "T_wc"), intr, self.config, tex)

    def train_fisher(
        self,
        surfel_map: SurfelMap,
        train_poses: Sequence[np.ndarray] | np.ndarray,
        intr: Intrinsics,
        mode: str | None = None,
        should_stop: ShouldStop = None,
    ) -> dict[str, Tensor]:
        """H_train matching ``mode``'s candidate Fisher (outputs, parameters and the 1/sigma_p^2 weight)."""
        cfg = self.config
        mode = mode or cfg.mode
        if mode == "fisherrf":
            return train_fisher(surfel_map, train_poses, intr, cfg.fisherrf_outputs, cfg.fisherrf_params, 1.0,
                                cfg.near_m, cfg.far_m, should_stop)  # fmt: skip
        return train_fisher(surfel_map, train_poses, intr, cfg.fisher_outputs, cfg.fisher_params,
                            1.0 / cfg.sigma_p**2, cfg.near_m, cfg.far_m, should_stop)  # fmt: skip

    def uncertainty(
        self,
        surfel_map: SurfelMap,
        h_train: dict[str, Tensor],
        T_wc: np.ndarray,
        intr: Intrinsics,
        tsdf: TSDFVolume | None = None,
    ) -> UncertaintyMaps:
        """Eq. 17-18 at any pose: U [H, W] from the per-surfel geometric variance, and U_roi = W_roi / sigma_p^2 U.

        Without a TSDF the ROI is empty (U_roi = 0). Pixels the map does not cover have U = 0 (Eq. 17
        composites surfels only).
        """
        cfg = self.config
        T = check_pose(T_wc, "T_wc")
        if len(surfel_map):
            _check_h_train(h_train, surfel_map, [p for p in cfg.fisher_params if p != "sh_rest"])
            var = surfel_variance(h_train, cfg.fisher_params, cfg.phi)
            u = render_surfel_scalar(surfel_map, var, T, intr, cfg.near_m, cfg.far_m)
        else:
            u = np.zeros((intr.height, intr.width))
        roi = np.zeros_like(u)
        if tsdf is not None:
            roi = self.roi(tsdf, T, intr, surfel_map).weights
        return UncertaintyMaps(u=u, u_roi=roi / cfg.sigma_p**2 * u, roi=roi)

    def fisherrf_uncertainty(
        self,
        surfel_map: SurfelMap,
        T_wc: np.ndarray,
        intr: Intrinsics,
        views: Sequence[np.ndarray] | np.ndarray,
    ) -> np.ndarray:
        """FisherRF's uncertainty map [H, W] (its render_uncertainty.py), for comparison with Eq. 17.

        Per Gaussian: the colour-parameter (sh_dc, sh_rest) Fisher of the colour image summed over
        ``views`` (FisherRF sums the training and the evaluated views), times the Gaussian's depth in the
        view (clamped >= 0); alpha-composited. Note FisherRF composites information, not its inverse.
        """
        cfg = self.config
        T = check_pose(T_wc, "T_wc")
        if len(surfel_map) == 0:
            return np.zeros((intr.height, intr.width))
        params = [p for p in ("sh_dc", "sh_rest") if p != "sh_rest" or surfel_map.sh_rest is not None]
        h = train_fisher(surfel_map, views, intr, ("color",), params, 1.0, cfg.near_m, cfg.far_m)
        per = sum(t.reshape(t.shape[0], -1).sum(-1) for t in h.values())
        viewmat, _ = camera_tensors(T, intr, dtype=torch.float64)
        z = surfel_map.means.detach().double() @ viewmat[2, :3] + viewmat[2, 3]
        return render_surfel_scalar(surfel_map, per.double() * z.clamp_min(0), T, intr, cfg.near_m, cfg.far_m)

    # -------------------------------------------------------------------------------- scoring
    def score(
        self,
        surfel_map: SurfelMap | None,
        h_train: dict[str, Tensor] | None,
        tsdf: TSDFVolume | None,
        train_poses: Sequence[np.ndarray] | np.ndarray | None,
        candidates: Sequence[np.ndarray] | np.ndarray,
        intr: Intrinsics,
        mode: str | None = None,
        close_front_memory: CloseFrontMemory | None = None,
        should_stop: ShouldStop = None,
        kept_space: ObservedSpace | None = None,
    ) -> NBVResult:
        """Score candidate poses ([M, 4, 4], a list of 4x4, or [M, 7] position + xyzw quaternion rows).

        ``h_train``: the training Fisher matching the mode (see :meth:`train_fisher`; the Mapper's
        ``h_train`` fits the ROI modes); None computes it here from ``train_poses`` (one Fisher pass per
        pose). ``close_front_memory``: W_f kept incrementally; None computes it exactly from
        ``train_poses``. ``kept_space``: the unseen term's carved grid kept by the caller
        (:class:`~roigsf_ros.nbv.state.CarvedSpaceMemory`, for the box of this TSDF's surface); None carves it here
        from the map rendered at every ``train_poses`` (``unseen_source="carved"``). An empty map or a TSDF without
        surface gives zero scores and a ``reason``.
        ``should_stop`` is checked before each candidate (and training view): a node shutting down stops
        a long call within one candidate's work, raising :class:`ScoringStoppedError`.
        """
        cfg = self.config
        mode = mode or cfg.mode
        if mode not in MODES:
            raise InputError("mode", f"unknown score mode '{mode}' (choose from {', '.join(MODES)})")
        if not isinstance(intr, Intrinsics):
            raise InputError("intr", f"expected Intrinsics, got {type(intr).__name__}")
        cands = _as_pose_list(candidates, "candidates")
        poses = _as_pose_list(train_poses, "train_poses", allow_empty=True)
        m = len(cands)
        timings: dict[str, float] = {}
        cpu: dict[str, float] = {}
        reasons: list[str] = []
        t0 = _clock()
        surfel_map = surfel_map if surfel_map is not None else SurfelMap.empty()
        need_fisher = cfg.uses_fisher(mode)  # epsilon 0 (an ablation) skips H_train and every Fisher render
        need_voxels = mode != "fisherrf"
        empty_map = len(surfel_map) == 0
        if need_fisher and empty_map:
            reasons.append("the surfel map is empty: Fisher scores are 0")
        if len(poses) == 0 and not empty_map and (need_voxels or (need_fisher and h_train is None)):
            reasons.append(  # a map from Mapper.load holds its keyframe poses apart: keyframe_poses is empty
                "no training poses: nothing to fuse the TSDF from or to sum H_train over (a loaded map's keyframe "
                "poses are Mapper.map_keyframes()[1], not keyframe_poses)"
            )

        vox, voxel_size = None, 1.0
        if need_voxels:
            vox = self.surface(tsdf)
            if vox is None or len(vox.centres_m) == 0:
                reasons.append(
                    "no TSDF (none given, or no keyframe fused into it): ROI and close-front are 0"
                    if tsdf is None
                    else "the TSDF has no surface voxels: ROI and close-front are 0"
                )
                vox = None
            else:
                voxel_size = tsdf.voxel_size_m
        frontier = None
        if vox is not None and cfg.frontier_weight > 0 and mode in ROI_MODES:
            frontier = tsdf.frontier_mask(vox)
        w_f = None
        if vox is not None and mode in ("roi-gsurfisher", "close-front"):
            mem = close_front_memory or CloseFrontMemory.from_poses(vox, poses, intr, voxel_size, cfg)
            w_f = mem.fused_weight(vox)
        timings["setup"], cpu["setup"] = map(float, _since(t0))

        t0 = _clock()
        h = None
        inv: dict[str, np.ndarray] = {}
        params: list[str] = []
        if need_fisher and not empty_map:
            if mode == "fisherrf":
                params = [p for p in cfg.fisherrf_params if p != "sh_rest" or surfel_map.sh_rest is not None]
            else:
                params = [p for p in cfg.fisher_params if p != "sh_rest" or surfel_map.sh_rest is not None]
            h = h_train if h_train is not None else self.train_fisher(surfel_map, poses, intr, mode, should_stop)
            _check_h_train(h, surfel_map, params)
            prior = cfg.fisherrf_lambda if mode == "fisherrf" else cfg.phi
            inv = inverse_denominators(h, {k: tuple(getattr(surfel_map, k).shape) for k in params}, prior)
        timings["h_train"], cpu["h_train"] = map(float, _since(t0))

        ds = cfg.fisher_downsample
        intr_f = downsampled(intr, ds)
        fisher = np.zeros(m)
        cf = np.zeros(m)
        n_pix = np.zeros(m, dtype=np.int64)
        mass = np.zeros(m)
        n_vox = np.zeros(m, dtype=np.int64)
        flagged = np.zeros(m, dtype=bool)
        use_unseen = cfg.unseen_weight > 0 and mode in ROI_MODES
        unseen = np.ones(m) if use_unseen else None
        # What the unseen term needs (its box, carved grid, back-face tests), built once per call, not per candidate.
        unseen_term, unseen_build = None, np.zeros(2)
        if use_unseen:
            t0 = _clock()
            unseen_term = UnseenTerm.build(cfg, surfel_map, vox, voxel_size, poses, intr_f, should_stop, kept_space)
            unseen_build = _since(t0)
        # Candidates whose frustum cannot meet the mapped region (surface voxels, surfels, the unseen term's box)
        # score nothing: they are flagged without any rendering.
        box = _mapped_region(vox, voxel_size, None if empty_map or not need_fisher else surfel_map, cfg, use_unseen)
        sees = np.array([box is None or frustum_meets_box(T, intr, box[0], box[1], cfg.near_m, cfg.far_m)
                         for T in cands], dtype=bool)  # fmt: skip
        live = np.flatnonzero(sees)
        # Texture only where a candidate may look (the chunk's in-frustum voxels), classified once per voxel.
        use_texture = vox is not None and mode in ROI_MODES
        textured = np.zeros(len(vox.centres_m), dtype=bool) if use_texture else None
        classified = np.zeros(len(vox.centres_m), dtype=bool) if use_texture else None
        acc = {k: np.zeros(2) for k in ("roi", "close_front", "fisher", "unseen", "texture")}
        acc["unseen"] += unseen_build
        for lo in range(0, len(live), _ROI_CHUNK):  # chunks: a stop is seen soon, ROI images stay few
            chunk = live[lo : lo + _ROI_CHUNK]
            chunk_poses = np.stack([cands[i] for i in chunk])
            check_stop(should_stop)
            t0 = _clock()
            if use_texture:
                need = frustum_union(vox, chunk_poses, intr, cfg) & ~classified
                if need.any():
                    textured |= voxel_texture(vox.centres_m, None if empty_map else surfel_map, voxel_size, cfg,
                                              only=need)  # fmt: skip
                    classified |= need
            acc["texture"] += _since(t0)
            t0 = _clock()
            rois = None
            if vox is not None:  # the ROI and close-front of the chunk's candidates, in parallel (numba)
                rois = batch_roi(vox, voxel_size, chunk_poses, intr, cfg, textured,
                                 frontier=frontier, fused_weight=w_f)  # fmt: skip
                n_vox[chunk], n_pix[chunk], mass[chunk] = rois.n_visible_voxels, rois.n_pixels, rois.mass
                if w_f is not None:
                    cf[chunk] = rois.close_front
            acc["roi"] += _since(t0)
            for j, i in enumerate(chunk):
                check_stop(should_stop)
                t0 = _clock()
                if inv:  # a Fisher mode with a map: Eq. 10 weights made once per score() call
                    f = self._candidate_fisher(surfel_map, inv, params, cands[i], mode, intr_f,
                                               rois.weights[j] if rois is not None else None, mass[i])  # fmt: skip
                    if f is not None:
                        fisher[i] = f
                        if mode == "fisherrf":
                            flagged[i] = f == 0.0  # every entry of F is >= 0 and every weight > 0
                acc["fisher"] += _since(t0)
                if unseen_term is not None:
                    t0 = _clock()
                    u = unseen_term.measure(surfel_map, cands[i], i, intr_f)
                    if u is not None:
                        unseen[i] = u
                    acc["unseen"] += _since(t0)
        if unseen_term is not None:
            t0 = _clock()
            unseen_term.finish(unseen, should_stop)
            unseen[~sees] = 0.0
            acc["unseen"] += _since(t0)
        for i in range(m):
            if need_voxels:
                flagged[i] = n_vox[i] == 0 and (unseen is None or unseen[i] == 0)
            elif h is None or not sees[i]:
                flagged[i] = True
        tex = acc.pop("texture")
        timings["setup"] += float(tex[0])
        cpu["setup"] += float(tex[1])
        for k, (wall, proc) in acc.items():
            timings[k], cpu[k] = float(wall), float(proc)
        timings["roi_close_front"] = timings["roi"] + timings["close_front"]
        timings |= {f"{k}_cpu": v for k, v in cpu.items()}

        # Eq. 15's z-scores over the candidates that have scores: a flagged candidate (it sees no surface / gets
        # no Fisher) has no F or I_vis, and its placeholder zeros would shift the means and inflate the spreads,
        # changing the balance of epsilon and delta among the others. Flagged candidates get 0 and rank last.
        fused = np.zeros(m)
        ok = ~flagged if (~flagged).any() else np.ones(m, dtype=bool)
        if mode == "roi-gsurfisher":
            fused[ok] = fuse_scores(fisher[ok], cf[ok], cfg.epsilon, cfg.delta, cfg.close_front_min_std)
        elif mode == "close-front":
            fused[ok] = zscore(cf[ok], cfg.close_front_min_std)
        else:
            fused[ok] = zscore(fisher[ok])
        if unseen is not None:
            fused[ok] = fused[ok] + cfg.unseen_weight * zscore(unseen[ok], cfg.unseen_min_std)
        if cfg.fisherrf_weight > 0 and mode in ROI_MODES:
            t0 = _clock()
            rf = self.score(surfel_map, None, None, poses, cands, intr, "fisherrf", should_stop=should_stop)
            fused[ok] = fused[ok] + cfg.fisherrf_weight * zscore(rf.fisher[ok])
            timings["fisherrf_term"] = float(_since(t0)[0])
        if not np.all(np.isfinite(fused)):  # defensive: scores are built finite
            raise InputError("scores", "non-finite fused score")
        if flagged.all() and not reasons:
            reasons.append("no candidate sees any surface")
        ranking = rank_candidates(fused, flagged)
        return NBVResult(
            mode=mode,
            fused=fused,
            fisher=fisher,
            close_front=cf,
            best_index=int(ranking[0]),
            ranking=ranking,
            top_k=ranking[: cfg.top_k].copy(),
            flagged=flagged,
            n_roi_pixels=n_pix,
            roi_mass=mass,
            n_visible_voxels=n_vox,
            reason="; ".join(reasons),
            timings_s=timings,
            unseen=unseen,
            n_skipped=int(m - len(live)),
        )

    def _candidate_fisher(
        self,
        surfel_map: SurfelMap,
        inv: dict[str, np.ndarray],
        params: list[str],
        T: np.ndarray,
        mode: str,
        intr_f: Intrinsics,
        roi_weights: np.ndarray | None,
        mass: float,
    ) -> float | None:
        """A candidate's Fisher score: FisherRF's over the whole view, or Eq. 9-10's over its ROI (``roi_weights``,
        at the full resolution; None or zero ``mass``: no ROI in view, no score); ``inv`` holds Eq. 10's weights.
        """
        cfg = self.config
        ds = cfg.fisher_downsample
        if mode == "fisherrf":
            w = None
            if ds > 1:
                w = torch.full((intr_f.height, intr_f.width), float(ds * ds), dtype=surfel_map.dtype)
            return fisher_weighted_sum(surfel_map, T, intr_f, inv, outputs=cfg.fisherrf_outputs, params=params,
                                       pixel_weights=w, near=cfg.near_m, far=cfg.far_m)  # fmt: skip
        if roi_weights is None or mass <= 0:
            return None
        w = torch.as_tensor(block_mean(roi_weights, ds) * (ds * ds / cfg.sigma_p**2), dtype=surfel_map.dtype)
        return fisher_weighted_sum(surfel_map, T, intr_f, inv, outputs=cfg.fisher_outputs, params=params,
                                   pixel_weights=w, near=cfg.near_m, far=cfg.far_m)  # fmt: skip


def frustum_meets_box(
    T_wc: np.ndarray,
    intr: Intrinsics,
    lo: np.ndarray,
    hi: np.ndarray,
    near_m: float,
    far_m: float,
    margin_px: float = 3.0,
) -> bool:
    """Whether the frustum of ``T_wc`` (``near_m``..``far_m``, image grown by ``margin_px``) may meet box [lo, hi].

    Conservative: False only when all 8 corners lie outside one of the frustum's 6 planes (a box that misses
    the frustum near one of its edges can still give True).
    """
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    T = np.asarray(T_wc, dtype=np.float64)
    pc = (corners - T[:3, 3]) @ T[:3, :3]  # camera frame
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    if (z < near_m).all() or (z > far_m).all():
        return False
    for coord, c, f, size in ((x, intr.cx, intr.fx, intr.width), (y, intr.cy, intr.fy, intr.height)):
        a_lo = (-0.5 - margin_px - c) / f  # side planes coord = a z through the camera centre
        a_hi = (size - 0.5 + margin_px - c) / f
        if (coord < a_lo * z).all() or (coord > a_hi * z).all():
            return False
    return True


def _mapped_region(
    vox: SurfaceVoxels | None, voxel_size_m: float, surfel_map: SurfelMap | None, cfg: NBVConfig, unseen: bool
) -> tuple[np.ndarray, np.ndarray] | None:
    """Box (lo, hi) holding all a candidate can score: surface voxels (grown by a voxel, and by the unseen term's
    margin), surfels' reach (3.4 sigma, as :func:`~roigsf_ros.render.fisher.frustum_subset`); None: no skipping.
    """
    boxes = []
    if vox is not None:
        if unseen and not np.isfinite(cfg.unseen_bbox_margin_m):
            return None  # every pixel counts in U(x): a candidate looking anywhere scores
        grow = voxel_size_m + (cfg.unseen_bbox_margin_m if unseen else 0.0)
        boxes.append((vox.centres_m.min(0) - grow, vox.centres_m.max(0) + grow))
    if surfel_map is not None:
        with torch.no_grad():
            means = surfel_map.means.detach().to("cpu", torch.float64).numpy()
            reach = 3.4 * float(surfel_map.log_scales.detach().max().exp()) + 1e-6
        boxes.append((means.min(0) - reach, means.max(0) + reach))
    if not boxes:
        return None
    return np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)


def _clock() -> tuple[float, float]:
    """(wall, process CPU) seconds now."""
    return time.perf_counter(), time.process_time()


def _since(t0: tuple[float, float]) -> np.ndarray:
    """(wall, process CPU) seconds elapsed since ``t0``."""
    return np.subtract(_clock(), t0)


def _check_h_train(h_train: dict[str, Tensor], surfel_map: SurfelMap, params: Sequence[str]) -> None:
    """InputError unless ``h_train`` has every parameter in ``params`` shaped like the map's tensor."""
    if not isinstance(h_train, dict):
        raise InputError("h_train", f"expected a dict of tensors, got {type(h_train).__name__}")
    _check_entries(h_train, {name: tuple(getattr(surfel_map, name).shape) for name in params})
    for name in params:
        if not bool(torch.isfinite(h_train[name]).all()) or bool((h_train[name] < 0).any()):
            raise InputError("h_train", f"'{name}' must be finite and >= 0")


def _check_entries(h_train: dict[str, Tensor], shapes: dict[str, tuple[int, ...]]) -> None:
    """InputError unless ``h_train`` has an entry of each shape in ``shapes`` (parameter name -> the map's shape)."""
    for name, want in shapes.items():
        if name not in h_train:
            raise InputError("h_train", f"has no entry '{name}' (it covers {', '.join(h_train) or 'nothing'})")
        if tuple(h_train[name].shape) != tuple(want):
            raise InputError("h_train", f"'{name}' has shape {list(h_train[name].shape)}, the map has {list(want)}")


__all__ = [
    "NBVResult",
    "NBVScorer",
    "UncertaintyMaps",
    "block_mean",
    "depth_error_ause",
    "downsampled",
    "frustum_meets_box",
    "fuse_scores",
    "gain_with",
    "information_gain",
    "inverse_denominators",
    "rank_candidates",
    "render_surfel_scalar",
    "surfel_variance",
    "train_fisher",
    "zscore",
]
