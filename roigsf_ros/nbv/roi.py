"""View region of interest (ROI-GSurFisher Eq. 7-8): TSDF surface voxels weighted and splatted into a candidate.

For a candidate camera the near-surface TSDF voxels that face it, lie in its frustum and are not hidden
behind a nearer surface (:func:`voxel_visibility`) each get a geometric weight (Eq. 7)

    W(l, x) = W_angle^beta * W_scale^gamma * (1 + mu * W_cover),

- ``W_angle``: a Gaussian bump (``angle_sigma_deg``) of the incidence angle (between the voxel's outward
  normal and the direction to the camera) around a preferred angle, ``angle_pref_texture_poor_deg``
  (30 deg) where the surface is texture-poor and ``angle_pref_texture_rich_deg`` (40 deg) where it is
  texture-rich (:func:`voxel_texture` classifies voxels once per scoring call);
- ``W_scale``: a Gaussian bump in log scale (``footprint_sigma_ln``) of the voxel's projected footprint
  ``f * voxel_size / z`` pixels around ``footprint_pref_px`` (2.5 px);
- ``W_cover = 1 / max(w, 1)``: the inverse TSDF fusion weight (frames fused), 1 for a voxel seen once;

and is splatted into an [H, W] map with a bilinear (tent) kernel K (Eq. 8). The kernel's half-width is
``max(1, footprint_px)`` pixels: exactly bilinear for voxels smaller than a pixel, widened for nearer
voxels so that their splats tile the projected surface instead of leaving dotted holes.

Norm of Eq. 8 (the paper does not define it) is, per pixel, ``sum K W / max(sum K, 1) / (1 + mu)``:
the kernel-weighted mean voxel weight (so a pixel's weight does not grow with the number of voxels that
land in it, which would let far surfaces, packing many voxels per pixel, beat the footprint preference),
scaled down where the kernel mass is below one voxel (silhouette edges), divided by the largest
possible ``W``. W_roi is therefore in [0, 1] on the same absolute scale for every candidate, so Eq. 9's
sums are comparable across candidates (a per-candidate max-normalisation would not be). Pixels no
visible voxel reaches are exactly 0 (outside the ROI).

Visibility runs as three compiled numba passes (frustum, z-buffer + occlusion test, splat entries) when
numba is installed, else as the vectorised numpy reference; both give the same result (tested).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from roigsf_ros.core.camera import Intrinsics, check_pose
from roigsf_ros.core.errors import InputError
from roigsf_ros.mapping.tsdf import SurfaceVoxels
from roigsf_ros.nbv.config import NBVConfig
from roigsf_ros.render.numba_setup import KERNEL_LOCK, Kernels, n_threads, numba_available, prange
from roigsf_ros.render.surfels import SurfelMap
from roigsf_ros.render.vecmath import acos_unit, exp_nonpositive

_N_WORKERS = 2
"""Threads of the texture test's KD-tree query (the project targets 2 cores; results do not depend on it)."""
_LONE_MIN_VOXELS = 4096
"""Below this many surface voxels a lone camera's ROI stays on one thread (splitting costs more than it saves)."""
LUMA_RGB = np.array([0.299, 0.587, 0.114])
"""ITU-R BT.601 luma weights, for the texture measure of :func:`voxel_texture`."""


@dataclass
class VoxelView:
    """The surface voxels one camera sees (front-facing, in its frustum, not occluded), K of them.

    ``index`` [K] int64 rows into the SurfaceVoxels arrays; ``u_px``, ``v_px`` [K] projection (pixel
    centre = integer); ``z_m`` [K] camera depth; ``cos_incidence`` [K] in (0, 1], cosine between the
    outward normal and the direction to the camera; ``footprint_px`` [K] = f * voxel_size / z.
    """

    index: np.ndarray
    u_px: np.ndarray
    v_px: np.ndarray
    z_m: np.ndarray
    cos_incidence: np.ndarray
    footprint_px: np.ndarray
    splat: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    """Tent-kernel splats of these voxels (flat pixel [E], row into this view [E], kernel [E]), if kept."""

    def __len__(self) -> int:
        return int(self.index.shape[0])


@dataclass
class ViewROI:
    """ROI of one candidate: the map ``weights`` [H, W] (W_roi in [0, 1]) and its per-voxel parts.

    ``view`` holds the visible voxels; ``voxel_weight`` [K] is W(l, x) of Eq. 7 and ``w_angle``,
    ``w_scale``, ``w_cover`` [K] its factors; ``textured`` [K] the texture class used for the angle.
    """

    weights: np.ndarray
    view: VoxelView
    voxel_weight: np.ndarray
    w_angle: np.ndarray
    w_scale: np.ndarray
    w_cover: np.ndarray
    textured: np.ndarray

    @property
    def n_pixels(self) -> int:
        """Number of ROI pixels (weight > 0)."""
        return int(np.count_nonzero(self.weights > 0))

    @property
    def mass(self) -> float:
        """Sum of the ROI weights over the image."""
        return float(self.weights.sum())


# ------------------------------------------------------------------------------- voxel weights
def incidence_weight(theta_deg: np.ndarray, textured: np.ndarray, cfg: NBVConfig) -> np.ndarray:
    """W_angle [K]: Gaussian bump of the incidence angle around 30 deg (texture-poor) / 40 deg (texture-rich)."""
    theta = np.asarray(theta_deg, dtype=np.float64)
    pref = np.where(np.asarray(textured, bool), cfg.angle_pref_texture_rich_deg, cfg.angle_pref_texture_poor_deg)
    return np.exp(-0.5 * ((theta - pref) / cfg.angle_sigma_deg) ** 2)


def footprint_weight(footprint_px: np.ndarray, cfg: NBVConfig) -> np.ndarray:
    """W_scale [K]: Gaussian bump of ln(footprint) around ln(2.5 px); symmetric in scale ratios."""
    fp = np.maximum(np.asarray(footprint_px, dtype=np.float64), 1e-12)
    return np.exp(-0.5 * (np.log(fp / cfg.footprint_pref_px) / cfg.footprint_sigma_ln) ** 2)


def coverage_weight(tsdf_weight: np.ndarray) -> np.ndarray:
    """W_cover [K] = 1 / max(w, 1): the inverse TSDF fusion weight (frame count), at most 1."""
    return 1.0 / np.maximum(np.asarray(tsdf_weight, dtype=np.float64), 1.0)


