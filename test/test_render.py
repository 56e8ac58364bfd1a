"""2DGS rendering: the fast renderer against the dense reference (values and gradients), analytic cases."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.render import fisher
from roigsf_ros.render import rasterize as render
from roigsf_ros.render import reference as render_reference
from roigsf_ros.render.numba_setup import balanced_bounds, n_threads, numba_available, set_numba_threads
from roigsf_ros.render.rasterize import RenderOutput, camera_tensors, render_map
from roigsf_ros.render.surfels import SurfelMap, rotmat_to_quat

OUTPUTS = ("features", "alpha", "depth", "median_depth", "normal", "distortion")
F64 = torch.float64


def random_scene(kind: str, seed: int, n: int = 24, width: int = 20, height: int = 15, dtype=F64):
    """Random tiny scenes: ``mixed`` overlapping surfels, ``opaque`` stacks (early stop), ``behind``
    (surfels behind / straddling the camera), ``grazing`` (planes nearly along the view rays)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 0.4
    means[:, 2] += 2.0
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 2, generator=g, dtype=dtype) * 0.3 + 0.05
    opac = torch.rand(n, generator=g, dtype=dtype) * 0.9 + 0.05
    feats = torch.rand(n, 4, generator=g, dtype=dtype)
    if kind == "opaque":
        opac = torch.full((n,), 0.995, dtype=dtype)
        means[:, :2] *= 0.3
    elif kind == "behind":
        means[: n // 2, 2] = torch.linspace(-1.0, 0.5, n // 2, dtype=dtype)
        scales[: n // 2] *= 3
    elif kind == "grazing":
        # Normals nearly perpendicular to the ray to the centre: rotate the tangent plane to contain it.
        d = means / means.norm(dim=-1, keepdim=True)
        up = torch.tensor([0.0, 1.0, 0.0], dtype=dtype).expand_as(d)
        tu = torch.linalg.cross(up, d, dim=-1)
        tu = tu / tu.norm(dim=-1, keepdim=True)
        nrm = torch.linalg.cross(tu, d, dim=-1)
        nrm = nrm + 0.05 * torch.randn(n, 3, generator=g, dtype=dtype)
        nrm = nrm / nrm.norm(dim=-1, keepdim=True)
        tv = torch.linalg.cross(nrm, tu, dim=-1)
        tv = tv / tv.norm(dim=-1, keepdim=True)
        tu = torch.linalg.cross(tv, nrm, dim=-1)
        quats = rotmat_to_quat(torch.stack([tu, tv, nrm], -1))
    f = 18.0
    K = torch.tensor([[f, 0, (width - 1) / 2], [0, f * 1.1, (height - 1) / 2], [0, 0, 1]], dtype=dtype)
    c, s = math.cos(0.1), math.sin(0.1)
    T_wc = torch.tensor([[c, 0, s, 0.05], [0, 1, 0, -0.02], [-s, 0, c, 0.03], [0, 0, 0, 1]], dtype=dtype)
    viewmat = torch.linalg.inv(T_wc)
    return [means, quats, scales, opac, feats], viewmat, K, width, height


NEEDS_NUMBA = pytest.mark.skipif(not numba_available(), reason="numba is not installed")
BACKENDS = ["torch", pytest.param("numba", marks=NEEDS_NUMBA)]
NEEDS_CUDA = pytest.mark.skipif(
    not torch.cuda.is_available(),
    reason="no CUDA device: the torch backend's CUDA path is checked where a GPU is lent (scripts/device_check.sh)",
)
TARGETS = [
    pytest.param("torch", "cpu", id="torch"),
    pytest.param("numba", "cpu", id="numba", marks=NEEDS_NUMBA),
    pytest.param("torch", "cuda", id="cuda", marks=NEEDS_CUDA),
]
"""(backend, device) of every fast path; ``cuda`` is the torch backend on CUDA tensors."""


def fast(backend: str):
    """The fast renderer with a fixed backend."""
    return lambda *a, **k: render.rasterize_surfels(*a, backend=backend, **k)


def on(x, device):
    """``x`` on ``device`` when it is a tensor or a RenderOutput (its fields), else unchanged."""
    if isinstance(x, RenderOutput):
        return RenderOutput(**{f.name: getattr(x, f.name).to(device) for f in dataclasses.fields(x)})
    return x.to(device) if isinstance(x, torch.Tensor) else x


def assert_same_render(a: RenderOutput, grads_a, b: RenderOutput, grads_b, grad_rtol: float = 1e-9) -> None:
    """Finite outputs equal to 1e-10, the same contributors and visible surfels, finite gradients equal to
    ``grad_rtol`` (relative, and of the largest entry)."""
    for k in OUTPUTS:
        x, y = getattr(a, k), getattr(b, k)
        assert torch.isfinite(x).all(), k
        assert torch.allclose(x, y, rtol=1e-10, atol=1e-10), (k, (x - y).abs().max())
    assert torch.equal(a.n_contrib, b.n_contrib)
    assert torch.equal(a.visible, b.visible)
    for i, (x, y) in enumerate(zip(grads_a, grads_b, strict=True)):
        assert torch.isfinite(x).all(), i
        assert torch.allclose(x, y, rtol=grad_rtol, atol=grad_rtol * y.abs().max()), (i, (x - y).abs().max())


def run_both(tensors, viewmat, K, width, height, weights_seed=0, backend="torch", fast_kw=None, device="cpu", **kw):
    """Values and input gradients of a random linear loss over all outputs, from both renderers
    (``fast_kw``: extra arguments of the fast one; ``device``: where the fast one runs; results on the CPU)."""
    results = []
    for fn, extra, dev in ((fast(backend), fast_kw or {}, device), (render_reference.rasterize_surfels, {}, "cpu")):
        leaves = [on(t, dev).clone().requires_grad_() for t in tensors]
        args = {k: on(v, dev) for k, v in {**kw, **extra}.items()}
        out = fn(*leaves, on(viewmat, dev), on(K, dev), width, height, **args)
        g = torch.Generator().manual_seed(weights_seed)
        probes = {k: torch.randn(getattr(out, k).shape, generator=g, dtype=F64) for k in OUTPUTS}
        loss = sum((getattr(out, k) * on(probes[k], dev)).sum() for k in OUTPUTS)
        loss.backward()
        results.append((on(out, "cpu"), [leaf.grad.cpu() for leaf in leaves]))
    return results


@pytest.mark.parametrize(("backend", "device"), TARGETS)
@pytest.mark.parametrize("kind", ["mixed", "opaque", "behind", "grazing"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fast_matches_reference(kind: str, seed: int, backend: str, device: str) -> None:
    """Each fast path (``cuda``: the torch backend on CUDA tensors) against the reference run on the CPU."""
    tensors, viewmat, K, w, h = random_scene(kind, seed)
    bg = torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=F64)
    (fast, g_fast), (ref, g_ref) = run_both(tensors, viewmat, K, w, h, background=bg, backend=backend, device=device)
    assert ref.n_contrib.sum() > 0
    assert_same_render(fast, g_fast, ref, g_ref)


@NEEDS_CUDA
def test_cuda_room_render_matches_cpu() -> None:
    """The benchmark's room (20k surfels, 160x120, long tile lists and early stops) on CUDA and on the CPU, float64:
    the same image, depth and per-pixel contributors, and the same gradients."""
    from roigsf_ros.perf.render import room_camera, room_scene

    T_wc, intr = room_camera(160, 120)
    results = []
    for dev in ("cuda", "cpu"):
        m = room_scene(20_000, dtype=F64).to(device=dev).requires_grad_()
        out = render_map(m, T_wc, intr, backend="torch")
        (out.color.sum() + out.depth.sum() + out.alpha.sum()).backward()
        results.append((on(out, "cpu"), [p.grad.cpu() for p in m.parameters()]))
    (a, ga), (b, gb) = results
    assert b.n_contrib.float().mean() > 10 and b.alpha.min() > 0.2  # a closed room, many layers per pixel
    assert_same_render(a, ga, b, gb, grad_rtol=1e-8)


def test_opaque_scene_exercises_the_early_stop() -> None:
    tensors, viewmat, K, w, h = random_scene("opaque", 0)
    out = render_reference.rasterize_surfels(*tensors, viewmat, K, w, h)
    assert (out.alpha > 1 - 1e-3).any()  # some pixels saturated
    assert int(out.n_contrib.max()) < int((out.n_contrib > 0).sum())  # and stopped early


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("tile_size", [1, 3, 8])
def test_tile_size_does_not_change_the_result(tile_size: int, backend: str) -> None:
    tensors, viewmat, K, w, h = random_scene("mixed", 4, n=40)
    a = render.rasterize_surfels(*tensors, viewmat, K, w, h, backend="torch")
    b = render.rasterize_surfels(*tensors, viewmat, K, w, h, tile_size=tile_size, backend=backend)
    for k in OUTPUTS:
        assert torch.allclose(getattr(a, k), getattr(b, k), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(("backend", "device"), TARGETS)
def test_float32_close_to_float64_reference(backend: str, device: str) -> None:
    tensors, viewmat, K, w, h = random_scene("mixed", 5)
    ref = render_reference.rasterize_surfels(*tensors, viewmat, K, w, h)
    f32 = [t.float().to(device).requires_grad_() for t in tensors]
    out = render.rasterize_surfels(*f32, on(viewmat.float(), device), on(K.float(), device), w, h, backend=backend)
    for k in OUTPUTS:
        assert getattr(out, k).dtype == torch.float32 and getattr(out, k).device.type == device
        assert torch.allclose(getattr(out, k).double().cpu(), getattr(ref, k), atol=2e-4), k
    (out.features.sum() + out.depth.sum()).backward()
    assert all(t.grad is not None and t.grad.dtype == torch.float32 and torch.isfinite(t.grad).all() for t in f32)
    assert all(t.grad.device.type == device for t in f32)


def test_reference_gradients_match_finite_differences() -> None:
    tensors, viewmat, K, w, h = random_scene("mixed", 7, n=4, width=8, height=6)
    g = torch.Generator().manual_seed(1)
    probes = {k: torch.randn(10_000, generator=g, dtype=F64) for k in OUTPUTS}

    def f(*inputs):
        out = render_reference.rasterize_surfels(*inputs, viewmat, K, w, h)
        return sum((getattr(out, k).reshape(-1) * probes[k][: getattr(out, k).numel()]).sum() for k in OUTPUTS)

    leaves = [t.clone().requires_grad_() for t in tensors]
    assert torch.autograd.gradcheck(f, leaves, eps=1e-6, atol=1e-6, rtol=1e-5)


def fronto_surfel(z: float, opacity: float, color, x: float = 0.0, y: float = 0.0, s: float = 0.3):
    return (
        torch.tensor([[x, y, z]], dtype=F64),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64),  # identity: normal +z (away from the camera)
        torch.tensor([[s, s]], dtype=F64),
        torch.tensor([opacity], dtype=F64),
        torch.tensor([color], dtype=F64),
    )


def camera(width: int = 21, height: int = 17, f: float = 20.0):
    K = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], dtype=F64)
    return torch.eye(4, dtype=F64), K, width, height


RENDERERS = [
    pytest.param(fast("torch"), id="torch"),
    pytest.param(fast("numba"), id="numba", marks=NEEDS_NUMBA),
    pytest.param(render_reference.rasterize_surfels, id="reference"),
]


@pytest.mark.parametrize("fn", RENDERERS)
def test_fronto_parallel_opaque_surfel(fn) -> None:
    viewmat, K, w, h = camera()
    bg = torch.tensor([0.5, 0.5, 0.5], dtype=F64)
    out = fn(*fronto_surfel(2.0, 0.999, [0.2, 0.4, 0.8]), viewmat, K, w, h, background=bg)
    cy, cx = h // 2, w // 2
    a = 0.99  # alpha is clamped to 0.99
    assert out.alpha[cy, cx].item() == pytest.approx(a)
    assert out.depth[cy, cx].item() == pytest.approx(2.0 * a)
    assert out.expected_depth()[cy, cx].item() == pytest.approx(2.0)
    assert out.median_depth[cy, cx].item() == pytest.approx(2.0)
    assert out.normal[cy, cx].tolist() == pytest.approx([0.0, 0.0, -a])  # faces the camera (camera frame)
    assert out.features[cy, cx].tolist() == pytest.approx([0.2 * a + 0.005, 0.4 * a + 0.005, 0.8 * a + 0.005])
    assert out.distortion[cy, cx].item() == pytest.approx(0.0)
    # 4 px right of the centre the ray hits the plane 0.4 m off-centre: alpha = o exp(-(0.4 / 0.3)^2 / 2).
    expected = 0.999 * math.exp(-0.5 * ((4.0 / 20.0 * 2.0) / 0.3) ** 2)
    assert out.alpha[cy, cx + 4].item() == pytest.approx(expected, rel=1e-9)
    assert out.features[0, 0].tolist() == pytest.approx(bg.tolist())  # far corner: background only


@pytest.mark.parametrize("fn", RENDERERS)
@pytest.mark.parametrize(("front_opacity", "median"), [(0.6, 2.0), (0.4, 3.0)])
def test_median_and_expected_depth_two_layers(fn, front_opacity: float, median: float) -> None:
    viewmat, K, w, h = camera()
    a = fronto_surfel(2.0, front_opacity, [1.0, 0.0, 0.0])
    b = fronto_surfel(3.0, 0.9, [0.0, 1.0, 0.0])
    out = fn(*[torch.cat([u, v]) for u, v in zip(b, a, strict=True)], viewmat, K, w, h)  # input order irrelevant
    cy, cx = h // 2, w // 2
    w1, w2 = front_opacity, (1 - front_opacity) * 0.9
    assert out.median_depth[cy, cx].item() == pytest.approx(median)
    assert out.expected_depth()[cy, cx].item() == pytest.approx((2 * w1 + 3 * w2) / (w1 + w2))
    assert out.features[cy, cx].tolist() == pytest.approx([w1, w2, 0.0])
    m = lambda d: 100.0 / (100.0 - 0.2) * (1 - 0.2 / d)  # noqa: E731 - 2DGS's NDC-like distortion depth
    assert out.distortion[cy, cx].item() == pytest.approx(w1 * w2 * (m(3.0) - m(2.0)) ** 2)


@pytest.mark.parametrize("fn", RENDERERS)
def test_empty_and_fully_culled_maps(fn) -> None:
    viewmat, K, w, h = camera()
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    empty = [t[:0].clone().requires_grad_() for t in fronto_surfel(2.0, 0.5, [1.0, 1.0, 1.0])]
    behind = [t.clone().requires_grad_() for t in fronto_surfel(-2.0, 0.9, [1.0, 1.0, 1.0])]
    for inputs in (empty, behind):
        out = fn(*inputs, viewmat, K, w, h, background=bg)
        assert torch.equal(out.features, bg.expand(h, w, 3))
        assert torch.all(out.alpha == 0) and torch.all(out.depth == 0) and torch.all(out.n_contrib == 0)
        assert all(torch.isfinite(getattr(out, k)).all() for k in OUTPUTS)
        assert torch.all(out.expected_depth() == 0)
        sum(getattr(out, k).sum() for k in OUTPUTS).backward()  # still differentiable
        assert all(t.grad is not None and torch.all(t.grad == 0) for t in inputs)


def test_render_map_uses_colours_and_pose() -> None:
    g = torch.Generator().manual_seed(0)
    n = 30
    m = SurfelMap(
        means=torch.randn(n, 3, generator=g, dtype=F64) * 0.5 + torch.tensor([0.0, 0.0, 3.0], dtype=F64),
        quats=torch.randn(n, 4, generator=g, dtype=F64),
        log_scales=torch.full((n, 2), math.log(0.2), dtype=F64),
        opacity_logits=torch.randn(n, generator=g, dtype=F64),
        sh_dc=torch.randn(n, 3, generator=g, dtype=F64),
        sh_rest=torch.randn(n, 3, 3, generator=g, dtype=F64) * 0.2,
    )
    intr = Intrinsics(24, 18, 20.0, 20.0, 11.5, 8.5)
    T_wc = np.eye(4)
    T_wc[:3, 3] = [0.1, -0.2, 0.3]
    out = render_map(m, T_wc, intr)
    viewmat, K = camera_tensors(T_wc, intr, dtype=F64)
    assert torch.allclose(viewmat @ torch.as_tensor(T_wc), torch.eye(4, dtype=F64))
    cols = m.colors(m.means - torch.tensor([0.1, -0.2, 0.3], dtype=F64))
    ref = render_reference.rasterize_surfels(m.means, m.quats, m.scales(), m.opacities(), cols, viewmat, K, 24, 18)
    assert torch.allclose(out.color, ref.features, atol=1e-12)
    assert torch.allclose(out.normal_world(viewmat), ref.normal, atol=1e-12)  # identity rotation
    assert out.visible.any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_culled_render_equals_the_whole_render(backend: str) -> None:
    """``render_map(cull=True)`` renders the frustum's surfels only: the same images, ``visible`` per map surfel, and
    the same gradients (a culled surfel reaches no pixel)."""
    from roigsf_ros.perf.render import room_camera, room_scene

    m = room_scene(3000, seed=2, dtype=F64)
    m.sh_rest = torch.randn(len(m), 3, 3, generator=torch.Generator().manual_seed(1), dtype=F64) * 0.1
    culled_some = False
    for yaw in (20.0, 110.0, 250.0):
        T_wc, intr = room_camera(40, 30, yaw_deg=yaw)
        whole = m.clone().requires_grad_()
        part = m.clone().requires_grad_()
        a = render_map(whole, T_wc, intr, near=0.2, far=10.0, backend=backend)
        b = render_map(part, T_wc, intr, near=0.2, far=10.0, backend=backend, cull=True)
        for name in ("features", "alpha", "depth", "median_depth", "distortion", "n_contrib", "visible"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        assert torch.allclose(a.normal, b.normal, atol=1e-12)  # equal up to the order of a sum
        (a.features.sum() + a.depth.sum()).backward()
        (b.features.sum() + b.depth.sum()).backward()
        for k, p in whole.named_parameters().items():
            assert torch.allclose(p.grad, part.named_parameters()[k].grad, rtol=1e-9, atol=1e-12), k
        viewmat, _ = camera_tensors(T_wc, intr, dtype=F64)
        culled_some |= len(fisher.frustum_subset(m, viewmat, intr, 0.2, 10.0)) < len(m) // 2
        none = torch.zeros(len(m), 0, dtype=F64)  # no feature channel: alpha and depth only
        c = render_map(m, T_wc, intr, features=none, near=0.2, far=10.0, backend=backend, cull=True)
        assert c.features.shape == (30, 40, 0) and torch.equal(c.alpha, a.alpha.detach())
    assert culled_some  # the views do leave most of the room out


def test_input_validation() -> None:
    tensors, viewmat, K, w, h = random_scene("mixed", 0, n=3)
    with pytest.raises(ValueError, match="quats"):
        render.rasterize_surfels(tensors[0], tensors[1][:, :3], *tensors[2:], viewmat, K, w, h)
    with pytest.raises(ValueError, match="near"):
        render.rasterize_surfels(*tensors, viewmat, K, w, h, near=0.0)
    with pytest.raises(ValueError, match="backend"):
        render.rasterize_surfels(*tensors, viewmat, K, w, h, backend="cuda")
    with pytest.raises(ValueError, match=r"width must be an int \(pixels\), got float "):  # failed in a reshape
        render.rasterize_surfels(*tensors, viewmat, K, float(w), h)


@NEEDS_NUMBA
def test_numba_and_torch_pixel_boxes_agree() -> None:
    for kind, seed in (("mixed", 0), ("behind", 1), ("grazing", 2)):
        tensors, viewmat, K, w, h = random_scene(kind, seed, n=60)
        a = render.project_surfels(*tensors[:4], viewmat, K, w, h, backend="torch")
        b = render.project_surfels(*tensors[:4], viewmat, K, w, h, backend="numba")
        assert torch.equal(a.keep, b.keep)
        assert torch.equal(a.rect[a.keep], b.rect[b.keep])


def test_benchmark_room_scene_renders_a_closed_room() -> None:
    from roigsf_ros.perf.render import room_camera, room_scene

    m = room_scene(3000, seed=1)
    T_wc, intr = room_camera(40, 30)
    out = render_map(m, T_wc, intr)
    assert out.alpha.min() > 0.2 and out.n_contrib.float().mean() > 5
    d = out.expected_depth()
    assert 0.5 < float(d.median()) < 4.0


def test_benchmark_device_option_names_the_bad_device(capsys: pytest.CaptureFixture[str]) -> None:
    """``python -m roigsf_ros.perf.render --device ...``: a device that is not usable here is a one-line error."""
    from roigsf_ros.perf.render import main

    for device, problem in (("cuda:7", "CUDA device"), ("tpu", "not a torch device"), ("meta", "only cpu and cuda")):
        assert main(["--device", device, "--repeats", "1"]) == 2
        err = capsys.readouterr().err
        assert f"--device: '{device}'" in err and problem in err, err


@NEEDS_NUMBA
def test_numba_and_torch_select_the_same_pairs() -> None:
    tensors, viewmat, K, w, h = random_scene("opaque", 3, n=50)
    proj = render.project_surfels(*tensors[:4], viewmat, K, w, h)
    a = render.select_pairs(proj, w, h, backend="torch")
    b = render.select_pairs(proj, w, h, backend="numba")
    assert len(a) > 0
    for k in ("surf", "pix", "start", "offsets"):
        assert torch.equal(getattr(a, k), getattr(b, k)), k


@NEEDS_NUMBA
def test_concurrent_renders_from_threads() -> None:
    import threading

    tensors, viewmat, K, w, h = random_scene("mixed", 6, n=40)
    expected = render.rasterize_surfels(*tensors, viewmat, K, w, h, backend="numba").features
    results, errors = [], []

    def work() -> None:
        try:
            for _ in range(5):
                leaves = [t.clone().requires_grad_() for t in tensors]
                out = render.rasterize_surfels(*leaves, viewmat, K, w, h, backend="numba")
                out.features.sum().backward()
                results.append(out.features.detach())
        except Exception as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=work) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert len(results) == 15 and all(torch.equal(r, expected) for r in results)


@NEEDS_NUMBA
def test_numba_compact_pair_storage(monkeypatch) -> None:
    """Past PAIR_BUFFER_LIMIT the forward counts first and stores pairs compactly: same results."""
    monkeypatch.setattr(render, "PAIR_BUFFER_LIMIT", 0)
    tensors, viewmat, K, w, h = random_scene("opaque", 1)
    (fast, g_fast), (ref, g_ref) = run_both(tensors, viewmat, K, w, h, backend="numba")
    for k in OUTPUTS:
        assert torch.allclose(getattr(fast, k), getattr(ref, k), rtol=1e-10, atol=1e-10), k
    for a, b in zip(g_fast, g_ref, strict=True):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-9 * b.abs().max())
    proj = render.project_surfels(*tensors[:4], viewmat, K, w, h)
    numba_pairs = render.select_pairs(proj, w, h, backend="numba")
    assert torch.equal(numba_pairs.surf, render.select_pairs(proj, w, h, backend="torch").surf)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("tile_size", [2, 8])
