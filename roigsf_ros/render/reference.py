"""Dense reference 2DGS renderer: every pixel against every surfel, for checking the fast one.

Plain and obviously correct rather than fast ([pixels, surfels] tensors, a Python loop over the
surfels in depth order); use it on tiny scenes only. It follows hbb1/diff-surfel-rasterization:

- splat-to-pixel transform ``M = K [s_u t_u, s_v t_v, p]`` (camera frame), rows Tu, Tv, Tw, so that
  ``[x w, y w, w] = M [u, v, 1]`` with ``w`` the camera z; pixel (i, j) sits at x = i, y = j (OpenCV);
- ray-splat intersection ``k = x Tw - Tu``, ``l = y Tw - Tv``, ``p = k x l``, ``(u, v) = p.xy / p.z``
  (skipped where ``p.z == 0``);
- low-pass fallback ``rho = min(u^2 + v^2, 2 |pixel - projected centre|^2)``, ``G = exp(-rho / 2)``,
  ``alpha = min(0.99, opacity G)``; the per-surfel depth is the intersection's camera z where the
  3D term wins, else the centre's camera z (2DGS ``depth``); skipped: alpha < 1/255, depth < near;
- surfels whose centre z is outside (near, far] are culled; surfels are composited front to back
  in the order of their centre z (one order for all pixels, as 2DGS sorts per tile), stopping
  (without the crossing surfel) once transmittance would fall below 1e-4;
- outputs as :class:`roigsf_ros.render.rasterize.RenderOutput`; normals in the camera frame, flipped so that
  they face the camera (``n . p_centre <= 0``); median depth is the depth of the last surfel hit
  while the transmittance before it is above 0.5; distortion is 2DGS's per-pixel
  ``sum_{i>j} w_i w_j (m_i - m_j)^2`` with ``m = far / (far - near) (1 - near / depth)``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from roigsf_ros.render.rasterize import ALPHA_MAX, ALPHA_MIN, FILTER_INV_SQUARE, T_MIN, RenderOutput
from roigsf_ros.render.surfels import quat_to_rotmat


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
) -> RenderOutput:
    """Render N surfels (world ``means`` [N, 3], ``quats`` [N, 4] wxyz, ``scales`` [N, 2] metres,
    ``opacities`` [N], ``features`` [N, C]) seen by ``viewmat`` [4, 4] (world -> camera) and ``K`` [3, 3].
    """
    n, c = features.shape
    dt, dev = means.dtype, means.device
    R_cw, t_cw = viewmat[:3, :3].to(dt), viewmat[:3, 3].to(dt)
    K = K.to(dt)
    rot = quat_to_rotmat(quats)
    p_cam = means @ R_cw.T + t_cw  # [N, 3]
    tu_cam = (rot[:, :, 0] @ R_cw.T) * scales[:, 0:1]
    tv_cam = (rot[:, :, 1] @ R_cw.T) * scales[:, 1:2]
    n_cam = rot[:, :, 2] @ R_cw.T
    M = K @ torch.stack([tu_cam, tv_cam, p_cam], dim=-1)  # [N, 3, 3], rows Tu, Tv, Tw
    Tu, Tv, Tw = M[:, 0], M[:, 1], M[:, 2]
    z = p_cam[:, 2]
    keep = (z > near) & (z <= far)
    z_safe = torch.where(keep, z, torch.ones_like(z))
    centre = torch.stack([Tu[:, 2] / z_safe, Tv[:, 2] / z_safe], dim=-1)  # projected centre
    facing = (n_cam * p_cam).sum(-1, keepdim=True) > 0
    n_cam = torch.where(facing, -n_cam, n_cam)

    ys, xs = torch.meshgrid(torch.arange(height, device=dev), torch.arange(width, device=dev), indexing="ij")
    x = xs.reshape(-1, 1, 1).to(dt)  # [P, 1, 1]
    y = ys.reshape(-1, 1, 1).to(dt)
    k = x * Tw[None] - Tu[None]  # [P, N, 3]
    l_ = y * Tw[None] - Tv[None]
    p = torch.linalg.cross(k, l_, dim=-1)
    pz_ok = p[..., 2] != 0
    pz = torch.where(pz_ok, p[..., 2], torch.ones_like(p[..., 2]))
    u, v = p[..., 0] / pz, p[..., 1] / pz  # [P, N]
    rho3d = u * u + v * v
    d = centre[None] - torch.cat([x[..., 0], y[..., 0]], dim=-1)[:, None, :]  # centre - pixel
    rho2d = FILTER_INV_SQUARE * (d * d).sum(-1)
    use3d = rho3d <= rho2d
    rho = torch.where(use3d, rho3d, rho2d)
    depth = torch.where(use3d, u * Tw[None, :, 0] + v * Tw[None, :, 1] + Tw[None, :, 2], z[None].expand_as(u))
    alpha = torch.clamp(opacities[None] * torch.exp(-0.5 * rho), max=ALPHA_MAX)
    valid = keep[None] & pz_ok & (depth >= near) & (alpha >= ALPHA_MIN)
    depth_safe = torch.where(valid, depth, torch.ones_like(depth))
    m = far / (far - near) * (1.0 - near / depth_safe)

    P = height * width
    T = torch.ones(P, dtype=dt, device=dev)
    done = torch.zeros(P, dtype=torch.bool, device=dev)
    feat = torch.zeros(P, c, dtype=dt, device=dev)
    D = torch.zeros(P, dtype=dt, device=dev)
    N_ = torch.zeros(P, 3, dtype=dt, device=dev)
    M1 = torch.zeros(P, dtype=dt, device=dev)
    M2 = torch.zeros(P, dtype=dt, device=dev)
    dist = torch.zeros(P, dtype=dt, device=dev)
    median = torch.zeros(P, dtype=dt, device=dev)
    count = torch.zeros(P, dtype=torch.long, device=dev)
    visible = torch.zeros(n, dtype=torch.bool, device=dev)
    for i in torch.sort(z, stable=True).indices.tolist():
        a = alpha[:, i]
        ok = valid[:, i] & ~done
        test_T = T * (1 - a)
        stop = ok & (test_T < T_MIN)
        done = done | stop
        ok = ok & ~stop
        w = torch.where(ok, a * T, torch.zeros_like(a))
        di, mi = depth_safe[:, i], m[:, i]
        dist = dist + w * (mi * mi * (1 - T) + M2 - 2 * mi * M1)
        D = D + w * di
        M1 = M1 + w * mi
        M2 = M2 + w * mi * mi
        median = torch.where(ok & (T > 0.5), di, median)
        N_ = N_ + w[:, None] * n_cam[i]
        feat = feat + w[:, None] * features[i]
        T = torch.where(ok, test_T, T)
        count = count + ok.long()
        visible[i] = bool(ok.any())
    if background is not None:
        feat = feat + T[:, None] * background.to(dt)
    # Zero-valued link: outputs stay attached to the inputs' graph even with no surfels.
    link = sum(t[:0].sum() for t in (means, quats, scales, opacities, features))
    feat, T, D, median, N_, dist = (t + link for t in (feat, T, D, median, N_, dist))
    hw = (height, width)
    return RenderOutput(
        features=feat.reshape(*hw, c),
        alpha=(1 - T).reshape(hw),
        depth=D.reshape(hw),
        median_depth=median.reshape(hw),
        normal=N_.reshape(*hw, 3),
        distortion=dist.reshape(hw),
        n_contrib=count.reshape(hw),
        visible=visible,
    )


__all__ = [
    "rasterize_surfels",
]