def voxel_weight(
    theta_deg: np.ndarray, textured: np.ndarray, footprint_px: np.ndarray, tsdf_weight: np.ndarray, cfg: NBVConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 7: ``W = W_angle^beta W_scale^gamma (1 + mu W_cover)`` [K], with the three factors."""
    wa = incidence_weight(theta_deg, textured, cfg)
    ws = footprint_weight(footprint_px, cfg)
    wc = coverage_weight(tsdf_weight)
    return wa**cfg.beta * ws**cfg.gamma * (1.0 + cfg.mu * wc), wa, ws, wc


def voxel_texture(
    centres_m: np.ndarray,
    surfel_map: SurfelMap | None,
    voxel_size_m: float,
    cfg: NBVConfig,
    only: np.ndarray | None = None,
) -> np.ndarray:
    """Bool [M]: voxels on texture-rich surface (luma std of nearby surfel colours >= threshold).

    Texture is measured in 3D, once per scoring call, not in each candidate's image: the standard
    deviation of the luma of the map's (view-independent, SH degree 0) surfel colours among the
    ``texture_max_neighbours`` nearest surfels within ``texture_radius_voxels`` voxels of the voxel. It is
    a property of the surface, as the paper's texture-poor/rich regions are, and costs one KD-tree query
    instead of a render per candidate. Fewer than ``texture_min_neighbours`` surfels: texture-poor.
    ``only`` [M] bool: classify just these voxels (the rest come back False), e.g. :func:`frustum_union`'s.
    """
    centres = np.asarray(centres_m, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(len(centres), dtype=bool)
    if only is not None:
        if np.shape(only) != (len(centres),):
            raise InputError("only", f"expected shape [{len(centres)}], got {list(np.shape(only))}")
        sel = np.flatnonzero(only)
        if len(sel) < len(centres):
            out[sel] = voxel_texture(centres[sel], surfel_map, voxel_size_m, cfg)
            return out
    if surfel_map is None or len(surfel_map) < cfg.texture_min_neighbours or len(centres) == 0:
        return out
    with torch.no_grad():
        means = surfel_map.means.detach().to("cpu", torch.float64).numpy()
        luma = (0.5 + 0.28209479177387814 * surfel_map.sh_dc.detach().to("cpu", torch.float64).numpy()) @ LUMA_RGB
    k = int(min(cfg.texture_max_neighbours, len(means)))
    radius = cfg.texture_radius_voxels * voxel_size_m
    dist, idx = cKDTree(means).query(centres, k=k, distance_upper_bound=radius, workers=_N_WORKERS)
    dist, idx = dist.reshape(len(centres), k), idx.reshape(len(centres), k)
    ok = np.isfinite(dist)
    vals = np.where(ok, luma[np.minimum(idx, len(means) - 1)], 0.0)
    cnt = ok.sum(1)
    mean = vals.sum(1) / np.maximum(cnt, 1)
    var = (np.where(ok, vals - mean[:, None], 0.0) ** 2).sum(1) / np.maximum(cnt, 1)
    return (cnt >= cfg.texture_min_neighbours) & (np.sqrt(var) >= cfg.texture_std_threshold)


# ---------------------------------------------------------------------------------- visibility
def _splat_entries(
    u: np.ndarray, v: np.ndarray, half_width_px: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tent-kernel splats of points (u, v) [K] with per-point half-widths ``s`` [K] (>= 1 px).

    Returns flat pixel ids [E], point rows [E] and kernel values [E] >= 0, ``K = (1 - |dx|/s)(1 - |dy|/s)``
    (0 for pixels off the image, whose ids are clipped onto it). Points are grouped by ``ceil(s)`` so each
    group is one vectorised block of (2 ceil(s))^2 pixels; with s = 1 this is the bilinear kernel.
    """
    R = np.ceil(half_width_px - 1e-9).astype(np.int64)
    groups = np.unique(R)
    pix_l, row_l, k_l = [], [], []
    for r in groups:
        sel = np.arange(len(R)) if len(groups) == 1 else np.flatnonzero(r == R)
        offs = np.arange(-r + 1, r + 1)
        us, vs, s = u[sel, None], v[sel, None], half_width_px[sel, None]
        xs = np.floor(us).astype(np.int64) + offs  # [n, 2r]
        ys = np.floor(vs).astype(np.int64) + offs
        kx = np.maximum(0.0, 1.0 - np.abs(xs - us) / s) * ((xs >= 0) & (xs < width))
        ky = np.maximum(0.0, 1.0 - np.abs(ys - vs) / s) * ((ys >= 0) & (ys < height))
        n = len(sel)
        k_l.append((ky[:, :, None] * kx[:, None, :]).reshape(n * 4 * r * r))
        pix = (np.clip(ys, 0, height - 1) * width)[:, :, None] + np.clip(xs, 0, width - 1)[:, None, :]
        pix_l.append(pix.reshape(n * 4 * r * r))
        row_l.append(np.repeat(sel, 4 * r * r))
    if not pix_l:
        z = np.zeros(0, dtype=np.int64)
        return z, z, np.zeros(0)
    if len(pix_l) == 1:
        return pix_l[0], row_l[0], k_l[0]
    return np.concatenate(pix_l), np.concatenate(row_l), np.concatenate(k_l)


def _camera_geometry(
    voxels: SurfaceVoxels, T_wc: np.ndarray, intr: Intrinsics, voxel_size_m: float, cfg: NBVConfig
) -> dict[str, np.ndarray]:
    """In-frustum voxels of a camera: rows, projection, depth, incidence cosine and footprint (all [F])."""
    T = check_pose(T_wc, "T_wc")
    R, c = T[:3, :3], T[:3, 3]
    rel = np.asarray(voxels.centres_m, dtype=np.float64) - c  # camera centre -> voxel, world frame
    pc = rel @ R  # camera frame
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * pc[:, 0] / z + intr.cx
        v = intr.fy * pc[:, 1] / z + intr.cy
    ok = (z > cfg.near_m) & (z <= cfg.far_m)
    ok &= (u >= -0.5) & (u < intr.width - 0.5) & (v >= -0.5) & (v < intr.height - 0.5)
    rows = np.flatnonzero(ok)
    rel, z, u, v = rel[rows], z[rows], u[rows], v[rows]
    dist = np.linalg.norm(rel, axis=1)
    cos = -(np.asarray(voxels.normals)[rows] * rel).sum(1) / np.maximum(dist, 1e-12)
    f = math.sqrt(intr.fx * intr.fy)
    return {"rows": rows, "u": u, "v": v, "z": z, "cos": cos, "footprint": f * voxel_size_m / z, "f": np.array(f)}


def voxel_visibility(
    voxels: SurfaceVoxels,
    T_wc: np.ndarray,
    intr: Intrinsics,
    voxel_size_m: float,
    cfg: NBVConfig,
    backend: str = "auto",
) -> VoxelView:
    """Surface voxels that camera ``T_wc`` sees: front-facing (n . (c - x) > 0), in the frustum, unoccluded.

    Occlusion: every in-frustum voxel (whatever its facing) is splatted into a z-buffer with the same
    footprint-sized tent support as the ROI; a voxel is hidden when it lies more than a tolerance behind
    the z-buffer at its pixel. The tolerance is the surface band seen along the ray plus the depth change
    of a tilted surface across the splat support: ``(occlusion_tol_voxels * voxel_size + s z / f sin t) / cos t``
    with ``s`` the support in pixels and ``cos t`` clamped at ``occlusion_min_cos``. The clamp keeps grazing
    voxels (whose TSDF normals are the least reliable) from seeing through nearer surfaces; the price, some
    self-occlusion of surfaces seen at more than ~60 deg, costs little since both W_angle and cos/z are small there.

    ``backend``: ``"numba"`` (one compiled pass per stage, CPU), ``"numpy"`` (the vectorised reference)
    or ``"auto"`` (numba when installed); both give the same view up to float rounding.
    """
    if backend not in ("auto", "numba", "numpy"):
        raise InputError("backend", f"must be 'auto', 'numba' or 'numpy', got {backend!r}")
    if backend == "numba" or (backend == "auto" and numba_available()):
        return _visibility_numba(voxels, check_pose(T_wc, "T_wc"), intr, voxel_size_m, cfg)
    g = _camera_geometry(voxels, T_wc, intr, voxel_size_m, cfg)
    rows, u, v, z, cos, fp = g["rows"], g["u"], g["v"], g["z"], g["cos"], g["footprint"]
    front = cos > 0.0
    if not front.any():
        e = np.zeros(0)
        return VoxelView(np.zeros(0, dtype=np.int64), e, e, e, e, e)
    W, H = intr.width, intr.height
    support = np.clip(fp, 1.0, cfg.max_splat_radius_px)
    pix, row, k = _splat_entries(u, v, support, W, H)
    zbuf = torch.full((W * H,), math.inf, dtype=torch.float64)
    z_e = np.where(k > 0, z[row], math.inf)
    zbuf.scatter_reduce_(0, torch.from_numpy(pix), torch.from_numpy(z_e), reduce="amin")
    own = (np.clip(np.floor(v + 0.5), 0, H - 1) * W + np.clip(np.floor(u + 0.5), 0, W - 1)).astype(np.int64)
    cos_c = np.clip(cos, cfg.occlusion_min_cos, 1.0)
    sin_c = np.sqrt(1.0 - cos_c**2)
    tol = (cfg.occlusion_tol_voxels * voxel_size_m + support * z / g["f"] * sin_c) / cos_c
    keep = front & (z <= zbuf.numpy()[own] + tol)
    # The visible voxels' splats, reused by the ROI: entries of kept voxels, rows renumbered.
    new_row = np.cumsum(keep) - 1
    e_keep = keep[row] & (k > 0)
    splat = (pix[e_keep], new_row[row[e_keep]], k[e_keep])
    return VoxelView(rows[keep], u[keep], v[keep], z[keep], cos[keep], fp[keep], splat)


def _visibility_numba(
    voxels: SurfaceVoxels, T: np.ndarray, intr: Intrinsics, voxel_size_m: float, cfg: NBVConfig
) -> VoxelView:
    """:func:`voxel_visibility` with the numba kernels (same rules, no [voxels x pixels] temporaries)."""
    centres = np.ascontiguousarray(voxels.centres_m, dtype=np.float64).reshape(-1, 3)
    normals = np.ascontiguousarray(voxels.normals, dtype=np.float64).reshape(-1, 3)
    m = len(centres)
    R = np.ascontiguousarray(T[:3, :3], dtype=np.float64)
    c = np.ascontiguousarray(T[:3, 3], dtype=np.float64)
    W, H = intr.width, intr.height
    f = math.sqrt(intr.fx * intr.fy)
    rows = np.empty(m, np.int64)
    geo = np.empty((m, 5))  # u, v, z, cos, footprint
    k = _KERNELS
    n_in = k["geometry"](centres, normals, R, c, float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy),
                         W, H, float(cfg.near_m), float(cfg.far_m), f * voxel_size_m, rows, geo)  # fmt: skip
    geo = geo[:n_in]
    keep = np.zeros(n_in, np.bool_)
    n_entries = k["visibility"](geo, W, H, float(cfg.max_splat_radius_px), f, float(cfg.occlusion_tol_voxels) *
                                voxel_size_m, float(cfg.occlusion_min_cos), np.full(W * H, np.inf), keep)  # fmt: skip
    n_keep = int(keep.sum())
    pix = np.empty(n_entries, np.int64)
    row = np.empty(n_entries, np.int64)
    kv = np.empty(n_entries)
    n_e = k["splat"](geo, keep, W, H, float(cfg.max_splat_radius_px), pix, row, kv)
    g = geo[keep]
    return VoxelView(rows[:n_in][keep], g[:, 0].copy(), g[:, 1].copy(), g[:, 2].copy(), g[:, 3].copy(),
                     g[:, 4].copy(), (pix[:n_e], row[:n_e], kv[:n_e]) if n_keep else None)  # fmt: skip