def test_long_tile_lists_match_reference(backend: str, tile_size: int) -> None:
    """Hundreds of surfels per tile: the numba kernels' chunked lists (64 surfels a pass) and early stop."""
    tensors, viewmat, K, w, h = random_scene("mixed", 7, n=300, width=12, height=10)
    tensors[3] = tensors[3] * 0.6  # lower opacity: long lists before transmittance is spent
    bg = torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=F64)
    (fast, g_fast), (ref, g_ref) = run_both(
        tensors, viewmat, K, w, h, background=bg, backend=backend, fast_kw={"tile_size": tile_size}
    )
    assert int(ref.n_contrib.max()) > 64
    assert_same_render(fast, g_fast, ref, g_ref)


@pytest.mark.parametrize("backend", BACKENDS)
def test_without_distortion(backend: str) -> None:
    """``with_distortion=False``: a zero distortion map, every other output and gradient unchanged."""
    tensors, viewmat, K, w, h = random_scene("mixed", 8, n=40)
    res = {}
    for wd in (True, False):
        leaves = [t.clone().requires_grad_() for t in tensors]
        out = render.rasterize_surfels(*leaves, viewmat, K, w, h, with_distortion=wd, backend=backend)
        (out.features.sum() + out.depth.sum() + out.alpha.sum() + out.normal.sum()).backward()
        res[wd] = (out, [t.grad for t in leaves])
    (a, ga), (b, gb) = res[True], res[False]
    assert float(a.distortion.detach().abs().max()) > 0 and float(b.distortion.detach().abs().max()) == 0.0
    for k in ("features", "alpha", "depth", "median_depth", "normal"):
        assert torch.allclose(getattr(a, k), getattr(b, k), rtol=1e-12, atol=1e-12), k
    for x, y in zip(ga, gb, strict=True):
        assert torch.allclose(x, y, rtol=1e-12, atol=1e-12)


