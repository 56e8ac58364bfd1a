"""Fast differentiable 2DGS rasteriser, gsplat-style functional API, two backends.

Same model and outputs as :mod:`roigsf_ros.render.reference` (see its docstring for the exact
rules, taken from hbb1/diff-surfel-rasterization); both backends match it in values and gradients.

1. :func:`project_surfels` (per surfel): camera-frame splat transform, reduced to the adjugate
   rows ``A`` (so the ray-splat hit ``p = k x l = A [x, y, 1]`` is linear in the pixel), ``det``,
   centre depth and projected centre; a conservative pixel box holding every pixel where
   ``alpha >= 1/255`` (exact bound of the projected disc clipped at the near plane, with margins).
2. :func:`bin_tiles`: kept surfels binned into 4x4-pixel tiles, depth-sorted per tile.
3. ``backend="numba"`` (CPU, default when numba is installed): the whole render is compiled
   kernels in one ``torch.autograd.Function`` (projection, culling and pixel boxes in one pass;
   stable depth sort and binning; compositing written like the 2DGS CUDA rasteriser, front-to-back
   per pixel, with a hand-written back-to-front backward; the projection's backward), so a render
   costs a handful of kernel launches and no per-surfel torch operations. When the camera itself
   needs gradients, torch projects the surfels (:func:`project_packed`, culled with
   :func:`project_surfels`) and only the compositing runs in the kernels.
   ``backend="torch"`` (any device): :func:`select_pairs` walks the tiles in chunks with the
   per-pixel early stop to list the exact (pixel, surfel) contributions, and
   :func:`composite_pairs` composites them with plain differentiable tensor ops (transmittance by a
   per-pixel segmented scan).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from roigsf_ros.core.camera import Intrinsics, check_pose
from roigsf_ros.core.errors import InputError
from roigsf_ros.render.numba_setup import (
    KERNEL_LOCK,
    Kernels,
    balanced_bounds,
    n_threads,
    prange,
    use_numba,
)
from roigsf_ros.render.vecmath import exp_neg

if TYPE_CHECKING:
    from roigsf_ros.render.surfels import SurfelMap

ALPHA_MIN = 1.0 / 255.0
"""Contributions with alpha below this are skipped (2DGS)."""
ALPHA_MAX = 0.99
"""Alpha is clamped to this (2DGS)."""
T_MIN = 1e-4
"""A pixel stops (without the crossing surfel) once transmittance would drop below this (2DGS)."""
FILTER_INV_SQUARE = 2.0
"""Screen-space low-pass fallback: rho2d = FILTER_INV_SQUARE * |pixel - centre|^2 (2DGS FilterInvSquare)."""

# Rows of the packed per-surfel tensor used per (pixel, surfel) pair.
_AX0, _AX1, _AX2, _AY0, _AY1, _AY2, _AZ0, _AZ1, _AZ2, _DET, _TZ, _CX, _CY, _OPA = range(14)
NPACK = 14
"""Rows of the packed per-surfel tensor (:func:`project_packed`)."""


@dataclass
class RenderOutput:
    """Rendered maps of an H x W view (pixel (i, j) centre at x = i, y = j, OpenCV).

    ``features`` [H, W, C] (composited features + transmittance * background); ``alpha`` [H, W]
    accumulated opacity; ``depth`` [H, W] alpha-weighted camera-z depth in metres (not normalised,
    see :meth:`expected_depth`); ``median_depth`` [H, W] (0 where nothing was hit); ``normal``
    [H, W, 3] alpha-weighted unit surfel normals in the CAMERA frame, facing the camera;
    ``distortion`` [H, W] (2DGS depth-distortion term); ``n_contrib`` [H, W] number of contributing
    surfels; ``visible`` [N] surfels that contribute to at least one pixel.
    """

    features: Tensor
    alpha: Tensor
    depth: Tensor
    median_depth: Tensor
    normal: Tensor
    distortion: Tensor
    n_contrib: Tensor
    visible: Tensor

    @property
    def color(self) -> Tensor:
        """Alias of ``features`` (the RGB image [H, W, 3] when colours were rendered)."""
        return self.features

    def expected_depth(self, min_alpha: float = 1e-6) -> Tensor:
        """Depth normalised by alpha [H, W] (metres; 0 where alpha < ``min_alpha``)."""
        ok = self.alpha >= min_alpha
        return torch.where(ok, self.depth / torch.where(ok, self.alpha, torch.ones_like(self.alpha)), 0.0)

    def normal_world(self, viewmat: Tensor) -> Tensor:
        """``normal`` rotated to the world frame [H, W, 3] (``viewmat`` [4, 4] world -> camera)."""
        return self.normal @ viewmat[:3, :3].to(self.normal)


# ------------------------------------------------------------------------------------ cameras
def camera_tensors(
    T_wc: np.ndarray | Tensor,
    intr: Intrinsics,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> tuple[Tensor, Tensor]:
    """``viewmat`` [4, 4] (world -> camera, the inverse of camera-to-world ``T_wc``) and ``K`` [3, 3]."""
    if isinstance(T_wc, Tensor):
        T = T_wc.to(device=device, dtype=dtype)
        R, t = T[:3, :3], T[:3, 3]
        view = torch.eye(4, device=device, dtype=dtype)
        view = torch.cat([torch.cat([R.T, (-R.T @ t)[:, None]], 1), view[3:]], 0)
    else:
        T = np.asarray(T_wc, dtype=np.float64)
        V = np.eye(4)
        V[:3, :3] = T[:3, :3].T
        V[:3, 3] = -T[:3, :3].T @ T[:3, 3]
        view = torch.as_tensor(V, device=device, dtype=dtype)
    K = torch.as_tensor(intr.K, device=device, dtype=dtype)
    return view, K


# --------------------------------------------------------------------------------- projection
@dataclass
class Projection:
    """Per-surfel screen-space quantities of one view.

    ``packed`` [14, N] (differentiable): adjugate rows A (9), det, centre depth, centre x, y,
    opacity; ``normals`` [N, 3] camera-frame normals facing the camera; ``depth`` [N] centre camera z
    (sort key); ``rect`` [N, 4] inclusive pixel box x0, y0, x1, y1; ``keep`` [N] inside (near, far],
    on the image and able to reach alpha >= 1/255.
    """

    packed: Tensor
    normals: Tensor
    depth: Tensor
    rect: Tensor
    keep: Tensor


def project_surfels(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float = 0.2,
    far: float = 100.0,
    backend: str = "auto",
) -> Projection:
    """Project N surfels (world frame, metres; ``quats`` wxyz, any norm; ``scales`` [N, 2] activated)."""
    packed, normals, (Tu, Tv, Tw) = project_packed(means, quats, scales, opacities, viewmat, K, near, far)
    z = packed[_TZ]
    with torch.no_grad():
        if use_numba(backend, packed):
            rows = torch.stack([*Tu, *Tv, *Tw, packed[_CX], packed[_CY], opacities.to(packed.dtype)], -1)
            rect_np = np.empty((rows.shape[0], 4), np.int64)
            ok_np = np.empty(rows.shape[0], np.uint8)
            rows_np = rows.detach().double().contiguous().numpy()
            with KERNEL_LOCK:
                _KERNELS["boxes"](rows_np, width, height, float(near), rect_np, ok_np)
            rect, on_image = torch.from_numpy(rect_np), torch.from_numpy(ok_np.astype(np.bool_))
        else:
            rect, on_image = _pixel_boxes(Tu, Tv, Tw, packed[_CX], packed[_CY], opacities, width, height, near)
    keep = (z > near) & (z <= far) & on_image
    return Projection(packed=packed, normals=normals, depth=z.detach(), rect=rect, keep=keep)


def project_packed(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmat: Tensor,
    K: Tensor,
    near: float = 0.2,
    far: float = 100.0,
) -> tuple[Tensor, Tensor, tuple[list[Tensor], list[Tensor], list[Tensor]]]:
    """Differentiable core of :func:`project_surfels`: ``packed`` [14, N], camera-frame normals [N, 3]
    facing the camera, and the rows Tu, Tv, Tw of the splat-to-pixel transform (3 lists of 3 [N]).
    """
    dt = means.dtype
    V = viewmat.to(dt)
    Km = K.to(dt)
    r = [V[i, j] for i in range(3) for j in range(3)]
    t = [V[i, 3] for i in range(3)]
    qn = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    qw, qx, qy, qz = qn.unbind(-1)
    su, sv = scales.unbind(-1)
    mx, my, mz = means.unbind(-1)
    # Rotation columns t_u, t_v, t_w (world frame) of the normalised quaternion.
    tu = (1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy + qw * qz), 2 * (qx * qz - qw * qy))
    tv = (2 * (qx * qy - qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz + qw * qx))
    tw = (2 * (qx * qz + qw * qy), 2 * (qy * qz - qw * qx), 1 - 2 * (qx * qx + qy * qy))

    def rot(vec: tuple[Tensor, Tensor, Tensor], i: int) -> Tensor:
        return r[3 * i] * vec[0] + r[3 * i + 1] * vec[1] + r[3 * i + 2] * vec[2]

    a = [rot(tu, i) * su for i in range(3)]  # s_u t_u, camera frame
    b = [rot(tv, i) * sv for i in range(3)]  # s_v t_v
    c = [rot((mx, my, mz), i) + t[i] for i in range(3)]  # centre
    nrm = [rot(tw, i) for i in range(3)]
    k00, k01, k02, k11, k12 = Km[0, 0], Km[0, 1], Km[0, 2], Km[1, 1], Km[1, 2]
    # Rows of M = K [a b c] (K's last row is (0, 0, 1)).
    Tu = [k00 * col[0] + k01 * col[1] + k02 * col[2] for col in (a, b, c)]
    Tv = [k11 * col[1] + k12 * col[2] for col in (a, b, c)]
    Tw = [a[2], b[2], c[2]]
    z = c[2]
    # p = (x Tw - Tu) x (y Tw - Tv) = A [x, y, 1] (adjugate rows), depth = det / p_z.
    ax = (Tw[2] * Tv[1] - Tw[1] * Tv[2], Tu[2] * Tw[1] - Tu[1] * Tw[2], Tu[1] * Tv[2] - Tu[2] * Tv[1])
    ay = (Tw[0] * Tv[2] - Tw[2] * Tv[0], Tu[0] * Tw[2] - Tu[2] * Tw[0], Tu[2] * Tv[0] - Tu[0] * Tv[2])
    az = (Tw[1] * Tv[0] - Tw[0] * Tv[1], Tu[1] * Tw[0] - Tu[0] * Tw[1], Tu[0] * Tv[1] - Tu[1] * Tv[0])
    det = Tw[0] * ax[2] + Tw[1] * ay[2] + Tw[2] * az[2]
    in_range = (z > near) & (z <= far)
    z_safe = torch.where(in_range, z, torch.ones_like(z))
    cx, cy = Tu[2] / z_safe, Tv[2] / z_safe
    packed = torch.stack([*ax, *ay, *az, det, z, cx, cy, opacities.to(dt)], dim=0)
    facing = (nrm[0] * c[0] + nrm[1] * c[1] + nrm[2] * c[2]) > 0
    normals = torch.stack(nrm, dim=-1)
    normals = torch.where(facing[:, None], -normals, normals)
    return packed, normals, (Tu, Tv, Tw)


def _pixel_boxes(
    Tu: list[Tensor],
    Tv: list[Tensor],
    Tw: list[Tensor],
    cx: Tensor,
    cy: Tensor,
    opac: Tensor,
    width: int,
    height: int,
    near: float,
) -> tuple[Tensor, Tensor]:
    """Inclusive pixel boxes [N, 4] (x0, y0, x1, y1) that hold every pixel with alpha >= 1/255.

    Union of the 2D fallback disc and the image of the 3D disc ``u^2 + v^2 <= R2`` clipped to camera
    depth >= near (hits nearer than that are skipped). The image coordinate x = (Tu . s) / (Tw . s),
    s = (u, v, 1), is linear-fractional with a positive denominator there, so its extremes over the
    clipped disc lie at the circle's points with a vertical (horizontal for y) tangent image line, or
    at the two ends of the clipping chord z = near. Computed in float64 with margins.
    """
    f64 = torch.float64
    Tu = [t.detach().to(f64) for t in Tu]
    Tv = [t.detach().to(f64) for t in Tv]
    Tw = [t.detach().to(f64) for t in Tw]
    cx, cy, o = cx.detach().to(f64), cy.detach().to(f64), opac.detach().to(f64)
    # alpha >= 1/255  <=>  rho <= R2 = 2 ln(255 o); inflated for float32 rounding in the renderer.
    R2 = 2.0 * torch.log((255.0 * o).clamp_min(1e-30))
    visible = R2 > 0
    R2 = R2.clamp_min(0) * 1.01 + 1e-3
    # 2D fallback disc: 2 |pixel - centre|^2 <= R2.
    r2d = torch.sqrt(R2 / FILTER_INV_SQUARE)
    lo = [cx - r2d, cy - r2d]
    hi = [cx + r2d, cy + r2d]
    # Candidate disc points (u, v) for the extremes: tangent points of x = X and y = Y lines.
    z_min = near * (1 - 1e-6) - 1e-9
    cands_u, cands_v = [], []
    degenerate = torch.zeros_like(R2, dtype=torch.bool)
    iR2 = 1.0 / R2
    c22 = Tw[0] ** 2 + Tw[1] ** 2 - Tw[2] ** 2 * iR2
    for row in (Tu, Tv):
        c00 = row[0] ** 2 + row[1] ** 2 - row[2] ** 2 * iR2
        c02 = row[0] * Tw[0] + row[1] * Tw[1] - row[2] * Tw[2] * iR2
        disc = (c02 * c02 - c00 * c22).clamp_min(0).sqrt()
        degenerate |= c22.abs() < 1e-12 * (c02.abs() + c00.abs() + 1e-30)
        c22s = torch.where(degenerate, torch.ones_like(c22), c22)
        for sign in (-1.0, 1.0):
            X = (c02 + sign * disc) / c22s
            # Pull the line back to uv: L = row - X Tw; its pole on the circle is (L0, L1) * (-R2 / L2).
            L = [row[i] - X * Tw[i] for i in range(3)]
            L2 = torch.where(L[2] == 0, torch.full_like(L[2], 1e-300), L[2])
            cands_u.append(-L[0] * R2 / L2)
            cands_v.append(-L[1] * R2 / L2)
    # Ends of the chord z(u, v) = Tw0 u + Tw1 v + Tw2 = z_min.
    g2 = Tw[0] ** 2 + Tw[1] ** 2
    g2s = torch.where(g2 > 0, g2, torch.ones_like(g2))
    k = (z_min - Tw[2]) / g2s
    fu, fv = k * Tw[0], k * Tw[1]
    h = torch.sqrt(((R2 - (fu * fu + fv * fv)) / g2s).clamp_min(0))
    has_chord = (g2 > 0) & (fu * fu + fv * fv < R2)
    for sign in (-1.0, 1.0):
        cands_u.append(torch.where(has_chord, fu - sign * h * Tw[1], torch.zeros_like(fu)))
        cands_v.append(torch.where(has_chord, fv + sign * h * Tw[0], torch.zeros_like(fv)))
    big = 1e9
    for cu, cv in zip(cands_u, cands_v, strict=True):
        zc = Tw[0] * cu + Tw[1] * cv + Tw[2]
        ok = torch.isfinite(zc) & (zc >= z_min - 1e-9) & (zc > 0)
        zs = torch.where(ok, zc, torch.ones_like(zc))
        for i, row in enumerate((Tu, Tv)):
            val = (row[0] * cu + row[1] * cv + row[2]) / zs
            lo[i] = torch.where(ok, torch.minimum(lo[i], val), lo[i])
            hi[i] = torch.where(ok, torch.maximum(hi[i], val), hi[i])
    lo = [torch.where(degenerate, torch.full_like(v, -big), v) for v in lo]
    hi = [torch.where(degenerate, torch.full_like(v, big), v) for v in hi]
    x0, y0, x1, y1 = (v.nan_to_num(0.0, big, -big).clamp(-big, big) for v in (lo[0], lo[1], hi[0], hi[1]))
    finite = torch.stack([*lo, *hi]).isfinite().all(0)
    px0 = torch.ceil(x0 - 0.5).clamp_min(0)
    px1 = torch.floor(x1 + 0.5).clamp_max(width - 1)
    py0 = torch.ceil(y0 - 0.5).clamp_min(0)
    py1 = torch.floor(y1 + 0.5).clamp_max(height - 1)
    on_image = visible & finite & (px0 <= px1) & (py0 <= py1)
    rect = torch.stack([px0, py0, px1, py1], dim=-1).long()
    return rect, on_image


def pair_alpha_depth(rows: tuple[Tensor, ...] | list[Tensor], x: Tensor, y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Alpha, depth (camera z, metres) and p_z of surfels (``rows``: the 14 packed rows) at pixels x, y.

    Shapes broadcast; no masking (callers skip alpha < 1/255, depth < near and p_z == 0).
    """
    ax0, ax1, ax2, ay0, ay1, ay2, az0, az1, az2, det, tz, cx, cy, opa = rows
    pz = az0 * x + az1 * y + az2
    inv = 1.0 / pz
    u = (ax0 * x + ax1 * y + ax2) * inv
    v = (ay0 * x + ay1 * y + ay2) * inv
    rho3d = u * u + v * v
    dx = cx - x
    dy = cy - y
    rho2d = FILTER_INV_SQUARE * (dx * dx + dy * dy)
    use3d = rho3d <= rho2d
    rho = torch.where(use3d, rho3d, rho2d)
    depth = torch.where(use3d, det * inv, tz)
    alpha = torch.clamp(opa * torch.exp(-0.5 * rho), max=ALPHA_MAX)
    return alpha, depth, pz