def _geometry(
    centres: np.ndarray,
    normals: np.ndarray,
    R: np.ndarray,
    c: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    near: float,
    far: float,
    f_vox: float,
    rows: np.ndarray,
    geo: np.ndarray,
) -> int:
    """In-frustum voxels (numba helper), as :func:`_camera_geometry`: rows, then u, v, z, cos, footprint per row."""
    n = 0
    for i in range(centres.shape[0]):
        r0 = centres[i, 0] - c[0]
        r1 = centres[i, 1] - c[1]
        r2 = centres[i, 2] - c[2]
        z = r0 * R[0, 2] + r1 * R[1, 2] + r2 * R[2, 2]
        if not (z > near and z <= far):
            continue
        u = fx * (r0 * R[0, 0] + r1 * R[1, 0] + r2 * R[2, 0]) / z + cx
        v = fy * (r0 * R[0, 1] + r1 * R[1, 1] + r2 * R[2, 1]) / z + cy
        if not (u >= -0.5 and u < width - 0.5 and v >= -0.5 and v < height - 0.5):
            continue
        dist = max(np.sqrt(r0 * r0 + r1 * r1 + r2 * r2), 1e-12)
        rows[n] = i
        geo[n, 0] = u
        geo[n, 1] = v
        geo[n, 2] = z
        geo[n, 3] = -(normals[i, 0] * r0 + normals[i, 1] * r1 + normals[i, 2] * r2) / dist
        geo[n, 4] = f_vox / z
        n += 1
    return n