@NEEDS_NUMBA
def test_numba_camera_gradients_match_torch() -> None:
    """A camera with gradients takes the torch projection + numba compositing path: same as torch."""
    tensors, viewmat, K, w, h = random_scene("mixed", 9, n=40)
    results = []
    for backend in ("torch", "numba"):
        leaves = [t.clone().requires_grad_() for t in tensors]
        vm = viewmat.clone().requires_grad_()
        out = render.rasterize_surfels(*leaves, vm, K, w, h, backend=backend)
        g = torch.Generator().manual_seed(1)
        loss = sum(
            (getattr(out, k) * torch.randn(getattr(out, k).shape, generator=g, dtype=F64)).sum() for k in OUTPUTS
        )
        loss.backward()
        results.append((out, [t.grad for t in [*leaves, vm]]))
    (a, ga), (b, gb) = results
    assert_same_render(a, ga, b, gb)


@NEEDS_NUMBA
def test_numba_projection_kernel_matches_torch() -> None:
    """The fused projection/culling kernel gives project_surfels' rows, normals, boxes and culling."""
    for kind, seed in (("mixed", 0), ("behind", 1), ("grazing", 2)):
        tensors, viewmat, K, w, h = random_scene(kind, seed, n=60)
        ref = render.project_surfels(*tensors[:4], viewmat, K, w, h, backend="torch")
        n = tensors[0].shape[0]
        pk, nrm, thr = np.empty((n, render.NPACK)), np.empty((n, 3)), np.empty(n)
        rect, keep = np.empty((n, 4), np.int32), np.empty(n, np.uint8)
        f = [t.numpy() for t in tensors[:4]]
        render._KERNELS["project"](*f, viewmat.numpy(), K.numpy(), w, h, 0.2, 100.0, pk, nrm, rect, thr, keep)
        kept = torch.from_numpy(keep.astype(bool))
        assert torch.equal(kept, ref.keep)
        assert torch.equal(torch.from_numpy(rect).long()[kept], ref.rect[ref.keep])
        assert torch.allclose(torch.from_numpy(pk).T, ref.packed, rtol=1e-12, atol=1e-12)
        assert torch.allclose(torch.from_numpy(nrm), ref.normals, rtol=1e-12, atol=1e-12)


