"""The surfel mapper: keyframe insertion, 2DGS optimisation, densify/prune, training Fisher, mesh.

GauS-SLAM-style mapping with known poses, on the CPU (numba kernels) or a CUDA device (``device``). A keyframe
(RGB-D + pose) is validated, new surfels are seeded where the current map does not explain it (rendered alpha < 0.5,
or the input depth lies in front of the rendered depth), then the map is optimised for ``iters_per_keyframe`` steps
over the newest keyframe and random past ones with the 2DGS losses, pruned, and the keyframe's diagonal Fisher is
added to ``h_train`` (the training information that the NBV score divides by). :func:`run_offline` runs a whole
sequence through a keyframe policy and writes the map, the mesh, metrics and a comparison strip.
"""

from __future__ import annotations

import json
import logging
import math
import warnings
from collections.abc import Generator, Iterable
from dataclasses import MISSING, asdict, dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from roigsf_ros.core.camera import Intrinsics, check_pose, load_pose
from roigsf_ros.core.config import Config
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import atomic_path, write_json
from roigsf_ros.core.frame import Frame, check_float_colour
from roigsf_ros.mapping import losses
from roigsf_ros.render.fisher import fisher_diag, frustum_subset
from roigsf_ros.render.numba_setup import KERNEL_LOCK, Kernels, numba_available, prange
from roigsf_ros.render.rasterize import RenderOutput, render_map
from roigsf_ros.render.surfels import PARAM_NAMES, SurfelMap, check_device, surfels_from_rgbd

if TYPE_CHECKING:
    import open3d as o3d

log = logging.getLogger(__name__)

DEPTH_MODES = ("expected", "median")
"""Rendered depth used for evaluation or meshing: alpha-normalised expected depth, or median depth."""


@dataclass(frozen=True)
class MapperConfig(Config):
    """Every tunable of the mapper (ROS parameters carry the same names). Units: metres, pixels."""

    iters_per_keyframe: int = 10
    """Optimiser steps after each keyframe (GauS-SLAM uses 40 on a GPU; scaled for the CPU)."""
    views_per_iteration: int = 1
    """Keyframes rendered and summed per optimiser step."""
    newest_keyframe_prob: float = 0.5
    """Chance that a view slot of a step is the newest keyframe; the rest are drawn from the window."""
    keyframe_window: int = 0
    """Past keyframes drawn from: the most recent this many (0 = all keyframes)."""
    final_iters: int = 0
    """Extra steps over random keyframes at the end of an offline run (a global refinement)."""

    lr_means: float = 2e-4
    """Adam step of surfel centres (metres)."""
    lr_quats: float = 2e-3
    """Adam step of the rotation quaternions."""
    lr_log_scales: float = 5e-3
    """Adam step of the log scales (2DGS)."""
    lr_opacity_logits: float = 5e-2
    """Adam step of the opacity logits (2DGS, GauS-SLAM)."""
    lr_sh_dc: float = 1e-2
    """Adam step of the zeroth SH coefficient (4x 2DGS's 2.5e-3 for the few CPU iterations)."""

    lambda_dssim: float = 0.2
    """D-SSIM share of the colour loss (3DGS/2DGS)."""
    weight_colour: float = 1.0
    """Weight of the colour loss."""
    weight_depth: float = 1.0
    """Weight of the depth L1 (alpha-weighted rendered depth vs input depth, valid pixels)."""
    weight_normal: float = 0.05
    """Weight of the 2DGS normal-consistency loss."""
    weight_distortion: float = 0.0
    """Weight of the 2DGS depth-distortion loss (2DGS: 0 unbounded, 1000 for objects)."""

    near_m: float = 0.1
    """Near plane of the renderer."""
    min_depth_m: float = 0.1
    """Input depth at or below this is invalid (masked and counted)."""
    max_depth_m: float = 10.0
    """Input depth above this is invalid (masked and counted)."""

    init_opacity: float = 0.9
    """Opacity of new surfels."""
    init_scale_factor: float = 0.7
    """New surfel radius (std) as a fraction of its pixel footprint times the seeding stride."""
    init_max_stretch: float = 1.0
    """New surfels' axis along the surface's tilt is their radius over the cosine of the incidence angle, at most
    this many times longer (a pixel's footprint on a tilted surface; 1 = isotropic, as in SplaTAM and GauS-SLAM)."""
    densify_stride: int = 1
    """One new surfel per ``densify_stride`` x ``densify_stride`` pixel block."""
    densify_alpha_threshold: float = 0.5
    """Seed surfels where the map renders alpha below this (GauS-SLAM's silhouette rule)."""
    densify_depth_margin_m: float = 0.05
    """Also seed where the input depth is in front of the rendered depth by more than this."""

    prune_opacity: float = 0.01
    """Prune surfels whose opacity fell below this."""
    prune_max_scale_m: float = 0.5
    """Prune surfels whose larger scale grew beyond this (degenerate, smeared)."""
    prune_min_scale_m: float = 1e-5
    """Prune surfels whose larger scale shrank below this (vanished)."""
    prune_every: int = 1
    """Prune after every this many keyframes."""

    track_h_train: bool = True
    """Keep the running diagonal Fisher of the training views."""
    h_train_lazy: bool = True
    """Add new keyframes' Fisher when ``h_train`` is next read (same result when read after every
    keyframe, as NBV policies do; free for runs that never read it); False: right after each one."""
    fisher_outputs: tuple[str, ...] = ("color", "depth")
    """Rendered outputs whose Fisher makes up ``h_train`` (see roigsf_ros.render.fisher)."""
    fisher_params: tuple[str, ...] = ("means", "quats", "log_scales", "opacity_logits", "sh_dc")
    """SurfelMap parameters ``h_train`` covers."""

    mesh_voxel_size_m: float = 0.02
    """TSDF voxel size of the exported mesh."""
    mesh_sdf_trunc_m: float = 0.08
    """TSDF truncation distance of the exported mesh."""
    mesh_min_alpha: float = 0.5
    """Rendered depth is fused only where the map's alpha reaches this."""
    mesh_depth: str = "median"
    """Rendered depth fused into the mesh: "median" (sharp at edges, 2DGS bounded) or "expected"."""
    eval_depth: str = "expected"
    """Rendered depth compared with the input in evaluation: "expected" or "median"."""

    seed: int = 0
    """Seed of the keyframe sampling."""
    device: str = "cpu"
    """Torch device of the map and the optimisation: "cpu" (numba kernels) or "cuda[:N]" (the plain-torch renderer;
    tested on an H100 and an H200, but 1.2-3.0x slower per training step than the numba kernels on 2 CPU cores; the
    kernels use every CPU, and on the H200 machine's 16 cores they rendered as fast as its GPU at 320x240 and faster at
    160x120; docs/measured-figures.md, CUDA)."""

    def validate(self) -> MapperConfig:
        """Return self if every field is in range, else raise InputError naming the field."""
        checks: dict[str, tuple[bool, str]] = {  # name -> (in range, the range as the error says it)
            "iters_per_keyframe": (self.iters_per_keyframe >= 0, ">= 0"),
            "views_per_iteration": (self.views_per_iteration >= 1, ">= 1"),
            "newest_keyframe_prob": (0.0 <= self.newest_keyframe_prob <= 1.0, "in [0, 1]"),
            "keyframe_window": (self.keyframe_window >= 0, ">= 0"),
            "final_iters": (self.final_iters >= 0, ">= 0"),
            "lambda_dssim": (0.0 <= self.lambda_dssim <= 1.0, "in [0, 1]"),
            "near_m": (self.near_m > 0, "> 0"),
            "min_depth_m": (self.min_depth_m >= 0, ">= 0"),
            "max_depth_m": (
                self.max_depth_m > max(self.min_depth_m, self.near_m),
                f"> min_depth_m and near_m ({max(self.min_depth_m, self.near_m)!r})",
            ),
            "init_opacity": (0.0 < self.init_opacity < 1.0, "in (0, 1)"),
            "init_scale_factor": (self.init_scale_factor > 0, "> 0"),
            "init_max_stretch": (self.init_max_stretch >= 1.0, ">= 1"),
            "densify_stride": (self.densify_stride >= 1, ">= 1"),
            "densify_alpha_threshold": (0.0 < self.densify_alpha_threshold <= 1.0, "in (0, 1]"),
            "densify_depth_margin_m": (self.densify_depth_margin_m > 0, "> 0"),
            "prune_opacity": (0.0 <= self.prune_opacity < 1.0, "in [0, 1)"),
            "prune_max_scale_m": (
                self.prune_max_scale_m > self.prune_min_scale_m >= 0,
                f"> prune_min_scale_m ({self.prune_min_scale_m!r}), which must be >= 0",
            ),
            "prune_every": (self.prune_every >= 1, ">= 1"),
            "mesh_voxel_size_m": (self.mesh_voxel_size_m > 0, "> 0"),
            "mesh_sdf_trunc_m": (
                self.mesh_sdf_trunc_m >= self.mesh_voxel_size_m,
                f">= mesh_voxel_size_m ({self.mesh_voxel_size_m!r})",
            ),
            "mesh_min_alpha": (0.0 <= self.mesh_min_alpha <= 1.0, "in [0, 1]"),
            "mesh_depth": (self.mesh_depth in DEPTH_MODES, f"one of {', '.join(DEPTH_MODES)}"),
            "eval_depth": (self.eval_depth in DEPTH_MODES, f"one of {', '.join(DEPTH_MODES)}"),
        }
        for name in ("lr_means", "lr_quats", "lr_log_scales", "lr_opacity_logits", "lr_sh_dc"):
            checks[name] = (getattr(self, name) >= 0, ">= 0")
        for name in ("weight_colour", "weight_depth", "weight_normal", "weight_distortion"):
            checks[name] = (getattr(self, name) >= 0, ">= 0")
        for name, (ok, rule) in checks.items():
            value = getattr(self, name)
            finite = not isinstance(value, float) or math.isfinite(value)
            if not ok or not finite:
                kind = "" if finite else "a finite number "
                raise InputError(f"mapper.{name}", f"must be {kind}{rule}, got {value!r}")
        check_device(self.device, "mapper.device")
        return self

    def learning_rates(self) -> dict[str, float]:
        """Adam step per SurfelMap parameter group."""
        return {
            "means": self.lr_means,
            "quats": self.lr_quats,
            "log_scales": self.lr_log_scales,
            "opacity_logits": self.lr_opacity_logits,
            "sh_dc": self.lr_sh_dc,
        }