# ----------------------------------------------------------------------------------- selection
@dataclass
class Pairs:
    """Contributing (pixel, surfel) pairs, grouped by pixel (row-major id) in front-to-back order.

    ``surf`` [M], ``pix`` [M] (long); ``start`` [M] index of the first pair of the same pixel;
    ``offsets`` [P + 1] where pixel p owns pairs offsets[p]:offsets[p + 1].
    """

    surf: Tensor
    pix: Tensor
    start: Tensor
    offsets: Tensor

    def __len__(self) -> int:
        return int(self.surf.shape[0])


@dataclass
class TileBins:
    """Surfel ids per tile (row-major tiles of ``size`` x ``size`` pixels), depth-sorted within a tile.

    Tile t owns ``surf[start[t]:start[t] + count[t]]`` (long tensors); ``ntx`` tiles per row.
    """

    surf: Tensor
    start: Tensor
    count: Tensor
    size: int
    ntx: int
    nty: int


@torch.no_grad()
def bin_tiles(proj: Projection, width: int, height: int, tile_size: int = 4) -> TileBins:
    """Bin the kept surfels into the tiles their pixel boxes touch, sorted by centre depth (stable)."""
    dev = proj.packed.device
    ts = int(tile_size)
    ntx, nty = -(-width // ts), -(-height // ts)
    n_tiles = ntx * nty
    idx = proj.keep.nonzero().squeeze(1)
    order = idx.index_select(0, torch.sort(proj.depth.index_select(0, idx), stable=True).indices)
    rect = proj.rect.index_select(0, order)
    tx0, ty0 = rect[:, 0] // ts, rect[:, 1] // ts
    nx = rect[:, 2] // ts - tx0 + 1
    cnt = nx * (rect[:, 3] // ts - ty0 + 1)
    rep = torch.repeat_interleave(torch.arange(order.numel(), device=dev), cnt)
    j = torch.arange(rep.numel(), device=dev) - (torch.cumsum(cnt, 0) - cnt).index_select(0, rep)
    nx_r = nx.index_select(0, rep)
    tile = (ty0.index_select(0, rep) + j // nx_r) * ntx + tx0.index_select(0, rep) + j % nx_r
    tile, perm = torch.sort(tile, stable=True)
    surf = order.index_select(0, rep.index_select(0, perm))  # tile-major, depth-minor
    count = torch.bincount(tile, minlength=n_tiles)
    return TileBins(surf=surf, start=torch.cumsum(count, 0) - count, count=count, size=ts, ntx=ntx, nty=nty)


@torch.no_grad()
def select_pairs(
    proj: Projection,
    width: int,
    height: int,
    near: float = 0.2,
    tile_size: int = 4,
    chunk: int = 32,
    backend: str = "auto",
) -> Pairs:
    """The exact contributing pairs (2DGS rules) by tile binning and front-to-back walks per pixel."""
    packed = proj.packed.detach()
    dev, dt = packed.device, packed.dtype
    n = packed.shape[1]
    P = width * height
    empty = torch.zeros(0, dtype=torch.long, device=dev)
    if not bool(proj.keep.any()):
        return Pairs(empty, empty, empty, torch.zeros(P + 1, dtype=torch.long, device=dev))
    bins = bin_tiles(proj, width, height, tile_size)
    if use_numba(backend, packed):
        res = numba_forward(proj, packed.new_zeros(n, 0), bins, width, height, near, 100.0, None)
        return res.pairs()
    ts, ntx, n_tiles = bins.size, bins.ntx, bins.ntx * bins.nty
    tl_surf, t_start, t_count = bins.surf, bins.start, bins.count
    e_total = tl_surf.numel()

    data = torch.cat([packed, packed.new_zeros(NPACK, 1)], dim=1)  # null surfel n: opacity 0
    data[_AZ2, n] = 1.0
    q = torch.arange(ts * ts, device=dev)
    tiles = torch.arange(n_tiles, device=dev)
    px_all = ((tiles % ntx) * ts)[:, None] + (q % ts)[None]  # [tiles, Q]
    py_all = ((tiles // ntx) * ts)[:, None] + (q // ts)[None]
    inside = (px_all < width) & (py_all < height)
    pix_all = torch.where(inside, py_all * width + px_all, torch.zeros_like(px_all))
    T_all = torch.ones(n_tiles, ts * ts, dtype=dt, device=dev)
    done_all = ~inside
    slots = torch.zeros(P, dtype=torch.long, device=dev)
    out_pix, out_slot, out_surf = [], [], []
    ar = torch.arange(chunk, device=dev)
    active = (t_count > 0).nonzero().squeeze(1)
    c = 0
    while active.numel() > 0:
        a_start = t_start.index_select(0, active) + c * chunk
        a_end = t_start.index_select(0, active) + t_count.index_select(0, active)
        pos = a_start[:, None] + ar[None]  # [A, B]
        sid = tl_surf.index_select(0, pos.clamp_max(e_total - 1).reshape(-1)).view_as(pos)
        sid = torch.where(pos < a_end[:, None], sid, n)
        rows = data.index_select(1, sid.reshape(-1)).view(NPACK, -1, 1, chunk).unbind(0)  # each [A, 1, B]
        x = px_all.index_select(0, active).to(dt)[:, :, None]  # [A, Q, 1]
        y = py_all.index_select(0, active).to(dt)[:, :, None]
        alpha, depth, pz = pair_alpha_depth(rows, x, y)
        done = done_all.index_select(0, active)
        T_in = T_all.index_select(0, active)
        valid = (alpha >= ALPHA_MIN) & (depth >= near) & (pz != 0) & ~done[:, :, None]
        a0 = torch.where(valid, alpha, torch.zeros_like(alpha))
        T_after = T_in[:, :, None] * torch.cumprod(1 - a0, dim=-1)
        cross = valid & (T_after < T_MIN)
        acc = valid & ~cross
        a1 = torch.where(acc, alpha, torch.zeros_like(alpha))
        T_all[active] = T_in * torch.prod(1 - a1, dim=-1)
        done_all[active] = done | cross.any(-1)
        pix = pix_all.index_select(0, active)  # [A, Q]
        nz = acc.nonzero()
        if nz.numel():
            ai, qi, bi = nz.unbind(1)
            p_ids = pix[ai, qi]
            excl = (torch.cumsum(acc, -1) - acc.long())[ai, qi, bi]
            out_pix.append(p_ids)
            out_slot.append(slots.index_select(0, p_ids) + excl)
            out_surf.append(sid[ai, bi])
            slots.index_add_(0, pix.reshape(-1), acc.sum(-1).reshape(-1))
        more = (t_count.index_select(0, active) > (c + 1) * chunk) & ~done_all.index_select(0, active).all(-1)
        active = active[more]
        c += 1
    offsets = torch.zeros(P + 1, dtype=torch.long, device=dev)
    offsets[1:] = torch.cumsum(slots, 0)
    m = int(offsets[-1])
    if m == 0:
        return Pairs(empty, empty, empty, offsets)
    pix_cat = torch.cat(out_pix)
    flat = offsets.index_select(0, pix_cat) + torch.cat(out_slot)
    surf = torch.empty(m, dtype=torch.long, device=dev)
    surf[flat] = torch.cat(out_surf)
    pix = torch.empty(m, dtype=torch.long, device=dev)
    pix[flat] = pix_cat
    return Pairs(surf=surf, pix=pix, start=offsets.index_select(0, pix), offsets=offsets)


# --------------------------------------------------------------------------------- compositing
def _seg_exclusive_cumsum(x: Tensor, start: Tensor) -> Tensor:
    """Per-segment exclusive prefix sums of flat ``x`` [M] (float64 scan, segments given by ``start``)."""
    cs = torch.cumsum(x.double(), 0)
    excl = cs - x.double()
    return excl - excl.index_select(0, start)


def composite_pairs(
    proj: Projection,
    features: Tensor,
    pairs: Pairs,
    width: int,
    height: int,
    near: float = 0.2,
    far: float = 100.0,
    background: Tensor | None = None,
    with_distortion: bool = True,
) -> RenderOutput:
    """Differentiable front-to-back compositing of the selected pairs into the output maps."""
    dt, dev = proj.packed.dtype, proj.packed.device
    n, C = features.shape
    P = width * height
    features = features.to(dt)
    # Zero-valued links keep every output attached to the inputs' autograd graph (empty views too).
    link = proj.packed[:, :0].sum() + features[:0].sum() + proj.normals[:0].sum()
    zeros = lambda *s: torch.zeros(*s, dtype=dt, device=dev)  # noqa: E731
    surf, pix = pairs.surf, pairs.pix
    rows = proj.packed.index_select(1, surf).unbind(0)
    x = (pix % width).to(dt)
    y = torch.div(pix, width, rounding_mode="floor").to(dt)
    alpha, depth, _ = pair_alpha_depth(rows, x, y)
    lg = torch.log1p(-alpha)
    T_before = torch.exp(_seg_exclusive_cumsum(lg, pairs.start)).to(dt)
    w = alpha * T_before
    acc = zeros(P).index_add(0, pix, w) + link
    feat = zeros(P, C).index_add(0, pix, w[:, None] * features.index_select(0, surf)) + link
    if background is not None:
        feat = feat + (1 - acc)[:, None] * background.to(dt)
    dmap = zeros(P).index_add(0, pix, w * depth) + link
    nmap = zeros(P, 3).index_add(0, pix, w[:, None] * proj.normals.index_select(0, surf)) + link
    if with_distortion and len(pairs):
        mz = far / (far - near) * (1.0 - near / depth)
        wm = w * mz
        m1 = _seg_exclusive_cumsum(wm, pairs.start).to(dt)
        m2 = _seg_exclusive_cumsum(wm * mz, pairs.start).to(dt)
        dist = zeros(P).index_add(0, pix, w * (mz * mz * (1 - T_before) + m2 - 2 * mz * m1)) + link
    else:
        dist = zeros(P) + link
    count = pairs.offsets[1:] - pairs.offsets[:-1]
    with torch.no_grad():
        n_half = torch.zeros(P, dtype=torch.long, device=dev).index_add_(0, pix, (T_before > 0.5).long())
    has = n_half > 0
    med_idx = torch.where(has, pairs.offsets[:-1] + n_half - 1, torch.zeros_like(n_half))
    if len(pairs):
        median = torch.where(has, depth.index_select(0, med_idx.clamp_max(len(pairs) - 1)), 0.0) + link
    else:
        median = zeros(P) + link
    visible = torch.zeros(n, dtype=torch.bool, device=dev)
    visible[surf] = True
    hw = (height, width)
    return RenderOutput(
        features=feat.reshape(*hw, C),
        alpha=acc.reshape(hw),
        depth=dmap.reshape(hw),
        median_depth=median.reshape(hw),
        normal=nmap.reshape(*hw, 3),
        distortion=dist.reshape(hw),
        n_contrib=count.reshape(hw),
        visible=visible,
    )


# ------------------------------------------------------------------------------ numba backend
# CPU kernels written like the 2DGS CUDA rasteriser. Per tile (a work item), the tile's depth-sorted
# list is processed in chunks of _CHUNK surfels: a lane pass computes alpha and depth of every
# (tile pixel, surfel) of the chunk in one straight loop over the surfels (LLVM vectorises it), then
# each pixel composites its surfels of the chunk front to back. The backward walks the list back to
# front, each surfel over the pixels that accepted it, rebuilding transmittance by division as
# diff-surfel-rasterization's backward does. Projection, culling, pixel boxes, sorting and binning
# are kernels too, and so is the projection's backward. They are plain Python here, compiled by
# numba on first use (cached on disk) and always run in float64 (one specialisation to compile).

_CHUNK = 64
"""Surfels of a tile's list per lane pass of the forward kernel (a multiple of 8)."""


def _pixel_box(
    u0: float, u1: float, u2: float, v0: float, v1: float, v2: float, w0: float, w1: float, w2: float,
    cx: float, cy: float, o: float, width: int, height: int, near: float, rect: np.ndarray, i: int,
) -> bool:  # fmt: skip
    """Pixel box of one surfel (numba helper): the bound of :func:`_pixel_boxes`, written to ``rect[i]``.

    Rows Tu (u0..u2), Tv, Tw of the splat-to-pixel transform, projected centre, opacity; returns
    whether the box is on the image (``rect[i]`` is (0, 0, -1, -1) when not).
    """
    big = 1e9
    z_min = near * (1 - 1e-6) - 1e-9
    rect[i, 0] = 0
    rect[i, 1] = 0
    rect[i, 2] = -1
    rect[i, 3] = -1
    if not 255.0 * o > 1.0:
        return False
    R2 = 2.0 * np.log(255.0 * o) * 1.01 + 1e-3
    r2d = np.sqrt(R2 / 2.0)
    lo_x, hi_x, lo_y, hi_y = cx - r2d, cx + r2d, cy - r2d, cy + r2d
    iR2 = 1.0 / R2
    c22 = w0 * w0 + w1 * w1 - w2 * w2 * iR2
    degenerate = False
    # Tangent points of the lines x = X (row = Tu) and y = Y (row = Tv), then the chord ends.
    for k in range(6):
        if k < 4:
            if k < 2:
                a0, a1, a2 = u0, u1, u2
            else:
                a0, a1, a2 = v0, v1, v2
            c00 = a0 * a0 + a1 * a1 - a2 * a2 * iR2
            c02 = a0 * w0 + a1 * w1 - a2 * w2 * iR2
            if abs(c22) < 1e-12 * (abs(c02) + abs(c00) + 1e-30):
                degenerate = True
                continue
            disc = np.sqrt(max(c02 * c02 - c00 * c22, 0.0))
            X = (c02 + (disc if k % 2 else -disc)) / c22
            L0, L1, L2 = a0 - X * w0, a1 - X * w1, a2 - X * w2
            if L2 == 0.0:
                L2 = 1e-300
            cu = -L0 * R2 / L2
            cv = -L1 * R2 / L2
        else:
            g2 = w0 * w0 + w1 * w1
            if not g2 > 0.0:
                continue
            kk = (z_min - w2) / g2
            fu, fv = kk * w0, kk * w1
            if not fu * fu + fv * fv < R2:
                continue
            h = np.sqrt(max((R2 - (fu * fu + fv * fv)) / g2, 0.0))
            sg = 1.0 if k == 4 else -1.0
            cu = fu - sg * h * w1
            cv = fv + sg * h * w0
        zc = w0 * cu + w1 * cv + w2
        if not (np.isfinite(zc) and zc >= z_min - 1e-9 and zc > 0.0):
            continue
        px = (u0 * cu + u1 * cv + u2) / zc
        py = (v0 * cu + v1 * cv + v2) / zc
        lo_x = min(lo_x, px)
        hi_x = max(hi_x, px)
        lo_y = min(lo_y, py)
        hi_y = max(hi_y, py)
    if degenerate:
        lo_x, lo_y, hi_x, hi_y = -big, -big, big, big
    if not (np.isfinite(lo_x) and np.isfinite(hi_x) and np.isfinite(lo_y) and np.isfinite(hi_y)):
        return False
    x0 = max(np.ceil(max(lo_x, -big) - 0.5), 0.0)
    x1 = min(np.floor(min(hi_x, big) + 0.5), width - 1.0)
    y0 = max(np.ceil(max(lo_y, -big) - 0.5), 0.0)
    y1 = min(np.floor(min(hi_y, big) + 0.5), height - 1.0)
    if x0 <= x1 and y0 <= y1:
        rect[i, 0] = int(x0)
        rect[i, 1] = int(y0)
        rect[i, 2] = int(x1)
        rect[i, 3] = int(y1)
        return True
    return False


def _k_boxes(rows: np.ndarray, width: int, height: int, near: float, rect: np.ndarray, ok: np.ndarray) -> None:
    """Per-surfel pixel boxes (numba): the same bound as :func:`_pixel_boxes`, one surfel at a time.

    ``rows`` [N, 12] float64: Tu (3), Tv (3), Tw (3), centre x, y, opacity.
    """
    for i in prange(rows.shape[0]):
        r = rows[i]
        on = _pixel_box(
            r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8], r[9], r[10], r[11], width, height, near, rect, i
        )
        ok[i] = 1 if on else 0


def _k_project(
    means: np.ndarray,
    quats: np.ndarray,
    scales: np.ndarray,
    opac: np.ndarray,
    V: np.ndarray,
    Km: np.ndarray,
    width: int,
    height: int,
    near: float,
    far: float,
    pk: np.ndarray,
    nrm: np.ndarray,
    rect: np.ndarray,
    thr: np.ndarray,
    keep: np.ndarray,
) -> None:
    """Projection and culling in one pass (numba): :func:`project_packed`'s rows ``pk`` [N, 14] and
    normals ``nrm`` [N, 3], the pixel box ``rect`` [N, 4], the alpha test threshold ``thr`` (``rho``
    above it means alpha < 1/255) and ``keep`` (centre depth in (near, far] and the box on the image).
    """
    k00, k01, k02, k11, k12 = Km[0, 0], Km[0, 1], Km[0, 2], Km[1, 1], Km[1, 2]
    for i in prange(means.shape[0]):
        qw, qx, qy, qz = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        nc = max(np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
        w, x, y, z = qw / nc, qx / nc, qy / nc, qz / nc
        tu0, tu1, tu2 = 1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)
        tv0, tv1, tv2 = 2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)
        tw0, tw1, tw2 = 2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)
        su, sv = scales[i, 0], scales[i, 1]
        m0, m1, m2 = means[i, 0], means[i, 1], means[i, 2]
        a0 = (V[0, 0] * tu0 + V[0, 1] * tu1 + V[0, 2] * tu2) * su
        a1 = (V[1, 0] * tu0 + V[1, 1] * tu1 + V[1, 2] * tu2) * su
        a2 = (V[2, 0] * tu0 + V[2, 1] * tu1 + V[2, 2] * tu2) * su
        b0 = (V[0, 0] * tv0 + V[0, 1] * tv1 + V[0, 2] * tv2) * sv
        b1 = (V[1, 0] * tv0 + V[1, 1] * tv1 + V[1, 2] * tv2) * sv
        b2 = (V[2, 0] * tv0 + V[2, 1] * tv1 + V[2, 2] * tv2) * sv
        c0 = V[0, 0] * m0 + V[0, 1] * m1 + V[0, 2] * m2 + V[0, 3]
        c1 = V[1, 0] * m0 + V[1, 1] * m1 + V[1, 2] * m2 + V[1, 3]
        c2 = V[2, 0] * m0 + V[2, 1] * m1 + V[2, 2] * m2 + V[2, 3]
        n0 = V[0, 0] * tw0 + V[0, 1] * tw1 + V[0, 2] * tw2
        n1 = V[1, 0] * tw0 + V[1, 1] * tw1 + V[1, 2] * tw2
        n2 = V[2, 0] * tw0 + V[2, 1] * tw1 + V[2, 2] * tw2
        u0, u1, u2 = k00 * a0 + k01 * a1 + k02 * a2, k00 * b0 + k01 * b1 + k02 * b2, k00 * c0 + k01 * c1 + k02 * c2
        v0, v1, v2 = k11 * a1 + k12 * a2, k11 * b1 + k12 * b2, k11 * c1 + k12 * c2
        w0, w1, w2 = a2, b2, c2
        ax0, ax1, ax2 = w2 * v1 - w1 * v2, u2 * w1 - u1 * w2, u1 * v2 - u2 * v1
        ay0, ay1, ay2 = w0 * v2 - w2 * v0, u0 * w2 - u2 * w0, u2 * v0 - u0 * v2
        az0, az1, az2 = w1 * v0 - w0 * v1, u1 * w0 - u0 * w1, u0 * v1 - u1 * v0
        in_range = c2 > near and c2 <= far
        zs = c2 if in_range else 1.0
        o = opac[i]
        pk[i, 0], pk[i, 1], pk[i, 2], pk[i, 3], pk[i, 4], pk[i, 5] = ax0, ax1, ax2, ay0, ay1, ay2
        pk[i, 6], pk[i, 7], pk[i, 8] = az0, az1, az2
        pk[i, 9] = w0 * ax2 + w1 * ay2 + w2 * az2
        pk[i, 10], pk[i, 11], pk[i, 12], pk[i, 13] = c2, u2 / zs, v2 / zs, o
        sg = -1.0 if n0 * c0 + n1 * c1 + n2 * c2 > 0 else 1.0
        nrm[i, 0], nrm[i, 1], nrm[i, 2] = sg * n0, sg * n1, sg * n2
        thr[i] = 2.0 * np.log(max(255.0 * o, 1e-300)) * (1 + 1e-6) + 1e-6
        keep[i] = 0
        if in_range:  # the box only of surfels that can be kept
            on = _pixel_box(u0, u1, u2, v0, v1, v2, w0, w1, w2, u2 / zs, v2 / zs, o, width, height, near, rect, i)
            keep[i] = 1 if on else 0
        else:
            rect[i, 0] = 0
            rect[i, 1] = 0
            rect[i, 2] = -1
            rect[i, 3] = -1


def _argsort_positive(z: np.ndarray) -> np.ndarray:
    """Stable argsort of positive float64 values (numba helper): LSD radix sort of their bit patterns.

    Positive IEEE doubles order as their bits do; 8-bit digits, a pass skipped when every value has
    the same digit.
    """
    n = z.shape[0]
    keys = z.view(np.uint64)
    idx = np.arange(n)
    tmp = np.empty(n, np.int64)
    cnt = np.empty(257, np.int64)
    for shift in range(0, 64, 8):
        sh = np.uint64(shift)
        for k in range(257):
            cnt[k] = 0
        for i in range(n):
            cnt[((keys[idx[i]] >> sh) & np.uint64(255)) + 1] += 1
        if cnt.max() == n:
            continue
        for k in range(256):
            cnt[k + 1] += cnt[k]
        for i in range(n):
            d = (keys[idx[i]] >> sh) & np.uint64(255)
            tmp[cnt[d]] = idx[i]
            cnt[d] += 1
        idx, tmp = tmp, idx
    return idx


def _k_bin(
    pk: np.ndarray,
    nrm: np.ndarray,
    rect: np.ndarray,
    thr: np.ndarray,
    keep: np.ndarray,
    feats: np.ndarray,
    ts: int,
    ntx: int,
    nty: int,
    n_blocks: int,
) -> tuple[np.ndarray, ...]:
    """Sort the kept surfels by centre depth (stable), renumber them by that order and bin them into tiles.

    Returns ``order`` [K] (input index of each kept surfel, nearest first), their rows ``pk``,
    ``nrm``, ``rect``, ``thr``, ``feats``, the tile lists (``surf``, ``start``, ``count``: ids in
    depth order) and ``bounds``, ``n_blocks`` contiguous ranges of tiles of about equal work.
    """
    n = keep.shape[0]
    nk = 0
    for i in range(n):
        nk += keep[i]
    kept = np.empty(nk, np.int64)
    j = 0
    for i in range(n):
        if keep[i]:
            kept[j] = i
            j += 1
    z = np.empty(nk)
    for j in range(nk):
        z[j] = pk[kept[j], 10]
    order = kept[_argsort_positive(z)]  # kept centres are beyond the near plane: z > 0
    n_ch = feats.shape[1]
    pk_l = np.empty((nk, 14))
    nrm_l = np.empty((nk, 3))
    rect_l = np.empty((nk, 4), np.int32)
    thr_l = np.empty(nk)
    feats_l = np.empty((nk, n_ch))
    n_tiles = ntx * nty
    for j in prange(nk):  # a gather in depth order: memory-latency bound, so both threads
        i = order[j]
        for k in range(14):
            pk_l[j, k] = pk[i, k]
        for k in range(3):
            nrm_l[j, k] = nrm[i, k]
        for k in range(4):
            rect_l[j, k] = rect[i, k]
        thr_l[j] = thr[i]
        for k in range(n_ch):
            feats_l[j, k] = feats[i, k]
    count = np.zeros(n_tiles, np.int64)
    for j in range(nk):
        for ty in range(rect_l[j, 1] // ts, rect_l[j, 3] // ts + 1):
            for tx in range(rect_l[j, 0] // ts, rect_l[j, 2] // ts + 1):
                count[ty * ntx + tx] += 1
    start = np.empty(n_tiles, np.int64)
    acc = 0
    for t in range(n_tiles):
        start[t] = acc
        acc += count[t]
    fill = start.copy()
    surf = np.empty(acc, np.int32)
    for j in range(nk):
        for ty in range(rect_l[j, 1] // ts, rect_l[j, 3] // ts + 1):
            for tx in range(rect_l[j, 0] // ts, rect_l[j, 2] // ts + 1):
                t = ty * ntx + tx
                surf[fill[t]] = j
                fill[t] += 1
    return order, pk_l, nrm_l, rect_l, thr_l, feats_l, surf, start, count, _tile_bounds(count, n_blocks)


def _tile_bounds(count: np.ndarray, n_blocks: int) -> np.ndarray:
    """``n_blocks`` contiguous ranges of the tiles of about equal work (entries + 1 per tile), as
    :func:`~roigsf_ros.render.numba_setup.balanced_bounds` (numba helper): the blocks' tile bounds [n_blocks + 1].
    """
    n_tiles = count.shape[0]
    bounds = np.empty(n_blocks + 1, np.int64)
    bounds[0] = 0
    bounds[n_blocks] = n_tiles
    total = n_tiles
    for t in range(n_tiles):
        total += count[t]
    cum = 0
    t = 0
    for blk in range(1, n_blocks):
        goal = total * blk / n_blocks
        while t < n_tiles and cum + count[t] + 1 <= goal:
            cum += count[t] + 1
            t += 1
        bounds[blk] = t
    return bounds


def _k_mask_tiles(
    pixel_mask: np.ndarray, width: int, height: int, ts: int, ntx: int, count: np.ndarray, n_blocks: int
) -> np.ndarray:
    """Zeroes ``count`` [T] (in place) of the tiles with no pixel in ``pixel_mask`` [H * W] (bool) and returns the
    blocks' tile bounds over what is left (:func:`_tile_bounds`).
    """
    for t in range(count.shape[0]):
        if count[t] == 0:
            continue
        x0 = (t % ntx) * ts
        y0 = (t // ntx) * ts
        on = False
        for y in range(y0, min(y0 + ts, height)):
            for x in range(x0, min(x0 + ts, width)):
                on = on or pixel_mask[y * width + x]
        if not on:
            count[t] = 0
    return _tile_bounds(count, n_blocks)


def _k_forward(
    pk: np.ndarray,
    feats: np.ndarray,
    nrm: np.ndarray,
    bg: np.ndarray,
    thr: np.ndarray,
    rect: np.ndarray,
    tl_surf: np.ndarray,
    t_start: np.ndarray,
    t_count: np.ndarray,
    bounds: np.ndarray,
    width: int,
    height: int,
    ts: int,
    ntx: int,
    near: float,
    far: float,
    with_dist: bool,
    compact: bool,
    store: bool,
    o_feat: np.ndarray,
    o_alpha: np.ndarray,
    o_depth: np.ndarray,
    o_median: np.ndarray,
    o_normal: np.ndarray,
    o_dist: np.ndarray,
    o_count: np.ndarray,
    o_medidx: np.ndarray,
    o_T: np.ndarray,
    o_M1: np.ndarray,
    o_M2: np.ndarray,
    pair_buf: np.ndarray,
    pair_e: np.ndarray,
    pix_off: np.ndarray,
    o_vis: np.ndarray,
    t_last: np.ndarray,
) -> None:
    """Forward walk (numba): per tile, its depth-sorted list in chunks; a lane pass, then each pixel.

    The lane pass computes, for every pixel of the tile and every surfel of the chunk, alpha (0
    where the pair is skipped: outside the surfel's box, ``p_z == 0``, ``rho`` above the threshold,
    depth before the near plane, alpha < 1/255) and depth, in a loop over the chunk's surfels
    that LLVM vectorises. Each pixel then composites its chunk front to back (stopping, without the
    crossing surfel, once transmittance would fall below 1e-4), exactly as a per-pixel walk. Writes
    the outputs, the accepted surfel ids per pixel (``pair_buf`` from ``pix_off``), the sums the
    backward needs and ``t_last[t]``, one past the last list position any pixel of tile t accepted.
    Pixel q of tile t stores its ids from ``Q * start[t] + q * count[t]`` (a bound that needs no
    counting pass), or with ``compact`` from the given ``pix_off``; ``store=False`` only counts.
    ``with_dist=False`` skips the distortion sums (zeros).
    """
    n_ch = feats.shape[1]
    mscale = far / (far - near)
    Q = ts * ts
    CH = _CHUNK
    for b in prange(bounds.shape[0] - 1):
        S = np.zeros((18 + n_ch, CH))  # the chunk's packed rows (14), threshold, normals (3), features (C)
        sidj = np.empty(CH, np.int64)
        box = np.zeros((4, CH))
        al = np.empty((Q, CH))
        dep = np.empty((Q, CH))
        mz = np.empty((Q, CH))
        WL = np.empty(CH)
        visj = np.empty(CH, np.bool_)
        Tq = np.empty(Q)
        cnt = np.empty(Q, np.int64)
        done = np.empty(Q, np.bool_)
        D = np.empty(Q)
        M1 = np.empty(Q)
        M2 = np.empty(Q)
        dist = np.empty(Q)
        med = np.empty(Q)
        medi = np.empty(Q, np.int64)
        accn = np.empty((Q, 3))
        accf = np.empty((Q, n_ch))
        base = np.empty(Q, np.int64)
        idx = np.empty(CH, np.int64)
        for t in range(bounds[b], bounds[b + 1]):
            n_t = t_count[t]
            s = t_start[t]
            x_base = (t % ntx) * ts
            y_base = (t // ntx) * ts
            n_done = 0
            for q in range(Q):
                xi = x_base + q % ts
                yi = y_base + q // ts
                base[q] = Q * s + q * n_t
                if compact and xi < width and yi < height:
                    base[q] = pix_off[yi * width + xi]
                Tq[q] = 1.0
                cnt[q] = 0
                D[q] = 0.0
                M1[q] = 0.0
                M2[q] = 0.0
                dist[q] = 0.0
                med[q] = 0.0
                medi[q] = -1
                for c in range(3):
                    accn[q, c] = 0.0
                for c in range(n_ch):
                    accf[q, c] = 0.0
                done[q] = xi >= width or yi >= height
                if done[q]:
                    n_done += 1
            last = 0
            for lo in range(0, n_t, CH):
                if n_done == Q:
                    break
                n = min(CH, n_t - lo)
                npad = (n + 7) // 8 * 8
                for j in range(npad):
                    visj[j] = False
                    if j < n:
                        sid = tl_surf[s + lo + j]
                        sidj[j] = sid
                        for k in range(14):
                            S[k, j] = pk[sid, k]
                        S[14, j] = thr[sid]
                        for k in range(3):
                            S[15 + k, j] = nrm[sid, k]
                        for k in range(n_ch):
                            S[18 + k, j] = feats[sid, k]
                        box[0, j] = float(max(rect[sid, 0], x_base))
                        box[1, j] = float(min(rect[sid, 2], x_base + ts - 1))
                        box[2, j] = float(max(rect[sid, 1], y_base))
                        box[3, j] = float(min(rect[sid, 3], y_base + ts - 1))
                    else:  # padding: an empty box
                        box[0, j] = 1.0
                        box[1, j] = 0.0
                a0s, a1s, a2s, b0s, b1s, b2s = S[0], S[1], S[2], S[3], S[4], S[5]
                c0s, c1s, c2s, dets, tzs, cxs, cys, opas, ths = (
                    S[6],
                    S[7],
                    S[8],
                    S[9],
                    S[10],
                    S[11],
                    S[12],
                    S[13],
                    S[14],
                )
                n0s, n1s, n2s = S[15], S[16], S[17]
                bx0, bx1, by0, by1 = box[0], box[1], box[2], box[3]
                # Lane pass: alpha (0 = skipped) and depth of every (pixel, surfel of the chunk).
                for q in range(Q):
                    if done[q]:
                        continue
                    x = float(x_base + q % ts)
                    y = float(y_base + q // ts)
                    alq = al[q]
                    depq = dep[q]
                    for j in range(npad):
                        pz = c0s[j] * x + c1s[j] * y + c2s[j]
                        nz = pz != 0.0
                        inv = 1.0 / (pz if nz else 1.0)
                        u = (a0s[j] * x + a1s[j] * y + a2s[j]) * inv
                        v = (b0s[j] * x + b1s[j] * y + b2s[j]) * inv
                        r3 = u * u + v * v
                        dx = cxs[j] - x
                        dy = cys[j] - y
                        r2 = 2.0 * (dx * dx + dy * dy)
                        use3 = r3 <= r2
                        rho = r3 if use3 else r2
                        depth = dets[j] * inv if use3 else tzs[j]
                        ok = (x >= bx0[j]) & (x <= bx1[j]) & (y >= by0[j]) & (y <= by1[j])
                        ok = ok & nz & (rho <= ths[j]) & (depth >= near)
                        a = opas[j] * exp_neg(-0.5 * rho if ok else 0.0)
                        a = 0.99 if a > 0.99 else a
                        ok = ok & (a >= 1.0 / 255.0)
                        alq[j] = a if ok else 0.0
                        depq[j] = depth if ok else 1.0
                    if with_dist:
                        mzq = mz[q]
                        for j in range(npad):
                            mzq[j] = mscale * (1.0 - near / depq[j])
                # Each pixel composites the chunk front to back: a walk over the accepted lanes for
                # transmittance and the weights, then the weighted sums over the lanes (vectorised).
                for q in range(Q):
                    if done[q]:
                        continue
                    T = Tq[q]
                    c = cnt[q]
                    M1q, M2q, dq, mq, mi = M1[q], M2[q], dist[q], med[q], medi[q]
                    nacc = 0
                    alq = al[q]
                    depq = dep[q]
                    mzq = mz[q]
                    for j in range(npad):
                        WL[j] = 0.0
                        idx[nacc] = j
                        nacc += alq[j] > 0.0
                    for kk in range(nacc):
                        j = idx[kk]
                        a = alq[j]
                        test_T = T * (1.0 - a)
                        if test_T < 1e-4:
                            done[q] = True
                            n_done += 1
                            break
                        w = a * T
                        WL[j] = w
                        if with_dist:
                            m = mzq[j]
                            dq += w * (m * m * (1.0 - T) + M2q - 2.0 * m * M1q)
                            M1q += w * m
                            M2q += w * m * m
                        up = T > 0.5  # median: the last surfel hit while T > 0.5 (a select, no branch)
                        mq = depq[j] if up else mq
                        mi = c if up else mi
                        if store:
                            pair_buf[base[q] + c] = sidj[j]
                            pair_e[base[q] + c] = lo + j
                        c += 1
                        T = test_T
                        last = max(last, lo + j + 1)
                    Tq[q] = T
                    cnt[q] = c
                    M1[q], M2[q], dist[q], med[q], medi[q] = M1q, M2q, dq, mq, mi
                    sd = 0.0
                    s0 = 0.0
                    s1 = 0.0
                    s2 = 0.0
                    for j in range(npad):
                        w = WL[j]
                        hit = w != 0.0
                        visj[j] |= hit
                        sd += w * depq[j]
                        s0 += w * n0s[j] if hit else 0.0
                        s1 += w * n1s[j] if hit else 0.0
                        s2 += w * n2s[j] if hit else 0.0
                    D[q] += sd
                    accn[q, 0] += s0
                    accn[q, 1] += s1
                    accn[q, 2] += s2
                    for ch in range(n_ch):
                        fc = S[18 + ch]
                        sf = 0.0
                        for j in range(npad):
                            w = WL[j]
                            sf += w * fc[j] if w != 0.0 else 0.0
                        accf[q, ch] += sf
                for j in range(n):
                    if visj[j]:
                        o_vis[sidj[j]] = 1  # idempotent store; concurrent writers all write 1
            t_last[t] = last
            for q in range(Q):
                xi = x_base + q % ts
                yi = y_base + q // ts
                if xi >= width or yi >= height:
                    continue
                p = yi * width + xi
                pix_off[p] = base[q]
                T = Tq[q]
                for c in range(n_ch):
                    o_feat[p, c] = accf[q, c] + T * bg[c]
                o_alpha[p] = 1.0 - T
                o_depth[p] = D[q]
                o_median[p] = med[q]
                for c in range(3):
                    o_normal[p, c] = accn[q, c]
                o_dist[p] = dist[q]
                o_count[p] = cnt[q]
                o_medidx[p] = medi[q]
                o_T[p] = T
                o_M1[p] = M1[q]
                o_M2[p] = M2[q]


def _k_backward(
    pk: np.ndarray,
    feats: np.ndarray,
    nrm: np.ndarray,
    bg: np.ndarray,
    tl_surf: np.ndarray,
    t_start: np.ndarray,
    t_last: np.ndarray,
    bounds: np.ndarray,
    width: int,
    height: int,
    ts: int,
    ntx: int,
    pair_e: np.ndarray,
    pix_off: np.ndarray,
    count: np.ndarray,
    medidx: np.ndarray,
    T_fin: np.ndarray,
    M1t: np.ndarray,
    M2t: np.ndarray,
    near: float,
    far: float,
    with_dist: bool,
    g_feat: np.ndarray,
    g_alpha: np.ndarray,
    g_depth: np.ndarray,
    g_med: np.ndarray,
    g_normal: np.ndarray,
    g_dist: np.ndarray,
    gp: np.ndarray,
    gf: np.ndarray,
    gn: np.ndarray,
) -> None:
    """Backward walk (numba): per tile, its list back to front in chunks of _CHUNK surfels.

    Per chunk and pixel: a lane pass (vectorised) computes for every surfel of the chunk alpha,
    ``1 / (1 - alpha)`` and ``val``, the gradient of the pixel's loss with respect to the surfel's
    weight; the pixel then walks its accepted surfels of the chunk back to front (``pair_e``: their
    list positions), rebuilding transmittance by division as 2DGS's per-pixel backward does, which
    gives each one's weight and ``dA``, the gradient with respect to its alpha; a second lane pass
    (vectorised) turns these into gradients of the packed rows, normal and features, summed per
    surfel of the chunk and added once per (tile, surfel) to the block's buffers ``gp`` [B, K, 14],
    ``gn`` [B, K, 3], ``gf`` [B, K, C].
    """
    n_ch = feats.shape[1]
    mscale = far / (far - near)
    Q = ts * ts
    CH = _CHUNK
    NG = 17 + n_ch
    for b in prange(bounds.shape[0] - 1):
        S = np.zeros((NG, CH))  # the chunk's packed rows (14), normals (3), features (C)
        sidj = np.empty(CH, np.int64)
        EX = np.empty(CH)  # exp(-rho / 2)
        INV = np.empty(CH)  # 1 / p_z
        AQ = np.empty(CH)  # alpha (clamped)
        IM = np.empty(CH)  # 1 / (1 - alpha)
        VAL = np.empty(CH)  # d loss / d weight
        DDW = np.empty(CH)  # distortion part of d loss / d depth, per unit weight
        WL = np.empty(CH)  # weight of the accepted pairs (0 elsewhere)
        DA = np.empty(CH)  # d loss / d alpha of the accepted pairs
        GX = np.empty(CH)  # median-depth gradient of the pair that gave the median
        AC = np.empty(CH, np.bool_)  # accepted pairs of the pixel
        G = np.zeros((NG, CH))  # per chunk surfel: gradients of the packed rows, normal, features
        hitj = np.empty(CH, np.bool_)
        ptr = np.empty(Q, np.int64)
        off = np.empty(Q, np.int64)
        Tq = np.empty(Q)
        Sq = np.empty(Q)
        for t in range(bounds[b], bounds[b + 1]):
            s = t_start[t]
            x_base = (t % ntx) * ts
            y_base = (t // ntx) * ts
            active = 0
            for q in range(Q):
                xi = x_base + q % ts
                yi = y_base + q // ts
                ptr[q] = -1
                off[q] = 0
                Tq[q] = 1.0
                Sq[q] = 0.0
                if xi >= width or yi >= height:
                    continue
                p = yi * width + xi
                ptr[q] = count[p] - 1
                off[q] = pix_off[p]
                if ptr[q] >= 0:
                    active += 1
                Tq[q] = T_fin[p]
                acc = 0.0
                for c in range(n_ch):
                    acc += g_feat[p, c] * bg[c]
                Sq[q] = T_fin[p] * acc
            hi = t_last[t]
            while hi > 0 and active > 0:
                lo = max(0, hi - CH)
                n = hi - lo
                npad = (n + 7) // 8 * 8
                for j in range(npad):
                    if j < n:
                        sid = tl_surf[s + lo + j]
                        sidj[j] = sid
                        for k in range(14):
                            S[k, j] = pk[sid, k]
                        for k in range(3):
                            S[14 + k, j] = nrm[sid, k]
                        for k in range(n_ch):
                            S[17 + k, j] = feats[sid, k]
                    else:
                        for k in range(NG):
                            S[k, j] = 0.0
                        S[8, j] = 1.0
                    hitj[j] = False
                    for k in range(NG):
                        G[k, j] = 0.0
                a0s, a1s, a2s, b0s, b1s, b2s = S[0], S[1], S[2], S[3], S[4], S[5]
                c0s, c1s, c2s, dets, tzs, cxs, cys, opas = S[6], S[7], S[8], S[9], S[10], S[11], S[12], S[13]
                n0s, n1s, n2s = S[14], S[15], S[16]
                for q in range(Q):
                    if ptr[q] < 0 or pair_e[off[q] + ptr[q]] < lo:
                        continue
                    xi = x_base + q % ts
                    yi = y_base + q // ts
                    x = float(xi)
                    y = float(yi)
                    p = yi * width + xi
                    ga, gdp, gdi = g_alpha[p], g_depth[p], g_dist[p]
                    gn0, gn1, gn2 = g_normal[p, 0], g_normal[p, 1], g_normal[p, 2]
                    Wt = 1.0 - T_fin[p]
                    M1 = M1t[p]
                    M2 = M2t[p]
                    # Lane pass 1: alpha, 1 / (1 - alpha) and d loss / d weight of every surfel of the chunk.
                    for j in range(npad):
                        pz = c0s[j] * x + c1s[j] * y + c2s[j]
                        inv = 1.0 / (pz if pz != 0.0 else 1.0)
                        u = (a0s[j] * x + a1s[j] * y + a2s[j]) * inv
                        v = (b0s[j] * x + b1s[j] * y + b2s[j]) * inv
                        r3 = u * u + v * v
                        dx = cxs[j] - x
                        dy = cys[j] - y
                        r2 = 2.0 * (dx * dx + dy * dy)
                        use3 = r3 <= r2
                        rho = r3 if use3 else r2
                        depth = dets[j] * inv if use3 else tzs[j]
                        ex = exp_neg(-0.5 * rho if rho < 40.0 else -20.0)
                        a = opas[j] * ex
                        a = 0.99 if a > 0.99 else a
                        EX[j] = ex
                        INV[j] = inv
                        AQ[j] = a
                        IM[j] = 1.0 / (1.0 - a)
                        val = ga + gdp * depth
                        if with_dist:
                            inv_d = 1.0 / depth
                            m = mscale * (1.0 - near * inv_d)
                            val += gdi * (m * m * Wt - 2.0 * m * M1 + M2)
                            DDW[j] = gdi * 2.0 * (m * Wt - M1) * mscale * near * inv_d * inv_d
                        val += gn0 * n0s[j] + gn1 * n1s[j]
                        val += gn2 * n2s[j]
                        VAL[j] = val
                    for c in range(n_ch):
                        gc = g_feat[p, c]
                        fc = S[17 + c]
                        for j in range(npad):
                            VAL[j] += gc * fc[j]
                    # The pixel's accepted surfels of the chunk, back to front: weight and d loss / d alpha.
                    for j in range(npad):
                        WL[j] = 0.0
                        DA[j] = 0.0
                        GX[j] = 0.0
                        AC[j] = False
                    T = Tq[q]
                    Sp = Sq[q]
                    i = ptr[q]
                    o = off[q]
                    md = medidx[p]
                    while i >= 0:
                        e = pair_e[o + i]
                        if e < lo:
                            break
                        j = e - lo
                        inv1m = IM[j]
                        val = VAL[j]
                        T = T * inv1m
                        w = AQ[j] * T
                        DA[j] = T * val - Sp * inv1m
                        Sp += w * val
                        WL[j] = w
                        AC[j] = True
                        hitj[j] = True
                        if i == md:
                            GX[j] = g_med[p]
                        i -= 1
                    if i < 0:
                        active -= 1
                    ptr[q] = i
                    Tq[q] = T
                    Sq[q] = Sp
                    # Lane pass 2: gradients of the packed rows, normal and features, summed per surfel.
                    G0, G1, G2, G3, G4, G5, G6 = G[0], G[1], G[2], G[3], G[4], G[5], G[6]
                    G7, G8, G9, G10, G11, G12, G13 = G[7], G[8], G[9], G[10], G[11], G[12], G[13]
                    GN0, GN1, GN2 = G[14], G[15], G[16]
                    for j in range(npad):
                        ok = AC[j]
                        inv = INV[j]
                        u = (a0s[j] * x + a1s[j] * y + a2s[j]) * inv
                        v = (b0s[j] * x + b1s[j] * y + b2s[j]) * inv
                        r3 = u * u + v * v
                        dx = cxs[j] - x
                        dy = cys[j] - y
                        r2 = 2.0 * (dx * dx + dy * dy)
                        use3 = (r3 <= r2) & ok
                        use2 = (r3 > r2) & ok
                        w = WL[j]
                        dA = DA[j]
                        ex = EX[j]
                        free = (opas[j] * ex <= 0.99) & ok  # alpha not clamped
                        grho = -0.5 * (opas[j] * ex) * dA if free else 0.0
                        gdep = gdp * w
                        if with_dist:
                            gdep += DDW[j] * w if ok else 0.0
                        gdep += GX[j]
                        depth = dets[j] * inv
                        gu = grho * 2.0 * u
                        gv = grho * 2.0 * v
                        gpx = gu * inv if use3 else 0.0
                        gpy = gv * inv if use3 else 0.0
                        gpz = (-(gu * u + gv * v) * inv - gdep * depth * inv) if use3 else 0.0
                        G0[j] += gpx * x
                        G1[j] += gpx * y
                        G2[j] += gpx
                        G3[j] += gpy * x
                        G4[j] += gpy * y
                        G5[j] += gpy
                        G6[j] += gpz * x
                        G7[j] += gpz * y
                        G8[j] += gpz
                        G9[j] += gdep * inv if use3 else 0.0
                        G10[j] += gdep if use2 else 0.0
                        G11[j] += grho * 4.0 * dx if use2 else 0.0
                        G12[j] += grho * 4.0 * dy if use2 else 0.0
                        G13[j] += dA * ex if free else 0.0
                        GN0[j] += gn0 * w
                        GN1[j] += gn1 * w
                        GN2[j] += gn2 * w
                    for c in range(n_ch):
                        gc = g_feat[p, c]
                        Gc = G[17 + c]
                        for j in range(npad):
                            Gc[j] += gc * WL[j]
                for j in range(n):
                    if hitj[j]:
                        sid = sidj[j]
                        for k in range(14):
                            gp[b, sid, k] += G[k, j]
                        for k in range(3):
                            gn[b, sid, k] += G[14 + k, j]
                        for c in range(n_ch):
                            gf[b, sid, c] += G[17 + c, j]
                hi = lo


def _k_project_vjp(
    means: np.ndarray,
    quats: np.ndarray,
    scales: np.ndarray,
    V: np.ndarray,
    Km: np.ndarray,
    near: float,
    far: float,
    order: np.ndarray,
    gp: np.ndarray,
    gn: np.ndarray,
    gf: np.ndarray,
    g_means: np.ndarray,
    g_quats: np.ndarray,
    g_scales: np.ndarray,
    g_opac: np.ndarray,
    g_feats: np.ndarray,
) -> None:
    """Backward of :func:`_k_project` (numba): the block sums of ``gp`` [B, K, 14] (packed rows), ``gn``
    [B, K, 3] (normals) and ``gf`` [B, K, C] (features) of the kept surfels, chained to the inputs'
    gradients (means, quats, scales, opacities, features) at the rows ``order`` names.
    """
    k00, k01, k02, k11, k12 = Km[0, 0], Km[0, 1], Km[0, 2], Km[1, 1], Km[1, 2]
    nb = gp.shape[0]
    n_ch = gf.shape[2]
    for j in prange(order.shape[0]):
        i = order[j]
        g0 = g1 = g2 = g3 = g4 = g5 = g6 = g7 = g8 = g9 = g10 = g11 = g12 = g13 = 0.0
        gn0 = gn1 = gn2 = 0.0
        for b in range(nb):
            gb = gp[b, j]
            g0 += gb[0]
            g1 += gb[1]
            g2 += gb[2]
            g3 += gb[3]
            g4 += gb[4]
            g5 += gb[5]
            g6 += gb[6]
            g7 += gb[7]
            g8 += gb[8]
            g9 += gb[9]
            g10 += gb[10]
            g11 += gb[11]
            g12 += gb[12]
            g13 += gb[13]
            gn0 += gn[b, j, 0]
            gn1 += gn[b, j, 1]
            gn2 += gn[b, j, 2]
        for c in range(n_ch):
            acc = 0.0
            for b in range(nb):
                acc += gf[b, j, c]
            g_feats[i, c] = acc
        # Forward quantities (as _k_project).
        qw, qx, qy, qz = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        nq = np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        nc = max(nq, 1e-12)
        w, x, y, z = qw / nc, qx / nc, qy / nc, qz / nc
        tu0, tu1, tu2 = 1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)
        tv0, tv1, tv2 = 2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)
        tw0, tw1, tw2 = 2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)
        su, sv = scales[i, 0], scales[i, 1]
        m0, m1, m2 = means[i, 0], means[i, 1], means[i, 2]
        ra0 = V[0, 0] * tu0 + V[0, 1] * tu1 + V[0, 2] * tu2
        ra1 = V[1, 0] * tu0 + V[1, 1] * tu1 + V[1, 2] * tu2
        ra2 = V[2, 0] * tu0 + V[2, 1] * tu1 + V[2, 2] * tu2
        rb0 = V[0, 0] * tv0 + V[0, 1] * tv1 + V[0, 2] * tv2
        rb1 = V[1, 0] * tv0 + V[1, 1] * tv1 + V[1, 2] * tv2
        rb2 = V[2, 0] * tv0 + V[2, 1] * tv1 + V[2, 2] * tv2
        a0, a1, a2 = ra0 * su, ra1 * su, ra2 * su
        b0, b1, b2 = rb0 * sv, rb1 * sv, rb2 * sv
        c0 = V[0, 0] * m0 + V[0, 1] * m1 + V[0, 2] * m2 + V[0, 3]
        c1 = V[1, 0] * m0 + V[1, 1] * m1 + V[1, 2] * m2 + V[1, 3]
        c2 = V[2, 0] * m0 + V[2, 1] * m1 + V[2, 2] * m2 + V[2, 3]
        n0 = V[0, 0] * tw0 + V[0, 1] * tw1 + V[0, 2] * tw2
        n1 = V[1, 0] * tw0 + V[1, 1] * tw1 + V[1, 2] * tw2
        n2 = V[2, 0] * tw0 + V[2, 1] * tw1 + V[2, 2] * tw2
        u0, u1, u2 = k00 * a0 + k01 * a1 + k02 * a2, k00 * b0 + k01 * b1 + k02 * b2, k00 * c0 + k01 * c1 + k02 * c2
        v0, v1, v2 = k11 * a1 + k12 * a2, k11 * b1 + k12 * b2, k11 * c1 + k12 * c2
        w0, w1, w2 = a2, b2, c2
        ax2 = u1 * v2 - u2 * v1
        ay2 = u2 * v0 - u0 * v2
        az2 = u0 * v1 - u1 * v0
        in_range = c2 > near and c2 <= far
        zs = c2 if in_range else 1.0
        sg = -1.0 if n0 * c0 + n1 * c1 + n2 * c2 > 0 else 1.0
        # Reverse: packed rows -> Tu (u), Tv (v), Tw (w).
        gdet = g9
        gax0, gax1, gax2 = g0, g1, g2 + gdet * w0
        gay0, gay1, gay2 = g3, g4, g5 + gdet * w1
        gaz0, gaz1, gaz2 = g6, g7, g8 + gdet * w2
        gw0 = gdet * ax2 + gay0 * v2 - gay1 * u2 - gaz0 * v1 + gaz1 * u1
        gw1 = gdet * ay2 - gax0 * v2 + gax1 * u2 + gaz0 * v0 - gaz1 * u0
        gw2 = gdet * az2 + gax0 * v1 - gax1 * u1 - gay0 * v0 + gay1 * u0 + g10
        gu0 = gay1 * w2 - gay2 * v2 - gaz1 * w1 + gaz2 * v1
        gu1 = -gax1 * w2 + gax2 * v2 + gaz1 * w0 - gaz2 * v0
        gu2 = gax1 * w1 - gax2 * v1 - gay1 * w0 + gay2 * v0
        gv0 = -gay0 * w2 + gay2 * u2 + gaz0 * w1 - gaz2 * u1
        gv1 = gax0 * w2 - gax2 * u2 - gaz0 * w0 + gaz2 * u0
        gv2 = -gax0 * w1 + gax2 * u1 + gay0 * w0 - gay2 * u0
        if in_range:
            gu2 += g11 / zs
            gv2 += g12 / zs
            gw2 -= (g11 * (u2 / zs) + g12 * (v2 / zs)) / zs
        else:
            gu2 += g11
            gv2 += g12
        # Tu_j = k00 A0j + k01 A1j + k02 A2j, Tv_j = k11 A1j + k12 A2j, Tw_j = A2j; A = [a b c].
        ga0, ga1, ga2 = k00 * gu0, k01 * gu0 + k11 * gv0, k02 * gu0 + k12 * gv0 + gw0
        gb0, gb1, gb2 = k00 * gu1, k01 * gu1 + k11 * gv1, k02 * gu1 + k12 * gv1 + gw1
        gc0, gc1, gc2 = k00 * gu2, k01 * gu2 + k11 * gv2, k02 * gu2 + k12 * gv2 + gw2
        g_scales[i, 0] = ga0 * ra0 + ga1 * ra1 + ga2 * ra2
        g_scales[i, 1] = gb0 * rb0 + gb1 * rb1 + gb2 * rb2
        g_opac[i] = g13
        for k in range(3):
            g_means[i, k] = V[0, k] * gc0 + V[1, k] * gc1 + V[2, k] * gc2
        gtu0 = (V[0, 0] * ga0 + V[1, 0] * ga1 + V[2, 0] * ga2) * su
        gtu1 = (V[0, 1] * ga0 + V[1, 1] * ga1 + V[2, 1] * ga2) * su
        gtu2 = (V[0, 2] * ga0 + V[1, 2] * ga1 + V[2, 2] * ga2) * su
        gtv0 = (V[0, 0] * gb0 + V[1, 0] * gb1 + V[2, 0] * gb2) * sv
        gtv1 = (V[0, 1] * gb0 + V[1, 1] * gb1 + V[2, 1] * gb2) * sv
        gtv2 = (V[0, 2] * gb0 + V[1, 2] * gb1 + V[2, 2] * gb2) * sv
        gtw0 = (V[0, 0] * gn0 + V[1, 0] * gn1 + V[2, 0] * gn2) * sg
        gtw1 = (V[0, 1] * gn0 + V[1, 1] * gn1 + V[2, 1] * gn2) * sg
        gtw2 = (V[0, 2] * gn0 + V[1, 2] * gn1 + V[2, 2] * gn2) * sg
        # Rotation columns of the normalised quaternion (w, x, y, z).
        gqw = 2.0 * (z * gtu1 - y * gtu2 - z * gtv0 + x * gtv2 + y * gtw0 - x * gtw1)
        gqx = 2.0 * (y * gtu1 + z * gtu2 + y * gtv0 - 2.0 * x * gtv1 + w * gtv2 + z * gtw0 - w * gtw1 - 2.0 * x * gtw2)
        gqy = 2.0 * (-2.0 * y * gtu0 + x * gtu1 - w * gtu2 + x * gtv0 + z * gtv2 + w * gtw0 + z * gtw1 - 2.0 * y * gtw2)
        gqz = 2.0 * (-2.0 * z * gtu0 + w * gtu1 + x * gtu2 - w * gtv0 - 2.0 * z * gtv1 + y * gtv2 + x * gtw0 + y * gtw1)
        if nq > 1e-12:
            dot = w * gqw + x * gqx + y * gqy + z * gqz
            g_quats[i, 0] = (gqw - w * dot) / nq
            g_quats[i, 1] = (gqx - x * dot) / nq
            g_quats[i, 2] = (gqy - y * dot) / nq
            g_quats[i, 3] = (gqz - z * dot) / nq
        else:
            g_quats[i, 0] = gqw / nc
            g_quats[i, 1] = gqx / nc
            g_quats[i, 2] = gqy / nc
            g_quats[i, 3] = gqz / nc


_KERNELS = Kernels(
    boxes=_k_boxes,
    project=_k_project,
    bin=_k_bin,
    project_vjp=_k_project_vjp,
    helpers=(_pixel_box, _argsort_positive, _tile_bounds),
)
"""The compiled projection, pixel-box, binning and projection-backward kernels (compiled on first use)."""
_SERIAL_KERNELS = Kernels(parallel=False, mask_tiles=_k_mask_tiles, helpers=(_tile_bounds,))
"""Small one-thread kernels (a tile pass of one view)."""
_RASTER_KERNELS = Kernels(
    # Reassociation lets LLVM vectorise the per-lane sums and contract products into fused
    # multiply-adds (results move by ~1e-16 relative); no "nnan"/"ninf", so non-finite values keep
    # IEEE semantics.
    fastmath={"contract", "reassoc", "nsz", "arcp"},
    forward=_k_forward,
    backward=_k_backward,
    helpers=(exp_neg,),
)
"""The compiled forward and backward compositing kernels (compiled on first use)."""

PAIR_BUFFER_LIMIT = 1 << 25
"""Above this many int32 slots (128 MiB) the forward counts contributions first and stores them compactly."""


@dataclass
class _NumbaResult:
    """Outputs of the numba forward walk (numpy arrays over P pixels) and what the backward needs."""

    feat: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    median: np.ndarray
    normal: np.ndarray
    dist: np.ndarray
    count: np.ndarray
    medidx: np.ndarray
    T: np.ndarray
    M1: np.ndarray
    M2: np.ndarray
    pair_buf: np.ndarray
    pair_e: np.ndarray
    pix_off: np.ndarray
    vis: np.ndarray
    t_last: np.ndarray

    def pairs(self) -> Pairs:
        """The accepted pairs as a flat :class:`Pairs` (per pixel, front to back)."""
        count = torch.from_numpy(self.count.astype(np.int64))
        P = count.numel()
        offsets = torch.zeros(P + 1, dtype=torch.long)
        offsets[1:] = torch.cumsum(count, 0)
        pix = torch.repeat_interleave(torch.arange(P), count)
        start = offsets.index_select(0, pix)
        src = torch.from_numpy(self.pix_off).index_select(0, pix) + torch.arange(pix.numel()) - start
        surf = torch.from_numpy(self.pair_buf.astype(np.int64)).index_select(0, src)
        return Pairs(surf=surf, pix=pix, start=start, offsets=offsets)


@dataclass
class _Binned:
    """Kept surfels of one view as the numba kernels take them (float64 rows, ids in depth order), binned."""

    order: np.ndarray  # [K] input index of each kept surfel, nearest centre first
    pk: np.ndarray  # [K, 14]
    nrm: np.ndarray  # [K, 3]
    rect: np.ndarray  # [K, 4] int32
    thr: np.ndarray  # [K]
    feats: np.ndarray  # [K, C]
    surf: np.ndarray  # tile lists (ids into the K rows), depth order within a tile
    start: np.ndarray
    count: np.ndarray
    bounds: np.ndarray  # tile ranges of the thread blocks
    size: int
    ntx: int


def _f64(t: Tensor) -> np.ndarray:
    """A CPU tensor as a contiguous float64 numpy array (no copy when it already is one)."""
    return t.detach().to(torch.float64).contiguous().numpy()


def _project_and_bin(
    means: np.ndarray,
    quats: np.ndarray,
    scales: np.ndarray,
    opac: np.ndarray,
    feats: np.ndarray,
    V: np.ndarray,
    Km: np.ndarray,
    width: int,
    height: int,
    near: float,
    far: float,
    tile_size: int,
) -> _Binned:
    """Project, cull, sort and bin (numba kernels, float64 inputs)."""
    n = means.shape[0]
    pk = np.empty((n, NPACK))
    nrm = np.empty((n, 3))
    rect = np.empty((n, 4), np.int32)
    thr = np.empty(n)
    keep = np.empty(n, np.uint8)
    ts = int(tile_size)
    ntx, nty = -(-width // ts), -(-height // ts)
    with KERNEL_LOCK:
        _KERNELS["project"](
            means, quats, scales, opac, V, Km, width, height, float(near), float(far), pk, nrm, rect, thr, keep
        )
        out = _KERNELS["bin"](pk, nrm, rect, thr, keep, feats, ts, ntx, nty, n_threads())
    return _Binned(*out, size=ts, ntx=ntx)


def _forward_pass(
    pk: np.ndarray,
    feats: np.ndarray,
    nrm: np.ndarray,
    bg: np.ndarray,
    thr: np.ndarray,
    rect: np.ndarray,
    surf: np.ndarray,
    start: np.ndarray,
    count: np.ndarray,
    bounds: np.ndarray,
    ts: int,
    ntx: int,
    width: int,
    height: int,
    near: float,
    far: float,
    with_dist: bool,
) -> _NumbaResult:
    """The forward kernel on float64 numpy inputs: allocations, the counting pass when needed, the walk."""
    P = width * height
    n_ch = feats.shape[1]
    r = _NumbaResult(
        feat=np.empty((P, n_ch)),
        alpha=np.empty(P),
        depth=np.empty(P),
        median=np.empty(P),
        normal=np.empty((P, 3)),
        dist=np.empty(P),
        count=np.empty(P, np.int32),
        medidx=np.empty(P, np.int32),
        T=np.empty(P),
        M1=np.empty(P),
        M2=np.empty(P),
        pair_buf=np.empty(0, np.int32),
        pair_e=np.empty(0, np.int32),
        pix_off=np.zeros(P, np.int64),
        vis=np.zeros(pk.shape[0], np.uint8),
        t_last=np.zeros(count.shape[0], np.int64),
    )
    bound = ts * ts * surf.shape[0]  # ids one pass can store without counting first
    compact = bound > PAIR_BUFFER_LIMIT

    def walk(compact: bool, store: bool) -> None:
        with KERNEL_LOCK:
            _RASTER_KERNELS["forward"](
                pk, feats, nrm, bg, thr, rect, surf, start, count, bounds, width, height, ts, ntx,
                float(near), float(far), with_dist, compact, store,
                r.feat, r.alpha, r.depth, r.median, r.normal, r.dist, r.count, r.medidx, r.T, r.M1, r.M2,
                r.pair_buf, r.pair_e, r.pix_off, r.vis, r.t_last,
            )  # fmt: skip

    if compact:  # counting pass, then exact per-pixel offsets
        walk(False, False)
        r.pix_off[:] = np.cumsum(r.count, dtype=np.int64) - r.count
        bound = int(r.count.sum())
    r.pair_buf = np.empty(max(1, bound), np.int32)
    r.pair_e = np.empty(max(1, bound), np.int32)
    walk(compact, True)
    return r


def numba_forward(
    proj: Projection,
    features: Tensor,
    bins: TileBins,
    width: int,
    height: int,
    near: float,
    far: float,
    background: Tensor | None,
    with_distortion: bool = True,
) -> _NumbaResult:
    """Run the forward kernel on the surfels of ``proj`` binned by ``bins`` (detached, float64)."""
    pk = _f64(proj.packed.T)
    feats = _f64(features)
    n_ch = feats.shape[1]
    bg = np.zeros(n_ch) if background is None else _f64(background)
    o64 = proj.packed[_OPA].detach().double()
    thr = (2.0 * torch.log((255.0 * o64).clamp_min(1e-300))).numpy() * (1 + 1e-6) + 1e-6
    rect = proj.rect.to(torch.int32).contiguous().numpy()
    bounds = balanced_bounds(bins.count + 1, n_threads())
    return _forward_pass(
        pk, feats, _f64(proj.normals), bg, thr, rect, bins.surf.numpy(), bins.start.numpy(), bins.count.numpy(),
        bounds, bins.size, bins.ntx, width, height, near, far, with_distortion,
    )  # fmt: skip


def numba_bins(
    means: np.ndarray,
    quats: np.ndarray,
    scales: np.ndarray,
    opacities: np.ndarray,
    viewmat: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    near: float = 0.2,
    far: float = 100.0,
    tile_size: int = 4,
    pixel_mask: np.ndarray | None = None,
) -> _Binned:
    """The kept surfels of a view binned into tiles by the numba kernels (float64 numpy inputs, activated
    scales and opacities): projection, culling, depth sort and binning, as the render's forward walk takes them.

    With ``pixel_mask`` [H * W] (bool), the tiles without a pixel in the mask get empty lists (``count`` 0;
    ``bounds`` split the others). Surfel ids in the lists index the returned ``order`` (input indices).
    """
    feats = np.zeros((means.shape[0], 0))
    bn = _project_and_bin(means, quats, scales, opacities, feats, viewmat, K, width, height, near, far, tile_size)
    if pixel_mask is not None:  # one kernel: this is per NBV candidate (issue 12)
        mask = np.ascontiguousarray(pixel_mask, np.bool_).reshape(-1)
        if mask.size != width * height:
            raise ValueError(f"pixel_mask has {mask.size} entries, the image {width * height} pixels")
        with KERNEL_LOCK:
            bn.bounds = _SERIAL_KERNELS["mask_tiles"](mask, width, height, bn.size, bn.ntx, bn.count, n_threads())
    return bn


def numba_pairs(
    means: np.ndarray,
    quats: np.ndarray,
    scales: np.ndarray,
    opacities: np.ndarray,
    viewmat: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    near: float = 0.2,
    far: float = 100.0,
    tile_size: int = 4,
    pixel_mask: np.ndarray | None = None,
) -> tuple[np.ndarray, _NumbaResult]:
    """The contributing pairs of a view by the numba kernels (float64 numpy inputs, activated scales and
    opacities): :func:`numba_bins`, then the forward walk (no features).

    Returns ``order`` [K] (the input index of each kept surfel, nearest centre first) and the walk's
    result, whose surfel ids (``pair_buf``, ``vis``) index ``order``. With ``pixel_mask`` [H * W] (bool),
    only the tiles with a pixel in the mask are walked: the pixels of the others get no pairs.
    """
    bn = numba_bins(means, quats, scales, opacities, viewmat, K, width, height, near, far, tile_size, pixel_mask)
    r = _forward_pass(
        bn.pk, bn.feats, bn.nrm, np.zeros(0), bn.thr, bn.rect, bn.surf, bn.start, bn.count, bn.bounds, bn.size,
        bn.ntx, width, height, near, far, False,
    )  # fmt: skip
    return bn.order, r


def _backward_pass(
    r: _NumbaResult,
    pk: np.ndarray,
    feats: np.ndarray,
    nrm: np.ndarray,
    bg: np.ndarray,
    surf: np.ndarray,
    start: np.ndarray,
    bounds: np.ndarray,
    ts: int,
    ntx: int,
    width: int,
    height: int,
    near: float,
    far: float,
    with_dist: bool,
    grads: list[np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The backward kernel: per-block gradient sums of the packed rows, features and normals."""
    nb = bounds.shape[0] - 1
    n = pk.shape[0]
    gp = np.zeros((nb, n, NPACK))
    gf = np.zeros((nb, n, feats.shape[1]))
    gn = np.zeros((nb, n, 3))
    with KERNEL_LOCK:
        _RASTER_KERNELS["backward"](
            pk, feats, nrm, bg, surf, start, r.t_last, bounds, width, height, ts, ntx,
            r.pair_e, r.pix_off, r.count, r.medidx, r.T, r.M1, r.M2, float(near), float(far), with_dist,
            *grads, gp, gf, gn,
        )  # fmt: skip
    return gp, gf, gn


def _grads_f64(grads: tuple[Tensor, ...]) -> list[np.ndarray]:
    """The six image gradients (features, alpha, depth, median, normal, distortion) as float64 numpy."""
    return [_f64(g) for g in grads[:6]]


@dataclass(frozen=True)
class _View:
    """Camera and settings of one numba render (float64 numpy matrices)."""

    V: np.ndarray
    K: np.ndarray
    width: int
    height: int
    near: float
    far: float
    tile_size: int
    with_dist: bool


class _NumbaRender(torch.autograd.Function):
    """The whole numba render (projection, culling, binning, compositing) with a hand-written backward."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: object,
        means: Tensor,
        quats: Tensor,
        scales: Tensor,
        opacities: Tensor,
        features: Tensor,
        background: Tensor,
        view: _View,
    ) -> tuple[Tensor, ...]:
        dt = means.dtype
        m64, q64, s64, o64 = _f64(means), _f64(quats), _f64(scales), _f64(opacities)
        feats = _f64(features)
        bg = _f64(background)
        v = view
        bn = _project_and_bin(m64, q64, s64, o64, feats, v.V, v.K, v.width, v.height, v.near, v.far, v.tile_size)
        r = _forward_pass(
            bn.pk, bn.feats, bn.nrm, bg, bn.thr, bn.rect, bn.surf, bn.start, bn.count, bn.bounds, bn.size, bn.ntx,
            v.width, v.height, v.near, v.far, v.with_dist,
        )  # fmt: skip
        visible = np.zeros(means.shape[0], np.bool_)
        visible[bn.order[r.vis.view(np.bool_)]] = True
        ctx.state = (m64, q64, s64, bg, bn, r, view)
        ctx.dtypes = (dt, features.dtype, background.dtype)
        count = torch.from_numpy(r.count.astype(np.int64))
        vis = torch.from_numpy(visible)
        ctx.mark_non_differentiable(count, vis)
        outs = (r.feat, r.alpha, r.depth, r.median, r.normal, r.dist)
        return (*(torch.from_numpy(o).to(dt) for o in outs), count, vis)

    @staticmethod
    def backward(ctx: object, *grads: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        m64, q64, s64, bg, bn, r, v = ctx.state
        dt, f_dt, bg_dt = ctx.dtypes
        g = _grads_f64(grads)
        gp, gf, gn = _backward_pass(
            r, bn.pk, bn.feats, bn.nrm, bg, bn.surf, bn.start, bn.bounds, bn.size, bn.ntx,
            v.width, v.height, v.near, v.far, v.with_dist, g,
        )  # fmt: skip
        n = m64.shape[0]
        g_means, g_quats, g_scales = np.zeros((n, 3)), np.zeros((n, 4)), np.zeros((n, 2))
        g_opac, g_feats = np.zeros(n), np.zeros((n, bn.feats.shape[1]))
        with KERNEL_LOCK:
            _KERNELS["project_vjp"](
                m64, q64, s64, v.V, v.K, float(v.near), float(v.far), bn.order, gp, gn, gf,
                g_means, g_quats, g_scales, g_opac, g_feats,
            )  # fmt: skip
        g_bg = None
        if ctx.needs_input_grad[5]:
            g_bg = torch.from_numpy(g[0].T @ r.T).to(bg_dt)
        t = torch.from_numpy
        return (
            t(g_means).to(dt),
            t(g_quats).to(dt),
            t(g_scales).to(dt),
            t(g_opac).to(dt),
            t(g_feats).to(f_dt),
            g_bg,
            None,
        )


def _render_numba(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
    background: Tensor | None,
    with_distortion: bool,
    tile_size: int,
) -> RenderOutput:
    """The numba path of :func:`rasterize_surfels` (camera without gradient)."""
    dt = means.dtype
    C = features.shape[1]
    bg = torch.zeros(C, dtype=dt) if background is None else background.to(dt)
    view = _View(
        _f64(viewmat), _f64(K), int(width), int(height), float(near), float(far), int(tile_size), with_distortion
    )
    feat, alpha, depth, median, normal, dist, count, visible = _NumbaRender.apply(
        means, quats, scales, opacities, features.to(dt), bg, view
    )
    hw = (height, width)
    return RenderOutput(
        features=feat.reshape(*hw, C),
        alpha=alpha.reshape(hw),
        depth=depth.reshape(hw),
        median_depth=median.reshape(hw),
        normal=normal.reshape(*hw, 3),
        distortion=dist.reshape(hw),
        n_contrib=count.reshape(hw),
        visible=visible,
    )


class _NumbaRasterize(torch.autograd.Function):
    """Compositing of surfels projected by torch with the numba kernels (hand-written backward).

    The path for a camera with gradients: torch autograd handles the projection.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: object,
        packed: Tensor,
        features: Tensor,
        normals: Tensor,
        background: Tensor,
        proj: Projection,
        bins: TileBins,
        width: int,
        height: int,
        near: float,
        far: float,
        with_dist: bool,
    ) -> tuple[Tensor, ...]:
        r = numba_forward(proj, features, bins, width, height, near, far, background, with_dist)
        ctx.save_for_backward(packed, features, normals, background)
        ctx.r, ctx.meta = r, (width, height, near, far, with_dist)
        ctx.bins = bins
        count = torch.from_numpy(r.count.astype(np.int64))
        visible = torch.from_numpy(r.vis.astype(np.bool_))
        ctx.mark_non_differentiable(count, visible)
        outs = (r.feat, r.alpha, r.depth, r.median, r.normal, r.dist)
        return (*(torch.from_numpy(o).to(packed.dtype) for o in outs), count, visible)

    @staticmethod
    def backward(ctx: object, *grads: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        packed, features, normals, background = ctx.saved_tensors
        r, (width, height, near, far, with_dist) = ctx.r, ctx.meta
        bins = ctx.bins
        bounds = balanced_bounds(bins.count + 1, n_threads())
        gp, gf, gn = _backward_pass(
            r, _f64(packed.T), _f64(features), _f64(normals), _f64(background), bins.surf.numpy(),
            bins.start.numpy(), bounds, bins.size, bins.ntx, width, height, near, far, with_dist, _grads_f64(grads),
        )  # fmt: skip
        g_packed = torch.from_numpy(gp.sum(0)).T.to(packed.dtype)
        g_feat = torch.from_numpy(gf.sum(0)).to(features.dtype)
        g_nrm = torch.from_numpy(gn.sum(0)).to(normals.dtype)
        g_bg = (grads[0].double() * torch.from_numpy(r.T)[:, None]).sum(0).to(background.dtype)
        return g_packed, g_feat, g_nrm, g_bg, None, None, None, None, None, None, None


def _composite_numba(
    proj: Projection,
    features: Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
    background: Tensor | None,
    tile_size: int,
    with_distortion: bool,
) -> RenderOutput:
    """Bin, then composite with the numba kernels (autograd through :class:`_NumbaRasterize`)."""
    dt = proj.packed.dtype
    C = features.shape[1]
    bins = bin_tiles(proj, width, height, tile_size)
    bg = torch.zeros(C, dtype=dt) if background is None else background.to(dt)
    feat, alpha, depth, median, normal, dist, count, visible = _NumbaRasterize.apply(
        proj.packed, features.to(dt), proj.normals, bg, proj, bins, width, height, near, far, with_distortion
    )
    hw = (height, width)
    return RenderOutput(
        features=feat.reshape(*hw, C),
        alpha=alpha.reshape(hw),
        depth=depth.reshape(hw),
        median_depth=median.reshape(hw),
        normal=normal.reshape(*hw, 3),
        distortion=dist.reshape(hw),
        n_contrib=count.reshape(hw),
        visible=visible,
    )


# ------------------------------------------------------------------------------------ front doors
def rasterize_surfels(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float = 0.2,
    far: float = 100.0,
    background: Tensor | None = None,
    with_distortion: bool = True,
    tile_size: int = 4,
    backend: str = "auto",
) -> RenderOutput:
    """Render N surfels (world ``means`` [N, 3] m, ``quats`` [N, 4] wxyz, ``scales`` [N, 2] m, ``opacities``
    [N] in (0, 1), ``features`` [N, C]) with ``viewmat`` [4, 4] world -> camera and ``K`` [3, 3] pixels.

    Matches :func:`roigsf_ros.render.reference.rasterize_surfels` in values and gradients. ``backend``:
    ``"numba"`` (CPU kernels, hand-written backward), ``"torch"`` (plain PyTorch, any device), or
    ``"auto"`` (numba for CPU tensors when it is installed). ``with_distortion=False`` skips the
    distortion map (zeros) and its gradient.
    """
    _check_inputs(means, quats, scales, opacities, features, viewmat, K, width, height, near, far)
    numba_path = use_numba(backend, means)
    if numba_path and not (viewmat.requires_grad or K.requires_grad):
        # Everything in numba kernels, the projection's backward included.
        return _render_numba(
            means, quats, scales, opacities, features, viewmat, K, width, height, near, far, background,
            with_distortion, tile_size,
        )  # fmt: skip
    bk = "numba" if numba_path else "torch"
    # Cull without autograd, then project differentiably only the surfels that can be seen.
    with torch.no_grad():
        cull = project_surfels(means, quats, scales, opacities, viewmat, K, width, height, near, far, backend=bk)
    kept = cull.keep.nonzero().squeeze(1)
    sel = (lambda t: t.index_select(0, kept)) if kept.numel() < means.shape[0] else (lambda t: t)
    packed, normals, _ = project_packed(sel(means), sel(quats), sel(scales), sel(opacities), viewmat, K, near, far)
    keep = torch.ones(kept.numel(), dtype=torch.bool, device=means.device)
    proj = Projection(packed=packed, normals=normals, depth=sel(cull.depth), rect=sel(cull.rect), keep=keep)
    if numba_path:
        out = _composite_numba(proj, sel(features), width, height, near, far, background, tile_size, with_distortion)
    else:
        pairs = select_pairs(proj, width, height, near, tile_size=tile_size, backend="torch")
        out = composite_pairs(proj, sel(features), pairs, width, height, near, far, background, with_distortion)
    if kept.numel() < means.shape[0]:
        visible = torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
        out.visible = visible.index_copy_(0, kept, out.visible)
    # Zero-valued link: outputs stay attached to every input's graph even when all are culled.
    link = sum(t[:0].sum() for t in (means, quats, scales, opacities, features))
    out.features = out.features + link
    return out


def render_map(
    surfel_map: object,
    T_wc: np.ndarray | Tensor,
    intr: Intrinsics,
    features: Tensor | None = None,
    background: Tensor | None = None,
    near: float = 0.2,
    far: float = 100.0,
    with_distortion: bool = True,
    tile_size: int = 4,
    backend: str = "auto",
    cull: bool = False,
) -> RenderOutput:
    """Render a :class:`~roigsf_ros.render.surfels.SurfelMap` from camera-to-world ``T_wc`` [4, 4].

    ``features`` [N, C] defaults to the map's colours (view-dependent when it has degree-1 SH). ``cull``: render
    only the surfels whose bounding sphere meets the view frustum (:func:`~roigsf_ros.render.fisher.frustum_subset`,
    conservative, so the images are the same); the projection then skips the others (in a room most of the map),
    and ``visible`` is still one flag per surfel of the map.
    """
    m = surfel_map
    if not hasattr(m, "opacity_logits"):  # a Mapper, say: its map is Mapper.map
        raise InputError("surfel_map", f"expected a SurfelMap (a Mapper's is mapper.map), got {type(m).__name__}")
    if not isinstance(intr, Intrinsics):
        raise InputError("intr", f"expected an Intrinsics, got {type(intr).__name__}")
    if not isinstance(T_wc, Tensor):  # a NaN or scaled pose rendered an empty or warped image without a word
        check_pose(T_wc, "T_wc")  # checked, not replaced: the render uses the pose as given
    viewmat, K = camera_tensors(T_wc, intr, device=m.device, dtype=m.dtype)
    if cull:
        from roigsf_ros.render.fisher import frustum_subset  # here: fisher imports this module

        idx = frustum_subset(m, viewmat.detach(), intr, near, far)
        if idx.numel() < len(m):
            sub_features = None if features is None else features.index_select(0, idx)
            out = _render_checked(m.select(idx), viewmat, K, intr, sub_features, background, near, far,
                                  with_distortion, tile_size, backend)  # fmt: skip
            visible = torch.zeros(len(m), dtype=torch.bool, device=m.device)
            out.visible = visible.index_copy_(0, idx, out.visible)
            return out
    return _render_checked(m, viewmat, K, intr, features, background, near, far, with_distortion, tile_size, backend)


def _render_checked(
    m: SurfelMap,
    viewmat: Tensor,
    K: Tensor,
    intr: Intrinsics,
    features: Tensor | None,
    background: Tensor | None,
    near: float,
    far: float,
    with_distortion: bool,
    tile_size: int,
    backend: str,
) -> RenderOutput:
    """:func:`render_map` of a map and camera already checked and turned into ``viewmat`` and ``K``."""
    if features is None:
        viewdirs = None
        if m.sh_rest is not None:
            cam_centre = -viewmat[:3, :3].T @ viewmat[:3, 3]
            viewdirs = m.means - cam_centre
        features = m.colors(viewdirs)
    return rasterize_surfels(
        m.means, m.quats, m.scales(), m.opacities(), features, viewmat, K, intr.width, intr.height,
        near=near, far=far, background=background, with_distortion=with_distortion, tile_size=tile_size,
        backend=backend,
    )  # fmt: skip


def _check_inputs(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
) -> None:
    tensors = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "features": features}
    for name, t in (tensors | {"viewmat": viewmat, "K": K}).items():
        if not isinstance(t, Tensor):  # numpy failed later on a missing attribute (requires_grad)
            raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__} (torch.as_tensor converts it)")
    n = means.shape[0]
    shapes = {"means": (means, (n, 3)), "quats": (quats, (n, 4)), "scales": (scales, (n, 2))}
    shapes |= {"opacities": (opacities, (n,)), "viewmat": (viewmat, (4, 4)), "K": (K, (3, 3))}
    for name, (t, shape) in shapes.items():
        if tuple(t.shape) != shape:
            raise ValueError(f"{name} must have shape {list(shape)}, got {list(t.shape)}")
    if features.dim() != 2 or features.shape[0] != n:
        raise ValueError(f"features must have shape [{n}, C], got {list(features.shape)}")
    for name, side in (("width", width), ("height", height)):  # a float failed deep in a reshape
        if isinstance(side, bool) or not isinstance(side, int | np.integer):
            raise ValueError(f"{name} must be an int (pixels), got {type(side).__name__} {side!r}")
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if not (0 < near < far) or not math.isfinite(far):
        raise ValueError(f"need 0 < near < far < inf, got near={near}, far={far}")


__all__ = [
    "ALPHA_MAX",
    "ALPHA_MIN",
    "FILTER_INV_SQUARE",
    "NPACK",
    "PAIR_BUFFER_LIMIT",
    "T_MIN",
    "Pairs",
    "Projection",
    "RenderOutput",
    "TileBins",
    "bin_tiles",
    "camera_tensors",
    "composite_pairs",
    "numba_bins",
    "numba_forward",
    "numba_pairs",
    "pair_alpha_depth",
    "project_packed",
    "project_surfels",
    "rasterize_surfels",
    "render_map",
    "select_pairs",
]