def test_numba_frustum_culling_equals_torch_and_culls_only_surfels_that_reach_no_pixel() -> None:
    """Issue 12: the frustum cull (each mapper render, each Fisher) in one numba pass instead of ~15 torch ops."""
    pytest.importorskip("numba")
    from roigsf_ros.data.scene import look_at
    from roigsf_ros.render.fisher import frustum_subset

    intr = Intrinsics(40, 30, 30.0, 30.0, 19.5, 14.5)
    rng = np.random.default_rng(5)
    n = 4000
    for dtype in (torch.float32, torch.float64):
        m = SurfelMap(
            means=torch.as_tensor(rng.uniform(-4.0, 4.0, (n, 3)), dtype=dtype),
            quats=torch.as_tensor(rng.normal(size=(n, 4)), dtype=dtype),
            log_scales=torch.as_tensor(np.log(rng.uniform(0.005, 0.3, (n, 2))), dtype=dtype),
            opacity_logits=torch.full((n,), 4.0, dtype=dtype),
            sh_dc=torch.zeros(n, 3, dtype=dtype),
        )
        for T in (np.eye(4), look_at(np.array([1.0, -0.5, -3.0]), np.zeros(3), np.array([0.0, -1.0, 0.0]))):
            viewmat, _ = camera_tensors(T, intr, dtype=dtype)
            fast = frustum_subset(m, viewmat, intr, 0.2, 5.0, backend="numba")
            ref = frustum_subset(m, viewmat, intr, 0.2, 5.0, backend="torch")
            assert torch.equal(fast, ref) and 0 < len(fast) < n
            culled = torch.ones(n, dtype=torch.bool)
            culled[fast] = False
            out = render_map(m.select(torch.nonzero(culled).squeeze(1)), T, intr, near=0.2, far=5.0)
            assert float(out.alpha.max()) == 0.0  # what the cull drops reaches no pixel