def depth_scale_note(metrics: dict[str, Any]) -> str:
    """A run's note when most of its keyframes' depth values were out of range (a wrong depth scale), from the
    ``mapper_*`` counters of its metrics (:class:`MapperStats`); "" otherwise.
    """
    out, total = metrics.get("mapper_depth_out_of_range_pixels"), metrics.get("mapper_depth_pixels")
    if not out or not total or out <= 0.5 * total:
        return ""
    return (f"{out / total:.0%} of the keyframes' depth values were outside min_depth_m..max_depth_m and masked: a "
            "depth scale off (a cam_params.json 'scale', millimetres read as metres)?")  # fmt: skip


@dataclass
class MapperStats:
    """Counters of what the mapper skipped, masked, added and removed (all logged as they happen)."""

    keyframes_added: int = 0
    frames_skipped_no_depth: int = 0
    invalid_depth_pixels: int = 0
    depth_pixels: int = 0
    """Depth pixels of the frames inserted (and of those skipped for no valid depth): the whole of which
    ``invalid_depth_pixels`` and ``depth_out_of_range_pixels`` are parts."""
    depth_out_of_range_pixels: int = 0
    """Invalid depth pixels with a finite, positive value outside ``min_depth_m``..``max_depth_m``: a wrong depth scale
    shows here (a sensor's holes, zero or NaN, do not)."""
    invalid_colour_pixels: int = 0
    steps: int = 0
    steps_skipped_nonfinite: int = 0
    surfels_added: int = 0
    surfels_pruned: int = 0
    surfels_removed_nonfinite: int = 0


@dataclass
class Keyframe:
    """A keyframe as the mapper keeps it: colour uint8 [H, W, 3], depth [H, W] (0 invalid), pose."""

    frame_id: int
    T_wc: np.ndarray
    rgb_u8: Tensor
    depth_m: Tensor
    valid: Tensor

    def rgb01(self, dtype: torch.dtype) -> Tensor:
        """Colour as float [H, W, 3] in [0, 1]."""
        return self.rgb_u8.to(dtype) / 255.0


