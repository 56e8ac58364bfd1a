"""Yardsticks: image metrics (PSNR, SSIM, depth L1), mesh metrics, uncertainty AUSE, comparison strips.

Mesh metrics follow the two families of papers the project compares with (see the method notes):
GauS-SLAM's precision/recall at a distance threshold tau and NICE-SLAM's accuracy, completion and
completion ratio. Both meshes are sampled uniformly by area with a seeded numpy generator, and
each sample's distance to the *other mesh's surface* is exact (open3d ``RaycastingScene``
point-to-triangle distance), not a distance to the other mesh's samples.

Recall can be measured against the part of the ground truth the cameras observed (the culling of
NICE-SLAM/GauS-SLAM evaluations): a GT sample counts when some pose sees it in the image, within
range, and not occluded by the GT mesh itself.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import open3d as o3d
from scipy.stats import spearmanr
from skimage.metrics import structural_similarity

from roigsf_ros.core.camera import Intrinsics, check_pose
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import atomic_path
from roigsf_ros.core.frame import COLOUR_FLOAT_MAX
from roigsf_ros.data.scene import camera_rays, load_mesh

o3c = o3d.core

COMPLETION_RATIO_TAU_M = 0.05
"""NICE-SLAM's completion ratio counts GT samples closer than 5 cm to the reconstruction."""

MeshLike = o3d.geometry.TriangleMesh | o3d.t.geometry.TriangleMesh | str | Path


# ----------------------------------------------------------------------------------------------
# Array helpers


def _to_numpy(x: Any, where: str) -> np.ndarray:
    """A numpy array of a numpy array (not copied) or of a torch tensor (detached, moved to the CPU)."""
    if hasattr(x, "detach") and hasattr(x, "cpu"):  # torch.Tensor without importing torch
        x = x.detach().cpu().numpy()
    try:
        return np.asarray(x)
    except (TypeError, ValueError) as exc:
        raise InputError(where, f"not an array: {exc}") from None


def _as_rgb01(img: Any, where: str) -> np.ndarray:
    """[H, W, 3] float64 in [0, 1] from uint8 or float images, [H, W, 3] or channel-first [3, H, W]."""
    a = _to_numpy(img, where)
    if a.ndim == 3 and a.shape[-1] != 3 and a.shape[0] == 3:
        a = np.moveaxis(a, 0, -1)
    if a.ndim != 3 or a.shape[-1] != 3:
        raise InputError(where, f"expected an [H, W, 3] (or [3, H, W]) colour image, got shape {a.shape}")
    if a.dtype == np.uint8:
        return a.astype(np.float64) / 255.0
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise InputError(where, "colour image has non-finite values")
    if a.size and float(np.median(a)) > COLOUR_FLOAT_MAX:  # a render's few values above 1 are clipped; not these
        raise InputError(where, f"colour floats have median {float(np.median(a)):g}: floats must be in [0, 1] "
                                "(0-255: give uint8), else clipping turns the image white")  # fmt: skip
    return np.clip(a, 0.0, 1.0)


def _pair_rgb(pred_rgb: Any, gt_rgb: Any) -> tuple[np.ndarray, np.ndarray]:
    pred, gt = _as_rgb01(pred_rgb, "pred_rgb"), _as_rgb01(gt_rgb, "gt_rgb")
    if pred.shape != gt.shape:
        raise InputError("pred_rgb", f"shape {pred.shape} differs from the ground truth's {gt.shape}")
    return pred, gt


# ----------------------------------------------------------------------------------------------
# Image metrics


def psnr(pred_rgb: Any, gt_rgb: Any) -> float:
    """Peak signal-to-noise ratio in dB, ``10 log10(1 / MSE)`` over [0, 1] colours (inf if identical).

    Accepts numpy or torch, [H, W, 3] or [3, H, W], uint8 (divided by 255) or float (clipped to [0, 1]; refused when
    most values are above 1, an image in 0-255 given as floats).
    """
    pred, gt = _pair_rgb(pred_rgb, gt_rgb)
    return _psnr_of_mse(float(np.mean((pred - gt) ** 2)))


def _psnr_of_mse(mse: float) -> float:
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