def _bilinear(u: float, v: float, s: float, width: int, height: int) -> tuple[int, float, float, float, float]:
    """The tent splat's common case (numba helper): a point under one pixel (``s == 1``) whose 2x2 pixels lie in the
    image. Returns the flat index of its top-left pixel and the kernel factors kx0, kx1, ky0, ky1 of the columns and
    rows, written as the general loops of :func:`_zbuffer` and :func:`_accumulate` compute them (the same values to
    the bit); index -1 (and zeros) where those loops must run.
    """
    bx = int(np.floor(u))
    by = int(np.floor(v))
    if not (s == 1.0 and bx >= 0 and by >= 0 and bx + 1 < width and by + 1 < height):
        return -1, 0.0, 0.0, 0.0, 0.0
    kx0 = 1.0 - abs(bx - u)  # > 0: bx = floor(u)
    kx1 = max(0.0, 1.0 - abs(bx + 1 - u))
    ky0 = 1.0 - abs(by - v)
    ky1 = max(0.0, 1.0 - abs(by + 1 - v))
    return by * width + bx, kx0, kx1, ky0, ky1


def _zbuffer(geo: np.ndarray, n: int, width: int, height: int, max_r: float, zbuf: np.ndarray) -> None:
    """Lowers ``zbuf`` [H W] to the depth of the first ``n`` rows of ``geo``'s tent splats (numba helper)."""
    for i in range(n):
        u, v, z = geo[i, 0], geo[i, 1], geo[i, 2]
        s = min(max(geo[i, 4], 1.0), max_r)
        p, _, kx1, _, ky1 = _bilinear(u, v, s, width, height)
        if p >= 0:  # the common case: the loop's 2x2 pixels, the first always covered
            if z < zbuf[p]:
                zbuf[p] = z
            if kx1 > 0.0 and z < zbuf[p + 1]:
                zbuf[p + 1] = z
            if ky1 > 0.0 and z < zbuf[p + width]:
                zbuf[p + width] = z
            if kx1 > 0.0 and ky1 > 0.0 and z < zbuf[p + width + 1]:
                zbuf[p + width + 1] = z
            continue
        bx = int(np.floor(u))
        by = int(np.floor(v))
        r = int(np.ceil(s - 1e-9))
        for oy in range(-r + 1, r + 1):
            y = by + oy
            if y < 0 or y >= height:
                continue
            ky = max(0.0, 1.0 - abs(y - v) / s)
            if ky <= 0.0:
                continue
            for ox in range(-r + 1, r + 1):
                x = bx + ox
                if x < 0 or x >= width:
                    continue
                kx = max(0.0, 1.0 - abs(x - u) / s)
                if ky * kx > 0.0:
                    p = y * width + x
                    if z < zbuf[p]:
                        zbuf[p] = z


def _occlusion(
    geo: np.ndarray,
    n: int,
    width: int,
    height: int,
    max_r: float,
    f: float,
    tol0: float,
    min_cos: float,
    zbuf: np.ndarray,
    keep: np.ndarray,
) -> int:
    """Marks ``keep`` for the front-facing rows not hidden behind ``zbuf`` (numba helper).

    Returns the number of splat entries of the kept voxels (an upper bound).
    """
    total = 0
    for i in range(n):
        cos = geo[i, 3]
        if not cos > 0.0:
            continue
        u, v, z = geo[i, 0], geo[i, 1], geo[i, 2]
        s = min(max(geo[i, 4], 1.0), max_r)
        own = int(min(max(np.floor(v + 0.5), 0.0), height - 1.0)) * width + int(
            min(max(np.floor(u + 0.5), 0.0), width - 1.0)
        )
        cos_c = min(max(cos, min_cos), 1.0)
        sin_c = np.sqrt(1.0 - cos_c * cos_c)
        tol = (tol0 + s * z / f * sin_c) / cos_c
        if z <= zbuf[own] + tol:
            keep[i] = True
            r = int(np.ceil(s - 1e-9))
            total += 4 * r * r
    return total


def _visibility(
    geo: np.ndarray,
    n: int,
    width: int,
    height: int,
    max_r: float,
    f: float,
    tol0: float,
    min_cos: float,
    zbuf: np.ndarray,
    keep: np.ndarray,
) -> int:
    """Z-buffer of the tent splats of the first ``n`` in-frustum voxels, then the occlusion test (numba helper).

    Marks ``keep`` and returns the number of splat entries of the kept voxels (an upper bound).
    """
    any_front = False
    for i in range(n):
        if geo[i, 3] > 0.0:
            any_front = True
            break
    if not any_front:
        return 0
    _zbuffer(geo, n, width, height, max_r, zbuf)
    return _occlusion(geo, n, width, height, max_r, f, tol0, min_cos, zbuf, keep)


def _k_geometry(
    centres: np.ndarray,
    normals: np.ndarray,
    R: np.ndarray,
    c: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    near: float,
    far: float,
    f_vox: float,
    rows: np.ndarray,
    geo: np.ndarray,
) -> int:
    """Kernel of :func:`_geometry` (one camera)."""
    return _geometry(centres, normals, R, c, fx, fy, cx, cy, width, height, near, far, f_vox, rows, geo)