class _SparseAdam:
    """Adam with per-surfel step counts that updates only the surfels seen in the step.

    Rows can be appended (zero state) and removed, so the state follows the surfel set.
    """

    def __init__(self, lrs: dict[str, float], betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15) -> None:
        self.lrs, self.betas, self.eps = lrs, betas, eps
        self.m: dict[str, Tensor] = {}
        self.v: dict[str, Tensor] = {}
        self.t: Tensor | None = None

    def sync(self, params: dict[str, Tensor]) -> None:
        """Create zero state for parameters seen for the first time."""
        for k, p in params.items():
            if k in self.lrs and k not in self.m:
                self.m[k] = torch.zeros_like(p.detach())
                self.v[k] = torch.zeros_like(p.detach())
        if self.t is None:
            n = next(iter(params.values())).shape[0]
            self.t = torch.zeros(n, dtype=torch.long, device=next(iter(params.values())).device)

    def append(self, n_new: int) -> None:
        """Zero state for ``n_new`` surfels added at the end."""
        for d in (self.m, self.v):
            for k, s in d.items():
                d[k] = torch.cat([s, s.new_zeros((n_new, *s.shape[1:]))])
        if self.t is not None:
            self.t = torch.cat([self.t, self.t.new_zeros(n_new)])

    def keep(self, keep: Tensor) -> None:
        """Keep the state rows where the bool mask ``keep`` is true."""
        for d in (self.m, self.v):
            for k, s in d.items():
                d[k] = s[keep]
        if self.t is not None:
            self.t = self.t[keep]

    @torch.no_grad()
    def step(self, params: dict[str, Tensor], rows: Tensor) -> None:
        """One Adam update of the surfel ``rows`` (index tensor) of every parameter with a gradient.

        CPU float tensors take a numba kernel (one pass over the rows per parameter, in place);
        other devices the same update in torch ops.
        """
        if rows.numel() == 0 or self.t is None:
            return
        b1, b2 = self.betas
        self.t.index_add_(0, rows, torch.ones_like(rows))
        if _numba_rows_ok(params, rows):
            rows_np, t_np = rows.numpy(), self.t.numpy()
            for k, p in params.items():
                if k not in self.lrs or p.grad is None:
                    continue
                n = p.shape[0]
                with KERNEL_LOCK:
                    _ADAM_KERNELS["adam"](
                        rows_np, t_np, p.detach().view(n, -1).numpy(), p.grad.view(n, -1).numpy(),
                        self.m[k].view(n, -1).numpy(), self.v[k].view(n, -1).numpy(),
                        float(self.lrs[k]), float(b1), float(b2), float(self.eps),
                    )  # fmt: skip
            return
        t = self.t.index_select(0, rows).to(next(iter(params.values())).dtype)
        c1, c2 = 1.0 - b1**t, 1.0 - b2**t
        for k, p in params.items():
            if k not in self.lrs or p.grad is None:
                continue
            g = p.grad.index_select(0, rows)
            m = self.m[k].index_select(0, rows).mul_(b1).add_(g, alpha=1.0 - b1)
            v = self.v[k].index_select(0, rows).mul_(b2).addcmul_(g, g, value=1.0 - b2)
            self.m[k].index_copy_(0, rows, m)
            self.v[k].index_copy_(0, rows, v)
            shape = (-1,) + (1,) * (p.dim() - 1)
            upd = (m / c1.view(shape)) / ((v / c2.view(shape)).sqrt() + self.eps)
            p.index_add_(0, rows, upd, alpha=-self.lrs[k])


def valid_depth_mask(depth_m: np.ndarray, config: MapperConfig) -> np.ndarray:
    """Bool [H, W]: finite depth within (min_depth_m, max_depth_m] of ``config`` (and beyond its near plane)."""
    d = np.asarray(depth_m)
    lo = max(config.min_depth_m, config.near_m)
    with np.errstate(invalid="ignore"):
        return np.isfinite(d) & (d > lo) & (d <= config.max_depth_m)


def _numba_rows_ok(params: dict[str, Tensor], rows: Tensor) -> bool:
    """Whether the numba row kernels apply: CPU float tensors with contiguous gradients, numba installed."""
    if rows.device.type != "cpu" or not numba_available():
        return False
    for p in params.values():
        if p.device.type != "cpu" or p.dtype not in (torch.float32, torch.float64) or not p.is_contiguous():
            return False
        if p.grad is not None and not p.grad.is_contiguous():
            return False
    return True


def _k_adam(
    rows: np.ndarray,
    t: np.ndarray,
    p: np.ndarray,
    g: np.ndarray,
    m: np.ndarray,
    v: np.ndarray,
    lr: float,
    b1: float,
    b2: float,
    eps: float,
) -> None:
    """Adam update of the ``rows`` of one parameter [N, k], in place (numba; ``t`` per-row step counts)."""
    for i in prange(rows.shape[0]):
        r = rows[i]
        c1 = 1.0 - b1 ** t[r]
        c2 = 1.0 - b2 ** t[r]
        for k in range(p.shape[1]):
            gk = g[r, k]
            mk = m[r, k] * b1 + (1.0 - b1) * gk
            vk = v[r, k] * b2 + (1.0 - b2) * gk * gk
            m[r, k] = mk
            v[r, k] = vk
            p[r, k] -= lr * ((mk / c1) / (np.sqrt(vk / c2) + eps))


def _k_rows_finite(rows: np.ndarray, g: np.ndarray) -> bool:
    """Whether every entry of the ``rows`` of ``g`` [N, k] is finite (numba)."""
    bad = 0
    for i in prange(rows.shape[0]):
        r = rows[i]
        for k in range(g.shape[1]):
            if not np.isfinite(g[r, k]):
                bad += 1
    return bad == 0


_ADAM_KERNELS = Kernels(adam=_k_adam, rows_finite=_k_rows_finite)
"""The sparse Adam update and the gradient check (compiled on first use)."""


