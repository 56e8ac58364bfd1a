"""Fast differentiable 2DGS rasteriser, gsplat-style functional API, two backends.

Same model and outputs as :mod:`roigsf_ros.render.reference` (see its docstring for the exact
rules, taken from hbb1/diff-surfel-rasterization); both backends match it in values and gradients.

1. :func:`project_surfels` (per surfel): camera-frame splat transform, reduced to the adjugate
   rows ``A`` (so the ray-splat hit ``p = k x l = A [x, y, 1]`` is linear in the pixel), ``det``,
   centre depth and projected centre; a conservative pixel box holding every pixel where
   ``alpha >= 1/255`` (exact bound of the projected disc clipped at the near plane, with margins).
   :func:`rasterize_surfels` culls with it without autograd, then projects only the kept surfels
   differentiably.
2. :func:`bin_tiles`: kept surfels binned into 4x4-pixel tiles, depth-sorted per tile.
3. ``backend="numba"`` (CPU, default when numba is installed): compiled kernels written like the
   2DGS CUDA rasteriser (front-to-back walk per pixel; hand-written back-to-front backward), wrapped
   in a ``torch.autograd.Function``; torch autograd handles the projection.
   ``backend="torch"`` (any device): :func:`select_pairs` walks the tiles in chunks with the
   per-pixel early stop to list the exact (pixel, surfel) contributions, and
   :func:`composite_pairs` composites them with plain differentiable tensor ops (transmittance by a
   per-pixel segmented scan).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.render.numba_setup import (
    KERNEL_LOCK,
    Kernels,
    balanced_bounds,
    n_threads,
    prange,
    use_numba,
)

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
# CPU kernels written like the 2DGS CUDA rasteriser: every pixel walks its tile's depth-sorted list
# front to back (forward), then its accepted surfels back to front (backward), rebuilding
# transmittance by division as diff-surfel-rasterization's backward does. Both loop over the tile's
# surfels outside and the pixels each covers inside. They are plain Python here, compiled by numba
# on first use (cached on disk) and always run in float64 (one specialisation to compile).


def _k_forward(
    pk: np.ndarray,
    feats: np.ndarray,
    nrm: np.ndarray,
    bg: np.ndarray,
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
    pix_off: np.ndarray,
    o_vis: np.ndarray,
    rect: np.ndarray,
    thr: np.ndarray,
    compact: bool,
    store: bool,
) -> None:
    """Forward walk (numba): per tile, surfels in depth order, each over the tile pixels its box covers.

    Every pixel sees its surfels in the same order as a per-pixel walk (2DGS), so the result is the
    same; looping surfels outside and pixels inside reads each surfel once per tile and skips the
    pixels outside its box without a test per pixel. Writes the outputs, the accepted surfel ids per
    pixel (``pair_buf`` from ``pix_off``) and the sums the backward needs. Pixel q of tile t stores
    its ids from ``Q * start[t] + q * count[t]`` (a bound that needs no counting pass), or with
    ``compact`` from the given ``pix_off``; ``store=False`` only counts.
    """
    n_ch = feats.shape[1]
    mscale = far / (far - near)
    Q = ts * ts
    for b in prange(bounds.shape[0] - 1):
        Tq = np.empty(Q)
        cnt = np.empty(Q, np.int64)
        done = np.empty(Q, np.bool_)
        D = np.empty(Q)
        M1 = np.empty(Q)
        M2 = np.empty(Q)
        dist = np.empty(Q)
        med = np.empty(Q)
        medi = np.empty(Q, np.int64)
        nq = np.empty((Q, 3))
        acc = np.empty((Q, n_ch))
        base = np.empty(Q, np.int64)
        for t in range(bounds[b], bounds[b + 1]):
            n_t = t_count[t]
            s = t_start[t]
            x_base = (t % ntx) * ts
            y_base = (t // ntx) * ts
            n_done = 0
            for q in range(Q):
                base[q] = Q * s + q * n_t
                if compact and x_base + q % ts < width and y_base + q // ts < height:
                    base[q] = pix_off[(y_base + q // ts) * width + x_base + q % ts]
                Tq[q] = 1.0
                cnt[q] = 0
                D[q] = 0.0
                M1[q] = 0.0
                M2[q] = 0.0
                dist[q] = 0.0
                med[q] = 0.0
                medi[q] = -1
                for c in range(3):
                    nq[q, c] = 0.0
                for c in range(n_ch):
                    acc[q, c] = 0.0
                done[q] = x_base + q % ts >= width or y_base + q // ts >= height
                if done[q]:
                    n_done += 1
            for e in range(n_t):
                if n_done == Q:
                    break
                sid = tl_surf[s + e]
                xa = max(rect[sid, 0], x_base)
                xb = min(rect[sid, 2], x_base + ts - 1)
                ya = max(rect[sid, 1], y_base)
                yb = min(rect[sid, 3], y_base + ts - 1)
                if xa > xb or ya > yb:
                    continue
                a0, a1, a2, b0, b1, b2 = pk[sid, 0], pk[sid, 1], pk[sid, 2], pk[sid, 3], pk[sid, 4], pk[sid, 5]
                c0, c1, c2, det, tz = pk[sid, 6], pk[sid, 7], pk[sid, 8], pk[sid, 9], pk[sid, 10]
                cx, cy, opa, th = pk[sid, 11], pk[sid, 12], pk[sid, 13], thr[sid]
                for yi in range(ya, yb + 1):
                    y = float(yi)
                    for xi in range(xa, xb + 1):
                        q = (yi - y_base) * ts + (xi - x_base)
                        if done[q]:
                            continue
                        x = float(xi)
                        pz = c0 * x + c1 * y + c2
                        if pz == 0.0:
                            continue
                        inv = 1.0 / pz
                        u = (a0 * x + a1 * y + a2) * inv
                        v = (b0 * x + b1 * y + b2) * inv
                        r3 = u * u + v * v
                        dx = cx - x
                        dy = cy - y
                        r2 = 2.0 * (dx * dx + dy * dy)
                        if r3 <= r2:
                            rho = r3
                            depth = det * inv
                        else:
                            rho = r2
                            depth = tz
                        # rho > th (th = 2 ln(255 o) plus a margin) means alpha < 1/255 for sure.
                        if rho > th or depth < near:
                            continue
                        a = opa * np.exp(-0.5 * rho)
                        if a > 0.99:
                            a = 0.99
                        if a < 1.0 / 255.0:
                            continue
                        T = Tq[q]
                        test_T = T * (1.0 - a)
                        if test_T < 1e-4:
                            done[q] = True
                            n_done += 1
                            continue
                        w = a * T
                        for c in range(n_ch):
                            acc[q, c] += w * feats[sid, c]
                        m = mscale * (1.0 - near / depth)
                        dist[q] += w * (m * m * (1.0 - T) + M2[q] - 2.0 * m * M1[q])
                        D[q] += w * depth
                        M1[q] += w * m
                        M2[q] += w * m * m
                        if T > 0.5:
                            med[q] = depth
                            medi[q] = cnt[q]
                        for c in range(3):
                            nq[q, c] += w * nrm[sid, c]
                        if store:
                            pair_buf[base[q] + cnt[q]] = sid
                        o_vis[sid] = 1  # idempotent store; concurrent writers all write 1
                        cnt[q] += 1
                        Tq[q] = test_T
            for q in range(Q):
                xi = x_base + q % ts
                yi = y_base + q // ts
                if xi >= width or yi >= height:
                    continue
                p = yi * width + xi
                pix_off[p] = base[q]
                T = Tq[q]
                for c in range(n_ch):
                    o_feat[p, c] = acc[q, c] + T * bg[c]
                o_alpha[p] = 1.0 - T
                o_depth[p] = D[q]
                o_median[p] = med[q]
                for c in range(3):
                    o_normal[p, c] = nq[q, c]
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
    t_count: np.ndarray,
    rect: np.ndarray,
    bounds: np.ndarray,
    width: int,
    height: int,
    ts: int,
    ntx: int,
    pair_buf: np.ndarray,
    pix_off: np.ndarray,
    count: np.ndarray,
    medidx: np.ndarray,
    T_fin: np.ndarray,
    M1t: np.ndarray,
    M2t: np.ndarray,
    near: float,
    far: float,
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
    """Backward walk (numba): per tile, the depth-sorted list back to front, each surfel over its pixels.

    A pixel's accepted surfels are a subsequence of its tile's list, so walking the list backwards
    and matching each pixel's next accepted id visits every pixel's contributions back to front, as
    2DGS's per-pixel backward does (transmittance rebuilt by division). A surfel's gradient over the
    tile's pixels is summed locally and added once per (tile, surfel) to the block's buffers.
    """
    n_ch = feats.shape[1]
    mscale = far / (far - near)
    Q = ts * ts
    for b in prange(bounds.shape[0] - 1):
        ptr = np.empty(Q, np.int64)
        Tq = np.empty(Q)
        Sq = np.empty(Q)
        lf = np.empty(n_ch)
        for t in range(bounds[b], bounds[b + 1]):
            n_t = t_count[t]
            s = t_start[t]
            x_base = (t % ntx) * ts
            y_base = (t // ntx) * ts
            active = 0
            for q in range(Q):
                xi = x_base + q % ts
                yi = y_base + q // ts
                ptr[q] = -1
                if xi >= width or yi >= height:
                    continue
                p = yi * width + xi
                ptr[q] = count[p] - 1
                if ptr[q] >= 0:
                    active += 1
                Tq[q] = T_fin[p]
                acc = 0.0
                for c in range(n_ch):
                    acc += g_feat[p, c] * bg[c]
                Sq[q] = T_fin[p] * acc
            for e in range(n_t - 1, -1, -1):
                if active == 0:
                    break
                sid = tl_surf[s + e]
                xa = max(rect[sid, 0], x_base)
                xb = min(rect[sid, 2], x_base + ts - 1)
                ya = max(rect[sid, 1], y_base)
                yb = min(rect[sid, 3], y_base + ts - 1)
                if xa > xb or ya > yb:
                    continue
                a0, a1, a2, b0, b1, b2 = pk[sid, 0], pk[sid, 1], pk[sid, 2], pk[sid, 3], pk[sid, 4], pk[sid, 5]
                c0, c1, c2, det, tz = pk[sid, 6], pk[sid, 7], pk[sid, 8], pk[sid, 9], pk[sid, 10]
                cx, cy, opa = pk[sid, 11], pk[sid, 12], pk[sid, 13]
                g0 = g1 = g2 = g3 = g4 = g5 = g6 = g7 = g8 = g9 = g10 = g11 = g12 = g13 = 0.0
                gn0 = gn1 = gn2 = 0.0
                for c in range(n_ch):
                    lf[c] = 0.0
                hit = False
                for yi in range(ya, yb + 1):
                    y = float(yi)
                    for xi in range(xa, xb + 1):
                        q = (yi - y_base) * ts + (xi - x_base)
                        i = ptr[q]
                        if i < 0:
                            continue
                        p = yi * width + xi
                        if pair_buf[pix_off[p] + i] != sid:
                            continue
                        ptr[q] = i - 1
                        if i == 0:
                            active -= 1
                        hit = True
                        x = float(xi)
                        pz = c0 * x + c1 * y + c2
                        inv = 1.0 / pz
                        u = (a0 * x + a1 * y + a2) * inv
                        v = (b0 * x + b1 * y + b2) * inv
                        r3 = u * u + v * v
                        dx = cx - x
                        dy = cy - y
                        r2 = 2.0 * (dx * dx + dy * dy)
                        use3 = r3 <= r2
                        if use3:
                            rho = r3
                            depth = det * inv
                        else:
                            rho = r2
                            depth = tz
                        ex = np.exp(-0.5 * rho)
                        a = opa * ex
                        clamped = a > 0.99
                        if clamped:
                            a = 0.99
                        inv1m = 1.0 / (1.0 - a)
                        T = Tq[q] * inv1m
                        Tq[q] = T
                        w = a * T
                        Wt = 1.0 - T_fin[p]
                        M1 = M1t[p]
                        inv_d = 1.0 / depth
                        m = mscale * (1.0 - near * inv_d)
                        gDi = g_dist[p]
                        val = g_alpha[p] + g_depth[p] * depth + gDi * (m * m * Wt - 2.0 * m * M1 + M2t[p])
                        for c in range(n_ch):
                            val += g_feat[p, c] * feats[sid, c]
                            lf[c] += g_feat[p, c] * w
                        val += g_normal[p, 0] * nrm[sid, 0] + g_normal[p, 1] * nrm[sid, 1]
                        val += g_normal[p, 2] * nrm[sid, 2]
                        gn0 += g_normal[p, 0] * w
                        gn1 += g_normal[p, 1] * w
                        gn2 += g_normal[p, 2] * w
                        dA = T * val - Sq[q] * inv1m
                        Sq[q] += w * val
                        gdep = g_depth[p] * w + gDi * 2.0 * w * (m * Wt - M1) * mscale * near * inv_d * inv_d
                        if i == medidx[p]:
                            gdep += g_med[p]
                        grho = 0.0
                        if not clamped:
                            g13 += dA * ex
                            grho = -0.5 * a * dA
                        if use3:
                            gu = grho * 2.0 * u
                            gv = grho * 2.0 * v
                            gpx = gu * inv
                            gpy = gv * inv
                            gpz = -(gu * u + gv * v) * inv - gdep * depth * inv
                            g0 += gpx * x
                            g1 += gpx * y
                            g2 += gpx
                            g3 += gpy * x
                            g4 += gpy * y
                            g5 += gpy
                            g6 += gpz * x
                            g7 += gpz * y
                            g8 += gpz
                            g9 += gdep * inv
                        else:
                            g11 += grho * 4.0 * dx
                            g12 += grho * 4.0 * dy
                            g10 += gdep
                if hit:
                    gp[b, sid, 0] += g0
                    gp[b, sid, 1] += g1
                    gp[b, sid, 2] += g2
                    gp[b, sid, 3] += g3
                    gp[b, sid, 4] += g4
                    gp[b, sid, 5] += g5
                    gp[b, sid, 6] += g6
                    gp[b, sid, 7] += g7
                    gp[b, sid, 8] += g8
                    gp[b, sid, 9] += g9
                    gp[b, sid, 10] += g10
                    gp[b, sid, 11] += g11
                    gp[b, sid, 12] += g12
                    gp[b, sid, 13] += g13
                    gn[b, sid, 0] += gn0
                    gn[b, sid, 1] += gn1
                    gn[b, sid, 2] += gn2
                    for c in range(n_ch):
                        gf[b, sid, c] += lf[c]


def _k_boxes(rows: np.ndarray, width: int, height: int, near: float, rect: np.ndarray, ok: np.ndarray) -> None:
    """Per-surfel pixel boxes (numba): the same bound as :func:`_pixel_boxes`, one surfel at a time.

    ``rows`` [N, 12] float64: Tu (3), Tv (3), Tw (3), centre x, y, opacity.
    """
    big = 1e9
    z_min = near * (1 - 1e-6) - 1e-9
    for i in prange(rows.shape[0]):
        u0, u1, u2, v0, v1, v2, w0, w1, w2, cx, cy, o = (
            rows[i, 0], rows[i, 1], rows[i, 2], rows[i, 3], rows[i, 4], rows[i, 5],
            rows[i, 6], rows[i, 7], rows[i, 8], rows[i, 9], rows[i, 10], rows[i, 11],
        )  # fmt: skip
        ok[i] = 0
        rect[i, 0] = 0
        rect[i, 1] = 0
        rect[i, 2] = -1
        rect[i, 3] = -1
        if not 255.0 * o > 1.0:
            continue
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
            continue
        x0 = max(np.ceil(max(lo_x, -big) - 0.5), 0.0)
        x1 = min(np.floor(min(hi_x, big) + 0.5), width - 1.0)
        y0 = max(np.ceil(max(lo_y, -big) - 0.5), 0.0)
        y1 = min(np.floor(min(hi_y, big) + 0.5), height - 1.0)
        if x0 <= x1 and y0 <= y1:
            ok[i] = 1
            rect[i, 0] = int(x0)
            rect[i, 1] = int(y0)
            rect[i, 2] = int(x1)
            rect[i, 3] = int(y1)


_KERNELS = Kernels(forward=_k_forward, backward=_k_backward, boxes=_k_boxes)
"""The compiled forward, backward and pixel-box kernels (compiled on first use)."""

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
    pix_off: np.ndarray
    vis: np.ndarray

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


def numba_forward(
    proj: Projection,
    features: Tensor,
    bins: TileBins,
    width: int,
    height: int,
    near: float,
    far: float,
    background: Tensor | None,
) -> _NumbaResult:
    """Run the forward kernel on detached CPU tensors (always in float64: one compiled specialisation)."""
    k = _KERNELS
    f64 = torch.float64
    pk = proj.packed.detach().T.to(f64).contiguous().numpy()
    dt = pk.dtype
    feats = features.detach().to(f64).contiguous().numpy()
    nrm = proj.normals.detach().to(f64).contiguous().numpy()
    n_ch = feats.shape[1]
    bg = np.zeros(n_ch, dt) if background is None else background.detach().to(f64).numpy()
    P = width * height
    ts = bins.size
    bounds = balanced_bounds(bins.count + 1, n_threads())
    rect = proj.rect.to(torch.int32).contiguous().numpy()
    o64 = proj.packed[_OPA].detach().double()
    thr = (2.0 * torch.log((255.0 * o64).clamp_min(1e-300))).numpy() * (1 + 1e-6) + 1e-6
    r = _NumbaResult(
        feat=np.empty((P, n_ch), dt),
        alpha=np.empty(P, dt),
        depth=np.empty(P, dt),
        median=np.empty(P, dt),
        normal=np.empty((P, 3), dt),
        dist=np.empty(P, dt),
        count=np.empty(P, np.int32),
        medidx=np.empty(P, np.int32),
        T=np.empty(P, dt),
        M1=np.empty(P, dt),
        M2=np.empty(P, dt),
        pair_buf=np.empty(0, np.int32),
        pix_off=np.zeros(P, np.int64),
        vis=np.zeros(pk.shape[0], np.uint8),
    )
    bound = ts * ts * bins.surf.numel()  # ids one pass can store without counting first
    compact = bound > PAIR_BUFFER_LIMIT
    if compact:  # counting pass, then exact per-pixel offsets
        with KERNEL_LOCK:
            _run_forward(k, pk, feats, nrm, bg, bins, bounds, width, height, near, far, r, rect, thr, False, False)
        r.pix_off[:] = np.cumsum(r.count, dtype=np.int64) - r.count
        bound = int(r.count.sum())
    r.pair_buf = np.empty(max(1, bound), np.int32)
    with KERNEL_LOCK:
        _run_forward(k, pk, feats, nrm, bg, bins, bounds, width, height, near, far, r, rect, thr, compact, True)
    return r


def _run_forward(
    k: dict[str, object],
    pk: np.ndarray,
    feats: np.ndarray,
    nrm: np.ndarray,
    bg: np.ndarray,
    bins: TileBins,
    bounds: np.ndarray,
    width: int,
    height: int,
    near: float,
    far: float,
    r: _NumbaResult,
    rect: np.ndarray,
    thr: np.ndarray,
    compact: bool,
    store: bool,
) -> None:
    k["forward"](
        pk, feats, nrm, bg, bins.surf.numpy(), bins.start.numpy(), bins.count.numpy(), bounds,
        width, height, bins.size, bins.ntx, float(near), float(far),
        r.feat, r.alpha, r.depth, r.median, r.normal, r.dist, r.count, r.medidx, r.T, r.M1, r.M2,
        r.pair_buf, r.pix_off, r.vis, rect, thr, compact, store,
    )  # fmt: skip


class _NumbaRasterize(torch.autograd.Function):
    """Compositing of projected surfels with the numba kernels (hand-written backward)."""

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
    ) -> tuple[Tensor, ...]:
        r = numba_forward(proj, features, bins, width, height, near, far, background)
        ctx.save_for_backward(packed, features, normals, background)
        ctx.r, ctx.meta = r, (width, near, far)
        ctx.bins, ctx.height, ctx.rect = bins, height, proj.rect.to(torch.int32).contiguous().numpy()
        count = torch.from_numpy(r.count.astype(np.int64))
        visible = torch.from_numpy(r.vis.astype(np.bool_))
        ctx.mark_non_differentiable(count, visible)
        outs = (r.feat, r.alpha, r.depth, r.median, r.normal, r.dist)
        return (*(torch.from_numpy(o).to(packed.dtype) for o in outs), count, visible)

    @staticmethod
    def backward(ctx: object, *grads: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        packed, features, normals, background = ctx.saved_tensors
        r, (width, near, far) = ctx.r, ctx.meta
        dt = torch.float64  # kernels run in float64 (one compiled specialisation); results cast back
        g = [gr.to(dt).contiguous().numpy() for gr in grads[:6]]
        n = packed.shape[1]
        nb = n_threads()
        bins = ctx.bins
        bounds = balanced_bounds(bins.count + 1, nb)
        pk = packed.detach().T.to(dt).contiguous().numpy()
        gp = np.zeros((nb, n, NPACK), pk.dtype)
        gf = np.zeros((nb, n, features.shape[1]), gp.dtype)
        gn = np.zeros((nb, n, 3), gp.dtype)
        with KERNEL_LOCK:
            _KERNELS["backward"](
                pk, features.detach().to(dt).contiguous().numpy(), normals.detach().to(dt).contiguous().numpy(),
                background.detach().to(dt).numpy(), bins.surf.numpy(), bins.start.numpy(), bins.count.numpy(),
                ctx.rect, bounds, width, ctx.height, bins.size, bins.ntx,
                r.pair_buf, r.pix_off, r.count, r.medidx, r.T, r.M1, r.M2, float(near), float(far),
                *g, gp, gf, gn,
            )  # fmt: skip
        g_packed = torch.from_numpy(gp.sum(0)).T.to(packed.dtype)
        g_feat = torch.from_numpy(gf.sum(0)).to(features.dtype)
        g_nrm = torch.from_numpy(gn.sum(0)).to(normals.dtype)
        g_bg = (grads[0].to(dt) * torch.from_numpy(r.T)[:, None]).sum(0).to(background.dtype)
        return g_packed, g_feat, g_nrm, g_bg, None, None, None, None, None, None


def _composite_numba(
    proj: Projection,
    features: Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
    background: Tensor | None,
    tile_size: int,
) -> RenderOutput:
    """Bin, then composite with the numba kernels (autograd through :class:`_NumbaRasterize`)."""
    dt = proj.packed.dtype
    C = features.shape[1]
    bins = bin_tiles(proj, width, height, tile_size)
    bg = torch.zeros(C, dtype=dt) if background is None else background.to(dt)
    feat, alpha, depth, median, normal, dist, count, visible = _NumbaRasterize.apply(
        proj.packed, features.to(dt), proj.normals, bg, proj, bins, width, height, near, far
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
    distortion map on the torch path (zeros).
    """
    _check_inputs(means, quats, scales, opacities, features, viewmat, K, width, height, near, far)
    numba_path = use_numba(backend, means)
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
        out = _composite_numba(proj, sel(features), width, height, near, far, background, tile_size)
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
) -> RenderOutput:
    """Render a :class:`~roigsf_ros.render.surfels.SurfelMap` from camera-to-world ``T_wc`` [4, 4].

    ``features`` [N, C] defaults to the map's colours (view-dependent when it has degree-1 SH).
    """
    m = surfel_map
    viewmat, K = camera_tensors(T_wc, intr, device=m.device, dtype=m.dtype)
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
    n = means.shape[0]
    shapes = {"means": (means, (n, 3)), "quats": (quats, (n, 4)), "scales": (scales, (n, 2))}
    shapes |= {"opacities": (opacities, (n,)), "viewmat": (viewmat, (4, 4)), "K": (K, (3, 3))}
    for name, (t, shape) in shapes.items():
        if tuple(t.shape) != shape:
            raise ValueError(f"{name} must have shape {list(shape)}, got {list(t.shape)}")
    if features.dim() != 2 or features.shape[0] != n:
        raise ValueError(f"features must have shape [{n}, C], got {list(features.shape)}")
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
    "numba_forward",
    "pair_alpha_depth",
    "project_packed",
    "project_surfels",
    "rasterize_surfels",
    "render_map",
    "select_pairs",
]