def _k_visibility(
    geo: np.ndarray,
    width: int,
    height: int,
    max_r: float,
    f: float,
    tol0: float,
    min_cos: float,
    zbuf: np.ndarray,
    keep: np.ndarray,
) -> int:
    """Kernel of :func:`_visibility` (one camera, every row of ``geo``)."""
    return _visibility(geo, geo.shape[0], width, height, max_r, f, tol0, min_cos, zbuf, keep)


def _k_splat(
    geo: np.ndarray,
    keep: np.ndarray,
    width: int,
    height: int,
    max_r: float,
    pix: np.ndarray,
    row: np.ndarray,
    kv: np.ndarray,
) -> int:
    """Tent-kernel entries (flat pixel, kept row, kernel > 0) of the kept voxels (numba); returns their number."""
    e = 0
    j = 0
    for i in range(geo.shape[0]):
        if not keep[i]:
            continue
        u, v = geo[i, 0], geo[i, 1]
        s = min(max(geo[i, 4], 1.0), max_r)
        r = int(np.ceil(s - 1e-9))
        bx = int(np.floor(u))
        by = int(np.floor(v))
        for oy in range(-r + 1, r + 1):
            y = by + oy
            ky = max(0.0, 1.0 - abs(y - v) / s) if 0 <= y < height else 0.0
            for ox in range(-r + 1, r + 1):
                x = bx + ox
                kx = max(0.0, 1.0 - abs(x - u) / s) if 0 <= x < width else 0.0
                k = ky * kx
                if k > 0.0:
                    pix[e] = y * width + x
                    row[e] = j
                    kv[e] = k
                    e += 1
        j += 1
    return e


def _voxel_weights(
    geo: np.ndarray,
    rows: np.ndarray,
    n: int,
    tsdf_w: np.ndarray,
    textured: np.ndarray,
    frontier: np.ndarray,
    prm: np.ndarray,
    use_frontier: bool,
    w: np.ndarray,
    pref: np.ndarray,
    fac: np.ndarray,
    tf: np.ndarray,
) -> None:
    """Eq. 7's weight W of the first ``n`` rows of ``geo`` into ``w`` (numba helper), as :func:`voxel_weight`;
    ``pref``, ``fac``, ``tf`` [>= n] are scratch. ``prm`` as :func:`_accumulate`'s.

    Two loops: the per-voxel gathers and the footprint's log (libm) row by row, then the angle's arccos and the
    exp with :mod:`~roigsf_ros.render.vecmath`'s, a loop LLVM vectorises (libm's arccos and exp in one scalar
    loop took most of :func:`_accumulate`'s time). Rows that are not kept get a weight too (unused).
    """
    p_poor, p_rich, a_sig, fp_pref, fp_sig, beta, gamma, mu, fw = (
        prm[0], prm[1], prm[2], prm[3], prm[4], prm[5], prm[6], prm[7], prm[8]
    )  # fmt: skip
    for i in range(n):
        idx = rows[i]
        pref[i] = p_rich if textured[idx] else p_poor
        f = 1.0 + mu / max(tsdf_w[idx], 1.0)  # 1 + mu W_cover
        if use_frontier:
            f = f * (1.0 + fw * (1.0 if frontier[idx] else 0.0)) / (1.0 + fw)
        fac[i] = f
        tf[i] = np.log(max(geo[i, 4], 1e-12) / fp_pref) / fp_sig
    for i in range(n):
        ta = (np.degrees(acos_unit(min(max(geo[i, 3], -1.0), 1.0))) - pref[i]) / a_sig
        t = tf[i]
        # W_angle^beta W_scale^gamma as one exp (no pow, one exp fewer; equal to rounding, tested)
        w[i] = exp_nonpositive(-0.5 * (beta * ta * ta + gamma * t * t)) * fac[i]


def _accumulate(
    geo: np.ndarray,
    rows: np.ndarray,
    keep: np.ndarray,
    n: int,
    tsdf_w: np.ndarray,
    textured: np.ndarray,
    frontier: np.ndarray,
    w_f: np.ndarray,
    width: int,
    height: int,
    max_r: float,
    prm: np.ndarray,
    use_frontier: bool,
    use_wf: bool,
    num: np.ndarray,
    den: np.ndarray,
) -> tuple[int, float]:
    """Eq. 7's weight of each kept row of the first ``n`` (:func:`_voxel_weights`), added into Eq. 8's tent sums
    ``num``, ``den`` (numba helper); returns the kept rows' number and their close-front gain (Eq. 14's I_vis, 0
    without ``use_wf``).

    ``prm``: pref poor, pref rich, angle sigma (deg), footprint pref (px), footprint sigma (ln), beta, gamma,
    mu, frontier weight.
    """
    weights = np.empty((4, n))  # W, then scratch
    _voxel_weights(geo, rows, n, tsdf_w, textured, frontier, prm, use_frontier, weights[0], weights[1], weights[2],
                   weights[3])  # fmt: skip
    n_vis = 0
    gain = 0.0
    for i in range(n):
        if not keep[i]:
            continue
        n_vis += 1
        u, v, z, cos, fp = geo[i, 0], geo[i, 1], geo[i, 2], geo[i, 3], geo[i, 4]
        w = weights[0, i]
        if use_wf:
            gain += max(cos / z - w_f[rows[i]], 0.0)
        s = min(max(fp, 1.0), max_r)
        q, kx0, kx1, ky0, ky1 = _bilinear(u, v, s, width, height)
        if q >= 0:  # the common case: the loop's 2x2 kernel values (the same sums)
            k = ky0 * kx0
            num[q] += k * w
            den[q] += k
            k = ky0 * kx1
            if k > 0.0:
                num[q + 1] += k * w
                den[q + 1] += k
            k = ky1 * kx0
            if k > 0.0:
                num[q + width] += k * w
                den[q + width] += k
            k = ky1 * kx1
            if k > 0.0:
                num[q + width + 1] += k * w
                den[q + width + 1] += k
            continue
        bx = int(np.floor(u))
        by = int(np.floor(v))
        r = int(np.ceil(s - 1e-9))
        for oy in range(-r + 1, r + 1):
            y = by + oy
            ky = max(0.0, 1.0 - abs(y - v) / s) if 0 <= y < height else 0.0
            if ky <= 0.0:
                continue
            for ox in range(-r + 1, r + 1):
                x = bx + ox
                kx = max(0.0, 1.0 - abs(x - u) / s) if 0 <= x < width else 0.0
                k = ky * kx
                if k > 0.0:
                    q = y * width + x
                    num[q] += k * w
                    den[q] += k
    return n_vis, gain