class Mapper:
    """Incremental 2DGS surfel map over posed RGB-D keyframes of one camera."""

    def __init__(self, intr: Intrinsics, config: MapperConfig | None = None) -> None:
        if not isinstance(intr, Intrinsics):  # else an AttributeError at the first keyframe
            raise InputError("intr", f"expected an Intrinsics (a source's .intrinsics), got {type(intr).__name__}")
        self.config = MapperConfig.given(config)
        self.intr = intr
        self.device = torch.device(self.config.device)
        self.dtype = torch.float32
        self.map = SurfelMap.empty(device=self.device, dtype=self.dtype)
        self.keyframes: list[Keyframe] = []
        self.stats = MapperStats()
        self._h_train: dict[str, Tensor] = {}
        self._fisher_pending: list[Keyframe] = []
        self.loaded_keyframe_ids: list[int] = []
        """Keyframe ids of a map read by :meth:`load` (its images are not stored, so not keyframes here)."""
        self.loaded_keyframe_poses = np.zeros((0, 4, 4))
        """Keyframe poses [K, 4, 4] of a map read by :meth:`load`."""
        self.h_train_loaded = False
        """Whether :meth:`load` read the saved map's training Fisher (``h_train.npz``): then :attr:`h_train` covers the
        loaded keyframes too, as it did in the mapper that saved it."""
        self._warned_loaded_h_train = False
        self._warned_out_of_range = False  # said once: most of a frame's depth out of range (_count_out_of_range)
        self._h_train_read = False  # something read h_train (a Fisher policy, the map cloud): a save then writes it
        self._rng = np.random.default_rng(self.config.seed)
        self._adam = _SparseAdam(self.config.learning_rates())
        self._version = 0  # bumped whenever the map changes (invalidates the render cache)
        self._cache: tuple[tuple[int, bytes], RenderOutput] | None = None
        self._reset_h_train()

    # ------------------------------------------------------------------------------ properties
    @property
    def n_surfels(self) -> int:
        """Number of surfels in the map."""
        return len(self.map)

    @property
    def keyframe_ids(self) -> list[int]:
        """Frame ids of the keyframes this mapper inserted, in insertion order (a loaded map's own are in
        ``loaded_keyframe_ids``; :meth:`map_keyframes` gives both).
        """
        return [kf.frame_id for kf in self.keyframes]

    @property
    def keyframe_poses(self) -> np.ndarray:
        """Keyframe poses [K, 4, 4] (camera-to-world)."""
        return np.stack([kf.T_wc for kf in self.keyframes]) if self.keyframes else np.zeros((0, 4, 4))

    def map_keyframes(self) -> tuple[list[int], np.ndarray]:
        """Ids and poses [K, 4, 4] of every keyframe of the map: a loaded map's first, then those added since.

        The one list of what the map was built from: :meth:`save` writes it, :meth:`mesh` fuses at its poses and
        the shared map's snapshots carry it, so a map loaded, extended and saved again keeps all its keyframes.
        """
        ids = [int(i) for i in self.loaded_keyframe_ids] + [int(kf.frame_id) for kf in self.keyframes]
        poses = [*self.loaded_keyframe_poses, *(kf.T_wc for kf in self.keyframes)]
        return ids, (np.stack(poses).astype(np.float64) if poses else np.zeros((0, 4, 4)))

    def valid_depth_mask(self, depth_m: np.ndarray) -> np.ndarray:
        """Bool [H, W]: finite depth within (min_depth_m, max_depth_m] (and beyond the near plane)."""
        return valid_depth_mask(depth_m, self.config)

    # ------------------------------------------------------------------------------- rendering
    def render(self, T_wc: np.ndarray, with_grad: bool = False) -> RenderOutput:
        """Render the map from ``T_wc`` [4, 4] (InputError if it is not a rigid transform).

        Without grad the last render is cached until the map changes, so the keyframe policy's
        check and the densification of the same frame share one render.
        """
        T = check_pose(T_wc, "T_wc")
        if with_grad:
            return self._render(T, self.config.weight_distortion > 0)
        key = (self._version, T.tobytes())
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        with torch.no_grad():
            out = self._render(T, False)
        self._cache = (key, out)
        return out

    def _render(self, T: np.ndarray, with_distortion: bool) -> RenderOutput:
        """Render the surfels that can reach the view (``cull``); ``visible`` covers the whole map."""
        return render_map(self.map, T, self.intr, near=self.config.near_m, with_distortion=with_distortion, cull=True)

    def _frustum_subset(self, T: np.ndarray) -> Tensor:
        """Indices of surfels that can reach the view from ``T`` [4, 4] (conservative: see fisher.frustum_subset)."""
        viewmat = torch.as_tensor(np.linalg.inv(T), dtype=self.dtype, device=self.device)
        return frustum_subset(self.map, viewmat, self.intr, near=self.config.near_m, far=math.inf)

    def render_alpha(self, T_wc: np.ndarray) -> np.ndarray:
        """Accumulated alpha [H, W] (float32 numpy) of the map seen from ``T_wc``."""
        if self.n_surfels == 0:
            return np.zeros((self.intr.height, self.intr.width), np.float32)
        return self.render(T_wc).alpha.cpu().numpy().astype(np.float32)

    def render_depth(self, out: RenderOutput, mode: str) -> Tensor:
        """The ``mode`` ("expected" or "median") depth [H, W] of a render (0 where nothing was hit)."""
        return out.expected_depth() if mode == "expected" else out.median_depth

    # ------------------------------------------------------------------------------ keyframes
    def _prepare(self, frame: Frame) -> tuple[np.ndarray, Tensor, Tensor, Tensor, int]:
        """Validate a frame: pose (InputError), sizes (InputError), depth/colour masked and counted."""
        where = f"frame {frame.index}"
        T = check_pose(frame.T_wc, f"{where} pose")
        h, w = self.intr.height, self.intr.width
        rgb = np.asarray(frame.rgb)
        depth = np.asarray(frame.depth_m, dtype=np.float32)
        if rgb.shape != (h, w, 3):
            raise InputError(where, f"colour has shape {rgb.shape}, expected ({h}, {w}, 3) for the intrinsics")
        if depth.shape != (h, w):
            raise InputError(where, f"depth has shape {depth.shape}, expected ({h}, {w}) for the intrinsics")
        if rgb.dtype != np.uint8:
            if not np.issubdtype(rgb.dtype, np.floating):
                raise InputError(where, f"colour has dtype {rgb.dtype}: give uint8 (0-255) or floats in [0, 1]")
            rgb_f = rgb.astype(np.float64)
            check_float_colour(rgb_f, where)
            bad = ~np.isfinite(rgb_f).all(-1)
            if bad.any():
                self.stats.invalid_colour_pixels += int(bad.sum())
                log.warning("%s: %d colour pixels are not finite; set to black", where, int(bad.sum()))
            rgb = (np.clip(np.nan_to_num(rgb_f, nan=0.0, posinf=1.0, neginf=0.0), 0, 1) * 255 + 0.5).astype(np.uint8)
        valid = self.valid_depth_mask(depth)
        n_bad = int(valid.size - valid.sum())
        depth = np.where(valid, depth, np.float32(0.0)).astype(np.float32)
        return (
            T,
            torch.from_numpy(np.ascontiguousarray(rgb)).to(self.device),
            torch.from_numpy(depth).to(self.device),
            torch.from_numpy(valid).to(self.device),
            n_bad,
        )

    def add_keyframe(self, frame: Frame, optimise: bool = True) -> bool:
        """Insert ``frame`` as a keyframe: seed surfels, optimise, prune, add its Fisher; False if skipped.

        A non-rigid pose or a size mismatch raises InputError; invalid depth pixels (NaN, zero,
        out of range) are masked and counted; a frame with no valid depth is skipped and counted.
        """
        steps = self.keyframe_schedule(frame, optimise=optimise)
        while True:
            try:
                next(steps)
            except StopIteration as done:
                return bool(done.value)

    def _count_out_of_range(self, frame: Frame) -> None:
        """Count the frame's finite depth values outside the valid range; the first time they are most of a frame's
        depth, warn once: a depth scale 6.55x off (``scale: 1000`` in a Replica cam_params.json) masked 93 % of every
        frame beyond ``max_depth_m`` and the run gave F@5cm 0.000 without a word.
        """
        d = np.asarray(frame.depth_m, dtype=np.float64)
        out = np.isfinite(d) & (d > 0) & ((d < self.config.min_depth_m) | (d > self.config.max_depth_m))
        n = int(out.sum())
        self.stats.depth_out_of_range_pixels += n
        if n > d.size // 2 and not self._warned_out_of_range:
            self._warned_out_of_range = True
            log.warning(
                "frame %d: %.0f %% of its depth values are outside min_depth_m %g to max_depth_m %g (%.3g-%.3g m) and "
                "masked: a depth scale off (a cam_params.json 'scale', millimetres read as metres)?",
                frame.index, 100.0 * n / d.size, self.config.min_depth_m, self.config.max_depth_m,
                float(d[out].min()), float(d[out].max()),
            )  # fmt: skip

    def no_depth_reason(self, depth_m: np.ndarray) -> str:
        """Why a frame has no valid depth, with the values it does have: a sensor's millimetres given as metres (a
        16UC1 image published as 32FC1) read as "values 450-4000, above max_depth_m 10", not only "out of range".
        """
        cfg = self.config
        d = np.asarray(depth_m, dtype=np.float64)
        d = d[np.isfinite(d) & (d > 0)]
        bounds = f"min_depth_m {cfg.min_depth_m:g} to max_depth_m {cfg.max_depth_m:g}"
        if d.size == 0:
            return f"no valid depth (every value NaN, infinite, zero or negative; valid is {bounds})"
        lo, hi = float(d.min()), float(d.max())
        hint = "; millimetres given as metres? (16UC1 depth is mm, 32FC1 m)" if lo > 5 * cfg.max_depth_m else ""
        return f"no valid depth (finite values {lo:.4g}-{hi:.4g} m, outside {bounds}{hint})"

    def keyframe_schedule(
        self, frame: Frame, slice_iters: int = 0, optimise: bool = True, flush_fisher: bool | None = None
    ) -> Generator[int, None, bool]:
        """:meth:`add_keyframe` as a schedule of steps, for callers that share the map between them.

        Insert and densify, then (``optimise``) ``iters_per_keyframe`` optimiser steps in slices of
        ``slice_iters`` (0: one slice), then prune every ``prune_every`` keyframes and queue the keyframe's
        Fisher, computed now when ``flush_fisher`` (None: unless ``h_train_lazy``). Yields after the
        insertion and after each slice (the number of steps just run), so a caller can release a lock
        between them or abandon the rest; returns whether the frame was inserted.
        """
        T, rgb_u8, depth, valid, n_bad = self._prepare(frame)
        self.stats.depth_pixels += int(valid.numel())
        if n_bad:
            self.stats.invalid_depth_pixels += n_bad
            log.debug("frame %d: %d of %d depth pixels invalid (masked)", frame.index, n_bad, valid.numel())
            self._count_out_of_range(frame)
        if not bool(valid.any()):
            self.stats.frames_skipped_no_depth += 1
            log.warning("frame %d: %s; keyframe skipped", frame.index, self.no_depth_reason(frame.depth_m))
            return False
        kf = Keyframe(frame_id=int(frame.index), T_wc=T, rgb_u8=rgb_u8, depth_m=depth, valid=valid)
        self.densify(kf)
        self.keyframes.append(kf)
        self.stats.keyframes_added += 1
        yield 0
        if optimise:
            newest = len(self.keyframes) - 1
            left = self.config.iters_per_keyframe
            while left > 0:
                n = min(slice_iters or left, left)
                self.optimise(n, newest=newest)
                left -= n
                yield n
            if len(self.keyframes) % self.config.prune_every == 0:
                self.prune()
        if self.config.track_h_train:
            self._fisher_pending.append(kf)
            if (not self.config.h_train_lazy) if flush_fisher is None else flush_fisher:
                self._flush_fisher()
        return True

    # -------------------------------------------------------------------------- densify/prune
    @torch.no_grad()
    def densify(self, kf: Keyframe) -> int:
        """Seed surfels from ``kf`` where the map renders alpha < threshold or lies behind its depth."""
        cfg = self.config
        mask = kf.valid.clone()
        if self.n_surfels:
            out = self.render(kf.T_wc)
            rendered = out.expected_depth()
            unseen = out.alpha < cfg.densify_alpha_threshold
            in_front = kf.depth_m < rendered - cfg.densify_depth_margin_m
            mask &= unseen | in_front
        if not bool(mask.any()):
            return 0
        new = surfels_from_rgbd(
            kf.rgb_u8.cpu().numpy(),
            kf.depth_m.cpu().numpy(),
            kf.T_wc,
            self.intr,
            mask=mask.cpu().numpy(),
            stride=cfg.densify_stride,
            opacity=cfg.init_opacity,
            scale_factor=cfg.init_scale_factor,
            max_stretch=cfg.init_max_stretch,
            min_depth=max(cfg.min_depth_m, cfg.near_m),
            max_depth=cfg.max_depth_m,
            device=self.device,
            dtype=self.dtype,
        )
        if len(new) == 0:
            return 0
        self._append(new)
        return len(new)

    def _append(self, new: SurfelMap) -> None:
        n_new = len(new)
        self.map = SurfelMap.cat([self.map.detach(), new.detach()])
        self._version += 1
        if self._adam.t is not None:
            self._adam.append(n_new)
        for k, h in self._h_train.items():
            self._h_train[k] = torch.cat([h, h.new_zeros((n_new, *h.shape[1:]))])
        self.stats.surfels_added += n_new

    def _keep(self, keep: Tensor) -> None:
        self.map = self.map.select(keep)
        self._version += 1
        self._adam.keep(keep)
        for k, h in self._h_train.items():
            self._h_train[k] = h[keep]

    @torch.no_grad()
    def prune(self) -> int:
        """Remove transparent, degenerate and non-finite surfels; returns how many went."""
        if self.n_surfels == 0:
            return 0
        cfg = self.config
        m = self.map
        finite = torch.ones(len(m), dtype=torch.bool, device=self.device)
        for t in m.parameters():
            finite &= torch.isfinite(t.reshape(len(m), -1)).all(-1)
        smax = m.scales().max(dim=-1).values
        remove = (m.opacities() < cfg.prune_opacity) | (smax > cfg.prune_max_scale_m) | (smax < cfg.prune_min_scale_m)
        remove |= ~finite
        n_nonfinite = int((~finite).sum())
        n_remove = int(remove.sum())
        if n_remove:
            self._keep(~remove)
            self.stats.surfels_pruned += n_remove - n_nonfinite
            self.stats.surfels_removed_nonfinite += n_nonfinite
            if n_nonfinite:
                log.warning("removed %d surfels with non-finite parameters", n_nonfinite)
        return n_remove

    # ----------------------------------------------------------------------------- optimising
    def _pick_views(self, newest: int | None) -> list[int]:
        """Keyframes of one step: per slot the newest (``newest_keyframe_prob``) or a random past one."""
        cfg = self.config
        k = len(self.keyframes)
        lo = max(0, k - cfg.keyframe_window) if cfg.keyframe_window else 0
        others = [i for i in range(lo, k) if i != newest]
        picked: list[int] = []
        for _ in range(min(cfg.views_per_iteration, k)):
            left = [i for i in others if i not in picked]
            can_newest = newest is not None and newest not in picked
            if can_newest and (not left or self._rng.random() < cfg.newest_keyframe_prob):
                picked.append(int(newest))
            elif left:
                picked.append(left[int(self._rng.integers(len(left)))])
        return picked

    def keyframe_loss(self, out: RenderOutput, kf: Keyframe) -> tuple[Tensor, dict[str, float]]:
        """The weighted 2DGS loss of one rendered keyframe, and its terms (for logs)."""
        cfg = self.config
        gt = kf.rgb01(self.dtype)
        terms: dict[str, Tensor] = {}
        terms["colour"] = losses.colour_loss(out.color, gt, cfg.lambda_dssim)
        terms["depth"] = losses.depth_l1(out.depth, kf.depth_m, kf.valid)
        if cfg.weight_normal > 0:
            terms["normal"] = losses.normal_consistency(out.normal, out.expected_depth(), out.alpha, self.intr)
        if cfg.weight_distortion > 0:
            terms["distortion"] = losses.distortion(out.distortion)
        weights = {
            "colour": cfg.weight_colour,
            "depth": cfg.weight_depth,
            "normal": cfg.weight_normal,
            "distortion": cfg.weight_distortion,
        }
        total = sum(weights[k] * v for k, v in terms.items())
        return total, {k: float(v.detach()) for k, v in terms.items()}

    def optimise(self, n_iters: int, newest: int | None = None) -> dict[str, float]:
        """Run ``n_iters`` optimiser steps over keyframe views; returns the last step's loss terms.

        A step whose loss or gradients are not finite is skipped (counted and logged), so no NaN
        ever reaches the map.
        """
        last: dict[str, float] = {}
        if not self.keyframes or self.n_surfels == 0:
            return last
        params = self.map.named_parameters()
        self.map.requires_grad_(True)
        self._adam.sync(params)
        trainable = {k: p for k, p in params.items() if k in self._adam.lrs}
        for _ in range(int(n_iters)):
            views = self._pick_views(newest)
            for p in params.values():
                p.grad = None
            total = None
            visible = torch.zeros(self.n_surfels, dtype=torch.bool, device=self.device)
            terms_acc: dict[str, float] = {}
            for i in views:
                kf = self.keyframes[i]
                out = self._render(kf.T_wc, self.config.weight_distortion > 0)
                loss, terms = self.keyframe_loss(out, kf)
                total = loss if total is None else total + loss
                visible |= out.visible
                terms_acc = {k: terms_acc.get(k, 0.0) + v / len(views) for k, v in terms.items()}
            assert total is not None
            total = total / len(views)
            if not bool(torch.isfinite(total)):
                self._skip_step("loss")
                continue
            total.backward()
            rows = visible.nonzero().squeeze(1)
            if not self._grads_finite(trainable, rows):
                self._skip_step("gradient")
                continue
            self._adam.step(trainable, rows)
            self._version += 1
            self.stats.steps += 1
            last = terms_acc | {"total": float(total.detach())}
        for p in params.values():
            p.grad = None
        self.map.requires_grad_(False)
        return last

    @staticmethod
    def _grads_finite(params: dict[str, Tensor], rows: Tensor) -> bool:
        """Whether every gradient is finite.

        Only the ``rows`` of the surfels in view can be non-zero (the render's gradient is exactly zero
        elsewhere), so on the CPU only those rows are checked (numba).
        """
        grads = [p.grad for p in params.values() if p.grad is not None]
        if _numba_rows_ok(params, rows):
            rows_np = rows.numpy()
            with KERNEL_LOCK:
                return all(_ADAM_KERNELS["rows_finite"](rows_np, g.view(g.shape[0], -1).numpy()) for g in grads)
        return all(bool(torch.isfinite(g).all()) for g in grads)

    def _skip_step(self, what: str) -> None:
        self.stats.steps_skipped_nonfinite += 1
        n = self.stats.steps_skipped_nonfinite
        log.warning("optimiser step skipped: non-finite %s (%d skipped so far)", what, n)

    def refine(self, n_iters: int) -> dict[str, float]:
        """``n_iters`` steps over uniformly random keyframes (no newest-keyframe preference), then prune."""
        out = self.optimise(n_iters, newest=None)
        self.prune()
        return out

    # ------------------------------------------------------------------------------- h_train
    @property
    def h_train(self) -> dict[str, Tensor]:
        """Diagonal Fisher of the training views, ``{param: tensor shaped like map.<param>}``.

        Kept aligned with the surfel set through densify/prune (new surfels start at zero). After :meth:`load` it
        is the saved one (``h_train.npz``) plus the keyframes inserted since; a map saved without it (before it was
        saved, or with ``track_h_train`` off) holds only the keyframes inserted since (the loaded ones have no images
        here): a warning says so, and ``NBVScorer.score(..., h_train=None)`` recomputes it from every keyframe pose.
        """
        if not self.h_train_complete and not self._warned_loaded_h_train:
            self._warned_loaded_h_train = True
            warnings.warn(
                f"Mapper.h_train holds the Fisher of the {len(self.keyframes)} keyframe(s) inserted here, not of the "
                f"{len(self.loaded_keyframe_ids)} read by load() (their images are not saved): give NBVScorer.score "
                "h_train=None to recompute it from every keyframe pose",
                RuntimeWarning,
                stacklevel=2,
            )
        self._h_train_read = True
        self._flush_fisher()
        return self._h_train

    @property
    def h_train_computed(self) -> bool:
        """Whether :attr:`h_train` is computed for every keyframe inserted (none waits for its lazy Fisher pass)."""
        return not self._fisher_pending

    @property
    def h_train_to_save(self) -> bool:
        """Whether :meth:`save` writes ``h_train.npz``: tracked, covering every keyframe, and computed or read before.

        A run that read it (every Fisher policy does) gets it saved with the last keyframes' passes done then: the lazy
        pass of the newest keyframe was still pending when ``roigsf map`` saved, so no Fisher run wrote the file. A run
        that never read it is not made to pay one Fisher pass per keyframe only to save it.
        """
        return self.config.track_h_train and self.h_train_complete and (self.h_train_computed or self._h_train_read)

    @property
    def h_train_complete(self) -> bool:
        """Whether :attr:`h_train` covers every keyframe of the map: built here, or loaded with its saved Fisher."""
        return not self.loaded_keyframe_ids or self.h_train_loaded

    def _reset_h_train(self) -> None:
        self._h_train = {}
        self._fisher_pending = []
        if self.config.track_h_train:
            params = self.map.named_parameters()
            for k in self.config.fisher_params:
                if k not in PARAM_NAMES:
                    raise InputError("mapper.fisher_params", f"unknown parameter {k!r}")
                if k in params:
                    self._h_train[k] = torch.zeros_like(params[k].detach())

    def keyframe_fisher(self, kf: Keyframe) -> dict[str, Tensor]:
        """Diagonal Fisher of one keyframe view under the current map (pixels with valid depth)."""
        full = {k: torch.zeros_like(v.detach()) for k, v in self.map.named_parameters().items()}
        full = {k: full[k] for k in self.config.fisher_params if k in full}
        idx = self._frustum_subset(kf.T_wc)
        if idx.numel() == 0:
            return full
        sub = fisher_diag(
            self.map.detach().select(idx),
            kf.T_wc,
            self.intr,
            outputs=self.config.fisher_outputs,
            params=tuple(full),
            pixel_weights=kf.valid.to(self.dtype),
            near=self.config.near_m,
        )
        for k, f in sub.items():
            if k in full:
                full[k].index_copy_(0, idx, torch.nan_to_num(f, nan=0.0, posinf=0.0, neginf=0.0))
        return full

    def _flush_fisher(self) -> None:
        pending, self._fisher_pending = self._fisher_pending, []
        if self.n_surfels == 0:
            return
        for kf in pending:
            for k, f in self.keyframe_fisher(kf).items():
                if k in self._h_train:
                    self._h_train[k] += f

    def recompute_h_train(self) -> dict[str, Tensor]:
        """Recompute ``h_train`` as the sum of every keyframe's Fisher under the current map."""
        self._reset_h_train()
        if self.config.track_h_train:
            self._fisher_pending = list(self.keyframes)
        return self.h_train

    def covered_mask(self, T_wc: np.ndarray) -> np.ndarray:
        """Bool [H, W]: the pixels where the map at ``T_wc`` renders alpha of at least ``densify_alpha_threshold``."""
        return (self.render(T_wc).alpha >= self.config.densify_alpha_threshold).cpu().numpy()

    def render_rgb_depth(self, T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The map at ``T_wc`` as evaluation sees it: rgb [H, W, 3] float in [0, 1], depth_m [H, W] (``eval_depth``)."""
        out = self.render(T_wc)
        rgb = out.color.clamp(0, 1).cpu().numpy()
        return rgb, self.render_depth(out, self.config.eval_depth).cpu().numpy()

    # ---------------------------------------------------------------------------------- mesh
    def rendered_rgbd(
        self, T_wc: np.ndarray, depth_mode: str | None = None, min_alpha: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The map's own RGB-D at ``T_wc``, as TSDF fusion takes it: depth_m [H, W] float32, rgb [H, W, 3] uint8.

        Depth is the ``depth_mode`` depth (default ``mesh_depth``), 0 where the accumulated alpha is below
        ``min_alpha`` (default ``mesh_min_alpha``): the mesh and the NBV scoring TSDF fuse exactly this.
        """
        cfg = self.config
        out = self.render(T_wc)
        depth = self.render_depth(out, cfg.mesh_depth if depth_mode is None else depth_mode)
        lo = cfg.mesh_min_alpha if min_alpha is None else float(min_alpha)
        depth = torch.where(out.alpha >= lo, depth, 0.0).cpu().numpy().astype(np.float32)
        rgb = (out.color.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
        return depth, rgb

    def mesh(self, poses: Iterable[np.ndarray] | None = None) -> o3d.geometry.TriangleMesh:
        """TSDF + marching-cubes mesh of rendered depth at ``poses`` (default: every keyframe's, loaded and added)."""
        # open3d is imported here, not with the module: mapping itself needs only torch (and numba on the CPU),
        # so the mapper runs on a machine without open3d, e.g. a GPU box (scripts/device_check.sh).
        from roigsf_ros.mapping.tsdf import tsdf_mesh_from_depths

        cfg = self.config
        if poses is None:
            poses = self.map_keyframes()[1]
        poses = list(poses)

        def frames() -> Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]]:
            for T in poses:
                depth, rgb = self.rendered_rgbd(T)
                yield depth, T, rgb

        return tsdf_mesh_from_depths(
            frames(),
            self.intr,
            voxel_size_m=cfg.mesh_voxel_size_m,
            sdf_trunc_m=cfg.mesh_sdf_trunc_m,
            depth_max_m=cfg.max_depth_m,
        )

    # ------------------------------------------------------------------------------ save/load
    def save(self, out_dir: str | Path) -> None:
        """Write ``map.ply`` (2DGS layout), ``keyframes.json`` (every keyframe of :meth:`map_keyframes`, loaded
        ones first; intrinsics, config) and, when it is computed and covers every keyframe, ``h_train.npz`` (the
        training Fisher the NBV score divides by), so that ``Mapper.load(d).save(d2)`` keeps the keyframes of ``d`` and
        a resumed map scores views as the one saved. (A run that never read :attr:`h_train` left it lazy: computing it
        only to save it would cost every such run one Fisher pass per keyframe; :attr:`h_train_to_save`.) Each file is
        written atomically; an ``h_train.npz`` already in ``out_dir`` that this save does not replace is removed (it
        was another map's).
        """
        out = Path(out_dir)
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:  # a regular file on the way: said as the package's error, naming the folder
            raise InputError(out, f"cannot create the map folder: {exc.strerror or exc}") from None
        saved_h_train, with_h_train = out / H_TRAIN_FILE, self.h_train_to_save
        if not with_h_train:  # another map's Fisher saved here before would not match this map: load refused it
            saved_h_train.unlink(missing_ok=True)
        self.map.save_ply(out / "map.ply")
        write_map_meta(out / "keyframes.json", *self.map_keyframes(), self.intr, self.config)
        if with_h_train:
            write_h_train(saved_h_train, self.h_train)

    @classmethod
    def load(cls, in_dir: str | Path, config: MapperConfig | None = None) -> Mapper:
        """A mapper with the map and keyframe poses of :meth:`save` (keyframe images are not stored).

        Everything is read and checked (:func:`read_map_meta`, :meth:`SurfelMap.load_ply`) before the
        mapper is built, and every error is an InputError naming the file (and the field), so a
        caller that keeps a map can keep it when the folder is bad. ``config`` replaces the saved one.
        """
        d = Path(in_dir)
        if not d.is_dir():  # said as a folder, not as its keyframes.json not found
            raise InputError(d, "is a file, not a saved map folder" if d.exists() else "no such map folder")
        meta_path = d / "keyframes.json"
        meta = read_map_meta(meta_path, with_config=config is None)
        surfel_map = SurfelMap.load_ply(d / "map.ply", dtype=torch.float32)  # on the CPU until the mapper exists
        try:
            mapper = cls(meta.intrinsics, config if config is not None else meta.config)
        except InputError as exc:
            if config is not None:  # the caller's own config
                raise
            raise InputError(meta_path, f"field 'config': {exc}") from None
        mapper.map = surfel_map.to(device=mapper.device, dtype=mapper.dtype)
        mapper._version += 1
        mapper._adam = _SparseAdam(mapper.config.learning_rates())
        mapper._reset_h_train()
        mapper.loaded_keyframe_ids = meta.keyframe_ids
        mapper.loaded_keyframe_poses = meta.keyframe_poses
        saved = d / H_TRAIN_FILE
        if mapper.config.track_h_train and saved.is_file():
            shapes = {k: tuple(v.shape) for k, v in mapper._h_train.items()}
            h = read_h_train(saved, len(surfel_map), shapes, covers_only=config is not None)
            if h is not None:
                mapper._h_train = {k: v.to(device=mapper.device, dtype=mapper.dtype) for k, v in h.items()}
                mapper.h_train_loaded = True
        return mapper