_PIN_CHILD = """
import json, os, sys
cpus = sorted(os.sched_getaffinity(0))[:2]
os.sched_setaffinity(0, set(cpus))  # this process may use two CPUs, as the project's target machine
import numpy as np
from roigsf_ros.render.numba_setup import pin_workers, pinned_workers, set_numba_threads, worker_ids
from roigsf_ros.render.rasterize import _KERNELS
_KERNELS["project"]  # the first parallel kernel set: pins here only with ROIGSF_PIN_THREADS=1
auto = pinned_workers()
workers = worker_ids()
before = {str(t): sorted(os.sched_getaffinity(t)) for t in workers}
first = pin_workers()
affinity = {str(t): sorted(os.sched_getaffinity(t)) for t in first}
one = set_numba_threads(1)
print(json.dumps({"cpus": cpus, "auto": len(auto), "before": before, "first": {str(k): v for k, v in first.items()},
                  "affinity": affinity, "workers": worker_ids(), "one": one, "after_one": len(pin_workers())}))
"""


@pytest.mark.skipif(not numba_available(), reason="numba is not installed")
@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="pinning needs two CPUs; this process may use one")
@pytest.mark.parametrize("setting", ["1", "0", None])
def test_numba_workers_pinned_one_per_cpu_when_asked(setting: str | None) -> None:
    """Two workers on two CPUs: ``ROIGSF_PIN_THREADS=1`` pins each to its own CPU at the first kernel, unset only
    when ``pin_workers()`` is called, ``0`` never; with one thread nothing is pinned."""
    env = dict(os.environ, NUMBA_NUM_THREADS="2")
    env.pop("ROIGSF_PIN_THREADS", None)
    if setting is not None:
        env["ROIGSF_PIN_THREADS"] = setting
    res = subprocess.run([sys.executable, "-c", _PIN_CHILD], env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["one"] == 1 and len(out["workers"]) == 1 and out["after_one"] == 0  # one worker: nothing to pin
    assert out["auto"] == (2 if setting == "1" else 0)
    if setting != "1":  # not pinned by the first kernel: each worker may run on both CPUs
        assert all(cpus == out["cpus"] for cpus in out["before"].values())
    if setting == "0":
        assert out["first"] == {}
        return
    assert sorted(out["first"].values()) == out["cpus"]  # one worker per CPU, every CPU used once
    assert all(out["affinity"][t] == [cpu] for t, cpu in out["first"].items())


@pytest.mark.skipif(not numba_available(), reason="numba is not installed")
def test_measure_numba_threads_script_writes_both_settings(tmp_path: Path) -> None:
    """scripts/measure_numba_threads.py (the pinning table, docs/measured-figures.md): unpinned and pinned children."""
    script = Path(__file__).resolve().parents[1] / "scripts" / "measure_numba_threads.py"
    out = tmp_path / "pin.json"
    res = subprocess.run([sys.executable, str(script), "--runs", "1", "--calls", "5", "--out", str(out)],
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr
    runs = json.loads(out.read_text())["runs"]
    assert [r["pin"] for r in runs] == [False, True] and runs[0]["pinned"] == 0
    assert all(len(r[k]) == 5 and min(r[k]) > 0 for r in runs for k in ("train", "fisher"))
    assert "scheduler" in res.stdout and "pinned" in res.stdout
    binning = json.loads(out.read_text())["binning"]  # the binning kernel both ways: the same lists
    assert binning["equal"] is True and binning["kept"] > 1000 and len(binning["default"]) == 200


_KERNEL_MODULE = """
import numpy as np
from roigsf_ros.render.numba_setup import prange


def k_double(x: np.ndarray) -> None:
    for i in prange(x.shape[0]):
        x[i] *= 2.0
"""


@pytest.mark.skipif(not numba_available(), reason="numba is not installed")
def test_kernel_cache_dropped_when_compile_options_change(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """numba keys its disk cache on the kernel's source file only; Kernels drops it when the options differ."""
    import importlib

    from roigsf_ros.render.numba_setup import Kernels

    (tmp_path / "kmod_cache_probe.py").write_text(_KERNEL_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    mod = importlib.import_module("kmod_cache_probe")
    cache = tmp_path / "__pycache__"

    def run(**options: object) -> None:
        x = np.ones(4)
        Kernels(double=mod.k_double, **options)["double"](x)
        assert x.tolist() == [2.0] * 4

    run()
    stamp = (cache / "kmod_cache_probe.k_double.roigsf-stamp").read_text()
    cached = sorted(p.name for p in cache.glob("kmod_cache_probe.k_double-*.nb[ic]"))
    assert cached and stamp
    mtimes = {p: p.stat().st_mtime_ns for p in cache.glob("*.nb[ic]")}
    run()  # the same options: the cache is kept (and loaded)
    assert {p: p.stat().st_mtime_ns for p in cache.glob("*.nb[ic]")} == mtimes
    run(fastmath=True)  # other options: the old code is dropped, compiled anew, the stamp changes
    assert (cache / "kmod_cache_probe.k_double.roigsf-stamp").read_text() != stamp
    assert all(p.stat().st_mtime_ns != mtimes.get(p) for p in cache.glob("kmod_cache_probe.k_double-*.nbc"))


_SEED_PROBE = """
import json, sys
sys.path.insert(0, sys.argv[1])
import numpy as np
from roigsf_ros.render.numba_setup import Kernels
from sub import kmod_seed_probe as m
k = Kernels(double=m.k_double)
x = np.ones(4)
k["double"](x)
d = k.dispatchers()["double"]
hits, misses = d.stats.cache_hits, d.stats.cache_misses
print(json.dumps({"x": x.tolist(), "hits": sum(hits.values()), "misses": sum(misses.values())}))
"""


@pytest.mark.skipif(not numba_available(), reason="numba is not installed")
def test_seeded_kernel_cache_loads_in_another_copy(tmp_path: Path) -> None:
    """set-up compiles the installed copy once and seeds the checkout from it: a byte-identical module at another path
    loads the copied code (no compile); a changed module is not seeded; a current cache is kept."""
    from roigsf_ros.render.numba_setup import STAMP_SUFFIX, seed_kernel_cache

    repo = Path(__file__).resolve().parents[1]
    roots = [tmp_path / name for name in ("installed", "checkout", "edited")]
    for root in roots:
        (root / "sub").mkdir(parents=True)
        (root / "sub" / "__init__.py").write_text("")
        (root / "sub" / "kmod_seed_probe.py").write_text(_KERNEL_MODULE)
    (roots[2] / "sub" / "kmod_seed_probe.py").write_text(_KERNEL_MODULE + "# edited\n")

    def run(root: Path) -> dict:
        res = subprocess.run([sys.executable, "-c", _SEED_PROBE, str(root)], cwd=repo, capture_output=True, text=True,
                             timeout=120)  # fmt: skip
        assert res.returncode == 0, res.stderr
        out = json.loads(res.stdout.strip().splitlines()[-1])
        assert out["x"] == [2.0] * 4
        return out

    assert run(roots[0]) == {"x": [2.0] * 4, "hits": 0, "misses": 1}  # compiled into installed/sub/__pycache__
    assert seed_kernel_cache(roots[0], roots[1]) == ["sub/kmod_seed_probe.k_double"]
    assert seed_kernel_cache(roots[0], roots[2]) == []  # the module differs: nothing copied
    assert not (roots[2] / "sub" / "__pycache__").exists()
    seeded = run(roots[1])
    assert seeded["hits"] == 1 and seeded["misses"] == 0  # loaded at another path, not compiled
    cache = roots[1] / "sub" / "__pycache__"
    mtimes = {p.name: p.stat().st_mtime_ns for p in cache.iterdir() if p.suffix in (".nbi", ".nbc", STAMP_SUFFIX)}
    assert len(mtimes) >= 3 and seed_kernel_cache(roots[0], roots[1]) == []  # current: kept as it is
    assert {p.name: p.stat().st_mtime_ns for p in cache.iterdir() if p.name in mtimes} == mtimes
    assert seed_kernel_cache(roots[0], roots[0]) == []


def test_kernel_stamp_is_the_same_in_every_process() -> None:
    """The cache stamp of a kernel set with a fastmath flag set is the same under different hash seeds (else every
    process would drop the others' cache and compile anew)."""
    code = "from roigsf_ros.render.rasterize import _RASTER_KERNELS as k; print(k.stamp())"
    stamps = set()
    for seed in ("1", "2", "3"):
        res = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, PYTHONHASHSEED=seed),
                             capture_output=True, text=True, timeout=120)  # fmt: skip
        assert res.returncode == 0, res.stderr
        stamps.add(res.stdout.strip().splitlines()[-1])
    assert len(stamps) == 1 and len(next(iter(stamps))) == 64


def test_balanced_bounds_split_the_same_from_numpy_and_torch() -> None:
    """The tile blocks of the numba kernels: contiguous, covering, about equal cost; numpy input takes no torch op."""
    rng = np.random.default_rng(0)
    for cost in (rng.integers(1, 50, 1200), np.ones(7, np.int64), np.array([1, 1, 500, 1, 1]), np.zeros(0, np.int64)):
        for parts in (1, 2, 3, 8):
            b = balanced_bounds(cost, parts)
            assert np.array_equal(b, balanced_bounds(torch.from_numpy(cost), parts)), (cost.size, parts)
            assert b[0] == 0 and b[-1] == cost.size and len(b) == parts + 1 and np.all(np.diff(b) >= 0)
    cost = rng.integers(1, 50, 1200)
    b = balanced_bounds(cost, 4)
    sums = [cost[lo:hi].sum() for lo, hi in itertools.pairwise(b)]
    assert max(sums) - min(sums) <= 2 * cost.max()  # equal up to the tile a cut falls in


@NEEDS_NUMBA
def test_pixel_mask_empties_exactly_the_tiles_without_a_masked_pixel() -> None:
    """``numba_bins(pixel_mask=...)``: the tiles (partial ones at the edges too) with no pixel in the mask get empty
    lists, the others keep theirs, and the thread blocks split what is left (contiguous, covering, about equal)."""
    g = torch.Generator().manual_seed(4)
    n, width, height = 400, 37, 22
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * torch.tensor([0.8, 0.5, 0.2], dtype=torch.float64)
    means[:, 2] += 2.0
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=torch.float64), dim=-1)
    scales = torch.rand(n, 2, generator=g, dtype=torch.float64) * 0.05 + 0.01
    opac = torch.full((n,), 0.8, dtype=torch.float64)
    intr = Intrinsics(width, height, 30.0, 30.0, width / 2, height / 2)
    viewmat, K = camera_tensors(np.eye(4), intr, dtype=torch.float64)
    args = [t.numpy() for t in (means, quats, scales, opac, viewmat, K)]
    full = render.numba_bins(*args, width, height)
    rng = np.random.default_rng(4)
    mask = rng.random((height, width)) < 0.02  # single pixels
    mask[:, 36] = True  # the partial tiles of the last column
    grid = np.zeros((24, 40), bool)
    grid[:height, :width] = mask
    on = grid.reshape(6, 4, 10, 4).any((1, 3)).reshape(-1)
    assert 0 < on.sum() < on.size and (full.count[~on] > 0).any()
    before = n_threads()
    for parts in (1, 2, 3):
        blocks = set_numba_threads(parts)  # as many blocks as threads (at most numba's maximum)
        try:
            bn = render.numba_bins(*args, width, height, pixel_mask=mask.reshape(-1))
        finally:
            set_numba_threads(before)
        assert np.array_equal(bn.count, np.where(on, full.count, 0))
        assert np.array_equal(bn.surf, full.surf) and np.array_equal(bn.start, full.start)
        b = bn.bounds
        assert b[0] == 0 and b[-1] == on.size and len(b) == blocks + 1 and np.all(np.diff(b) >= 0)
        sums = [int((bn.count[lo:hi] + 1).sum()) for lo, hi in itertools.pairwise(b)]
        assert max(sums) - min(sums) <= 2 * int(bn.count.max() + 1)
    with pytest.raises(ValueError, match="pixel_mask"):
        render.numba_bins(*args, width, height, pixel_mask=mask.reshape(-1)[:-1])