def _finish(num: np.ndarray, den: np.ndarray, mu: float, roi: np.ndarray) -> tuple[int, float]:
    """Eq. 8's norm of the tent sums into ``roi`` [H W] (numba helper); returns its pixels > 0 and its sum."""
    n_roi = 0
    mass = 0.0
    for p in range(num.shape[0]):
        val = num[p] / max(den[p], 1.0) / (1.0 + mu)
        val = min(max(val, 0.0), 1.0)
        roi[p] = val
        if val > 0.0:
            n_roi += 1
            mass += val
    return n_roi, mass


def _k_batch(
    centres: np.ndarray,
    normals: np.ndarray,
    tsdf_w: np.ndarray,
    textured: np.ndarray,
    frontier: np.ndarray,
    w_f: np.ndarray,
    poses: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    near: float,
    far: float,
    voxel_size: float,
    max_r: float,
    tol0: float,
    min_cos: float,
    prm: np.ndarray,
    use_frontier: bool,
    use_wf: bool,
    roi: np.ndarray,
    stats: np.ndarray,
) -> None:
    """ROI (Eq. 7-8) and close-front gain (Eq. 14) of many cameras, the cameras in parallel (numba).

    Per camera the same passes as :func:`view_roi` (:func:`_geometry`, :func:`_visibility`) and, per kept
    voxel, Eq. 7's weight accumulated into the tent-splat sums of Eq. 8 directly (:func:`_accumulate`).
    Writes ``roi`` [C, H W] and ``stats`` [C, 4]: visible voxels, ROI pixels, ROI mass, I_vis.
    """
    m = centres.shape[0]
    npix = width * height
    f = np.sqrt(fx * fy)
    for ci in prange(poses.shape[0]):  # one candidate per iteration, with its own scratch
        rows = np.empty(m, np.int64)
        geo = np.empty((m, 5))
        keep = np.zeros(m, np.bool_)
        zbuf = np.full(npix, np.inf)
        num = np.zeros(npix)
        den = np.zeros(npix)
        n_in = _geometry(centres, normals, poses[ci, :3, :3], poses[ci, :3, 3], fx, fy, cx, cy, width, height,
                         near, far, f * voxel_size, rows, geo)  # fmt: skip
        _visibility(geo, n_in, width, height, max_r, f, tol0, min_cos, zbuf, keep)
        n_vis, gain = _accumulate(geo, rows, keep, n_in, tsdf_w, textured, frontier, w_f, width, height, max_r, prm,
                                  use_frontier, use_wf, num, den)  # fmt: skip
        n_roi, mass = _finish(num, den, prm[7], roi[ci])
        stats[ci, 0] = n_vis
        stats[ci, 1] = n_roi
        stats[ci, 2] = mass
        stats[ci, 3] = gain


def _k_lone(
    centres: np.ndarray,
    normals: np.ndarray,
    tsdf_w: np.ndarray,
    textured: np.ndarray,
    frontier: np.ndarray,
    w_f: np.ndarray,
    pose: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    near: float,
    far: float,
    voxel_size: float,
    max_r: float,
    tol0: float,
    min_cos: float,
    prm: np.ndarray,
    use_frontier: bool,
    use_wf: bool,
    parts: int,
    roi: np.ndarray,
    stats: np.ndarray,
) -> None:
    """:func:`_k_batch` for one camera ``pose`` [4, 4], its voxels split into ``parts`` blocks done in parallel.

    Block t holds voxels t, t + parts, ...; each block projects its voxels and lowers its own z-buffer; the
    buffers' minimum is the camera's z-buffer (the same as one pass's); each block then tests its voxels against
    it and adds Eq. 7's weights into its own tent sums, which are added up (the same sums in another order).
    Writes ``roi`` [H W] and ``stats`` [4].
    """
    m = centres.shape[0]
    npix = width * height
    f = np.sqrt(fx * fy)
    R = pose[:3, :3]
    c = pose[:3, 3]
    cap = (m + parts - 1) // parts  # block t's rows: t * cap ... (t + 1) * cap
    rows = np.empty(parts * cap, np.int64)
    geo = np.empty((parts * cap, 5))
    keep = np.zeros(parts * cap, np.bool_)
    n_in = np.zeros(parts, np.int64)
    zbufs = np.full((parts, npix), np.inf)
    nums = np.zeros((parts, npix))
    dens = np.zeros((parts, npix))
    part_vis = np.zeros(parts, np.int64)
    part_gain = np.zeros(parts)
    for t in prange(parts):  # block t: voxels t, t + parts, ... (voxels come grouped in space; strides balance)
        lo, hi = t * cap, (t + 1) * cap
        n = _geometry(centres[t::parts], normals[t::parts], R, c, fx, fy, cx, cy, width, height, near, far,
                      f * voxel_size, rows[lo:hi], geo[lo:hi])  # fmt: skip
        for i in range(lo, lo + n):
            rows[i] = rows[i] * parts + t
        n_in[t] = n
        _zbuffer(geo[lo:hi], n, width, height, max_r, zbufs[t])
    zbuf = zbufs[0]
    for t in range(1, parts):
        for p in range(npix):
            zbuf[p] = min(zbuf[p], zbufs[t, p])
    for t in prange(parts):
        lo, hi = t * cap, (t + 1) * cap
        _occlusion(geo[lo:hi], n_in[t], width, height, max_r, f, tol0, min_cos, zbuf, keep[lo:hi])
        part_vis[t], part_gain[t] = _accumulate(geo[lo:hi], rows[lo:hi], keep[lo:hi], n_in[t], tsdf_w, textured,
                                                frontier, w_f, width, height, max_r, prm, use_frontier, use_wf,
                                                nums[t], dens[t])  # fmt: skip
    num = nums[0]
    den = dens[0]
    for t in range(1, parts):
        for p in range(npix):
            num[p] += nums[t, p]
            den[p] += dens[t, p]
    n_roi, mass = _finish(num, den, prm[7], roi)
    stats[0] = part_vis.sum()
    stats[1] = n_roi
    stats[2] = mass
    stats[3] = part_gain.sum()