def _config_from_json(values: object, path: Path) -> MapperConfig:
    """A saved map's config, each field's type checked first: InputError naming the file and the field.

    :meth:`MapperConfig.from_dict` alone would let a value of the wrong type through to ``validate``
    (a TypeError there) and name no file.
    """
    if not isinstance(values, dict):
        raise InputError(path, f"field 'config' must be an object of MapperConfig fields, got {_json_kind(values)}")
    defaults = {f.name: f.default for f in fields(MapperConfig)}
    kw: dict[str, object] = {}
    for name, value in values.items():
        if name not in defaults:
            raise InputError(path, f"unknown config field '{name}' (not a MapperConfig field)")
        default = defaults[name]
        if isinstance(default, tuple):
            ok = isinstance(value, list) and all(isinstance(v, str) for v in value)
        elif isinstance(default, bool) or isinstance(value, bool):
            ok = isinstance(value, bool) and isinstance(default, bool)
        elif isinstance(default, float):
            ok = isinstance(value, int | float)
            value = float(value) if ok else value
        else:  # int or str: exactly that type (a field without a default is left to the constructor)
            ok = default is MISSING or isinstance(value, type(default))
        if not ok:
            raise InputError(path, f"config field '{name}' must be {type(default).__name__}, got {value!r:.80}")
        kw[name] = value
    try:
        return MapperConfig.from_dict(kw)
    except InputError as exc:
        raise InputError(path, f"config field '{exc.where.removeprefix('mapper.')}': {exc.problem}") from None


