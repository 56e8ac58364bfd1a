"""Exact diagonal Fisher against brute-force per-pixel autograd of the reference renderer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.render import reference as render_reference
from roigsf_ros.render.fisher import (
    ALL_PARAMS,
    GEOMETRIC_PARAMS,
    fisher_diag,
    fisher_per_surfel,
    fisher_weighted_sum,
    frustum_subset,
    packed_jacobian,
)
from roigsf_ros.render.numba_setup import numba_available
from roigsf_ros.render.rasterize import camera_tensors, pair_alpha_depth, project_packed
from roigsf_ros.render.surfels import SurfelMap

F64 = torch.float64
BACKENDS = ["torch", pytest.param("numba", marks=pytest.mark.skipif(not numba_available(), reason="no numba"))]
INTR = Intrinsics(14, 11, 11.0, 11.5, 6.5, 5.0)


def scene(seed: int, n: int = 10, sh_rest: bool = True) -> SurfelMap:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=F64) * 0.4
    means[:, 2] += 2.0
    return SurfelMap(
        means=means,
        quats=torch.randn(n, 4, generator=g, dtype=F64),
        log_scales=torch.log(torch.rand(n, 2, generator=g, dtype=F64) * 0.3 + 0.05),
        opacity_logits=torch.randn(n, generator=g, dtype=F64) * 1.5,
        sh_dc=torch.randn(n, 3, generator=g, dtype=F64),
        sh_rest=torch.randn(n, 3, 3, generator=g, dtype=F64) * 0.3 if sh_rest else None,
    )


def pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=3) * 0.1
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + K + K @ K / 2  # close to a rotation; orthonormalise
    u, _, vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = u @ vt
    T[:3, 3] = rng.normal(size=3) * 0.05
    return T


def brute_force(m: SurfelMap, T_wc, outputs, params, weights=None, background=None) -> dict[str, torch.Tensor]:
    """One backward pass per pixel and channel through the dense reference renderer."""
    m = m.clone().requires_grad_()
    viewmat, K = camera_tensors(T_wc, INTR, dtype=F64)
    cam = -viewmat[:3, :3].T @ viewmat[:3, 3]
    cols = m.colors(m.means - cam if m.sh_rest is not None else None)
    out = render_reference.rasterize_surfels(
        m.means, m.quats, m.scales(), m.opacities(), cols, viewmat, K, INTR.width, INTR.height, background=background
    )
    chans = {
        "color": [out.features[..., c] for c in range(3)],
        "depth": [out.depth],
        "alpha": [out.alpha],
        "normal": [out.normal[..., c] for c in range(3)],
    }
    tensors = [getattr(m, k) for k in params]
    fisher = [torch.zeros_like(t) for t in tensors]
    for name in outputs:
        for ch in chans[name]:
            flat = ch.reshape(-1)
            for i in range(flat.numel()):
                grads = torch.autograd.grad(flat[i], tensors, retain_graph=True, allow_unused=True)
                wgt = 1.0 if weights is None else float(weights.reshape(-1)[i])
                for f, g in zip(fisher, grads, strict=True):
                    if g is not None:
                        f += wgt * g * g
    return dict(zip(params, fisher, strict=True))


def assert_close(a: dict, b: dict, rtol: float = 1e-10) -> None:
    assert a.keys() == b.keys()
    for k in a:
        scale = b[k].abs().max()
        if scale == 0:  # e.g. colour parameters for alpha / normal outputs
            assert torch.all(a[k] == 0), k
            continue
        assert (a[k] - b[k]).abs().max() <= rtol * scale, (k, ((a[k] - b[k]).abs().max() / scale).item())


@pytest.mark.parametrize(
    ("seed", "outputs"),
    [(0, ("color", "depth")), (1, ("alpha", "normal")), (2, ("color", "depth", "alpha", "normal"))],
)
def test_exact_against_brute_force(seed: int, outputs) -> None:
    m = scene(seed)
    T = pose(seed)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=F64) if seed == 0 else None
    expected = brute_force(m, T, outputs, ALL_PARAMS, background=bg)
    for backend in ("torch", "numba") if numba_available() else ("torch",):
        got = fisher_diag(m, T, INTR, outputs=outputs, params=ALL_PARAMS, background=bg, backend=backend)
        assert_close(got, expected)


@pytest.mark.parametrize("backend", BACKENDS)
def test_roi_weights_and_geometric_subset(backend: str) -> None:
    m = scene(3, sh_rest=False)
    T = pose(3)
    w = torch.rand(INTR.height, INTR.width, generator=torch.Generator().manual_seed(0), dtype=F64)
    w[:, : INTR.width // 2] = 0  # an ROI on the right half
    got = fisher_diag(m, T, INTR, outputs=("color", "depth"), pixel_weights=w, backend=backend)
    assert list(got) == list(GEOMETRIC_PARAMS)
    assert_close(got, brute_force(m, T, ("color", "depth"), GEOMETRIC_PARAMS, weights=w))
    full = fisher_diag(m, T, INTR, outputs=("color", "depth"), params=ALL_PARAMS, pixel_weights=w, backend=backend)
    for k in GEOMETRIC_PARAMS:
        assert torch.allclose(full[k], got[k], rtol=1e-12, atol=0)
    doubled = fisher_diag(m, T, INTR, outputs=("color", "depth"), pixel_weights=2 * w.numpy(), backend=backend)
    assert all(torch.allclose(doubled[k], 2 * got[k], rtol=1e-12, atol=0) for k in got)
    zero = fisher_diag(m, T, INTR, pixel_weights=torch.zeros_like(w), backend=backend)
    assert all(torch.all(v == 0) for v in zero.values())


@pytest.mark.parametrize("backend", BACKENDS)
def test_view_dependent_colour_without_the_means(backend: str) -> None:
    """Degree-1 SH colours depend on the view but on none of the chosen parameters: their values, read at the
    surfels' own rows without a per-surfel graph, against the brute force through the full render. Two surfels
    are off to the side, so the rows the numba kernel keeps are not the map's first ones."""
    m = scene(6, n=12)
    m.means[0] = torch.tensor([30.0, 0.0, 2.0], dtype=F64)
    m.means[5] = torch.tensor([0.0, -30.0, 2.0], dtype=F64)
    T = pose(6)
    params = ("quats", "log_scales")
    got = fisher_diag(m, T, INTR, outputs=("color", "depth", "alpha"), params=params, backend=backend)
    assert_close(got, brute_force(m, T, ("color", "depth", "alpha"), params))
    assert all(bool(v[[0, 5]].abs().sum() == 0) and bool(v.abs().sum() > 0) for v in got.values())