def _k_frustum_union(
    centres: np.ndarray,
    normals: np.ndarray,
    poses: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    near: float,
    far: float,
    mask: np.ndarray,
) -> None:
    """Marks ``mask`` [M] for the voxels in the frustum of any of ``poses`` [C, 4, 4] (:func:`_geometry`'s test)."""
    m = centres.shape[0]
    for ci in prange(poses.shape[0]):
        rows = np.empty(m, np.int64)
        geo = np.empty((m, 5))
        n = _geometry(centres, normals, poses[ci, :3, :3], poses[ci, :3, 3], fx, fy, cx, cy, width, height, near, far,
                      1.0, rows, geo)  # fmt: skip
        for i in range(n):
            mask[rows[i]] = True  # the same value from every thread


_HELPERS = (
    acos_unit,
    exp_nonpositive,
    _bilinear,
    _geometry,
    _zbuffer,
    _occlusion,
    _visibility,
    _voxel_weights,
    _accumulate,
    _finish,
)
# error_model "numpy": the voxel weights' divisions by loaded values would otherwise keep their loop scalar.
_KERNELS = Kernels(parallel=False, helpers=_HELPERS, error_model="numpy", geometry=_k_geometry,
                   visibility=_k_visibility, splat=_k_splat)  # fmt: skip
_BATCH_KERNELS = Kernels(helpers=_HELPERS, error_model="numpy", batch=_k_batch, lone=_k_lone, union=_k_frustum_union)


def frustum_union(voxels: SurfaceVoxels, poses: np.ndarray, intr: Intrinsics, cfg: NBVConfig) -> np.ndarray:
    """Bool [M]: the surface voxels in the frustum (``near_m``..``far_m``, the image) of any of ``poses`` [C, 4, 4].

    A superset of what any of those cameras can see: :func:`batch_roi` and :func:`view_roi` read per-voxel inputs
    (texture) only there.
    """
    centres = np.ascontiguousarray(voxels.centres_m, dtype=np.float64).reshape(-1, 3)
    P = np.ascontiguousarray(np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4))
    mask = np.zeros(len(centres), np.bool_)
    if len(centres) == 0 or len(P) == 0:
        return mask
    if not numba_available():
        for T in P:
            mask[_camera_geometry(voxels, T, intr, 1.0, cfg)["rows"]] = True
        return mask
    with KERNEL_LOCK:
        _BATCH_KERNELS["union"](
            centres, np.ascontiguousarray(voxels.normals, dtype=np.float64).reshape(-1, 3), P, float(intr.fx),
            float(intr.fy), float(intr.cx), float(intr.cy), intr.width, intr.height, float(cfg.near_m),
            float(cfg.far_m), mask,
        )  # fmt: skip
    return mask


# ------------------------------------------------------------------------------------------ ROI
def splat_roi(view: VoxelView, weights: np.ndarray, intr: Intrinsics, cfg: NBVConfig) -> np.ndarray:
    """Eq. 8: W_roi [H, W] = ``sum K W / max(sum K, 1) / (1 + mu)`` over the visible voxels' tent splats."""
    W, H = intr.width, intr.height
    if len(view) == 0:
        return np.zeros((H, W))
    if view.splat is not None:
        pix, row, k = view.splat
    else:
        support = np.clip(view.footprint_px, 1.0, cfg.max_splat_radius_px)
        pix, row, k = _splat_entries(view.u_px, view.v_px, support, W, H)
    num = np.bincount(pix, weights=k * weights[row], minlength=W * H)
    den = np.bincount(pix, weights=k, minlength=W * H)
    roi = num / np.maximum(den, 1.0) / (1.0 + cfg.mu)
    return np.clip(roi, 0.0, 1.0).reshape(H, W)


def view_roi(
    voxels: SurfaceVoxels,
    voxel_size_m: float,
    T_wc: np.ndarray,
    intr: Intrinsics,
    cfg: NBVConfig,
    textured: np.ndarray | None = None,
    view: VoxelView | None = None,
    frontier: np.ndarray | None = None,
) -> ViewROI:
    """The ROI (Eq. 7-8) of candidate ``T_wc``; ``textured`` [M] bool per voxel (None: all texture-poor).

    ``view`` may pass a visibility already computed for this pose (it is then not recomputed).
    ``frontier`` [M] bool (beyond the paper, :meth:`roigsf_ros.tsdf.TSDFVolume.frontier_mask`): with
    ``cfg.frontier_weight`` = phi_f > 0 a frontier voxel's W is multiplied by (1 + phi_f) and every W divided by
    (1 + phi_f), so W_roi stays in [0, 1]; None or phi_f = 0 is the paper's Eq. 7.
    """
    if not (np.isfinite(voxel_size_m) and voxel_size_m > 0):
        raise InputError("voxel_size_m", f"must be a positive number, got {voxel_size_m}")
    m = len(voxels.centres_m)
    if textured is None:
        textured = np.zeros(m, dtype=bool)
    elif np.shape(textured) != (m,):
        raise InputError("textured", f"expected shape [{m}], got {list(np.shape(textured))}")
    if view is None:
        view = voxel_visibility(voxels, T_wc, intr, voxel_size_m, cfg)
    tex = np.asarray(textured, bool)[view.index]
    theta = np.degrees(np.arccos(np.clip(view.cos_incidence, -1.0, 1.0)))
    w, wa, ws, wc = voxel_weight(theta, tex, view.footprint_px, np.asarray(voxels.weight)[view.index], cfg)
    fw = float(getattr(cfg, "frontier_weight", 0.0))
    if frontier is not None and fw > 0:
        if np.shape(frontier) != (m,):
            raise InputError("frontier", f"expected shape [{m}], got {list(np.shape(frontier))}")
        w = w * (1.0 + fw * np.asarray(frontier, bool)[view.index]) / (1.0 + fw)
    return ViewROI(splat_roi(view, w, intr, cfg), view, w, wa, ws, wc, tex)


