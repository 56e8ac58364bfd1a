"""Exact diagonal Fisher information of rendered 2DGS outputs, without a backward pass per pixel.

Gauss-Newton diagonal: ``F[theta] = sum_p W_p sum_c (d f_{p,c} / d theta)^2`` over the pixels p and
output channels c of one view (FisherRF; ROI-GSurFisher Eq. 9 with ``W_p = W_roi(p) / sigma_p^2``).

How: per pixel, ``f_{p,c} = sum_k w_k x_{k,c} + T_final bg_c`` with ``w_k = alpha_k T_k``. The
gradient of pixel p with respect to the parameters of its k-th surfel is

    J_{p,k,c} = g_{p,k,c} * d alpha_{p,k} / d theta_k + w_{p,k} * d x_{p,k,c} / d theta_k,
    g_{p,k,c} = T_k x_{k,c} - (sum_{j > k} w_j x_{j,c} + T_final bg_c) / (1 - alpha_k),

where the compositing derivative ``g`` is closed form (suffix sums per pixel) and ``d x / d theta``
of per-surfel features (colour, normal) comes from a small per-surfel graph. Squares are weighted
and summed per surfel. ``d alpha / d theta`` and ``d depth / d theta`` per (pixel, surfel) pair:

- numba backend (CPU): the chain rule through the per-surfel Jacobian of the projected rows
  (``d packed / d theta``, from 14 backward passes over the visible surfels), inside one
  back-to-front walk per pixel that also forms ``g`` and the squares;
- torch backend (any device): one backward pass over a graph in which every pair has its own leaf
  copy of its surfel's parameters (two passes with depth), in chunks of pairs.

Both equal per-pixel brute-force autograd of the reference renderer (tests: 1e-10, float64).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from roigsf_ros.camera import Intrinsics
from roigsf_ros.errors import InputError
from roigsf_ros.render import (
    KERNEL_LOCK,
    Pairs,
    Projection,
    _balanced_bounds,
    _kernels,
    _n_threads,
    _numba_forward,
    _use_numba,
    bin_tiles,
    camera_tensors,
    pair_alpha_depth,
    project_packed,
    project_surfels,
    select_pairs,
)
from roigsf_ros.surfels import PARAM_NAMES, SurfelMap

OUTPUTS = ("color", "depth", "alpha", "normal")
"""Rendered outputs a Fisher can be taken of: colour (3 channels), alpha-weighted depth, alpha, normal (3)."""
GEOMETRIC_PARAMS = ("means", "quats", "log_scales")
"""Surfel geometry {p, t_u, t_v, s_u, s_v} of ROI-GSurFisher, as SurfelMap parameter names."""
ALL_PARAMS = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
"""Every SurfelMap parameter (FisherRF-style full Fisher)."""
_ALIASES = {
    "rotation": "quats",
    "rotations": "quats",
    "scales": "log_scales",
    "opacity": "opacity_logits",
    "opacities": "opacity_logits",
    "color": "sh_dc",
    "colors": "sh_dc",
}


def _params_of(names: Sequence[str], surfel_map: SurfelMap) -> list[str]:
    out = []
    for name in names:
        key = _ALIASES.get(name, name)
        if key not in PARAM_NAMES:
            raise InputError("params", f"unknown parameter '{name}' (choose from {', '.join(PARAM_NAMES)})")
        if key == "sh_rest" and surfel_map.sh_rest is None:
            continue
        if key not in out:
            out.append(key)
    if not out:
        raise InputError("params", "no parameters selected")
    return out


def _seg_suffix_sum(x: Tensor, pairs: Pairs) -> Tensor:
    """Per-pixel exclusive suffix sums of flat ``x`` [M, ...] (float64)."""
    cs = torch.cumsum(x.double(), 0)
    ends = pairs.offsets[1:].index_select(0, pairs.pix) - 1  # last pair of each pair's pixel
    return cs.index_select(0, ends) - cs


def fisher_diag(
    surfel_map: SurfelMap,
    T_wc: np.ndarray | Tensor,
    intr: Intrinsics,
    outputs: Sequence[str] = ("color", "depth"),
    params: Sequence[str] = GEOMETRIC_PARAMS,
    pixel_weights: Tensor | np.ndarray | None = None,
    background: Tensor | None = None,
    near: float = 0.2,
    far: float = 100.0,
    tile_size: int = 4,
    backend: str = "auto",
    pair_chunk: int = 1 << 17,
) -> dict[str, Tensor]:
    """Diagonal Fisher of the rendered ``outputs`` of view ``T_wc`` [4, 4] w.r.t. the raw SurfelMap ``params``.

    ``pixel_weights`` [H, W] multiplies each pixel's squared gradients (ROI weight / sigma_p^2).
    Returns ``{name: tensor shaped like surfel_map.<name>}`` (detached, the map's dtype); surfels
    that contribute to no pixel get zeros. Colours are the map's (view-dependent with degree-1 SH).
    ``backend`` as in :func:`roigsf_ros.render.rasterize_surfels` (numba: one fused CPU kernel;
    torch: per-pair leaf copies, processed ``pair_chunk`` pairs at a time).
    """
    outs = list(dict.fromkeys(outputs))
    bad = [o for o in outs if o not in OUTPUTS]
    if bad or not outs:
        raise InputError("outputs", f"unknown or no outputs {bad} (choose from {', '.join(OUTPUTS)})")
    names = _params_of(params, surfel_map)
    m = surfel_map.detach()
    dt, dev = m.dtype, m.device
    W, H = intr.width, intr.height
    weights = None
    if pixel_weights is not None:
        weights = torch.as_tensor(pixel_weights, dtype=dt, device=dev)
        if tuple(weights.shape) != (H, W):
            raise InputError("pixel_weights", f"expected shape [{H}, {W}], got {list(weights.shape)}")
        weights = weights.reshape(-1)
    viewmat, K = camera_tensors(T_wc, intr, device=dev, dtype=dt)
    result = {k: torch.zeros_like(getattr(m, k)) for k in names}
    bg = torch.zeros(3, dtype=dt, device=dev) if background is None else background.to(dtype=dt, device=dev)
    with torch.no_grad():
        proj = project_surfels(m.means, m.quats, m.scales(), m.opacities(), viewmat, K, W, H, near, far)
    cam = (viewmat, K, W, H, near, far)
    if _use_numba(backend, proj.packed):
        _fisher_numba(m, names, outs, proj, cam, weights, bg, tile_size, result)
    else:
        pairs = select_pairs(proj, W, H, near, tile_size=tile_size, backend="torch")
        if len(pairs):
            _fisher_torch(m, names, outs, proj, pairs, cam, weights, bg, pair_chunk, result)
    return result


def _channels(
    m: SurfelMap, names: list[str], outs: list[str], viewmat: Tensor, K: Tensor, near: float, far: float, bg: Tensor
) -> tuple[dict[str, Tensor], list[tuple[Tensor | None, dict[str, Tensor], float]], Tensor]:
    """Leaf parameters, per-channel (per-surfel value or None for depth, its derivative dict, background),
    and the differentiable packed projection rows [14, N] of the surfels of ``m``.
    """
    n = len(m)
    leaves = {k: getattr(m, k).clone().requires_grad_(k in names) for k in PARAM_NAMES if getattr(m, k) is not None}
    opac = torch.sigmoid(leaves["opacity_logits"])
    cam_centre = -viewmat[:3, :3].T @ viewmat[:3, 3]
    viewdirs = leaves["means"] - cam_centre if m.sh_rest is not None else None
    colors = SurfelMap(**leaves).colors(viewdirs)
    packed, normals, _ = project_packed(
        leaves["means"], leaves["quats"], torch.exp(leaves["log_scales"]), opac, viewmat, K, near, far
    )
    want = list(names)

    def per_surfel(x: Tensor) -> dict[str, Tensor]:
        if not x.requires_grad:
            return {}
        grads = torch.autograd.grad(x.sum(), [leaves[k] for k in want], retain_graph=True, allow_unused=True)
        return {k: g.reshape(n, -1) for k, g in zip(want, grads, strict=True) if g is not None}

    channels: list[tuple[Tensor | None, dict[str, Tensor], float]] = []
    for o in outs:
        if o == "color":
            channels += [(colors[:, c].detach(), per_surfel(colors[:, c]), float(bg[c])) for c in range(3)]
        elif o == "normal":
            channels += [(normals[:, c].detach(), per_surfel(normals[:, c]), 0.0) for c in range(3)]
        elif o == "alpha":
            channels.append((torch.ones(n, dtype=m.dtype, device=m.device), {}, 0.0))
        else:
            channels.append((None, {}, 0.0))
    return leaves, channels, packed


def _fisher_numba(
    m: SurfelMap,
    names: list[str],
    outs: list[str],
    proj: Projection,
    cam: tuple,
    weights: Tensor | None,
    bg: Tensor,
    tile_size: int,
    result: dict[str, Tensor],
) -> None:
    """Fisher with the numba kernels: forward walk for the pairs, then one fused backward-style walk."""
    viewmat, K, W, H, near, far = cam
    dt = m.dtype
    if not bool(proj.keep.any()):
        return
    bins = bin_tiles(proj, W, H, tile_size)
    r = _numba_forward(proj, proj.packed.new_zeros(len(m), 0), bins, W, H, near, far, None)
    vis = torch.from_numpy(r.vis.astype(np.bool_)).nonzero().squeeze(1)
    if vis.numel() == 0:
        return
    sub = m.select(vis)
    leaves, channels, packed = _channels(sub, names, outs, viewmat, K, near, far, bg)
    nv = len(sub)
    sizes = [leaves[k][0].numel() for k in names]
    D = sum(sizes)
    # Per-surfel Jacobian of the packed rows w.r.t. the chosen raw parameters: [Nv, 14, D].
    jac = torch.zeros(nv, packed.shape[0], D, dtype=dt)
    geo = [k for k in names if k in ("means", "quats", "log_scales", "opacity_logits")]
    cols = {k: slice(sum(sizes[: names.index(k)]), sum(sizes[: names.index(k) + 1])) for k in names}
    if geo:
        for row in range(packed.shape[0]):
            gs = torch.autograd.grad(packed[row].sum(), [leaves[k] for k in geo], retain_graph=True, allow_unused=True)
            for k, g in zip(geo, gs, strict=True):
                if g is not None:
                    jac[:, row, cols[k]] = g.reshape(nv, -1)
    nch = len(channels)
    X = torch.zeros(nv, nch, dtype=dt)
    B = torch.zeros(nv, nch, D, dtype=dt)
    kind = np.zeros(nch, np.int64)  # 0: per-surfel value, no derivative; 1: with derivative B; 2: depth
    bgs = np.zeros(nch)
    for c, (x, b, bgc) in enumerate(channels):
        if x is None:
            kind[c] = 2
        else:
            X[:, c] = x
        for k, g in b.items():
            B[:, c, cols[k]] = g
            kind[c] = 1
        bgs[c] = bgc
    local = np.full(len(m), -1, np.int64)
    local[vis.numpy()] = np.arange(nv)
    nb = _n_threads()
    bounds = _balanced_bounds(torch.from_numpy(r.count.astype(np.int64)) + 1, nb)
    out = np.zeros((nb, nv, D), np.float64)
    wts = np.ones(W * H) if weights is None else weights.double().numpy()
    with KERNEL_LOCK:
        _fisher_kernel()(
            packed.detach().T.contiguous().double().numpy(), jac.transpose(1, 2).contiguous().double().numpy(),
            X.double().numpy(), B.double().numpy(), kind, bgs, local, r.pair_buf, r.pix_off, r.count,
            r.T.astype(np.float64), bounds, W, float(near), wts, out,
        )  # fmt: skip
    total = torch.from_numpy(out.sum(0)).to(dt)
    for k in names:
        result[k].view(len(m), -1).index_copy_(0, vis, total[:, cols[k]])


def _k_fisher(
    pk: np.ndarray,
    jac: np.ndarray,
    X: np.ndarray,
    B: np.ndarray,
    kind: np.ndarray,
    bg: np.ndarray,
    local: np.ndarray,
    pair_buf: np.ndarray,
    pix_off: np.ndarray,
    count: np.ndarray,
    T_fin: np.ndarray,
    bounds: np.ndarray,
    width: int,
    near: float,
    wts: np.ndarray,
    out: np.ndarray,
) -> None:
    """Back-to-front walk per pixel (numba): squared per-pixel gradients, weighted, summed per surfel.

    ``jac`` [Nv, D, 14] is d packed / d theta per surfel; channel ``kind`` 0 (per-surfel value whose
    parameters are not in theta: colour for geometric Fisher, alpha), 1 (per-surfel value with
    derivative ``B`` [Nv, nch, D]) or 2 (the pair's depth). Kind-0 channels share one term
    ``a^2 sum_c g_c^2``.
    """
    nch = X.shape[1]
    D = jac.shape[1]
    for b in _prange(bounds.shape[0] - 1):
        S = np.zeros(nch)
        g = np.zeros(nch)
        for p in range(bounds[b], bounds[b + 1]):
            cnt = count[p]
            wp = wts[p]
            if cnt == 0 or wp == 0.0:
                continue
            x = float(p % width)
            y = float(p // width)
            T = T_fin[p]
            for c in range(nch):
                S[c] = T * bg[c]
            off = pix_off[p]
            for i in range(cnt - 1, -1, -1):
                sid = local[pair_buf[off + i]]
                pz = pk[sid, 6] * x + pk[sid, 7] * y + pk[sid, 8]
                inv = 1.0 / pz
                u = (pk[sid, 0] * x + pk[sid, 1] * y + pk[sid, 2]) * inv
                v = (pk[sid, 3] * x + pk[sid, 4] * y + pk[sid, 5]) * inv
                r3 = u * u + v * v
                dx = pk[sid, 11] - x
                dy = pk[sid, 12] - y
                r2 = 2.0 * (dx * dx + dy * dy)
                use3 = r3 <= r2
                if use3:
                    rho = r3
                    depth = pk[sid, 9] * inv
                else:
                    rho = r2
                    depth = pk[sid, 10]
                ex = np.exp(-0.5 * rho)
                a = pk[sid, 13] * ex
                clamped = a > 0.99
                if clamped:
                    a = 0.99
                inv1m = 1.0 / (1.0 - a)
                T = T * inv1m
                w = a * T
                g2 = 0.0
                gd = 0.0
                has_d = False
                has_b = False
                for c in range(nch):
                    val = depth if kind[c] == 2 else X[sid, c]
                    g[c] = T * val - S[c] * inv1m
                    S[c] += w * val
                    if kind[c] == 0:
                        g2 += g[c] * g[c]
                    elif kind[c] == 2:
                        gd = g[c]
                        has_d = True
                    else:
                        has_b = True
                # d alpha / d packed: through rho (and the opacity), zero where alpha is clamped.
                da_o = 0.0 if clamped else ex
                da_rho = 0.0 if clamped else -0.5 * a
                for j in range(D):
                    aj = da_o * jac[sid, j, 13]
                    if use3:
                        jx = x * jac[sid, j, 0] + y * jac[sid, j, 1] + jac[sid, j, 2]
                        jy = x * jac[sid, j, 3] + y * jac[sid, j, 4] + jac[sid, j, 5]
                        jz = x * jac[sid, j, 6] + y * jac[sid, j, 7] + jac[sid, j, 8]
                        aj += da_rho * 2.0 * (u * (jx - u * jz) + v * (jy - v * jz)) * inv
                        ej = (jac[sid, j, 9] - depth * jz) * inv
                    else:
                        aj += da_rho * 4.0 * (dx * jac[sid, j, 11] + dy * jac[sid, j, 12])
                        ej = jac[sid, j, 10]
                    acc = aj * aj * g2
                    if has_d:
                        Jd = gd * aj + w * ej
                        acc += Jd * Jd
                    if has_b:
                        for c in range(nch):
                            if kind[c] == 1:
                                Jc = g[c] * aj + w * B[sid, c, j]
                                acc += Jc * Jc
                    out[b, sid, j] += wp * acc


_FISHER_KERNEL: list[object] = []


def _fisher_kernel() -> object:
    """The numba-compiled Fisher kernel (compiled on first use)."""
    if not _FISHER_KERNEL:
        import numba

        _kernels()  # sets the threading layer and numba's prange for the module-level kernels
        globals()["_prange"] = numba.prange
        _FISHER_KERNEL.append(numba.njit(parallel=True, cache=True, nogil=True)(_k_fisher))
    return _FISHER_KERNEL[0]


def _prange(n: int) -> range:
    """Stand-in for ``numba.prange`` until the kernel is compiled."""
    return range(n)


def _fisher_torch(
    m: SurfelMap,
    names: list[str],
    outs: list[str],
    proj: Projection,
    pairs: Pairs,
    cam: tuple,
    weights: Tensor | None,
    bg: Tensor,
    pair_chunk: int,
    result: dict[str, Tensor],
) -> None:
    """Fisher in plain torch: per-pair leaf copies, two backward passes per chunk of pairs."""
    viewmat, K, W, _, near, far = cam
    dt = m.dtype
    n = len(m)
    leaves, channels, _ = _channels(m, names, outs, viewmat, K, near, far, bg)
    want = list(names)
    # Forward compositing quantities per pair (no grad), float64 scans.
    surf, pix = pairs.surf, pairs.pix
    x_pix = (pix % W).to(dt)
    y_pix = torch.div(pix, W, rounding_mode="floor").to(dt)
    with torch.no_grad():
        rows = proj.packed.index_select(1, surf).unbind(0)
        alpha, depth, _ = pair_alpha_depth(rows, x_pix, y_pix)
        lg = torch.log1p(-alpha.double())
        cs = torch.cumsum(lg, 0)
        excl = cs - lg
        T_before = torch.exp(excl - excl.index_select(0, pairs.start))
        last = pairs.offsets[1:].index_select(0, pix) - 1
        T_final = torch.exp(cs.index_select(0, last) - excl.index_select(0, pairs.start))
        w = alpha.double() * T_before
        inv1m = 1.0 / (1.0 - alpha.double())
        coeffs = []  # (g [M], b dict, is_depth)
        for x, b, bgc in channels:
            xp = depth.double() if x is None else x.double().index_select(0, surf)
            g = T_before * xp - (_seg_suffix_sum(w * xp, pairs) + T_final * bgc) * inv1m
            coeffs.append((g.to(dt), b, x is None))
        wp = w.to(dt)
        pw = weights.index_select(0, pix) if weights is not None else None

    need_depth = any(is_d for _, _, is_d in coeffs)
    for lo in range(0, len(pairs), pair_chunk):
        sl = slice(lo, min(lo + pair_chunk, len(pairs)))
        s_idx = surf[sl]
        copies = {k: leaves[k].detach().index_select(0, s_idx).requires_grad_(k in want) for k in GEOMETRIC_PARAMS}
        copies["opacity_logits"] = leaves["opacity_logits"].detach().index_select(0, s_idx)
        copies["opacity_logits"].requires_grad_("opacity_logits" in want)
        grad_keys = [k for k in want if k in copies]
        packed, _, _ = project_packed(
            copies["means"], copies["quats"], torch.exp(copies["log_scales"]),
            torch.sigmoid(copies["opacity_logits"]), viewmat, K, near, far,
        )  # fmt: skip
        a_pair, d_pair, _ = pair_alpha_depth(packed.unbind(0), x_pix[sl], y_pix[sl])
        da = dd = {}
        if grad_keys:
            gs = torch.autograd.grad(a_pair.sum(), [copies[k] for k in grad_keys], retain_graph=need_depth)
            da = {k: g.reshape(g.shape[0], -1) for k, g in zip(grad_keys, gs, strict=True)}
            if need_depth:
                gs = torch.autograd.grad(d_pair.sum(), [copies[k] for k in grad_keys])
                dd = {k: g.reshape(g.shape[0], -1) for k, g in zip(grad_keys, gs, strict=True)}
        for k in want:
            acc = None
            for g, b, is_d in coeffs:
                J = None
                if k in da:
                    J = g[sl, None] * da[k]
                extra = dd.get(k) if is_d else (b[k].index_select(0, s_idx) if k in b else None)
                if extra is not None:
                    J = wp[sl, None] * extra if J is None else J + wp[sl, None] * extra
                if J is not None:
                    acc = J * J if acc is None else acc + J * J
            if acc is None:
                continue
            if pw is not None:
                acc = acc * pw[sl, None]
            result[k].view(n, -1).index_add_(0, s_idx, acc.to(dt))


def fisher_per_surfel(fisher: dict[str, Tensor]) -> Tensor:
    """Per-surfel scalar [N]: the sum of a Fisher dictionary's entries over each surfel's parameters."""
    tensors = list(fisher.values())
    if not tensors:
        raise InputError("fisher", "empty Fisher dictionary")
    return sum(t.reshape(t.shape[0], -1).sum(-1) for t in tensors)