MIN_EVAL_SIDE = 11
"""Smallest image side (px) of a sequence that is mapped and evaluated: SSIM's 11x11 Gaussian window."""


def check_eval_size(intr: Intrinsics, where: str = "image size") -> None:
    """InputError before any work when ``intr``'s image is too small to evaluate (``roigsf map --width 4`` mapped every
    frame, then failed in skimage's SSIM).
    """
    if min(intr.width, intr.height) < MIN_EVAL_SIDE:
        raise InputError(where, f"{intr.width}x{intr.height} px: evaluating a map needs at least {MIN_EVAL_SIDE} px a "
                         "side (SSIM's 11x11 window); give a larger image size (--width/--height)")  # fmt: skip


def ssim(pred_rgb: Any, gt_rgb: Any) -> float:
    """Structural similarity of two colour images, the standard setting of Wang et al. (2004).

    skimage with an 11x11 Gaussian window of sigma 1.5, population covariances, data range 1, averaged
    over the three channels; the same inputs as :func:`psnr`.
    """
    pred, gt = _pair_rgb(pred_rgb, gt_rgb)
    if min(pred.shape[:2]) < MIN_EVAL_SIDE:  # skimage's own message names a 7x7 minimum and a win_size not taken here
        raise InputError("pred_rgb", f"SSIM needs images of at least {MIN_EVAL_SIDE}x{MIN_EVAL_SIDE} px (its Gaussian "
                                     f"window), got {pred.shape[1]}x{pred.shape[0]}")  # fmt: skip
    try:
        value = structural_similarity(
            pred,
            gt,
            channel_axis=-1,
            data_range=1.0,
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
        )
    except ValueError as exc:  # e.g. an image smaller than the 11x11 window
        raise InputError("pred_rgb", f"SSIM cannot be computed: {exc}") from None
    return float(value)


def depth_l1(pred_depth_m: Any, gt_depth_m: Any, valid_pred_only: bool = False) -> float:
    """Mean absolute depth error in metres over pixels with valid (finite, > 0) ground truth.

    Pixels whose prediction is non-finite are always left out; with ``valid_pred_only`` also those
    predicted <= 0 (holes), which otherwise count with their full error. Raises InputError on a shape
    mismatch or when no pixel is left.
    """
    pred = _to_numpy(pred_depth_m, "pred_depth_m").astype(np.float64)
    gt = _to_numpy(gt_depth_m, "gt_depth_m").astype(np.float64)
    pred, gt = np.squeeze(pred), np.squeeze(gt)
    if pred.shape != gt.shape or pred.ndim != 2:
        raise InputError("pred_depth_m", f"shape {pred.shape} must equal the ground truth's {gt.shape}, [H, W]")
    mask = np.isfinite(gt) & (gt > 0) & np.isfinite(pred)
    if valid_pred_only:
        mask &= pred > 0
    if not mask.any():
        raise InputError("gt_depth_m", "no pixel has valid ground-truth (and predicted) depth")
    return float(np.mean(np.abs(pred[mask] - gt[mask])))


# ----------------------------------------------------------------------------------------------
# Meshes: loading, sampling, ray casting, visibility


def as_legacy_mesh(mesh: MeshLike, where: str = "mesh") -> o3d.geometry.TriangleMesh:
    """A legacy open3d TriangleMesh from a legacy or tensor mesh, or from a mesh file path."""
    if isinstance(mesh, o3d.geometry.TriangleMesh):
        return mesh
    if isinstance(mesh, o3d.t.geometry.TriangleMesh):
        return mesh.to_legacy()
    if isinstance(mesh, str | Path):
        return load_mesh(mesh)  # refused, naming the file: missing, unreadable, no triangles, non-finite vertices
    raise InputError(where, f"expected an open3d TriangleMesh or a path, got {type(mesh).__name__}")


def check_gt_mesh(path: str | Path) -> None:
    """InputError naming ``path`` unless it is a readable triangle mesh with finite vertices: checked before a run
    (a truncated or empty PLY was refused only when the run's last frame was evaluated, as ``gt_mesh``).
    """
    if not Path(path).is_file():
        raise InputError(path, "ground-truth mesh not found")
    load_mesh(path)