@dataclass
class BatchROI:
    """ROI and close-front of C candidates (:func:`batch_roi`): what scoring needs, without per-voxel parts.

    ``weights`` [C, H, W] W_roi; ``n_visible_voxels`` [C]; ``n_pixels`` [C] ROI pixels (> 0); ``mass`` [C] the
    ROI's sum; ``close_front`` [C] I_vis of Eq. 14 (0 without W_f).
    """

    weights: np.ndarray
    n_visible_voxels: np.ndarray
    n_pixels: np.ndarray
    mass: np.ndarray
    close_front: np.ndarray


def _fusion_weights(weight: np.ndarray) -> np.ndarray:
    """The TSDF weights [M] as the kernels read them: float32 (SurfaceVoxels' dtype) as they are, not converted to
    float64 on every call (262k voxels: a 2 MB write per candidate); any other dtype as float64.
    """
    w = np.asarray(weight)
    return np.ascontiguousarray(w if w.dtype == np.float32 else w.astype(np.float64))


def batch_roi(
    voxels: SurfaceVoxels,
    voxel_size_m: float,
    poses: np.ndarray,
    intr: Intrinsics,
    cfg: NBVConfig,
    textured: np.ndarray | None = None,
    frontier: np.ndarray | None = None,
    fused_weight: np.ndarray | None = None,
    backend: str = "auto",
) -> BatchROI:
    """:func:`view_roi` and :func:`~roigsf_ros.nbv.close_front.close_front_gain` of every pose of ``poses`` [C, 4, 4].

    The candidates are independent, so the numba backend splits them between the threads (one compiled
    pass per candidate, no per-voxel temporaries); with fewer candidates than threads it splits each one's
    voxels instead (:func:`_k_lone`). ``"numpy"`` loops over :func:`view_roi` (the reference; equal up to float
    summation order, tested). ``fused_weight`` [M] is W_f (None: close-front 0).
    """
    if backend not in ("auto", "numba", "numpy"):
        raise InputError("backend", f"must be 'auto', 'numba' or 'numpy', got {backend!r}")
    if not (np.isfinite(voxel_size_m) and voxel_size_m > 0):
        raise InputError("voxel_size_m", f"must be a positive number, got {voxel_size_m}")
    P = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    P = np.stack([check_pose(T, f"poses[{i}]") for i, T in enumerate(P)]) if len(P) else P
    m = len(voxels.centres_m)
    for name, arr in (("textured", textured), ("frontier", frontier), ("fused_weight", fused_weight)):
        if arr is not None and np.shape(arr) != (m,):
            raise InputError(name, f"expected shape [{m}], got {list(np.shape(arr))}")
    C, H, W = len(P), intr.height, intr.width
    out = BatchROI(np.zeros((C, H, W)), np.zeros(C, np.int64), np.zeros(C, np.int64), np.zeros(C), np.zeros(C))
    if C == 0 or m == 0:
        return out
    use_frontier = frontier is not None and float(cfg.frontier_weight) > 0
    if backend == "numpy" or (backend == "auto" and not numba_available()):
        for i, T in enumerate(P):
            r = view_roi(voxels, voxel_size_m, T, intr, cfg, textured, frontier=frontier if use_frontier else None)
            out.weights[i] = r.weights
            out.n_visible_voxels[i], out.n_pixels[i], out.mass[i] = len(r.view), r.n_pixels, r.mass
            if fused_weight is not None and len(r.view):
                out.close_front[i] = float(
                    np.maximum(r.view.cos_incidence / r.view.z_m - np.asarray(fused_weight)[r.view.index], 0.0).sum()
                )
        return out
    prm = np.array([cfg.angle_pref_texture_poor_deg, cfg.angle_pref_texture_rich_deg, cfg.angle_sigma_deg,
                    cfg.footprint_pref_px, cfg.footprint_sigma_ln, cfg.beta, cfg.gamma, cfg.mu,
                    float(cfg.frontier_weight)], dtype=np.float64)  # fmt: skip
    roi = np.zeros((C, H * W))
    stats = np.zeros((C, 4))
    voxel_args = (
        np.ascontiguousarray(voxels.centres_m, dtype=np.float64).reshape(-1, 3),
        np.ascontiguousarray(voxels.normals, dtype=np.float64).reshape(-1, 3),
        _fusion_weights(voxels.weight),
        np.zeros(m, np.bool_) if textured is None else np.ascontiguousarray(textured, dtype=np.bool_),
        np.ascontiguousarray(frontier, dtype=np.bool_) if use_frontier else np.zeros(1, np.bool_),
        np.zeros(1) if fused_weight is None else np.ascontiguousarray(fused_weight, dtype=np.float64),
    )
    cam_args = (float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy), W, H, float(cfg.near_m),
                float(cfg.far_m), float(voxel_size_m), float(cfg.max_splat_radius_px),
                float(cfg.occlusion_tol_voxels) * voxel_size_m, float(cfg.occlusion_min_cos), prm, use_frontier,
                fused_weight is not None)  # fmt: skip
    with KERNEL_LOCK:
        threads = n_threads()
        if threads <= C or m < _LONE_MIN_VOXELS:  # the cameras in parallel
            _BATCH_KERNELS["batch"](*voxel_args, np.ascontiguousarray(P), *cam_args, roi, stats)
        else:  # fewer cameras than threads: each one's voxels in parallel
            for i in range(C):
                _BATCH_KERNELS["lone"](*voxel_args, np.ascontiguousarray(P[i]), *cam_args, threads, roi[i], stats[i])
    out.weights = roi.reshape(C, H, W)
    out.n_visible_voxels = stats[:, 0].astype(np.int64)
    out.n_pixels = stats[:, 1].astype(np.int64)
    out.mass = stats[:, 2].copy()
    out.close_front = stats[:, 3].copy()
    return out


__all__ = [
    "LUMA_RGB",
    "BatchROI",
    "ViewROI",
    "VoxelView",
    "batch_roi",
    "coverage_weight",
    "footprint_weight",
    "frustum_union",
    "incidence_weight",
    "splat_roi",
    "view_roi",
    "voxel_texture",
    "voxel_visibility",
    "voxel_weight",
]