@pytest.mark.parametrize("backend", BACKENDS)
def test_weighted_sum_is_the_dense_fisher_dotted_with_the_weights(backend: str) -> None:
    """Eq. 10's sum without the dense result; view-dependent colour makes the colour depend on the means."""
    m = scene(5)
    T = pose(5)
    w = torch.rand(INTR.height, INTR.width, generator=torch.Generator().manual_seed(1), dtype=F64)
    w[: INTR.height // 2] = 0
    kw = {"outputs": ("color", "depth"), "pixel_weights": w, "backend": backend}
    dense = fisher_diag(m, T, INTR, **kw)
    assert_close(dense, brute_force(m, T, ("color", "depth"), GEOMETRIC_PARAMS, weights=w))
    rng = np.random.default_rng(0)
    entry = {k: rng.uniform(0.5, 2.0, getattr(m, k).numel()) for k in GEOMETRIC_PARAMS}
    want = sum(float((dense[k].numpy().reshape(-1) * entry[k]).sum()) for k in dense)
    assert want > 0 and fisher_weighted_sum(m, T, INTR, entry, **kw) == pytest.approx(want, rel=1e-12)
    away = T.copy()
    away[:3, :3] = T[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # looking away from every surfel
    assert fisher_weighted_sum(m, away, INTR, entry, backend=backend) == 0.0
    with pytest.raises(InputError, match="entry_weights"):
        fisher_weighted_sum(m, T, INTR, {"means": entry["means"]}, backend=backend)
    with pytest.raises(InputError, match=r"entry_weights\[quats\]"):
        fisher_weighted_sum(m, T, INTR, entry | {"quats": entry["quats"][:-1]}, backend=backend)


@pytest.mark.parametrize("backend", BACKENDS)
def test_invisible_surfels_get_zero(backend: str) -> None:
    m = scene(4, n=8)
    m.means[0] = torch.tensor([0.0, 0.0, -2.0], dtype=F64)  # behind the camera
    m.means[1] = torch.tensor([30.0, 0.0, 2.0], dtype=F64)  # off to the side
    m.opacity_logits[2] = -10.0  # too transparent to reach alpha 1/255
    got = fisher_diag(m, np.eye(4), INTR, outputs=("color", "depth"), params=ALL_PARAMS, backend=backend)
    per = fisher_per_surfel(got)
    assert per.shape == (8,)
    assert torch.all(per[:3] == 0) and torch.all(per[3:] >= 0) and per[3:].sum() > 0
    assert torch.allclose(per, sum(v.reshape(8, -1).sum(-1) for v in got.values()))
    empty = fisher_diag(SurfelMap.empty(dtype=F64), np.eye(4), INTR, backend=backend)
    assert all(v.shape[0] == 0 for v in empty.values())


@pytest.mark.skipif(
    not torch.cuda.is_available(),
    reason="no CUDA device: the torch backend's CUDA path is checked where a GPU is lent (scripts/device_check.sh)",
)
def test_cuda_matches_brute_force() -> None:
    """Fisher of a map on CUDA (the torch backend): brute force on the CPU to 1e-10, dense and weighted sum."""
    m = scene(5)
    T = pose(5)
    w = torch.rand(INTR.height, INTR.width, generator=torch.Generator().manual_seed(1), dtype=F64)
    w[: INTR.height // 2] = 0
    expected = brute_force(m, T, ("color", "depth"), ALL_PARAMS, weights=w)
    mc = m.to(device="cuda")
    got = fisher_diag(mc, T, INTR, outputs=("color", "depth"), params=ALL_PARAMS, pixel_weights=w.cuda())
    assert all(v.is_cuda for v in got.values())
    assert_close({k: v.cpu() for k, v in got.items()}, expected)
    rng = np.random.default_rng(0)
    entry = {k: rng.uniform(0.5, 2.0, getattr(m, k).numel()) for k in GEOMETRIC_PARAMS}
    want = sum(float((expected[k].numpy().reshape(-1) * entry[k]).sum()) for k in GEOMETRIC_PARAMS)
    kw = {"outputs": ("color", "depth"), "pixel_weights": w}
    assert want > 0 and fisher_weighted_sum(mc, T, INTR, entry, **kw) == pytest.approx(want, rel=1e-10)
    view_cuda, _ = camera_tensors(T, INTR, device="cuda", dtype=F64)
    view_cpu, _ = camera_tensors(T, INTR, dtype=F64)
    culled = frustum_subset(mc, view_cuda, INTR, 0.2, 100.0)
    assert culled.is_cuda and torch.equal(culled.cpu(), frustum_subset(m, view_cpu, INTR, 0.2, 100.0, backend="torch"))


@pytest.mark.parametrize("backend", BACKENDS)
def test_float32_close_to_float64(backend: str) -> None:
    m = scene(5)
    T = pose(5)
    a = fisher_diag(m, T, INTR, params=ALL_PARAMS, backend="torch")
    b = fisher_diag(m.to(dtype=torch.float32), T, INTR, params=ALL_PARAMS, backend=backend)
    assert all(v.dtype == torch.float32 for v in b.values())
    for k in a:
        assert torch.allclose(b[k].double(), a[k], rtol=1e-3, atol=1e-4 * a[k].abs().max()), k


def test_bad_arguments() -> None:
    m = scene(0, n=3)
    with pytest.raises(InputError, match="outputs"):
        fisher_diag(m, np.eye(4), INTR, outputs=("colour",))
    with pytest.raises(InputError, match="params"):
        fisher_diag(m, np.eye(4), INTR, params=("nope",))
    with pytest.raises(InputError, match="pixel_weights"):
        fisher_diag(m, np.eye(4), INTR, pixel_weights=np.ones((3, 3)))
    # a walk: a scaled pose gave an 8x larger Fisher without a word, a 2x2 one numpy's broadcast error
    with pytest.raises(InputError, match="T_wc"):
        fisher_diag(m, 2.0 * np.eye(4), INTR)
    with pytest.raises(InputError, match="T_wc"):
        fisher_diag(m, np.eye(2), INTR)
    with pytest.raises(InputError, match=r"T_wc: expected shape \[4, 4\], got \[2, 2\]"):
        fisher_diag(m, torch.eye(2, dtype=torch.float64), INTR)


def test_packed_jacobian_matches_autograd() -> None:
    """The closed-form d packed / d theta of the numba path equals autograd through project_packed."""
    pytest.importorskip("numba")
    m = scene(6, n=12, sh_rest=False)
    m.means[0, 2] = 0.1  # centre nearer than the near plane: the centre-pixel rows use z = 1
    m.quats[1] *= 3.0  # non-unit quaternions are normalised inside the projection
    viewmat, K = camera_tensors(pose(6), INTR, dtype=F64)
    pk, jac = packed_jacobian(m, viewmat, K, 0.2, 100.0)
    leaves = {k: getattr(m, k).clone().requires_grad_() for k in ("means", "quats", "log_scales", "opacity_logits")}
    packed, _, _ = project_packed(
        leaves["means"], leaves["quats"], leaves["log_scales"].exp(), leaves["opacity_logits"].sigmoid(),
        viewmat, K, 0.2, 100.0,
    )  # fmt: skip
    np.testing.assert_allclose(pk, packed.detach().T.numpy(), rtol=1e-12, atol=1e-12)
    cols = 0
    for k, leaf in leaves.items():
        width = leaf[0].numel()
        for row in range(packed.shape[0]):
            (g,) = torch.autograd.grad(packed[row].sum(), [leaf], retain_graph=True, allow_unused=True)
            want = np.zeros((len(m), width)) if g is None else g.reshape(len(m), -1).numpy()
            got = jac[:, cols : cols + width, row]
            np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10 * max(1.0, np.abs(want).max()), err_msg=k)
        cols += width


def test_frustum_culling_keeps_every_surfel_that_reaches_a_pixel() -> None:
    """Culled surfels reach alpha >= 1/255 at no pixel (so they can neither contribute nor stop a pixel)."""
    g = torch.Generator().manual_seed(7)
    n = 400
    m = scene(7, n=n, sh_rest=False)
    m.means = torch.randn(n, 3, generator=g, dtype=F64) * torch.tensor([3.0, 3.0, 2.0], dtype=F64)
    m.means[:, 2] += 1.0
    m.log_scales = torch.log(torch.rand(n, 2, generator=g, dtype=F64) * 0.5 + 0.02)
    m.opacity_logits = torch.full((n,), 5.0, dtype=F64)  # nearly opaque: the largest reach
    T = pose(7)
    viewmat, K = camera_tensors(T, INTR, dtype=F64)
    keep = torch.zeros(n, dtype=torch.bool)
    keep[frustum_subset(m, viewmat, INTR, 0.2, 100.0)] = True
    proj = project_packed(m.means, m.quats, m.scales(), m.opacities(), viewmat, K, 0.2, 100.0)[0]
    ys, xs = torch.meshgrid(torch.arange(INTR.height, dtype=F64), torch.arange(INTR.width, dtype=F64), indexing="ij")
    rows = [r[:, None] for r in proj.unbind(0)]
    alpha, depth, pz = pair_alpha_depth(rows, xs.reshape(1, -1), ys.reshape(1, -1))
    reaches = ((alpha >= 1 / 255) & (depth >= 0.2) & (pz != 0) & (proj[10][:, None] > 0.2)).any(1)
    assert reaches.sum() > 10 and (~keep).sum() > n / 4  # both sets are non-trivial here
    assert not bool((reaches & ~keep).any())
    # The culled surfels get exactly zero; both backends (which cull alike) agree.
    got = fisher_diag(m, T, INTR, outputs=("color", "depth"), backend="torch")
    assert all(torch.all(v[~keep] == 0) for v in got.values())
    if numba_available():
        assert_close(fisher_diag(m, T, INTR, outputs=("color", "depth"), backend="numba"), got, rtol=1e-9)


@pytest.mark.skipif(not numba_available(), reason="no numba")
def test_numba_blocks_match_torch_on_a_larger_view() -> None:
    """The tile-major numba kernel on many 4x4 pixel tiles (partial ones at the edges), ROI weights with
    zeros, view-dependent colours and normals (channels with their own derivatives), alpha clamping and
    both alpha branches (ray-splat and the screen-space fallback), against the torch backend."""
    intr = Intrinsics(37, 29, 30.0, 30.5, 18.0, 14.0)
    g = torch.Generator().manual_seed(11)
    n = 90
    m = scene(11, n=n)
    m.means = torch.randn(n, 3, generator=g, dtype=F64) * torch.tensor([0.6, 0.5, 0.3], dtype=F64)
    m.means[:, 2] += 2.5
    m.log_scales[:12] = math.log(0.004)  # sub-pixel surfels: the screen-space fallback
    m.opacity_logits[12:20] = 8.0  # alpha clamped at 0.99
    T = pose(11)
    viewmat, K = camera_tensors(T, intr, dtype=F64)
    rows = project_packed(m.means, m.quats, m.scales(), m.opacities(), viewmat, K, 0.2, 100.0)[0]
    ys, xs = torch.meshgrid(torch.arange(intr.height, dtype=F64), torch.arange(intr.width, dtype=F64), indexing="ij")
    r = [row[:, None] for row in rows.unbind(0)]
    x, y = xs.reshape(1, -1), ys.reshape(1, -1)
    alpha, _, pz = pair_alpha_depth(r, x, y)
    u = (r[0] * x + r[1] * y + r[2]) / pz
    v = (r[3] * x + r[4] * y + r[5]) / pz
    fallback = u * u + v * v > 2.0 * ((r[11] - x) ** 2 + (r[12] - y) ** 2)
    hit = alpha >= 1 / 255
    assert bool((hit & fallback).any()) and bool((hit & ~fallback).any()) and bool((alpha >= 0.99).any())
    w = torch.rand(intr.height, intr.width, generator=g, dtype=F64) + 0.5
    w[w < 0.8] = 0  # scattered zero weights (whole blocks and single pixels)
    w[:8, :12] = 0
    flat = SurfelMap(**{k: getattr(m, k) for k in ("means", "quats", "log_scales", "opacity_logits", "sh_dc")})
    cases = (
        (m, ("color", "depth"), GEOMETRIC_PARAMS),
        (m, ("color", "depth", "alpha", "normal"), ALL_PARAMS),
        (m, ("color", "depth"), ("quats", "log_scales")),  # view-dependent colour, no derivative: values at the rows
        (flat, ("color", "depth"), GEOMETRIC_PARAMS),  # colour without derivatives: the walk's fast path
        (flat, ("color", "depth", "alpha"), GEOMETRIC_PARAMS),  # the fast path with a fourth channel
        (flat, ("alpha", "color"), GEOMETRIC_PARAMS),  # the same without depth, alpha first
        (flat, ("color",), GEOMETRIC_PARAMS),
        (flat, ("depth", "alpha"), GEOMETRIC_PARAMS),
        # the chain rule's parameter groups (mean, quaternion, log scales) after a single column, at other offsets
        (flat, ("color", "depth"), ("opacity_logits", "log_scales", "quats", "means")),
    )
    for mp, outputs, params in cases:
        got = fisher_diag(mp, T, intr, outputs=outputs, params=params, pixel_weights=w, backend="numba")
        want = fisher_diag(mp, T, intr, outputs=outputs, params=params, pixel_weights=w, backend="torch")
        assert_close(got, want)
        assert all(bool(v.abs().sum() > 0) for k, v in want.items() if k != "sh_dc" or "color" in outputs)


@pytest.mark.skipif(not numba_available(), reason="no numba")
def test_numba_tile_walk_matches_torch_on_long_lists_and_early_stop() -> None:
    """The kernel's own walk: tile lists longer than one lane pass (several chunks), pixels that stop once
    transmittance would drop below 1e-4, surfels behind the camera and beyond the far plane, ROI weights
    with zero tiles and single zero pixels, partial edge tiles; against the torch backend."""
    from roigsf_ros.render.rasterize import numba_bins

    intr = Intrinsics(22, 17, 18.0, 18.5, 10.5, 8.0)
    g = torch.Generator().manual_seed(13)
    n = 320
    m = scene(13, n=n)
    m.means = torch.randn(n, 3, generator=g, dtype=F64) * torch.tensor([0.25, 0.2, 0.6], dtype=F64)
    m.means[:, 2] += 2.0
    m.log_scales = torch.log(torch.rand(n, 2, generator=g, dtype=F64) * 0.25 + 0.15)  # large: long lists
    m.opacity_logits = torch.randn(n, generator=g, dtype=F64) * 0.5 + 1.0
    m.means[:6, 2] = -1.0  # behind the camera
    m.means[6:9, 2] = 150.0  # beyond the far plane
    T = pose(13)
    viewmat, K = camera_tensors(T, intr, dtype=F64)
    f64 = [t.detach().numpy() for t in (m.means, m.quats, m.scales(), m.opacities())]
    bn = numba_bins(*f64, viewmat.numpy(), K.numpy(), intr.width, intr.height)
    assert bn.count.max() > 2 * 64  # lists of three lane passes and more
    with torch.no_grad():
        proj = project_packed(m.means, m.quats, m.scales(), m.opacities(), viewmat, K, 0.2, 100.0)[0]
    ys, xs = torch.meshgrid(torch.arange(intr.height, dtype=F64), torch.arange(intr.width, dtype=F64), indexing="ij")
    alpha, _, _ = pair_alpha_depth([r[:, None] for r in proj.unbind(0)], xs.reshape(1, -1), ys.reshape(1, -1))
    T_all = torch.prod(1 - torch.where(alpha >= 1 / 255, alpha, 0.0), 0)
    assert bool((T_all < 1e-4).any())  # some pixels stop before their last surfel
    w = torch.rand(intr.height, intr.width, generator=g, dtype=F64) + 0.25
    w[:4, :8] = 0  # two whole tiles
    w[w < 0.4] = 0  # single pixels
    for outputs, params, weights in (
        (("color", "depth"), GEOMETRIC_PARAMS, w),
        (("color", "depth"), GEOMETRIC_PARAMS, None),
        (("color", "depth", "alpha", "normal"), ALL_PARAMS, w),
    ):
        got = fisher_diag(m, T, intr, outputs=outputs, params=params, pixel_weights=weights, backend="numba")
        want = fisher_diag(m, T, intr, outputs=outputs, params=params, pixel_weights=weights, backend="torch")
        assert_close(got, want)
        assert all(torch.all(v[:9] == 0) for v in got.values())  # behind the camera, beyond the far plane
        assert all(bool(v.abs().sum() > 0) for v in want.values())


@pytest.mark.skipif(not numba_available(), reason="no numba")
def test_numba_empty_and_sparse_views_match_torch() -> None:
    """Views where the walk finds nothing (every surfel behind the camera; weights only where no surfel
    reaches) give zeros, and one weighted pixel gives what the torch backend gives."""
    m = scene(14, n=12)
    T = pose(14)
    behind = m.clone()
    behind.means[:, 2] = -2.0
    for backend in ("numba", "torch"):
        got = fisher_diag(behind, T, INTR, params=ALL_PARAMS, backend=backend)
        assert all(torch.all(v == 0) for v in got.values())
    viewmat, K = camera_tensors(T, INTR, dtype=F64)
    with torch.no_grad():
        proj = project_packed(m.means, m.quats, m.scales(), m.opacities(), viewmat, K, 0.2, 100.0)[0]
    ys, xs = torch.meshgrid(torch.arange(INTR.height, dtype=F64), torch.arange(INTR.width, dtype=F64), indexing="ij")
    alpha, _, _ = pair_alpha_depth([r[:, None] for r in proj.unbind(0)], xs.reshape(1, -1), ys.reshape(1, -1))
    reached = (alpha >= 1 / 255).any(0).reshape(INTR.height, INTR.width)
    assert bool(reached.any()) and bool((~reached).any())
    empty = torch.where(reached, 0.0, 1.0).to(F64)  # weights only on pixels no surfel reaches
    got = fisher_diag(m, T, INTR, params=ALL_PARAMS, pixel_weights=empty, backend="numba")
    assert all(torch.all(v == 0) for v in got.values())
    one = torch.zeros(INTR.height, INTR.width, dtype=F64)
    iy, ix = (int(i[0]) for i in torch.nonzero(reached, as_tuple=True))
    one[iy, ix] = 3.0
    for outputs in (("color", "depth"), ("alpha", "normal")):
        got = fisher_diag(m, T, INTR, outputs=outputs, params=ALL_PARAMS, pixel_weights=one, backend="numba")
        want = fisher_diag(m, T, INTR, outputs=outputs, params=ALL_PARAMS, pixel_weights=one, backend="torch")
        assert_close(got, want)


def test_packed_jacobian_zero_rows_per_parameter_kind() -> None:
    """The packed rows a parameter cannot move are exactly zero in the closed-form Jacobian (the numba Fisher
    kernel leaves them out of its chain rule): a mean moves neither the rows of the splat's axes (6-8) nor the
    opacity, a quaternion or log scale neither the centre rows (10-12) nor the opacity, log scale u not rows
    0-2, log scale v not rows 3-5, the opacity logit only the opacity."""
    pytest.importorskip("numba")
    m = scene(15, n=40, sh_rest=False)
    m.means[0, 2] = 0.1  # centre nearer than the near plane (the centre rows use z = 1)
    m.quats[1] *= 3.0
    viewmat, K = camera_tensors(pose(15), INTR, dtype=F64)
    _, jac = packed_jacobian(m, viewmat, K, 0.2, 100.0)  # [N, 10 parameters, 14 rows]
    zero_rows = {(0, 1, 2): (6, 7, 8, 13), (3, 4, 5, 6): (10, 11, 12, 13), (7,): (0, 1, 2, 10, 11, 12, 13)}
    zero_rows |= {(8,): (3, 4, 5, 10, 11, 12, 13), (9,): tuple(range(13))}
    for params, rows in zero_rows.items():
        block = jac[:, list(params)][:, :, list(rows)]
        assert np.all(block == 0.0), (params, rows)
    assert np.all(np.abs(jac).sum((0, 2)) > 0)  # every parameter moves some row