def _json_kind(value: object) -> str:
    """How a JSON value reads in an error: 'a list', 'a string', ..."""
    names = {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null"}
    return names.get(type(value), "a number")


H_TRAIN_FILE = "h_train.npz"
"""A saved map's running training Fisher, one array per parameter shaped as the map's (:meth:`Mapper.save`)."""


def write_h_train(path: str | Path, h_train: dict[str, Tensor]) -> None:
    """Write ``h_train`` (``{param: [N, ...] tensor}``) as ``path`` (an ``.npz``, float32), atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **{k: v.detach().cpu().numpy().astype(np.float32) for k, v in h_train.items()})


def read_h_train(
    path: str | Path, n_surfels: int, shapes: dict[str, tuple[int, ...]], covers_only: bool = False
) -> dict[str, Tensor] | None:
    """A saved map's ``h_train.npz``, checked against the map it belongs to: each of ``shapes``' parameters (the
    mapper's ``fisher_params``) present with its shape and finite, non-negative values; an InputError names the file.
    ``covers_only``: None instead of an error when a parameter is missing (a caller's own config that asks for
    other parameters than the saved map's; the Fisher is then recomputed from the poses).
    """
    where = Path(path)
    try:
        with np.load(where, allow_pickle=False) as data:
            arrays = {k: np.asarray(data[k]) for k in data.files}
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(where, f"not a readable training-Fisher file ({exc})") from None
    if covers_only and not set(shapes) <= set(arrays):
        return None
    out: dict[str, Tensor] = {}
    for name, shape in shapes.items():
        if name not in arrays:
            raise InputError(where, f"no array '{name}' (the map's fisher_params need it); it holds {sorted(arrays)}")
        a = arrays[name]
        want = (n_surfels, *shape[1:])
        if a.shape != want:
            raise InputError(where, f"array '{name}' has shape {list(a.shape)}, the map's {n_surfels} surfels need "
                             f"{list(want)} (another map's? without the file the map loads and its training Fisher is "
                             "recomputed from the keyframe poses)")  # fmt: skip
        if not (np.isfinite(a).all() and (a >= 0).all()):
            raise InputError(where, f"array '{name}' holds values that are not finite and >= 0 (a Fisher diagonal)")
        out[name] = torch.from_numpy(a.astype(np.float32))
    return out


@dataclass
class MapMeta:
    """The checked contents of a saved map's ``keyframes.json``."""

    intrinsics: Intrinsics
    keyframe_ids: list[int]
    keyframe_poses: np.ndarray  # [K, 4, 4] float64 camera-to-world
    config: MapperConfig | None  # None when not read (the caller brings its own)


_INTRINSICS_REQUIRED = ("width", "height", "fx", "fy", "cx", "cy")


def write_map_meta(
    path: str | Path, keyframe_ids: list[int], keyframe_poses: np.ndarray, intr: Intrinsics, config: MapperConfig
) -> None:
    """Write a saved map's ``keyframes.json`` (atomically), as :func:`read_map_meta` reads it.

    The one writer of the layout, for :meth:`Mapper.save` and the shared map's saves alike.
    """
    if len(keyframe_ids) != len(keyframe_poses):
        raise ValueError(f"{path}: {len(keyframe_poses)} keyframe poses for {len(keyframe_ids)} keyframe ids")
    write_json(
        path,
        {
            "keyframe_ids": [int(i) for i in keyframe_ids],
            "keyframe_poses": [np.asarray(T, dtype=np.float64).tolist() for T in keyframe_poses],
            "intrinsics": asdict(intr),
            "config": config.to_dict(),
        },
    )


def read_map_meta(path: str | Path, with_config: bool = True) -> MapMeta:
    """Read and check every field of a saved map's ``keyframes.json``; InputError naming the file and the field.

    Nothing is built from a file that fails: a JSON list instead of an object, a missing or unknown
    intrinsics key, a non-numeric width, a pose that is not rigid, ids and poses of different
    lengths, a bad config value. ``with_config=False`` skips the saved config (the caller has its own).
    """
    path = Path(path)
    try:
        meta = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, "not found (not a saved map folder)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(path, f"cannot read: {exc}") from None
    if not isinstance(meta, dict):
        raise InputError(path, f"expected a JSON object with 'intrinsics', 'keyframe_ids', ..., got {_json_kind(meta)}")

    cam = meta.get("intrinsics")
    if not isinstance(cam, dict):
        raise InputError(path, f"field 'intrinsics' must be an object, got {_json_kind(cam)}")
    known = [f.name for f in fields(Intrinsics)]
    for key in cam:
        if key not in known:
            raise InputError(path, f"field 'intrinsics.{key}' is unknown (expected {', '.join(known)})")
    for key in _INTRINSICS_REQUIRED:
        if key not in cam:
            raise InputError(path, f"field 'intrinsics.{key}' is missing")
    values: dict[str, Any] = {}
    for key, v in cam.items():
        try:
            ok = not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)
        except OverflowError:  # an integer too large for a float
            ok = False
        whole = key in ("width", "height")
        if not ok or (whole and v != int(v)) or (key not in ("cx", "cy") and v <= 0):
            need = "a positive whole number" if whole else "a finite number" + ("" if key in ("cx", "cy") else " > 0")
            raise InputError(path, f"field 'intrinsics.{key}' must be {need}, got {v!r}")
        values[key] = int(v) if whole else float(v)
    intr = Intrinsics(**values)

    ids = meta.get("keyframe_ids", [])
    if not isinstance(ids, list) or not all(isinstance(i, int) and not isinstance(i, bool) for i in ids):
        raise InputError(path, f"field 'keyframe_ids' must be a list of integers, got {ids!r:.80}")
    raw_poses = meta.get("keyframe_poses", [])
    if not isinstance(raw_poses, list):
        raise InputError(path, f"field 'keyframe_poses' must be a list of 4x4 matrices, got {_json_kind(raw_poses)}")
    poses = []
    for i, T in enumerate(raw_poses):
        where = f"{path}: field 'keyframe_poses[{i}]'"
        try:
            arr = np.asarray(T, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(where, f"must be a 4x4 matrix of numbers, got {T!r:.80}") from None
        poses.append(load_pose(arr, where, source=str(path)))
    if len(poses) != len(ids):
        raise InputError(path, f"field 'keyframe_poses' has {len(poses)} poses for {len(ids)} keyframe_ids")

    config = _config_from_json(meta.get("config", {}), path) if with_config else None  # its device checked too
    stacked = np.stack(poses) if poses else np.zeros((0, 4, 4))
    return MapMeta(intrinsics=intr, keyframe_ids=list(ids), keyframe_poses=stacked, config=config)


__all__ = [
    "DEPTH_MODES",
    "H_TRAIN_FILE",
    "Keyframe",
    "MapMeta",
    "Mapper",
    "MapperConfig",
    "MapperStats",
    "depth_scale_note",
    "read_h_train",
    "read_map_meta",
    "valid_depth_mask",
    "write_h_train",
    "write_map_meta",
]