def _triangles(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [V, 3] float64 and triangles [F, 3] int64 of a legacy mesh."""
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)


def sample_surface(mesh: MeshLike, n: int, seed: int = 0) -> np.ndarray:
    """``n`` points [n, 3] (float64, metres) uniform over the mesh surface by area, deterministic in ``seed``.

    Triangles are drawn with probability proportional to area, points inside them with the
    square-root barycentric rule; an empty (or zero-area) mesh gives [0, 3].
    """
    verts, tris = _triangles(as_legacy_mesh(mesh))
    if tris.size == 0 or n <= 0:
        return np.zeros((0, 3))
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    areas = np.where(np.isfinite(areas), areas, 0.0)
    total = float(areas.sum())
    if total <= 0.0:
        return np.zeros((0, 3))
    rng = np.random.default_rng(seed)
    cdf = np.cumsum(areas) / total
    idx = np.minimum(np.searchsorted(cdf, rng.random(n), side="right"), len(tris) - 1)
    r1, r2 = rng.random((2, n, 1))
    s = np.sqrt(r1)
    return (1.0 - s) * a[idx] + s * (1.0 - r2) * b[idx] + s * r2 * c[idx]


def raycasting_scene(mesh: MeshLike) -> o3d.t.geometry.RaycastingScene:
    """An open3d ray-casting/distance scene holding the mesh's triangles (CPU, BVH built lazily)."""
    legacy = as_legacy_mesh(mesh)
    scene = o3d.t.geometry.RaycastingScene()
    if len(legacy.triangles) > 0:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(legacy))
    return scene


def raycast_depth(
    mesh_or_scene: MeshLike | o3d.t.geometry.RaycastingScene, T_wc: np.ndarray, intr: Intrinsics
) -> np.ndarray:
    """Depth map [H, W] float32 (metres along the optical axis, 0 where no hit) of a mesh seen from ``T_wc``."""
    scene = (
        mesh_or_scene if isinstance(mesh_or_scene, o3d.t.geometry.RaycastingScene) else raycasting_scene(mesh_or_scene)
    )
    # The project's pixel convention (integer pixel coordinates are centres; open3d's
    # create_rays_pinhole samples u + 0.5). Ray directions have unit optical-axis component: t_hit is z-depth.
    rays = camera_rays(check_pose(T_wc, "T_wc"), intr)
    t_hit = scene.cast_rays(o3c.Tensor(rays))["t_hit"].numpy()
    return np.where(np.isfinite(t_hit), t_hit, 0.0).astype(np.float32)


def _point_distances(scene: o3d.t.geometry.RaycastingScene, points: np.ndarray, chunk: int = 500_000) -> np.ndarray:
    """Unsigned distance [N] (float64, metres) of each point to the scene's triangles."""
    out = np.empty(len(points))
    for i in range(0, len(points), chunk):
        query = o3c.Tensor(points[i : i + chunk].astype(np.float32))
        out[i : i + chunk] = scene.compute_distance(query).numpy()
    return out


