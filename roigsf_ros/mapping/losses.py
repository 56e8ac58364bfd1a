"""The 2DGS training losses: L1 + D-SSIM colour, depth L1, normal consistency and distortion.

Images are channel-last float tensors, ``[H, W, C]`` (or ``[B, H, W, C]``), as the renderer
returns them; depths are ``[H, W]`` metres. SSIM follows 3DGS/2DGS: an 11x11 Gaussian window
with sigma 1.5, zero padding, C1 = 0.01^2, C2 = 0.03^2.
"""

from __future__ import annotations

import functools

import torch
from torch.nn import functional

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.render.surfels import depth_to_points

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
_C1 = 0.01**2
_C2 = 0.03**2


@functools.lru_cache(maxsize=8)
def _gaussian_window(size: int, sigma: float, channels: int, dtype: torch.dtype) -> torch.Tensor:
    """The separable Gaussian window as a depthwise conv kernel [C, 1, size, size]."""
    g = _gaussian_1d(size, sigma)
    w2d = torch.outer(g, g).to(dtype)
    return w2d.expand(channels, 1, size, size).contiguous()


@functools.lru_cache(maxsize=8)
def _gaussian_pair(size: int, sigma: float, channels: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """The window's two 1D factors as depthwise conv kernels: vertical [C, 1, size, 1], horizontal [C, 1, 1, size]."""
    g = _gaussian_1d(size, sigma).to(dtype)
    return g.view(1, 1, size, 1).expand(channels, 1, size, 1).contiguous(), g.view(1, 1, 1, size).expand(
        channels, 1, 1, size
    ).contiguous()


def _gaussian_1d(size: int, sigma: float) -> torch.Tensor:
    """The normalised 1D Gaussian [size] (float64)."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _to_nchw(img: torch.Tensor) -> torch.Tensor:
    """[H, W, C] or [B, H, W, C] channel-last images as [B, C, H, W]."""
    if img.dim() == 3:
        img = img.unsqueeze(0)
    if img.dim() != 4:
        raise ValueError(f"expected [H, W, C] or [B, H, W, C] images, got shape {tuple(img.shape)}")
    return img.permute(0, 3, 1, 2)


def ssim_map(img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM of two channel-last images in [0, 1], as [B, C, H, W] (3DGS formulation)."""
    x, y = _to_nchw(img1), _to_nchw(img2)
    c = x.shape[1]
    wv, wh = _gaussian_pair(SSIM_WINDOW, SSIM_SIGMA, 5 * c, x.dtype)
    pad = SSIM_WINDOW // 2
    # The five moments in one grouped convolution, and the 11x11 window as its two 1D factors (the
    # same zero-padded result with 2 x 11 instead of 121 taps per pixel).
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    mom = functional.conv2d(stack, wv.to(x.device), padding=(pad, 0), groups=5 * c)
    mom = functional.conv2d(mom, wh.to(x.device), padding=(0, pad), groups=5 * c)
    mu1, mu2, e11, e22, e12 = mom.split(c, dim=1)
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s1, s2, s12 = e11 - mu1_sq, e22 - mu2_sq, e12 - mu12
    return ((2 * mu12 + _C1) * (2 * s12 + _C2)) / ((mu1_sq + mu2_sq + _C1) * (s1 + s2 + _C2))


def ssim(img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two channel-last images in [0, 1] (differentiable)."""
    return ssim_map(img1, img2).mean()


def colour_loss(
    rgb_render: torch.Tensor, rgb_gt: torch.Tensor, lambda_dssim: float = 0.2, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """``(1 - lambda) L1 + lambda (1 - SSIM)``; ``mask`` [H, W] restricts the L1 term (SSIM stays global)."""
    diff = (rgb_render - rgb_gt).abs()
    if mask is not None:
        m = mask.to(diff.dtype).unsqueeze(-1)
        l1 = (diff * m).sum() / (m.sum() * diff.shape[-1]).clamp_min(1.0)
    else:
        l1 = diff.mean()
    if lambda_dssim <= 0:
        return l1
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(rgb_render, rgb_gt))


def depth_l1(depth_render: torch.Tensor, depth_gt: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean absolute depth error (metres) over the ``valid`` pixels; zero when none is valid."""
    v = valid.to(depth_render.dtype)
    return ((depth_render - depth_gt).abs() * v).sum() / v.sum().clamp_min(1.0)


def depth_to_normal_cam(depth_m: torch.Tensor, intr: Intrinsics) -> torch.Tensor:
    """Camera-frame unit normals [H, W, 3] of a depth map by central differences, facing the camera.

    Border pixels are zero (as in 2DGS's ``depth_to_normal``), so they drop out of the loss.
    """
    pts = depth_to_points(depth_m, intr)
    out = torch.zeros_like(pts)
    dx = pts[1:-1, 2:] - pts[1:-1, :-2]
    dy = pts[2:, 1:-1] - pts[:-2, 1:-1]
    n = torch.linalg.cross(dx, dy, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    # dx x dy points away from a camera looking down +z at a surface; flip to face the camera.
    out[1:-1, 1:-1] = -n
    return out


def normal_consistency(
    normal_render_cam: torch.Tensor, depth_render: torch.Tensor, alpha: torch.Tensor, intr: Intrinsics
) -> torch.Tensor:
    """2DGS normal loss: mean of ``1 - <rendered normal, normal of rendered depth>`` weighted by alpha.

    ``normal_render_cam`` [H, W, 3] is the alpha-composited surfel normal in the camera frame;
    the depth normal is scaled by the detached alpha as in 2DGS.
    """
    n_depth = depth_to_normal_cam(depth_render, intr) * alpha.detach().unsqueeze(-1)
    err = 1.0 - (normal_render_cam * n_depth).sum(dim=-1)
    return err.mean()


def distortion(dist_map: torch.Tensor) -> torch.Tensor:
    """2DGS depth distortion loss: the mean of the renderer's per-pixel distortion map."""
    return dist_map.mean()


__all__ = [
    "SSIM_SIGMA",
    "SSIM_WINDOW",
    "colour_loss",
    "depth_l1",
    "depth_to_normal_cam",
    "distortion",
    "normal_consistency",
    "ssim",
    "ssim_map",
]