@pytest.mark.skipif(not numba_available(), reason="numba is not installed")
def test_kernel_compile_times_script_sums_each_kernels_compile_events(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """scripts/kernel_compile_times.py (the README's per-kernel compile times): a kernel compiled for two signatures
    during the warm-up is one row with two compiles, its time taken from numba's compile events."""
    import numba
    from conftest import load_script

    from roigsf_ros.nbv import warmup

    def _k_twice(x: np.ndarray) -> float:
        return float(x.sum() * 2.0)

    def fake_warm_up() -> dict[str, float]:
        kernel = numba.njit(cache=False)(_k_twice)
        kernel(np.ones(3))
        kernel(np.ones(3, np.float32))
        return {"mapping_s": 0.1, "scoring_s": 0.2, "total_s": 0.3}

    monkeypatch.setattr(warmup, "warm_up_kernels", fake_warm_up)
    out = tmp_path / "compile.json"
    assert load_script("kernel_compile_times").main(["--warm", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    row = next(r for r in data["kernels"] if r["kernel"].endswith("_k_twice"))
    assert row["compiles"] == 2 and row["seconds"] > 0
    assert data["cache"] == "warm" and data["warm_up_s"]["total_s"] == 0.3
    assert "_k_twice" in capsys.readouterr().out


@pytest.mark.skipif(not numba_available(), reason="numba is not installed")
def test_kernel_compile_times_script_writes_a_signature_list_the_warm_up_reads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--write-signatures`` writes each compiled kernel's signatures as a list ``warmup --jobs N`` reads back (the
    real list, from a cold compile, is checked against the warm-up in test_nbv.py); with ``--warm`` it refuses, the
    compile times it would write being cache loads."""
    from conftest import load_script

    from roigsf_ros.nbv import warmup

    monkeypatch.setattr(warmup, "warm_up_kernels", lambda: {"mapping_s": 0.1, "scoring_s": 0.2, "total_s": 0.3})
    monkeypatch.setattr(warmup, "SIGNATURES_PATH", tmp_path / "kernel_signatures.json")
    # The script points NUMBA_CACHE_DIR at its temporary folder: monkeypatch puts the variable back as it was.
    if "NUMBA_CACHE_DIR" in os.environ:
        monkeypatch.setenv("NUMBA_CACHE_DIR", os.environ["NUMBA_CACHE_DIR"])
    else:
        monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    warmup.compile_listed(sorted(warmup.load_signature_list(), key=lambda r: float(r["compile_s"]))[:1])
    script = load_script("kernel_compile_times")
    assert script.main(["--write-signatures"]) == 0
    written = {
        row["kernel"]: row["signatures"] for row in warmup.load_signature_list(tmp_path / "kernel_signatures.json")
    }
    assert written and written == warmup.compiled_signatures()
    with pytest.raises(SystemExit):
        script.main(["--warm", "--write-signatures"])