def gt_visible_mask(
    points: np.ndarray,
    gt_mesh: MeshLike | o3d.t.geometry.RaycastingScene,
    poses: np.ndarray | Sequence[np.ndarray],
    intr: Intrinsics,
    max_depth_m: float = 10.0,
    depth_tol_m: float = 0.03,
    min_depth_m: float = 0.01,
) -> np.ndarray:
    """Bool [N]: which points [N, 3] (on the GT mesh) some camera pose [P, 4, 4] observes.

    Observed = projects inside the image, lies ``min_depth_m < z <= max_depth_m`` in front of the
    camera, and the first hit of the GT mesh along the camera ray to it is no more than
    ``depth_tol_m`` (in depth) in front of it. One ray per still-unseen candidate point per pose,
    so the cost falls as points get marked.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    scene = gt_mesh if isinstance(gt_mesh, o3d.t.geometry.RaycastingScene) else raycasting_scene(gt_mesh)
    poses_arr = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    visible = np.zeros(len(pts), dtype=bool)
    for i, T_wc in enumerate(poses_arr):
        T = check_pose(T_wc, f"poses[{i}]")
        cand = np.flatnonzero(~visible)
        if cand.size == 0:
            break
        R, c = T[:3, :3], T[:3, 3]
        rel = pts[cand] - c  # world-frame ray from the camera centre to the point, [C, 3]
        pc = rel @ R  # camera frame: R^T (p - c)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = intr.fx * pc[:, 0] / z + intr.cx
            v = intr.fy * pc[:, 1] / z + intr.cy
        ok = (z > min_depth_m) & (z <= max_depth_m)
        ok &= (u >= -0.5) & (u < intr.width - 0.5) & (v >= -0.5) & (v < intr.height - 0.5)
        if not ok.any():
            continue
        sel, rel, z = cand[ok], rel[ok], z[ok]
        # Direction p - c: t = 1 at the point, so the hit's depth is t_hit * z.
        rays = np.concatenate([np.broadcast_to(c, rel.shape), rel], axis=1).astype(np.float32)
        t_hit = scene.cast_rays(o3c.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        visible[sel[t_hit * z >= z - depth_tol_m]] = True
    return visible


# ----------------------------------------------------------------------------------------------
# Mesh metrics


def _tau_name(tau_m: float) -> str:
    return f"{round(tau_m * 100.0, 6):g}cm"


UNIT_MISMATCH_RATIO = 300.0
"""How many times larger one mesh's extent may be than the other's before :func:`mesh_metrics` warns of a unit mistake
(a ground truth in millimetres against a map in metres gave recall 0 without a word)."""


def _warn_unit_mistakes(taus: list[float], gt_pts: np.ndarray, pred_pts: np.ndarray) -> None:
    """Warn of the two unit mistakes a caller of :func:`mesh_metrics` makes silently: thresholds in cm given as
    metres (``taus_m=(1, 5)`` reported as ``@100cm``/``@500cm``), and meshes in different units.
    """
    big = [t for t in taus if t > 1.0]
    if big:
        warnings.warn(f"mesh_metrics: taus_m {big} are metres ({', '.join(f'{100 * t:g} cm' for t in big)}); "
                      "thresholds in cm are taus_m=(0.01, 0.05)", RuntimeWarning, stacklevel=3)  # fmt: skip
    if len(pred_pts) == 0:
        return
    gt_size = float(np.linalg.norm(np.ptp(gt_pts, axis=0)))
    pred_size = float(np.linalg.norm(np.ptp(pred_pts, axis=0)))
    ratio = max(gt_size, pred_size) / max(min(gt_size, pred_size), 1e-12)
    if ratio > UNIT_MISMATCH_RATIO:
        warnings.warn(f"mesh_metrics: the ground truth spans {gt_size:.4g} and the reconstruction {pred_size:.4g} "
                      f"(units of each mesh), {ratio:.0f}x apart: meshes in different units (mm and m)?",
                      RuntimeWarning, stacklevel=3)  # fmt: skip


def mesh_metrics(
    pred_mesh: MeshLike,
    gt_mesh: MeshLike,
    taus_m: Iterable[float] = (0.01, 0.05),
    n_samples: int = 200_000,
    seed: int = 0,
    observed_poses: np.ndarray | Sequence[np.ndarray] | None = None,
    intr: Intrinsics | None = None,
    cull_max_depth_m: float = 10.0,
    cull_depth_tol_m: float = 0.03,
    gt_point_filter: Callable[[np.ndarray], np.ndarray] | None = None,
) -> dict[str, float | int]:
    """Reconstruction quality of ``pred_mesh`` against ``gt_mesh`` (metres), GauS-SLAM and NICE-SLAM style.

    Keys, for each tau in ``taus_m`` (named in cm, e.g. ``@1cm``): ``precision@1cm`` (fraction of
    reconstruction samples closer than tau to the GT surface), ``recall@1cm`` (fraction of GT samples
    closer than tau to the reconstruction), ``fscore@1cm`` (their harmonic mean). Also
    ``accuracy_cm`` (mean reconstruction-to-GT distance, cm), ``completion_cm`` (mean GT-to-reconstruction
    distance, cm), ``completion_ratio_5cm`` (fraction of GT samples within 5 cm), ``n_pred_samples``,
    ``n_gt_samples`` (GT samples used for recall/completion) and ``gt_observed_fraction``.

    ``n_samples`` points are drawn on each mesh (seeded). With ``observed_poses`` [P, 4, 4] and
    ``intr``, GT samples are culled to those the poses observe (:func:`gt_visible_mask`) before
    recall/completion; ``gt_point_filter(points [N, 3]) -> bool [N]`` culls further. Precision and
    accuracy always use the full GT surface. An empty reconstruction gives zeros and infinite
    distances (see :func:`to_json_safe`).
    """
    taus = [float(t) for t in taus_m]
    if not taus or not all(np.isfinite(t) and t > 0 for t in taus):
        raise InputError("taus_m", f"thresholds must be positive metres, got {taus}")
    if int(n_samples) <= 0:
        raise InputError("n_samples", f"must be positive, got {n_samples}")
    gt_legacy = as_legacy_mesh(gt_mesh, "gt_mesh")
    pred_legacy = as_legacy_mesh(pred_mesh, "pred_mesh")
    gt_pts = sample_surface(gt_legacy, int(n_samples), seed)
    if len(gt_pts) == 0:
        raise InputError("gt_mesh", "ground-truth mesh has no surface")
    pred_pts = sample_surface(pred_legacy, int(n_samples), seed + 1)
    _warn_unit_mistakes(taus, gt_pts, pred_pts)
    gt_scene = raycasting_scene(gt_legacy)

    keep = np.ones(len(gt_pts), dtype=bool)
    if observed_poses is not None:
        if intr is None:
            raise InputError("intr", "intrinsics are needed to cull the ground truth to the observed poses")
        keep &= gt_visible_mask(
            gt_pts, gt_scene, observed_poses, intr, max_depth_m=cull_max_depth_m, depth_tol_m=cull_depth_tol_m
        )
    if gt_point_filter is not None:
        keep &= np.asarray(gt_point_filter(gt_pts), dtype=bool).reshape(len(gt_pts))
    gt_used = gt_pts[keep]
    if len(gt_used) == 0:
        raise InputError("observed_poses", "no ground-truth sample survives the culling; check poses and intrinsics")

    if len(pred_pts) > 0:
        d_pred = _point_distances(gt_scene, pred_pts)  # reconstruction -> GT
        d_gt = _point_distances(raycasting_scene(pred_legacy), gt_used)  # GT -> reconstruction
    else:
        d_pred = np.zeros(0)
        d_gt = np.full(len(gt_used), np.inf)

    out: dict[str, float | int] = {}
    for tau in taus:
        name = _tau_name(tau)
        p = float(np.mean(d_pred < tau)) if len(d_pred) else 0.0
        r = float(np.mean(d_gt < tau))
        out[f"precision@{name}"] = p
        out[f"recall@{name}"] = r
        out[f"fscore@{name}"] = 2.0 * p * r / (p + r) if p + r > 0 else 0.0
    out["accuracy_cm"] = float(np.mean(d_pred)) * 100.0 if len(d_pred) else math.inf
    out["completion_cm"] = float(np.mean(d_gt)) * 100.0
    out["completion_ratio_5cm"] = float(np.mean(d_gt < COMPLETION_RATIO_TAU_M))
    out["n_pred_samples"] = len(pred_pts)
    out["n_gt_samples"] = len(gt_used)
    out["gt_observed_fraction"] = len(gt_used) / len(gt_pts)
    return out


def to_json_safe(obj: Any) -> Any:
    """A copy of nested dicts/lists/arrays with numpy scalars as Python numbers and inf/NaN as None."""
    if isinstance(obj, dict):
        return {str(k): to_json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_json_safe(v) for v in obj]
    if hasattr(obj, "detach") and hasattr(obj, "cpu"):
        obj = obj.detach().cpu().numpy()
    if isinstance(obj, np.ndarray):
        return to_json_safe(obj.tolist())
    if isinstance(obj, np.bool_ | bool):
        return bool(obj)
    if isinstance(obj, np.integer | int):
        return int(obj)
    if isinstance(obj, np.floating | float):
        return float(obj) if math.isfinite(float(obj)) else None
    return obj


# ----------------------------------------------------------------------------------------------
# Uncertainty calibration


def ause(
    uncertainty: Any, abs_error: Any, n_ratios: int = 100, max_ratio: float = 0.999, random_seed: int = 0
) -> dict[str, Any]:
    """Area under the sparsification error curve (FisherRF's definition), lower is better.

    For removal ratios ``linspace(0, max_ratio, n_ratios)`` keep the ``int((1 - r) n)`` samples with the
    smallest error (oracle) or the smallest uncertainty and take their mean error; both curves are divided
    by their joint maximum and ``ause`` is the trapezoidal area of (uncertainty - oracle). Non-finite pairs
    are dropped. Returns ``ause``, ``ause_raw`` (the same area before normalisation, in error units),
    ``ause_random_raw`` (``ause_raw`` of a uniform-random ordering of the same samples, permutation seeded
    by ``random_seed``: the no-information baseline), ``spearman_rho`` (Spearman rank correlation of
    uncertainty and error, NaN when either is constant), ``n`` (samples used), ``ratios``,
    ``curve_oracle`` and ``curve_uncertainty`` (normalised).

    Caveat of the joint-max normalisation (FisherRF's and Bayes' Rays' code): an ordering worse than
    random (e.g. reversed) keeps the largest errors longest, so its curve rises far above the mean error;
    dividing by that peak shrinks its area, and with heavy-tailed errors an anti-correlated map can score
    a *lower* (better-looking) ``ause`` than an informative one. ``ause_raw`` has no such inversion;
    read it against ``ause_random_raw`` (an informative map is below it). ``spearman_rho`` weighs all
    samples alike while AUSE is driven by the largest errors, so with a small |rho| the two can disagree.
    """
    unc = _to_numpy(uncertainty, "uncertainty").astype(np.float64).reshape(-1)
    err = _to_numpy(abs_error, "abs_error").astype(np.float64).reshape(-1)
    if unc.shape != err.shape:
        raise InputError("uncertainty", f"{unc.size} values but abs_error has {err.size}")
    if int(n_ratios) < 2 or not 0.0 <= max_ratio < 1.0:
        raise InputError(
            "n_ratios/max_ratio", f"need n_ratios >= 2 and 0 <= max_ratio < 1, got {n_ratios}, {max_ratio}"
        )
    ok = np.isfinite(unc) & np.isfinite(err)
    unc, err = unc[ok], err[ok]
    if err.size == 0:
        raise InputError("abs_error", "no finite (uncertainty, error) pair")
    if np.any(err < 0):
        raise InputError("abs_error", "absolute errors must be >= 0")
    n = err.size
    ratios = np.linspace(0.0, float(max_ratio), int(n_ratios))
    n_keep = np.maximum(((1.0 - ratios) * n).astype(np.int64), 1)

    def curve(order: np.ndarray) -> np.ndarray:
        # order: ascending by the ranking key; keeping the first k removes the k highest-ranked.
        csum = np.cumsum(err[order])
        return csum[n_keep - 1] / n_keep

    oracle = curve(np.argsort(err, kind="stable"))
    by_unc = curve(np.argsort(unc, kind="stable"))
    raw = float(np.trapezoid(by_unc - oracle, ratios))
    random_raw = float(np.trapezoid(curve(np.random.default_rng(int(random_seed)).permutation(n)) - oracle, ratios))
    # a constant ranks nothing: NaN (scipy would warn)
    rho = float(spearmanr(unc, err).statistic) if np.ptp(unc) > 0 and np.ptp(err) > 0 else float("nan")
    peak = max(float(oracle.max()), float(by_unc.max()))
    if peak > 0:
        oracle, by_unc = oracle / peak, by_unc / peak
    return {
        "ause": float(np.trapezoid(by_unc - oracle, ratios)),
        "ause_raw": raw,
        "ause_random_raw": random_raw,
        "spearman_rho": rho,
        "n": int(n),
        "ratios": ratios,
        "curve_oracle": oracle,
        "curve_uncertainty": by_unc,
    }


# ----------------------------------------------------------------------------------------------
# Visual comparison


def colorize_depth(depth_m: Any, lo_m: float, hi_m: float) -> np.ndarray:
    """[H, W, 3] uint8 RGB turbo colouring of depth between ``lo_m`` and ``hi_m``; invalid pixels black."""
    d = np.squeeze(_to_numpy(depth_m, "depth_m").astype(np.float64))
    if d.ndim != 2:
        raise InputError("depth_m", f"expected an [H, W] depth map, got shape {d.shape}")
    valid = np.isfinite(d) & (d > 0)
    scale = max(hi_m - lo_m, 1e-9)
    norm = np.clip((np.where(valid, d, lo_m) - lo_m) / scale, 0.0, 1.0)
    bgr = cv2.applyColorMap((norm * 255.0).round().astype(np.uint8), cv2.COLORMAP_TURBO)
    bgr[~valid] = 0
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def save_comparison_strip(
    path: str | Path,
    rows: Sequence[tuple[Any, Any, Any, Any]],
    labels: Sequence[str] | None = ("input", "render", "depth input", "depth render"),
) -> np.ndarray:
    """Write a PNG grid, one row per ``(rgb_in, rgb_render, depth_in_m, depth_render_m)``, atomically.

    Depths are turbo-coloured over the row's shared valid range (so the two are comparable); tiles are
    resized to the first row's input size; ``labels`` are written on the first row. Returns the RGB grid.
    """
    if not rows:
        raise InputError("rows", "need at least one (rgb_in, rgb_render, depth_in_m, depth_render_m) row")
    size: tuple[int, int] | None = None
    grid_rows = []
    for i, row in enumerate(rows):
        if len(row) != 4:
            raise InputError(f"rows[{i}]", f"expected 4 images, got {len(row)}")
        rgb_in = (_as_rgb01(row[0], f"rows[{i}][0]") * 255.0).round().astype(np.uint8)
        rgb_out = (_as_rgb01(row[1], f"rows[{i}][1]") * 255.0).round().astype(np.uint8)
        d_in = np.squeeze(_to_numpy(row[2], f"rows[{i}][2]").astype(np.float64))
        d_out = np.squeeze(_to_numpy(row[3], f"rows[{i}][3]").astype(np.float64))
        both = np.concatenate([d_in.reshape(-1), d_out.reshape(-1)])
        both = both[np.isfinite(both) & (both > 0)]
        lo, hi = (float(both.min()), float(both.max())) if both.size else (0.0, 1.0)
        tiles = [rgb_in, rgb_out, colorize_depth(d_in, lo, hi), colorize_depth(d_out, lo, hi)]
        if size is None:
            size = (rgb_in.shape[1], rgb_in.shape[0])
        tiles = [
            t if (t.shape[1], t.shape[0]) == size else cv2.resize(t, size, interpolation=cv2.INTER_NEAREST)
            for t in tiles
        ]
        grid_rows.append(np.concatenate(tiles, axis=1))
    grid = np.ascontiguousarray(np.concatenate(grid_rows, axis=0))
    if labels:
        assert size is not None
        scale = max(size[1] / 400.0, 0.35)
        for j, text in enumerate(list(labels)[:4]):
            org = (j * size[0] + 5, int(20 * scale) + 5)
            cv2.putText(grid, str(text), org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
            cv2.putText(grid, str(text), org, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR)):
            raise OSError(f"{path}: OpenCV could not write the image")
    return grid


RenderRGBDepth = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""A map rendered at a pose ``T_wc`` [4, 4]: (rgb [H, W, 3] float in [0, 1], depth_m [H, W])."""


@dataclass
class RenderMetrics:
    """Per-frame image metrics of a map rendered at held-out frames, and the comparison-strip rows."""

    psnr: list[float] = field(default_factory=list)
    ssim: list[float] = field(default_factory=list)
    depth_l1_m: list[float] = field(default_factory=list)
    frames_without_gt_depth: int = 0
    strip_rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)
    """(input rgb, rendered rgb, input depth (valid pixels), rendered depth) of the strip frames."""
    uncovered_fraction: list[float] = field(default_factory=list)
    """Per frame, the share of pixels the map does not cover (with ``covered``; holes: surface no keyframe saw)."""
    psnr_covered: list[float] = field(default_factory=list)
    """Per frame with covered pixels, the PSNR over those pixels alone."""
    sq_err_uncovered: float = 0.0
    """Sum over frames and pixels of the squared colour error (summed over channels) at uncovered pixels."""
    sq_err_total: float = 0.0
    """The same sum over all pixels."""

    def means(self) -> dict[str, float | int | None]:
        """Means over the frames (None where no frame had the metric), for metrics.json; the hole split when taken."""
        dl1 = float(np.mean(self.depth_l1_m)) if self.depth_l1_m else None
        out: dict[str, float | int | None] = {
            "n_eval_frames": len(self.psnr),
            "psnr": float(np.mean(self.psnr)) if self.psnr else None,
            "ssim": float(np.mean(self.ssim)) if self.ssim else None,
            "depth_l1_m": dl1,
            "depth_l1_cm": dl1 * 100.0 if dl1 is not None else None,
        }
        if self.uncovered_fraction:
            out["uncovered_pixel_fraction"] = float(np.mean(self.uncovered_fraction))
            out["uncovered_error_share"] = self.sq_err_uncovered / self.sq_err_total if self.sq_err_total else 0.0
            out["psnr_covered"] = float(np.mean(self.psnr_covered)) if self.psnr_covered else None
        return out


def render_metrics(
    render: RenderRGBDepth,
    frames: Iterable[Any],
    valid_depth: Callable[[np.ndarray], np.ndarray],
    with_ssim_and_depth: bool = True,
    strip: Collection[int] = (),
    covered: Callable[[np.ndarray], np.ndarray] | None = None,
) -> RenderMetrics:
    """PSNR (and SSIM, depth L1) of ``render`` at each frame's pose against its image; one loop for every caller.

    ``frames``: objects with ``rgb`` [H, W, 3] uint8, ``depth_m`` [H, W] and ``T_wc`` [4, 4];
    ``valid_depth``: the input depth pixels that count (the mapper's range test); ``strip``: positions
    in ``frames`` whose images go into :attr:`RenderMetrics.strip_rows`; ``covered``: the pixels [H, W] bool the
    map covers at a pose, to split the colour error between holes and the rest (where a PSNR gap comes from).
    """
    out = RenderMetrics()
    for i, f in enumerate(frames):
        rgb, depth = render(f.T_wc)
        out.psnr.append(psnr(rgb, f.rgb))
        if covered is not None:
            mask = np.asarray(covered(f.T_wc), dtype=bool)
            pred, gt = _pair_rgb(rgb, f.rgb)
            err = ((pred - gt) ** 2).sum(-1)
            out.uncovered_fraction.append(float(1.0 - mask.mean()))
            out.sq_err_uncovered += float(err[~mask].sum())
            out.sq_err_total += float(err.sum())
            if mask.any():
                out.psnr_covered.append(_psnr_of_mse(float(err[mask].mean()) / 3.0))
        if not with_ssim_and_depth:
            continue
        out.ssim.append(ssim(rgb, f.rgb))
        gt = np.where(valid_depth(f.depth_m), f.depth_m, 0.0)
        if gt.any():
            out.depth_l1_m.append(depth_l1(depth, gt))
        else:
            out.frames_without_gt_depth += 1
        if i in strip:
            out.strip_rows.append((f.rgb, rgb, gt, depth))
    return out


__all__ = [
    "COMPLETION_RATIO_TAU_M",
    "MIN_EVAL_SIDE",
    "MeshLike",
    "RenderMetrics",
    "RenderRGBDepth",
    "as_legacy_mesh",
    "ause",
    "check_eval_size",
    "check_gt_mesh",
    "colorize_depth",
    "depth_l1",
    "gt_visible_mask",
    "mesh_metrics",
    "psnr",
    "raycast_depth",
    "raycasting_scene",
    "render_metrics",
    "sample_surface",
    "save_comparison_strip",
    "ssim",
    "to_json_safe",
]
