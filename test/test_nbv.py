"""NBV scoring: z-score fusion and ranking, ROI-weighted Fisher vs brute force, the scorer's choices, uncertainty."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import torch

from roigsf_ros.core.camera import Intrinsics, matrix_to_quat_xyzw
from roigsf_ros.core.errors import InputError
from roigsf_ros.data.scene import MeshRenderer, look_at
from roigsf_ros.evaluation.metrics import raycast_depth, raycasting_scene
from roigsf_ros.mapping.tsdf import TSDFVolume
from roigsf_ros.nbv import warmup
from roigsf_ros.nbv.close_front import CloseFrontMemory
from roigsf_ros.nbv.config import NBVConfig
from roigsf_ros.nbv.scorer import (
    NBVResult,
    NBVScorer,
    block_mean,
    depth_error_ause,
    downsampled,
    frustum_meets_box,
    fuse_scores,
    gain_with,
    information_gain,
    inverse_denominators,
    rank_candidates,
    zscore,
)
from roigsf_ros.nbv.state import ScoringState
from roigsf_ros.nbv.unseen import SurfaceFacing, surfels_facing
from roigsf_ros.render.fisher import GEOMETRIC_PARAMS
from roigsf_ros.render.numba_setup import numba_available
from roigsf_ros.render.rasterize import camera_tensors, render_map
from roigsf_ros.render.reference import rasterize_surfels as reference_rasterize
from roigsf_ros.render.surfels import SH_C0, SurfelMap, rotmat_to_quat, surfels_from_rgbd

UP = np.array([0.0, 0.0, 1.0])
INTR = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


# ----------------------------------------------------------------------------- fusion, ranking
def test_zscore_is_finite_and_constant_inputs_give_zero() -> None:
    for const in ([3.0, 3.0, 3.0], [0.0], [1e12, 1e12], [1e-300, 1e-300]):
        z = zscore(np.array(const))
        assert np.all(z == 0.0)
    z = zscore(np.array([1.0, 2.0, 3.0, 10.0]))
    assert z.mean() == pytest.approx(0.0, abs=1e-12) and z.std() == pytest.approx(1.0)
    assert zscore(np.zeros(0)).shape == (0,)
    with pytest.raises(InputError, match="non-finite"):
        zscore(np.array([1.0, np.nan]))
    # A floor under the divisor: spreads above it are plain z-scores, spreads below it count for less.
    x = np.array([1.0, 2.0, 3.0, 10.0])
    np.testing.assert_array_equal(zscore(x, min_std=x.std() / 2), zscore(x))
    np.testing.assert_allclose(zscore(x, min_std=4 * x.std()), (x - x.mean()) / (4 * x.std()))
    assert np.all(zscore(np.full(3, 0.2), min_std=1.0) == 0.0)
    # Fusion (Eq. 15): scale-invariant per term; a constant term contributes nothing.
    f, i = np.array([1.0, 5.0, 3.0]), np.array([2.0, 2.0, 2.0])
    np.testing.assert_allclose(fuse_scores(f, i), 0.4 * zscore(f))
    np.testing.assert_allclose(fuse_scores(1e9 * f, np.array([0.0, 1.0, 0.0])), fuse_scores(f, [0.0, 7.0, 0.0]))
    assert np.all(fuse_scores(np.zeros(4), np.zeros(4)) == 0.0)


def test_ranking_is_descending_deterministic_and_puts_flagged_last() -> None:
    s = np.array([0.5, 2.0, 0.5, 2.0, -1.0])
    np.testing.assert_array_equal(rank_candidates(s), [1, 3, 0, 2, 4])
    flagged = np.array([False, True, False, False, False])
    np.testing.assert_array_equal(rank_candidates(s, flagged), [3, 0, 2, 4, 1])
    np.testing.assert_array_equal(rank_candidates(np.zeros(3)), [0, 1, 2])


def test_config_validation_and_from_dict() -> None:
    cfg = NBVConfig()
    assert (cfg.epsilon, cfg.delta, cfg.footprint_pref_px) == (0.4, 0.6, 2.5)
    assert (cfg.angle_pref_texture_poor_deg, cfg.angle_pref_texture_rich_deg) == (30.0, 40.0)
    assert cfg.fisher_params == GEOMETRIC_PARAMS and cfg.fisherrf_lambda == 1e-6
    for bad in ({"mode": "best"}, {"beta": 0.0}, {"mu": -1.0}, {"phi": float("nan")}, {"far_m": 0.1}, {"top_k": 0}):
        with pytest.raises(InputError):
            NBVConfig(**bad)
    with pytest.raises(InputError, match="outputs"):
        NBVConfig(fisher_outputs=("colour",))
    with pytest.raises(InputError, match="close_front_exact"):  # from a bench spec, "no" would read as true
        NBVConfig(close_front_exact="no")
    assert NBVConfig(close_front_exact=True).close_front_exact is True
    for bad in (True, False, "off", "TSDF"):  # "off": ROS and YAML read a bare off as false
        with pytest.raises(InputError, match=r"unseen_backfaces.*none, tsdf, surfels"):
            NBVConfig(unseen_backfaces=bad)
    got = NBVConfig.from_dict({"mode": "fisherrf", "fisher_outputs": ["color"], "mu": 0.5})
    assert got.mode == "fisherrf" and got.fisher_outputs == ("color",) and got.mu == 0.5
    with pytest.raises(InputError, match="unknown parameter"):
        NBVConfig.from_dict({"epsilonn": 0.3})


def test_downsampled_intrinsics_match_block_averaging() -> None:
    intr = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
    small = downsampled(intr, 2)
    assert (small.width, small.height, small.fx, small.cx) == (32, 24, 25.0, 15.5)
    img = np.arange(48 * 64, dtype=float).reshape(48, 64)
    assert block_mean(img, 2)[0, 0] == pytest.approx((0 + 1 + 64 + 65) / 4)
    assert downsampled(intr, 1) is intr


# --------------------------------------------------------------------- Fisher vs brute force
def _tiny_scene() -> tuple[SurfelMap, TSDFVolume, np.ndarray, Intrinsics]:
    """Nine tilted surfels on a plane 1.5 m away, a TSDF of the plane, an oblique view (16 x 12 px)."""
    intr = Intrinsics(16, 12, 14.0, 14.0, 7.5, 5.5)
    rng = np.random.default_rng(3)
    g = np.stack(np.meshgrid([-0.3, 0.0, 0.3], [-0.3, 0.0, 0.3], indexing="ij"), -1).reshape(-1, 2)
    means = np.column_stack([g, np.full(9, 1.5)]) + rng.normal(0, 0.02, (9, 3))
    R = np.stack([np.linalg.qr(np.eye(3) + 0.15 * rng.normal(size=(3, 3)))[0] for _ in range(9)])
    R *= np.sign(np.linalg.det(R))[:, None, None]
    smap = SurfelMap(
        means=torch.tensor(means),
        quats=rotmat_to_quat(torch.tensor(R)) * torch.tensor(rng.uniform(0.8, 1.2, (9, 1))),  # non-unit on purpose
        log_scales=torch.tensor(np.log(rng.uniform(0.08, 0.16, (9, 2)))),
        opacity_logits=torch.tensor(rng.uniform(0.5, 2.0, 9)),
        sh_dc=torch.tensor((rng.uniform(0.1, 0.9, (9, 3)) - 0.5) / SH_C0),
    )
    plane = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 0.01).translate((-0.5, -0.5, 1.5))
    scene = raycasting_scene(plane)
    vol = TSDFVolume(voxel_size_m=0.03)
    for eye in ([0.0, 0.0, 0.0], [0.3, 0.2, 0.2], [-0.3, -0.1, 0.1]):
        T = look_at(np.array(eye), np.array([0.0, 0.0, 1.5]), np.array([0.0, -1.0, 0.0]))
        vol.integrate(raycast_depth(scene, T, intr), T, intr)
    T = look_at(np.array([0.35, -0.25, 0.3]), np.array([0.05, 0.0, 1.5]), np.array([0.0, -1.0, 0.0]))
    return smap, vol, T, intr


def test_roi_weighted_fisher_score_equals_brute_force_autograd() -> None:
    smap, vol, T, intr = _tiny_scene()
    cfg = NBVConfig(sigma_p=0.5, fisher_outputs=("color", "depth"))
    scorer = NBVScorer(cfg)
    rng = np.random.default_rng(4)
    h_train = {k: torch.tensor(rng.uniform(0.0, 2.0, tuple(getattr(smap, k).shape))) for k in GEOMETRIC_PARAMS}
    res = scorer.score(smap, h_train, vol, [], [T], intr, mode="roi-fisher")
    roi = scorer.roi(vol, T, intr, smap).weights
    # The ROI is non-trivial here: graded weights, some pixels outside it.
    assert 0 < (roi > 0).sum() < roi.size and roi.max() > 2 * roi[roi > 0].min()

    leaves = {k: getattr(smap, k).clone().requires_grad_(True) for k in GEOMETRIC_PARAMS}
    viewmat, K = camera_tensors(T, intr, dtype=torch.float64)
    out = reference_rasterize(
        leaves["means"], leaves["quats"], torch.exp(leaves["log_scales"]), torch.sigmoid(smap.opacity_logits),
        smap.colors(), viewmat, K, intr.width, intr.height, near=cfg.near_m, far=cfg.far_m,
    )  # fmt: skip
    F = {k: torch.zeros_like(v) for k, v in leaves.items()}
    w = roi / cfg.sigma_p**2
    for y, x in zip(*np.nonzero(w), strict=True):
        for value in (*out.features[y, x].unbind(), out.depth[y, x]):
            grads = torch.autograd.grad(value, list(leaves.values()), retain_graph=True, allow_unused=True)
            for k, g in zip(leaves, grads, strict=True):
                if g is not None:
                    F[k] += w[y, x] * g**2
    brute = sum(float((F[k] / (h_train[k] + cfg.phi)).sum()) for k in F)
    assert brute > 0
    assert res.fisher[0] == pytest.approx(brute, rel=1e-8)
    assert res.n_roi_pixels[0] == (roi > 0).sum() and res.roi_mass[0] == pytest.approx(roi.sum())


# ------------------------------------------------------------------------------ two-panel world
def _panel(x: float) -> o3d.geometry.TriangleMesh:
    b = o3d.geometry.TriangleMesh.create_box(0.02, 1.6, 1.2).translate((x - 0.01, -0.8, 0.4))
    b.paint_uniform_color([0.6, 0.5, 0.4])
    return b


class World:
    """Panel A (x = +2) seen closely by three training views; panel B (x = -2) once, far and obliquely."""

    def __init__(self) -> None:
        self.renderer = MeshRenderer(_panel(2.0) + _panel(-2.0), texture_strength=1.0)
        self.train = [look_at(np.array([0.5, y, 1.0]), np.array([2.0, 0.5 * y, 1.0]), UP) for y in (-0.3, 0.0, 0.3)]
        self.train.append(look_at(np.array([1.0, 1.6, 1.0]), np.array([-2.0, -0.2, 1.0]), UP))
        self.tsdf = TSDFVolume(voxel_size_m=0.04)
        maps = []
        self.memory = CloseFrontMemory(self.tsdf.voxel_size_m, NBVConfig())
        for T in self.train:
            rgb, d = self.renderer.render(T, INTR)
            self.tsdf.integrate(d, T, INTR, rgb)
            self.memory.add_view(NBVScorer().surface(self.tsdf), T, INTR)  # incrementally, after integrating
            if T is self.train[1] or T is self.train[3]:  # seed once per panel (no duplicate surfel layers)
                maps.append(surfels_from_rgbd(rgb, d, T, INTR, stride=2, dtype=torch.float64))
        self.map = SurfelMap.cat(maps)
        self.n_a = len(maps[0])  # surfels 0..n_a-1 lie on panel A
        self.view_a = self.train[1]  # a training view of A, again
        self.view_b = look_at(np.array([-0.9, 0.0, 1.0]), np.array([-2.0, 0.0, 1.0]), UP)  # close, frontal on B
        self.view_up = look_at(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 3.0]), np.array([1.0, 0.0, 0.0]))
        self.candidates = np.stack([self.view_a, self.view_b, self.view_up])
        self.h_train = NBVScorer().train_fisher(self.map, self.train, INTR)


@pytest.fixture(scope="module")
def world() -> World:
    return World()


def test_scorer_prefers_the_weakly_observed_panel_in_every_mode(world: World) -> None:
    scorer = NBVScorer()
    for mode in ("roi-gsurfisher", "roi-fisher", "close-front", "fisherrf"):
        h = world.h_train if mode != "fisherrf" else None  # FisherRF's colour-only H_train is computed here
        res = scorer.score(world.map, h, world.tsdf, world.train, world.candidates, INTR, mode=mode)
        assert res.mode == mode and res.best_index == 1, mode
        np.testing.assert_array_equal(res.ranking, [1, 0, 2])
        np.testing.assert_array_equal(res.flagged, [False, False, True])  # looking at the sky
        assert np.all(np.isfinite(res.fused)) and res.reason == ""
        assert res.fisher[2] == 0.0 and res.close_front[2] == 0.0
        np.testing.assert_array_equal(res.top_k, res.ranking[:5])
        if mode in ("roi-gsurfisher", "close-front"):
            assert res.close_front[0] == 0.0 and res.close_front[1] > 0.0  # a repeated training view gains nothing
        if mode != "fisherrf":
            assert res.n_roi_pixels[1] > 0.9 * INTR.width * INTR.height and res.n_visible_voxels[2] == 0
            assert res.fisher[1] > res.fisher[0] > 0.0 or mode == "close-front"
    fused = scorer.score(world.map, world.h_train, world.tsdf, world.train, world.candidates, INTR)
    ok = ~fused.flagged  # z-scores over the candidates that see surface; the flagged one gets 0
    np.testing.assert_allclose(fused.fused[ok], 0.4 * fused_z(fused.fisher[ok]) + 0.6 * fused_z(fused.close_front[ok]))
    assert fused.fused[2] == 0.0


def test_candidates_rounded_to_float32_are_scored_as_the_exact_ones(world: World) -> None:
    """A walk: the keyframes' own poses rounded to float32 changed the chosen view. Their I_vis, exactly 0 at the exact
    poses, became rounding noise (1e-7 1/m here), which the plain z-score of Eq. 15 blew up to full strength.
    ``close_front_min_std`` (0.01 1/m) floors z(I_vis)'s divisor: the rounded poses score as the exact ones; 0 (the
    plain z-score) still shows the noise at full strength."""
    exact = np.stack(world.train[:3])
    rounded = exact.astype(np.float32).astype(np.float64)
    for floor, same in ((NBVConfig().close_front_min_std, True), (0.0, False)):
        scorer = NBVScorer(NBVConfig(close_front_min_std=floor))
        a = scorer.score(world.map, world.h_train, world.tsdf, world.train, exact, INTR)
        b = scorer.score(world.map, world.h_train, world.tsdf, world.train, rounded, INTR)
        assert np.all(a.close_front == 0.0) and 0.0 < b.close_front.max() < 1e-5, b.close_front
        assert np.allclose(a.fused, b.fused, atol=1e-4) == same, (floor, a.fused, b.fused)
    with pytest.raises(InputError, match="close_front_min_std"):
        NBVConfig(close_front_min_std=-1.0)


def test_a_candidate_that_sees_nothing_does_not_change_the_others_fused_scores(world: World) -> None:
    """Eq. 15's z-scores are over scored candidates: adding a flagged one (looking at the sky, F = I_vis = 0 as
    placeholders) must leave the other candidates' fused scores, and so their order, unchanged."""
    scorer = NBVScorer()
    extra = look_at(np.array([0.9, 0.4, 1.0]), np.array([2.0, 0.1, 1.2]), UP)  # a third view of panel A
    cands = np.stack([world.view_a, world.view_b, extra])
    base = scorer.score(world.map, world.h_train, world.tsdf, world.train, cands, INTR)
    more = scorer.score(world.map, world.h_train, world.tsdf, world.train, np.stack([*cands, world.view_up]), INTR)
    assert more.flagged.tolist() == [False, False, False, True] and not base.flagged.any()
    np.testing.assert_allclose(more.fused[:3], base.fused, rtol=1e-9, atol=1e-12)
    for mode in ("roi-fisher", "close-front", "fisherrf"):
        h = world.h_train if mode != "fisherrf" else None
        b = scorer.score(world.map, h, world.tsdf, world.train, cands, INTR, mode=mode)
        m = scorer.score(world.map, h, world.tsdf, world.train, np.stack([*cands, world.view_up]), INTR, mode=mode)
        np.testing.assert_allclose(m.fused[:3], b.fused, rtol=1e-9, atol=1e-12, err_msg=mode)


def test_candidates_that_cannot_see_the_map_are_skipped_before_any_rendering(world: World, monkeypatch) -> None:
    """Issue 12: a candidate whose frustum misses the mapped region costs no ROI, Fisher or unseen render."""
    import roigsf_ros.nbv.scorer as scorer_mod

    lo, hi = np.array([-1.0, -1.0, 0.0]), np.array([1.0, 1.0, 2.0])
    assert frustum_meets_box(look_at(np.array([0.0, -3.0, 1.0]), np.zeros(3), UP), INTR, lo, hi, 0.2, 10.0)
    assert not frustum_meets_box(look_at(np.array([0.0, -3.0, 1.0]), np.array([0.0, -6.0, 1.0]), UP), INTR, lo, hi,
                                 0.2, 10.0)  # fmt: skip
    assert not frustum_meets_box(look_at(np.array([0.0, -3.0, 1.0]), np.zeros(3), UP), INTR, lo, hi, 0.2, 1.5)
    away = look_at(np.array([0.0, 0.0, 4.0]), np.array([0.0, 0.0, 9.0]), np.array([1.0, 0.0, 0.0]))  # looking up
    calls = []
    real = scorer_mod.fisher_weighted_sum
    monkeypatch.setattr(scorer_mod, "fisher_weighted_sum", lambda *a, **k: calls.append(1) or real(*a, **k))
    cands = np.stack([world.view_a, world.view_b, away])
    for mode, kw in (("roi-gsurfisher", {}), ("roi-gsurfisher", {"unseen_weight": 1.0}), ("fisherrf", {})):
        scorer = NBVScorer(replace(NBVConfig(), **kw))
        h = world.h_train if mode != "fisherrf" else scorer.train_fisher(world.map, world.train, INTR, mode)
        calls.clear()
        res = scorer.score(world.map, h, world.tsdf, world.train, cands, INTR, mode=mode)
        assert res.n_skipped == 1 and res.flagged.tolist() == [False, False, True] and len(calls) == 2, (mode, kw)
        assert res.fisher[2] == 0.0 and res.n_visible_voxels[2] == 0
        assert res.unseen is None or res.unseen[2] == 0.0
        two = scorer.score(world.map, h, world.tsdf, world.train, cands[:2], INTR, mode=mode)
        np.testing.assert_allclose(res.fused[:2], two.fused, rtol=1e-12, atol=1e-12)
        assert res.fused[2] == 0.0 and res.ranking[-1] == 2
    inf_margin = NBVScorer(replace(NBVConfig(), unseen_weight=1.0, unseen_bbox_margin_m=float("inf")))
    res = inf_margin.score(world.map, world.h_train, world.tsdf, world.train, cands, INTR)
    assert res.n_skipped == 0 and res.unseen[2] == 1.0  # every pixel counts in U(x): nothing can be skipped


def fused_z(x: np.ndarray) -> np.ndarray:
    return (x - x.mean()) / x.std()


def test_dividing_by_training_information_steers_away_from_trained_surfels(world: World) -> None:
    scorer = NBVScorer()
    cands = world.candidates[:2]
    n, n_a = len(world.map), world.n_a

    def h_with(big_on_a: bool) -> dict[str, torch.Tensor]:
        big = torch.zeros(n, dtype=torch.float64)
        big[:n_a] = 1e6 if big_on_a else 0.0
        big[n_a:] = 0.0 if big_on_a else 1e6
        return {k: big.reshape(-1, *[1] * (getattr(world.map, k).dim() - 1)).expand_as(getattr(world.map, k)).clone()
                for k in GEOMETRIC_PARAMS}  # fmt: skip

    a_trained = scorer.score(world.map, h_with(True), world.tsdf, world.train, cands, INTR, mode="roi-fisher")
    b_trained = scorer.score(world.map, h_with(False), world.tsdf, world.train, cands, INTR, mode="roi-fisher")
    assert a_trained.best_index == 1 and b_trained.best_index == 0
    assert a_trained.fisher[0] < 1e-3 * a_trained.fisher[1]
    assert b_trained.fisher[1] < 1e-3 * b_trained.fisher[0]


def test_incremental_memory_and_input_forms_give_the_same_scores(world: World) -> None:
    scorer = NBVScorer()
    exact = scorer.score(world.map, world.h_train, world.tsdf, world.train, world.candidates, INTR, mode="close-front")
    inc = scorer.score(world.map, world.h_train, world.tsdf, [], world.candidates, INTR, mode="close-front",
                       close_front_memory=world.memory)  # fmt: skip
    assert inc.best_index == exact.best_index == 1
    # Voxels that entered the surface band after a view was added do not get that view's weight, so the
    # incremental gain can only be higher; here the views barely overlap and it is (nearly) the same.
    assert np.all(inc.close_front >= exact.close_front - 1e-9)
    assert inc.close_front[1] == pytest.approx(exact.close_front[1], rel=0.05)
    # Candidates as [M, 7] position + (x, y, z, w) quaternion rows and as a list of matrices.
    rows = np.stack([np.concatenate([T[:3, 3], matrix_to_quat_xyzw(T[:3, :3])]) for T in world.candidates])
    for form in (rows, list(world.candidates)):
        res = scorer.score(world.map, world.h_train, world.tsdf, world.train, form, INTR, mode="close-front")
        np.testing.assert_allclose(res.close_front, exact.close_front, rtol=1e-9)


def test_fisher_downsampling_keeps_the_choice(world: World) -> None:
    full = NBVScorer().score(world.map, world.h_train, world.tsdf, world.train, world.candidates, INTR, "roi-fisher")
    half = NBVScorer(NBVConfig(fisher_downsample=2)).score(
        world.map, world.h_train, world.tsdf, world.train, world.candidates, INTR, mode="roi-fisher"
    )
    assert half.best_index == full.best_index == 1
    np.testing.assert_allclose(half.fisher, full.fisher, rtol=0.5)  # same units: weights scaled by 4


def test_bad_and_degenerate_inputs(world: World) -> None:
    scorer = NBVScorer()
    args = (world.map, world.h_train, world.tsdf, world.train)
    with pytest.raises(InputError, match="no candidate"):
        scorer.score(*args, [], INTR)
    with pytest.raises(InputError, match="no candidate"):
        scorer.score(*args, np.zeros((0, 4, 4)), INTR)
    with pytest.raises(InputError, match="unit quaternion"):
        scorer.score(*args, np.array([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 2.0]]), INTR)
    with pytest.raises(InputError, match="rigid"):
        scorer.score(*args, np.diag([1.0, 2.0, 1.0, 1.0])[None], INTR)
    with pytest.raises(InputError, match="expected"):
        scorer.score(*args, np.zeros((2, 3, 3)), INTR)
    with pytest.raises(InputError, match="mode"):
        scorer.score(*args, world.candidates, INTR, mode="random")
    bad_h = dict(world.h_train)
    bad_h["means"] = bad_h["means"][:-1]
    with pytest.raises(InputError, match="means"):
        scorer.score(world.map, bad_h, world.tsdf, world.train, world.candidates, INTR)
    with pytest.raises(InputError, match="has no entry"):
        scorer.score(world.map, {"means": world.h_train["means"]}, world.tsdf, world.train, world.candidates, INTR)

    def check_zero(res: object, field: str, reason: str) -> None:
        assert reason in res.reason
        assert np.all(getattr(res, field) == 0.0) and np.all(np.isfinite(res.fused))
        assert res.best_index == 0 and list(res.ranking) == [0, 1, 2]

    empty = SurfelMap.empty(dtype=torch.float64)
    for mode in ("roi-fisher", "fisherrf"):
        res = scorer.score(empty, None, world.tsdf, world.train, world.candidates, INTR, mode=mode)
        check_zero(res, "fisher", "surfel map is empty")
    for smap in (empty, None):
        res = scorer.score(smap, None, world.tsdf, world.train, world.candidates, INTR, mode="roi-gsurfisher")
        assert "surfel map is empty" in res.reason and not res.fisher.any()
        assert res.best_index == 1  # close-front still works from the TSDF
    no_surface = TSDFVolume(voxel_size_m=0.04)
    for tsdf, reason in ((no_surface, "no surface voxels"), (None, "no TSDF")):
        for mode in ("roi-gsurfisher", "roi-fisher", "close-front"):
            res = scorer.score(world.map, world.h_train, tsdf, world.train, world.candidates, INTR, mode=mode)
            check_zero(res, "fisher", reason)
            check_zero(res, "close_front", reason)
            assert res.flagged.all()
    # a map from Mapper.load keeps its keyframe poses in map_keyframes(): given its empty keyframe_poses, the scores
    # were 0 with "no TSDF given" alone, which named the symptom, not the empty poses
    res = scorer.score(world.map, None, None, np.zeros((0, 4, 4)), world.candidates, INTR, mode="roi-gsurfisher")
    assert "no training poses" in res.reason and "map_keyframes" in res.reason and not res.fused.any()
    res = scorer.score(world.map, world.h_train, world.tsdf, world.train, world.candidates, INTR)
    assert "no training poses" not in res.reason


# ----------------------------------------------------------------------------- uncertainty, AUSE
def test_pixel_uncertainty_is_high_where_training_information_is_low(world: World) -> None:
    scorer = NBVScorer()
    u_a = scorer.uncertainty(world.map, world.h_train, world.view_a, INTR, world.tsdf)
    u_b = scorer.uncertainty(world.map, world.h_train, world.view_b, INTR, world.tsdf)
    for maps in (u_a, u_b):
        for img in (maps.u, maps.u_roi, maps.roi):
            assert img.shape == (48, 64) and np.all(np.isfinite(img)) and img.min() >= 0.0
        assert np.all(maps.u_roi[maps.roi == 0] == 0.0)
        np.testing.assert_allclose(maps.u_roi, maps.roi / NBVConfig().sigma_p ** 2 * maps.u)
    # 100x less training information on panel B's surfels: B's uncertainty grows ~100x, A's view is unchanged.
    low_b = {k: v.clone() for k, v in world.h_train.items()}
    for v in low_b.values():
        v[world.n_a :] *= 0.01
    u_a2 = scorer.uncertainty(world.map, low_b, world.view_a, INTR, world.tsdf)
    u_b2 = scorer.uncertainty(world.map, low_b, world.view_b, INTR, world.tsdf)
    np.testing.assert_allclose(u_a2.u, u_a.u, rtol=1e-9)
    covered = u_b.u > 1e-3 * u_b.u.max()
    assert covered.mean() > 0.9
    np.testing.assert_allclose(u_b2.u[covered] / u_b.u[covered], 100.0, rtol=0.03)  # phi keeps it a bit below
    assert np.all(scorer.uncertainty(world.map, low_b, world.view_a, INTR).roi == 0)  # no TSDF: no ROI
    up = scorer.uncertainty(world.map, world.h_train, world.view_up, INTR, world.tsdf)
    assert not up.u.any() and not up.roi.any()  # nothing rendered there
    rrf = scorer.fisherrf_uncertainty(world.map, world.view_b, INTR, [*world.train, world.view_b])
    assert rrf.shape == (48, 64) and np.all(np.isfinite(rrf)) and rrf.min() >= 0 and rrf.max() > 0
    assert not scorer.fisherrf_uncertainty(SurfelMap.empty(), world.view_b, INTR, world.train).any()


def test_depth_error_ause_of_uncertainty_maps(world: World) -> None:
    scorer = NBVScorer()
    T = look_at(np.array([0.8, 0.5, 1.2]), np.array([2.0, 0.2, 0.9]), UP)
    with torch.no_grad():
        pred = render_map(world.map, T, INTR).expected_depth().numpy()
    gt = world.renderer.render_depth(T, INTR)
    err = np.abs(pred - gt)
    assert depth_error_ause(err, pred, gt)["ause"] == pytest.approx(0.0, abs=1e-12)  # the oracle itself
    rng = np.random.default_rng(0)
    assert depth_error_ause(rng.random(err.shape), pred, gt)["ause"] > 0.0
    u = scorer.uncertainty(world.map, world.h_train, T, INTR).u
    res = depth_error_ause(torch.tensor(u), pred, gt)
    assert np.isfinite(res["ause"]) and res["ause"] >= 0.0
    ok = (pred > 0) & (gt > 0)
    assert res["n"] == int(ok.sum()) and -1.0 <= res["spearman_rho"] <= 1.0
    assert res["ause_random_raw"] == depth_error_ause(-u, pred, gt)["ause_random_raw"] > 0.0  # same pixels, seed 0
    back = depth_error_ause(-err, pred, gt)  # the oracle reversed: worse than random in raw AUSE, rho = -1
    assert back["ause_raw"] > back["ause_random_raw"] and back["spearman_rho"] == pytest.approx(-1.0)
    with pytest.raises(InputError, match="no pixel"):
        depth_error_ause(u, np.zeros_like(pred), gt)
    with pytest.raises(InputError, match="shapes"):
        depth_error_ause(u[:-1], pred, gt)


# ------------------------------------------------------------------------------------ benchmark
def test_perf_nbv_runs_on_a_tiny_room_and_writes_json(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    from roigsf_ros.cli import main
    from roigsf_ros.render.numba_setup import numba_available, set_numba_threads

    out = tmp_path / "nbv.json"
    args = ["perf", "nbv", "--repeats", "1", "--threads", "1", "--surfels", "1500", "--width", "40", "--height", "30"]
    try:
        assert main([*args, "--candidates", "4", "--voxel-size", "0.1", "--keyframes", "2,5", "--out", str(out)]) == 0
    finally:  # back to numba's default thread count (the benchmark set 1)
        if numba_available():
            import numba

            set_numba_threads(numba.config.NUMBA_NUM_THREADS)
    data = json.loads(out.read_text())
    assert data["benchmark"] == "nbv" and data["surfels"] == 1500 and data["surface_voxels"] > 100
    assert data["environment"]["threads"] == 1 and data["environment"]["versions"]["torch"] == torch.__version__
    assert data["environment"]["numba_threads"] == (1 if numba_available() else None)  # what numba took
    rows = {(r["mode"], r["fisher_downsample"]) for r in data["rows"]}
    assert rows == {(m, d) for m in ("roi-gsurfisher", "fisherrf") for d in (1, 2)}
    for r in data["rows"]:
        assert r["n_candidates"] == 4 and r["n_flagged"] == 0  # every candidate in the room sees surface
        assert r["train_fwd_bwd_ms"] > 0 and r["fisher_ms"] > 0 and r["score_s"] > 0 and r["score_state_s"] > 0
        assert r["state_best_index"] == r["best_index"]  # the planner's kept state scores as the one-shot call
        parts = r["roi_ms"] + r["close_front_ms"] + r["fisher_ms"]
        assert r["candidate_ms"] == pytest.approx(parts, rel=1e-9)  # one repeat: the median is the sum
        if r["mode"] == "roi-gsurfisher":
            assert r["roi_ms"] > 0 and r["phases_s"]["roi"] > 0
        else:
            assert r["roi_ms"] < 0.05 * r["fisher_ms"]  # FisherRF has no ROI: only loop overhead
    # planner requests by keyframe count: the kept grid renders each keyframe once and, the map being the same,
    # scores as rendering at every request; only the unseen variants have an unseen phase
    req = {(r["variant"], r["keyframes"]): r for r in data["requests"]}
    assert set(req) == {(v, k) for v in ("roi-gsurfisher", "F3", "F3, kept grid") for k in (2, 5)}
    for k in (2, 5):
        assert req["roi-gsurfisher", k]["unseen_s"] == 0.0 and req["F3", k]["unseen_s"] > 0
        assert req["F3, kept grid", k]["renders"] == k and req["F3", k]["renders"] is None
        assert req["F3, kept grid", k]["best_index"] == req["F3", k]["best_index"]
        assert all(req[v, k]["request_s"] > 0 and req[v, k]["sync_one_s"] > 0 for v in ("F3", "F3, kept grid"))
    assert "ratio" in capsys.readouterr().out
    assert main([*args, "--candidates", "0"]) == 2  # bad input: one-line error
    assert main([*args, "--keyframes", "0,4"]) == 2


def test_unseen_term_pulls_towards_space_the_map_has_not_seen(world: World) -> None:
    """Beyond the paper: a map of panel A only. Paper mode flags the view of unmapped panel B (its ROI is
    empty) and picks A again; ``unseen_weight`` > 0 prefers B, whose pixels the map has not seen."""
    map_a = world.map.select(torch.arange(world.n_a))
    tsdf = TSDFVolume(voxel_size_m=0.04)
    for T in world.train[:3]:
        rgb, d = world.renderer.render(T, INTR)
        tsdf.integrate(d, T, INTR, rgb)
    h = NBVScorer().train_fisher(map_a, world.train[:3], INTR)
    cands = np.stack([world.view_a, world.view_b])
    paper = NBVScorer().score(map_a, h, tsdf, world.train[:3], cands, INTR)
    assert paper.best_index == 0 and paper.unseen is None
    for mode in ("roi-gsurfisher", "roi-fisher"):
        cfg = NBVConfig(unseen_weight=1.0, unseen_bbox_margin_m=float("inf"))  # B lies outside A's box
        res = NBVScorer(cfg).score(map_a, h, tsdf, world.train[:3], cands, INTR, mode=mode)
        assert res.best_index == 1, mode
        assert res.unseen[1] > 0.9 and res.unseen[0] < 0.5 and not res.flagged[1]
    with pytest.raises(InputError):
        NBVConfig(unseen_weight=-1.0)


@pytest.mark.parametrize("test", ["tsdf", "surfels"])
def test_unseen_backfaces_count_the_back_of_the_mapped_surface_as_unseen(world: World, test: str) -> None:
    """Beyond the paper: 2DGS surfels render from both sides, so from behind panel A the alpha test calls its
    pixels seen; with ``unseen_backfaces`` they are unseen: the TSDF's outward normals there, and the normals of the
    surfels seeded from A's training view, face that view, away from this camera. A view of A's front keeps its U."""
    behind = look_at(np.array([3.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), UP)
    cands = np.stack([world.view_a, behind])
    args = (world.map, world.h_train, world.tsdf, world.train, cands, INTR)
    alpha_only = NBVScorer(NBVConfig(unseen_weight=1.0)).score(*args)
    backs = NBVScorer(NBVConfig(unseen_weight=1.0, unseen_backfaces=test)).score(*args)
    assert alpha_only.unseen[1] < 0.2 and backs.unseen[1] > 0.7
    assert backs.unseen[0] == pytest.approx(alpha_only.unseen[0], abs=0.02)
    assert alpha_only.best_index == 0 and backs.best_index == 1
    facing = surfels_facing(world.map, behind)
    assert not facing[: world.n_a].any() and bool(surfels_facing(world.map, world.view_a)[: world.n_a].all())


def test_unconfirmed_backfaces_spare_the_back_a_keyframe_saw(world: World) -> None:
    """``unseen_backfaces="unconfirmed"``: panel A is 2 cm thick, within the mapper's 5 cm densify margin, so a view
    of its back seeds nothing and A's surfels keep facing the front. Its back counts as unseen (as with "surfels")
    while no keyframe saw it from behind; a keyframe behind A that looks away, or the ones in front of A, confirm
    nothing; once a keyframe behind A looked at it, its back is seen and U falls to the alpha test's."""
    behind = look_at(np.array([3.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), UP)
    cands = np.stack([world.view_a, behind])
    cfg = NBVConfig(unseen_weight=1.0, unseen_backfaces="unconfirmed")

    def unseen(config: NBVConfig, poses: list[np.ndarray]) -> np.ndarray:
        return NBVScorer(config).score(world.map, world.h_train, world.tsdf, poses, cands, INTR).unseen

    surfels = unseen(replace(cfg, unseen_backfaces="surfels"), world.train)
    assert surfels[1] > 0.7
    np.testing.assert_allclose(unseen(cfg, world.train), surfels)
    away = look_at(np.array([3.0, 0.2, 1.0]), np.array([4.0, 0.2, 1.0]), UP)  # behind A, looking away from it
    np.testing.assert_allclose(unseen(cfg, [*world.train, away]), surfels)
    saw = look_at(np.array([3.5, 0.2, 1.1]), np.array([2.0, 0.0, 1.0]), UP)  # behind A, looking at its back
    confirmed = unseen(cfg, [*world.train, saw])
    alpha_only = unseen(NBVConfig(unseen_weight=1.0), [*world.train, saw])
    assert confirmed[1] < 0.2 and confirmed[1] == pytest.approx(alpha_only[1], abs=0.03)
    assert confirmed[0] == pytest.approx(surfels[0])  # a view of A's front has no backs to confirm
    with pytest.raises(InputError, match="unseen_confirm_margin_m"):
        NBVConfig(unseen_confirm_margin_m=0.0)


def test_carved_unseen_source_counts_what_no_keyframe_observed(world: World) -> None:
    """``unseen_source="carved"``: the keyframes' rendered depth carves the box. A repeated training view of panel
    A sees nothing unseen; the view of A's back does (no keyframe looked at it: the space behind A is unknown) with no
    back-face test; once a keyframe behind A looked at it, the space in front of its back is carved and U falls.
    The scorer's U is the carved grid's own count, the area measure puts the surface where the unknown ends, and the
    cell measure counts the grid's frontier cells the view looks into, the ray measure the unknown cells its rays
    cross."""
    from roigsf_ros.nbv import carved_space, rays_meet_box

    behind = look_at(np.array([3.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), UP)
    cands = np.stack([world.view_a, behind])
    cfg = NBVConfig(unseen_weight=1.0, unseen_source="carved")

    def unseen(config: NBVConfig, poses: list[np.ndarray]) -> np.ndarray:
        return NBVScorer(config).score(world.map, world.h_train, world.tsdf, poses, cands, INTR).unseen

    u = unseen(cfg, world.train)
    assert u[0] < 0.05 and u[1] > 0.7
    vox = NBVScorer().surface(world.tsdf)
    lo, hi = vox.centres_m.min(0) - 0.1, vox.centres_m.max(0) + 0.1
    space = carved_space(world.map, world.train, INTR, lo, hi, cfg)
    enter, leave = space.unseen_depths(behind, INTR, cfg.near_m, cfg.far_m)
    meets = rays_meet_box(behind, INTR, lo, hi)
    assert u[1] == pytest.approx(((enter > 0) & meets).sum() / rays_meet_count(behind, vox))
    c = (INTR.height // 2, INTR.width // 2)
    assert leave[c] == pytest.approx(1.0, abs=0.1)  # A's back lies 1 m from the camera
    area = unseen(replace(cfg, unseen_measure="area"), world.train)
    assert area[1] == pytest.approx((leave[enter > 0] ** 2).sum() / (INTR.fx * INTR.fy))
    cells = unseen(replace(cfg, unseen_measure="cells"), world.train)
    _, frontier = space.unseen_frontier(behind, INTR, cfg.near_m, cfg.far_m)
    assert cells[1] == pytest.approx(len(frontier) * cfg.unseen_voxel_m**2) and cells[1] > 0 and cells[0] < cells[1]
    rays = unseen(replace(cfg, unseen_measure="rays"), world.train)  # unknown cells crossed, per counted pixel
    hole = (enter > 0) & meets
    expected = (leave - enter)[hole].sum() / cfg.unseen_voxel_m / rays_meet_count(behind, vox)
    assert rays[1] == pytest.approx(expected) and rays[1] > 1 and rays[0] < rays[1]  # the box ends 0.1 m behind A
    saw = look_at(np.array([3.5, 0.2, 1.1]), np.array([2.0, 0.0, 1.0]), UP)  # behind A, looking at its back
    assert unseen(cfg, [*world.train, saw])[1] < 0.2
    with pytest.raises(InputError, match="unseen_source"):
        NBVConfig(unseen_source="tsdf")
    with pytest.raises(InputError, match="finite unseen_bbox_margin_m"):
        NBVConfig(unseen_source="carved", unseen_bbox_margin_m=float("inf"))
    with pytest.raises(InputError, match="unseen_voxel_m"):
        NBVConfig(unseen_voxel_m=0.0)
    with pytest.raises(InputError, match="unseen_measure"):
        NBVConfig(unseen_measure="cells")  # the map source has no cells
    with pytest.raises(InputError, match=r"^unseen_measure: rays counts carved cells"):
        NBVConfig(unseen_measure="rays")


def _map_rgbd(m: SurfelMap):
    """The map's median depth at a pose where its alpha reaches 0.5 (0 elsewhere), as a scoring TSDF fuses it."""

    def render(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with torch.no_grad():
            out = render_map(m, T, INTR)
        depth = torch.where(out.alpha >= 0.5, out.median_depth, 0.0).numpy().astype(np.float32)
        return depth, np.zeros((INTR.height, INTR.width, 3), np.uint8)

    return render


def test_a_kept_carved_grid_renders_each_keyframe_once(world: World) -> None:
    """``unseen_carve_rerender`` false: a kept scoring state renders each keyframe for the carved grid once and
    carves only the new ones; its first call scores as rendering at every call does (the same renders), and the
    unseen term's build and measures are timed as their own phase. Rendering every keyframe at every call made a
    planner request grow with the map."""
    cfg = NBVConfig(unseen_weight=1.0, unseen_source="carved", unseen_measure="rays")
    behind = look_at(np.array([3.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), UP)
    cands = np.stack([world.view_a, world.view_b, behind])
    poses = np.stack(world.train)
    outputs = ("color", "depth")
    render = _map_rgbd(world.map)
    every = ScoringState(cfg, 0.04, 0.16, 10.0)
    kept = ScoringState(replace(cfg, unseen_carve_rerender=False), 0.04, 0.16, 10.0)
    assert every.carved is None and kept.carved is not None
    first = [s.score(world.map, world.h_train, outputs, poses[:3], cands, INTR, render) for s in (every, kept)]
    np.testing.assert_array_equal(first[0].unseen, first[1].unseen)
    np.testing.assert_array_equal(first[0].fused, first[1].fused)
    assert first[1].unseen[2] > first[1].unseen[0] and first[0].timings_s["unseen"] > 0
    assert kept.carved.renders == 3
    kept.score(world.map, world.h_train, outputs, poses, cands, INTR, render)
    assert kept.carved.renders == 4  # only the new keyframe rendered
    paper = NBVScorer().score(world.map, world.h_train, world.tsdf, world.train, cands, INTR)
    assert paper.timings_s["unseen"] == 0.0
    with pytest.raises(InputError, match=r"^unseen_carve_rerender: false keeps the carved grid"):
        NBVConfig(unseen_carve_rerender=False)  # the map source keeps no grid
    with pytest.raises(InputError, match="unseen_carve_rerender"):
        NBVConfig(unseen_source="carved", unseen_carve_rerender="no")


def test_the_kept_carved_grid_is_the_grid_of_every_kept_depth_carved_at_once(world: World) -> None:
    """:class:`CarvedSpaceMemory`: the grid carved keyframe by keyframe equals the one carved from all kept depths
    at once, cell for cell; a larger box carves the kept depths again without rendering; a keyframe set that does not
    extend the kept one starts afresh. A changed map does not change what a kept keyframe carved."""
    from roigsf_ros.mapping.observed_space import ObservedSpace
    from roigsf_ros.nbv.state import CarvedSpaceMemory
    from roigsf_ros.nbv.unseen import carve_depths, carved_space

    cfg = NBVConfig(unseen_weight=1.0, unseen_source="carved", unseen_carve_rerender=False)
    poses = np.stack(world.train)
    vox = NBVScorer().surface(world.tsdf)
    box = (vox.centres_m.min(0) - 0.1, vox.centres_m.max(0) + 0.1)
    mem = CarvedSpaceMemory()
    mem.space(world.map, poses[:2], INTR, box, cfg)
    grid = mem.space(world.map, poses, INTR, box, cfg)
    assert (mem.renders, mem.carves) == (4, 4)
    at_once = ObservedSpace.carve(*box, cfg.unseen_voxel_m, poses, carve_depths(world.map, poses, INTR, cfg), INTR,
                                  cfg.far_m)  # fmt: skip
    np.testing.assert_array_equal(grid.state, at_once.state)
    np.testing.assert_array_equal(grid.state, carved_space(world.map, poses, INTR, *box, cfg).state)
    wider = (box[0] - 0.2, box[1] + 0.2)
    grid = mem.space(world.map, poses, INTR, wider, cfg)
    assert (mem.renders, mem.carves) == (4, 8)
    np.testing.assert_array_equal(grid.state, carved_space(world.map, poses, INTR, *wider, cfg).state)
    only_b = world.map.select(torch.arange(world.n_a, len(world.map)))  # panel A gone from the map
    assert mem.space(only_b, poses, INTR, wider, cfg) is grid and mem.renders == 4
    assert not np.array_equal(carved_space(only_b, poses, INTR, *wider, cfg).state, grid.state)
    mem.space(world.map, poses[::-1], INTR, wider, cfg)
    assert mem.renders == 8  # not an extension of the kept keyframes


def test_unseen_min_stretch_counts_long_unknown_stretches_and_those_from_the_box_side(world: World) -> None:
    """``unseen_min_stretch_m``: 0 is the carved count to the bit; above 0 a pixel stays unseen only where the unknown
    stretch it looks through last is at least that long, or begins where its ray enters the box (the grid cannot say
    how long it is). Panel B, seen once far and obliquely, looks unseen from close in front through short uncarved
    stretches, which a minimum drops; A's back, seen from outside the box through 7 cm of it, stays unseen."""
    from roigsf_ros.nbv import box_depths, carved_space, carved_unseen, rays_meet_box

    behind = look_at(np.array([3.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), UP)  # outside the box, at A's back
    cands = np.stack([world.view_a, behind, world.view_b])
    cfg = NBVConfig(unseen_weight=1.0, unseen_source="carved")

    def unseen(config: NBVConfig) -> np.ndarray:
        return NBVScorer(config).score(world.map, world.h_train, world.tsdf, world.train, cands, INTR).unseen

    base = unseen(cfg)
    assert unseen(replace(cfg, unseen_min_stretch_m=0.0)) == pytest.approx(base, abs=0)
    vox = NBVScorer().surface(world.tsdf)
    lo, hi = vox.centres_m.min(0) - 0.1, vox.centres_m.max(0) + 0.1
    space = carved_space(world.map, world.train, INTR, lo, hi, cfg)
    for s in (0.05, 0.2, 10.0):
        u = unseen(replace(cfg, unseen_min_stretch_m=s))
        for i, T in enumerate(cands):
            enter, leave = space.unseen_depths(T, INTR, cfg.near_m, cfg.far_m)
            meets = rays_meet_box(T, INTR, lo, hi)
            from_side = enter <= box_depths(T, INTR, lo, hi)[0] + cfg.unseen_voxel_m
            kept = (enter > 0) & meets & ((leave - enter >= s) | from_side)
            assert u[i] == pytest.approx(kept.sum() / meets.sum(), abs=1e-12)
            hole, _enter, _leave = carved_unseen(space, T, INTR, (lo, hi), replace(cfg, unseen_min_stretch_m=s))
            np.testing.assert_array_equal(hole & meets, kept)
        assert u[1] > 0.99 and u[0] == base[0] == 0.0
        assert u[2] < base[2] - 0.05
    assert unseen(replace(cfg, unseen_min_stretch_m=10.0))[2] == 0.0
    for bad in ({"unseen_min_stretch_m": 0.2}, {"unseen_min_stretch_m": 0.2, "unseen_source": "carved",
                "unseen_measure": "cells"}, {"unseen_min_stretch_m": -0.1, "unseen_source": "carved"}):  # fmt: skip
        with pytest.raises(InputError, match="unseen_min_stretch_m"):
            NBVConfig(**bad)


def test_unseen_term_builds_only_what_its_settings_use_and_measures_the_scorers_u(world: World) -> None:
    """nbv.unseen.UnseenTerm.build, once per scoring call: the box around the surface voxels (none with an infinite
    margin); the carved grid only for ``unseen_source="carved"`` and a map that renders; the TSDF's normals only for
    the map's render with back-face test "tsdf", the keyframes' renders only for "unconfirmed"; a plan only with
    ``unseen_plan_views`` > 1. Its measure of each candidate is the U the scorer reports."""
    from roigsf_ros.nbv.unseen import UnseenTerm, unseen_box

    vox = NBVScorer().surface(world.tsdf)
    size = world.tsdf.voxel_size_m

    def build(surfel_map: SurfelMap = world.map, **kw: object) -> UnseenTerm:
        return UnseenTerm.build(NBVConfig(unseen_weight=1.0, **kw), surfel_map, vox, size, world.train, INTR)

    plain = build()
    np.testing.assert_array_equal(np.stack(plain.box), np.stack(unseen_box(vox, plain.cfg)))
    assert np.all(plain.box[0] < vox.centres_m.min(0)) and np.all(plain.box[1] > vox.centres_m.max(0))
    assert (plain.space, plain.facing, plain.seen_by, plain.plan) == (None, None, None, None)
    assert build(unseen_bbox_margin_m=float("inf")).box is None
    assert build(unseen_backfaces="tsdf").facing is not None
    seen_by = build(unseen_backfaces="unconfirmed").seen_by
    assert seen_by is not None and len(seen_by.poses) == len(world.train)
    carved = build(unseen_source="carved", unseen_backfaces="unconfirmed")
    assert carved.space is not None and carved.seen_by is None and carved.plan is None
    assert build(unseen_source="carved", unseen_plan_views=2).plan == {}
    assert build(unseen_source="carved", unseen_measure="rays", unseen_rarity=1.0).plan == {}
    empty = SurfelMap.empty(dtype=world.map.dtype)
    assert build(empty, unseen_source="carved").space is None
    for kw in ({}, {"unseen_source": "carved"}, {"unseen_measure": "area"}):
        cfg = NBVConfig(unseen_weight=1.0, **kw)
        res = NBVScorer(cfg).score(world.map, world.h_train, world.tsdf, world.train, world.candidates, INTR)
        term = build(**kw)
        intr_f = downsampled(INTR, cfg.fisher_downsample)
        for i in range(len(world.candidates)):
            assert term.measure(world.map, world.candidates[i], i, intr_f) == pytest.approx(res.unseen[i], abs=1e-12)


def test_unseen_plan_views_scores_a_candidate_with_the_views_that_would_complete_it(world: World) -> None:
    """``unseen_plan_views``: with 1 the scorer's U is each candidate's carved pixel fraction; with 2 it is what the
    candidate and its best partner show together, built from the carved grid's entry cells of each view (the
    library's plan over them), never less than the candidate's own, and the same cell seen by both counted once."""
    from roigsf_ros.nbv import UnseenCells, carved_space, planned_unseen, rays_meet_box

    behind = look_at(np.array([3.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), UP)
    beside = look_at(np.array([3.0, 0.4, 1.0]), np.array([2.0, 0.0, 1.0]), UP)
    cands = np.stack([world.view_a, behind, beside])
    cfg = NBVConfig(unseen_weight=1.0, unseen_source="carved")

    def scored(config: NBVConfig) -> np.ndarray:
        return NBVScorer(config).score(world.map, world.h_train, world.tsdf, world.train, cands, INTR).unseen

    own = scored(cfg)
    assert scored(replace(cfg, unseen_plan_views=1)) == pytest.approx(own, abs=0)
    planned = scored(replace(cfg, unseen_plan_views=2))
    vox = NBVScorer().surface(world.tsdf)
    lo, hi = vox.centres_m.min(0) - 0.1, vox.centres_m.max(0) + 0.1
    space = carved_space(world.map, world.train, INTR, lo, hi, cfg)
    views = [
        UnseenCells.from_pixels(space.unseen_cells(T, INTR, cfg.near_m, cfg.far_m), rays_meet_box(T, INTR, lo, hi))
        for T in cands
    ]
    assert [v.fraction for v in views] == pytest.approx(own)
    assert planned == pytest.approx(planned_unseen(views, 2))
    assert np.all(planned >= own - 1e-12) and planned[0] > own[0]  # the front view's partner sees A's back
    # behind and beside look at the same back of A: together they add less than their two fractions
    assert planned[1] < own[1] + own[2]
    _, frontier = space.unseen_frontier(behind, INTR, cfg.near_m, cfg.far_m)
    assert set(views[1].cells.tolist()) <= set(frontier.tolist())


def test_unseen_rarity_divides_each_unseen_pixel_by_the_candidates_looking_into_its_block(world: World) -> None:
    """``unseen_rarity``: the scorer's U is the carved grid's entry cells of each candidate (each pixel weighed 1, or
    its stretch in cells for rays; their sum is the direct U to rounding) with each cell's share over n^beta, n the
    candidates entering its block. The two views behind A look into the same back of it, so with beta 1 each keeps
    about half of its U (the front view sees no unseen space either way), and no U grows."""
    from roigsf_ros.nbv import UnseenCells, carved_space, planned_unseen, rarity_blocks, rarity_weighted, rays_meet_box

    behind = look_at(np.array([3.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), UP)
    beside = look_at(np.array([3.0, 0.4, 1.0]), np.array([2.0, 0.0, 1.0]), UP)
    cands = np.stack([world.view_a, behind, beside])
    vox = NBVScorer().surface(world.tsdf)
    lo, hi = vox.centres_m.min(0) - 0.1, vox.centres_m.max(0) + 0.1

    def scored(config: NBVConfig) -> np.ndarray:
        return NBVScorer(config).score(world.map, world.h_train, world.tsdf, world.train, cands, INTR).unseen

    for measure in ("rays", "pixels"):
        cfg = NBVConfig(unseen_weight=1.0, unseen_source="carved", unseen_measure=measure)
        space = carved_space(world.map, world.train, INTR, lo, hi, cfg)
        views = []
        for T in cands:
            enter, leave, cell = space.unseen_rays(T, INTR, cfg.near_m, cfg.far_m)
            weight = (leave - enter) / space.voxel_m if measure == "rays" else None
            views.append(UnseenCells.from_pixels(cell, rays_meet_box(T, INTR, lo, hi), weight))
        direct = scored(cfg)
        assert [v.fraction for v in views] == pytest.approx(direct, rel=1e-9)
        for beta, block_m in ((1.0, 0.1), (0.5, 0.25)):
            rare = scored(replace(cfg, unseen_rarity=beta, unseen_rarity_block_m=block_m))
            want = planned_unseen(rarity_weighted(views, beta, rarity_blocks(space, block_m)), 1)
            assert rare == pytest.approx(want, rel=1e-9)
            assert np.all(rare <= direct + 1e-12)
        rare = scored(replace(cfg, unseen_rarity=1.0))
        assert direct[1] > 0.1 and direct[2] > 0.1
        assert 0.3 * direct[1] < rare[1] < 0.75 * direct[1] and 0.3 * direct[2] < rare[2] < 0.75 * direct[2]
    block_of = rarity_blocks(space, 0.1)  # 4 cells of 2.5 cm a side
    ids = block_of(np.ravel_multi_index(([0, 3, 4, 0], [0, 3, 0, 0], [0, 0, 0, 7]), space.state.shape))
    assert ids[0] == ids[1] and len(set(ids.tolist())) == 3


def test_unseen_min_std_floors_only_the_unseen_terms_divisor(world: World) -> None:
    """``unseen_min_std``: the unseen term is ``kappa (U - mean U) / max(std U, floor)`` over the scored candidates,
    beside the paper's unchanged Eq. 15. Floor 0 is the plain z-score; a floor far above U's spread leaves the paper's
    ranking, so Fisher and close-front decide when the candidates' U hardly differ."""
    cands = np.stack(
        [
            world.view_a,
            look_at(np.array([3.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), UP),
            look_at(np.array([-0.5, 0.6, 1.2]), np.array([2.0, 0.0, 1.0]), UP),
            look_at(np.array([0.2, -0.7, 0.9]), np.array([2.0, 0.3, 1.0]), UP),
            look_at(np.array([0.8, 0.1, 1.0]), np.array([2.0, -0.4, 1.1]), UP),
        ]
    )

    def scored(config: NBVConfig) -> NBVResult:
        return NBVScorer(config).score(world.map, world.h_train, world.tsdf, world.train, cands, INTR)

    paper = scored(NBVConfig())
    plain = scored(NBVConfig(unseen_weight=2.0))
    ok = ~plain.flagged
    u = plain.unseen[ok]
    assert ok.sum() >= 3 and u.std() > 0
    np.testing.assert_allclose(plain.fused[ok], paper.fused[ok] + 2.0 * zscore(u), atol=1e-9)
    for floor in (u.std() / 2, 3 * u.std()):
        floored = scored(NBVConfig(unseen_weight=2.0, unseen_min_std=float(floor)))
        np.testing.assert_array_equal(floored.unseen, plain.unseen)
        expect = paper.fused[ok] + 2.0 * (u - u.mean()) / max(u.std(), floor)
        np.testing.assert_allclose(floored.fused[ok], expect, atol=1e-9)
    far_above = scored(NBVConfig(unseen_weight=2.0, unseen_min_std=1e6))
    np.testing.assert_array_equal(far_above.ranking, paper.ranking)
    with pytest.raises(InputError, match="unseen_min_std"):
        NBVConfig(unseen_min_std=-0.01)


def test_a_zero_weight_drops_its_term_and_epsilon_0_renders_no_fisher(world: World, monkeypatch) -> None:
    """Issue 10's ablations of the fused score: ``epsilon=0`` drops z(F) and skips H_train and every Fisher render,
    ``delta=0`` drops z(I_vis); the other terms keep their weights. All three weights 0 leave no score: refused."""
    import roigsf_ros.nbv.scorer as scorer_mod

    cands = np.stack(
        [
            world.view_a,
            world.view_b,
            look_at(np.array([3.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), UP),
            look_at(np.array([0.8, 0.1, 1.0]), np.array([2.0, -0.4, 1.1]), UP),
        ]
    )
    full = NBVConfig(unseen_weight=1.0, unseen_source="carved")
    ref = NBVScorer(full).score(world.map, world.h_train, world.tsdf, world.train, cands, INTR)
    ok = ~ref.flagged
    assert ok.sum() >= 3 and ref.fisher[ok].std() > 0 and ref.close_front[ok].std() > 0 and ref.unseen[ok].std() > 0
    z_f, z_c, z_u = zscore(ref.fisher[ok]), zscore(ref.close_front[ok]), zscore(ref.unseen[ok])
    calls = []
    monkeypatch.setattr(scorer_mod, "fisher_weighted_sum", lambda *a, **k: calls.append(1) or 0.0)
    monkeypatch.setattr(NBVScorer, "train_fisher", lambda *a, **k: calls.append(2) or {})
    no_f = NBVScorer(replace(full, epsilon=0.0)).score(world.map, None, world.tsdf, world.train, cands, INTR)
    assert calls == [] and not no_f.fisher.any()
    state = ScoringState(replace(full, epsilon=0.0), 0.04, 0.12, 10.0, cache_h_train=True)  # as the planner node
    _, _, h = state.update(world.map, None, ("color", "depth"), np.stack(world.train), INTR,
                           lambda T: world.renderer.render(T, INTR)[::-1])  # fmt: skip
    assert h is None and calls == []  # no H_train for a score without F
    assert full.uses_fisher() and not replace(full, epsilon=0.0).uses_fisher() and not full.uses_fisher("close-front")
    np.testing.assert_array_equal(no_f.flagged, ref.flagged)
    np.testing.assert_allclose(no_f.fused[ok], 0.6 * z_c + z_u, atol=1e-9)
    monkeypatch.undo()
    no_c = NBVScorer(replace(full, delta=0.0)).score(world.map, world.h_train, world.tsdf, world.train, cands, INTR)
    np.testing.assert_allclose(no_c.fused[ok], 0.4 * z_f + z_u, atol=1e-9)
    u_only = NBVScorer(replace(full, epsilon=0.0, delta=0.0)).score(world.map, None, world.tsdf, world.train, cands,
                                                                      INTR)  # fmt: skip
    np.testing.assert_allclose(u_only.fused[ok], z_u, atol=1e-9)
    assert u_only.best_index == int(np.flatnonzero(ok)[np.argmax(ref.unseen[ok])])
    with pytest.raises(InputError, match="no term"):
        NBVConfig(epsilon=0.0, delta=0.0)
    with pytest.raises(InputError, match="epsilon"):
        NBVConfig(epsilon=-0.1)


def test_fisherrf_weight_adds_the_z_scored_fisherrf_score_and_0_is_the_method_as_before(world: World) -> None:
    """``fisherrf_weight`` kappa_r (beyond the paper) adds kappa_r z(R), R the scores mode ``fisherrf`` gives the same
    candidates, over the candidates the other terms are z-scored on; 0 leaves every score as it was, to the bit."""
    cands = np.stack(
        [
            world.view_a,
            world.view_b,
            look_at(np.array([0.8, 0.1, 1.0]), np.array([2.0, -0.4, 1.1]), UP),
            world.view_up,
        ]
    )
    base_cfg = NBVConfig(unseen_weight=1.0, unseen_source="carved")
    ref = NBVScorer(base_cfg).score(world.map, world.h_train, world.tsdf, world.train, cands, INTR)
    same = NBVScorer(replace(base_cfg, fisherrf_weight=0.0)).score(world.map, world.h_train, world.tsdf, world.train,
                                                                     cands, INTR)  # fmt: skip
    np.testing.assert_array_equal(same.fused, ref.fused)
    assert "fisherrf_term" not in same.timings_s
    rf = NBVScorer(base_cfg).score(world.map, None, None, world.train, cands, INTR, mode="fisherrf")
    ok = ~ref.flagged
    assert ok.sum() >= 3 and rf.fisher[ok].std() > 0
    for kappa in (0.5, 2.0):
        out = NBVScorer(replace(base_cfg, fisherrf_weight=kappa)).score(world.map, world.h_train, world.tsdf,
                                                                        world.train, cands, INTR)  # fmt: skip
        np.testing.assert_array_equal(out.flagged, ref.flagged)
        np.testing.assert_allclose(out.fused[ok], ref.fused[ok] + kappa * zscore(rf.fisher[ok]), rtol=1e-12, atol=1e-12)
        assert (out.fused[~ok] == 0.0).all() and out.timings_s["fisherrf_term"] > 0
    # The term alone decides when the others are off: the pick is FisherRF's among the candidates that see surface.
    rf_only = NBVScorer(NBVConfig(epsilon=0.0, delta=0.0, fisherrf_weight=1.0))
    alone = rf_only.score(world.map, None, world.tsdf, world.train, cands, INTR)
    assert alone.best_index == int(np.flatnonzero(ok)[np.argmax(rf.fisher[ok])])
    with pytest.raises(InputError, match="fisherrf_weight"):
        NBVConfig(fisherrf_weight=-1.0)
    with pytest.raises(InputError, match="no term"):
        NBVConfig(epsilon=0.0, delta=0.0, fisherrf_weight=0.0)


def test_surface_facing_marks_points_on_the_back_of_the_tsdf_surface(world: World) -> None:
    """``unseen_backfaces="tsdf"``'s test: a pixel is back-facing where its point lies in a surface voxel's cell and
    that voxel's outward normal points away from the camera; a point in no surface voxel's cell is not."""
    behind = look_at(np.array([3.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), UP)
    vox = NBVScorer().surface(world.tsdf)
    facing = SurfaceFacing.build(vox, world.tsdf.voxel_size_m)
    depth = np.full((INTR.height, INTR.width), 1.0)
    front, back = facing.backfacing(world.view_a, INTR, depth * 1.5), facing.backfacing(behind, INTR, depth)
    assert not front.any() and back[INTR.height // 2, INTR.width // 2] and back.mean() > 0.7
    assert not facing.backfacing(behind, INTR, depth * 0.5).any()  # 0.5 m in front of A: free space, no voxel
    assert not facing.backfacing(behind, INTR, np.zeros_like(depth)).any()  # no rendered surface


def test_unseen_term_ignores_rays_that_miss_the_mapped_region(world: World) -> None:
    """Rays that never meet the box of the mapped surface (an object scene's background, the sky) are not unseen
    surface: the view straight up sees only such rays and gets U = 0."""
    from roigsf_ros.nbv import rays_meet_box

    lo, hi = np.array([-1.0, -1.0, -1.0]), np.array([1.0, 1.0, 1.0])
    inside = rays_meet_box(np.eye(4), INTR, lo, hi)
    assert inside.all()  # a camera inside the box: every ray meets it
    away = np.eye(4)
    away[:3, 3] = [0.0, 0.0, 3.0]  # outside, looking +z, away from the box
    assert not rays_meet_box(away, INTR, lo, hi).any()
    towards = look_at(np.array([0.0, 0.0, -3.0]), np.zeros(3), np.array([0.0, -1.0, 0.0]))
    hits = rays_meet_box(towards, INTR, lo, hi)
    assert hits[INTR.height // 2, INTR.width // 2] and 0 < hits.mean() < 1  # the box fills the image centre only
    sky = look_at(np.array([0.0, 0.0, 3.0]), np.array([0.0, 0.0, 5.0]), np.array([1.0, 0.0, 0.0]))  # above the map
    cands = np.stack([world.view_a, world.view_b, sky])
    res = NBVScorer(NBVConfig(unseen_weight=1.0)).score(world.map, world.h_train, world.tsdf, world.train, cands, INTR)
    assert res.unseen[2] == 0.0 and res.flagged[2]
    res = NBVScorer(NBVConfig(unseen_weight=1.0, unseen_bbox_margin_m=float("inf"))).score(
        world.map, world.h_train, world.tsdf, world.train, cands, INTR
    )
    assert res.unseen[2] == 1.0 and not res.flagged[2]  # without the box every empty pixel counts


def test_box_exit_depth_is_where_the_ray_leaves_the_box() -> None:
    """The depth at which ``unseen_measure="area"`` puts unseen surface: from inside a box, looking down +z, the
    centre ray leaves through the far face (z = 3) and the corner ray, 32 deg off in x, through the side x = -1
    first; a box behind the camera is never met (0)."""
    from roigsf_ros.nbv import box_exit_depth, rays_meet_box

    lo, hi = np.array([-1.0, -1.0, -1.0]), np.array([1.0, 1.0, 3.0])
    z = box_exit_depth(np.eye(4), INTR, lo, hi)
    assert z[INTR.height // 2, INTR.width // 2] == pytest.approx(3.0)
    assert z[0, 0] == pytest.approx(50.0 / 31.5)  # x = -1 at depth fx / cx
    assert rays_meet_box(np.eye(4), INTR, lo, hi).all()
    behind = np.eye(4)
    behind[:3, 3] = [0.0, 0.0, 4.0]
    assert not box_exit_depth(behind, INTR, lo, hi).any() and not rays_meet_box(behind, INTR, lo, hi).any()


def test_unseen_area_weighs_each_unseen_pixel_by_its_footprint(world: World) -> None:
    """``unseen_measure="area"``: a map of panel A only, in a TSDF that also holds panel B. A near and a far view of
    unmapped B both see only unseen pixels (the fractions tie), but the far one shows about 3x the surface; the near
    one's U is the footprint (z / fx)(z / fy) at the box's far face summed over the image; a view of A's back (the
    surfel test) puts its unseen surface at the back's rendered depth, 1 m, not at the box's face 4 m farther."""
    map_a = world.map.select(torch.arange(world.n_a))
    near = look_at(np.array([-0.9, 0.0, 1.0]), np.array([-2.0, 0.0, 1.0]), UP)
    far = look_at(np.array([0.6, 0.0, 1.0]), np.array([-2.0, 0.0, 1.0]), UP)
    behind = look_at(np.array([3.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), UP)
    cands = np.stack([near, far, behind])
    base = NBVConfig(unseen_weight=1.0, unseen_backfaces="surfels")
    h = NBVScorer().train_fisher(map_a, world.train[:3], INTR)
    args = (map_a, h, world.tsdf, world.train, cands, INTR)
    pixels = NBVScorer(base).score(*args).unseen
    area = NBVScorer(replace(base, unseen_measure="area")).score(*args).unseen
    assert pixels[0] == pytest.approx(1.0) and pixels[1] == pytest.approx(1.0, abs=0.01)
    vox = NBVScorer().surface(world.tsdf)
    z_face = -0.9 - (vox.centres_m[:, 0].min() - 0.1)  # from x = -0.9 to the box's face at x = min - 0.1
    assert area[0] == pytest.approx(INTR.width * INTR.height * z_face**2 / (INTR.fx * INTR.fy), rel=0.01)
    assert area[1] > 2.5 * area[0]  # 3.1x: the box's sides cut the far view's edge rays short
    n_back = pixels[2] * rays_meet_count(behind, vox)
    assert pixels[2] > 0.7 and area[2] == pytest.approx(n_back / (INTR.fx * INTR.fy), rel=0.1)
    with pytest.raises(InputError, match="unseen_measure"):
        NBVConfig(unseen_measure="volume")
    with pytest.raises(InputError, match="finite unseen_bbox_margin_m"):
        NBVConfig(unseen_measure="area", unseen_bbox_margin_m=float("inf"))


def rays_meet_count(T_wc: np.ndarray, vox: object) -> int:
    """Pixels of ``T_wc`` whose ray meets the unseen term's box (default margin 0.1 m) around the surface voxels."""
    from roigsf_ros.nbv import rays_meet_box

    c = vox.centres_m  # type: ignore[attr-defined]
    return int(rays_meet_box(T_wc, INTR, c.min(0) - 0.1, c.max(0) + 0.1).sum())


def test_information_gain_is_eq10_summed_over_the_parameters() -> None:
    """Eq. 10 with the denominators precomputed once per score() call equals the plain per-entry formula."""
    g = torch.Generator().manual_seed(3)
    f = {"means": torch.rand(50, 3, generator=g), "log_scales": torch.rand(50, 2, generator=g)}
    h = {k: torch.rand(v.shape, generator=g) * 10 for k, v in f.items()} | {"quats": torch.ones(50, 4)}
    plain = sum(float((f[k].double() / (h[k].double() + 0.1)).sum()) for k in f)
    assert information_gain(f, h, 0.1) == pytest.approx(plain, rel=1e-12)
    inv = inverse_denominators(h, {k: tuple(v.shape) for k, v in f.items()}, 0.1)
    assert gain_with(f, inv) == pytest.approx(plain, rel=1e-12)
    with pytest.raises(InputError, match="no entry 'opacity_logits'"):
        information_gain(f | {"opacity_logits": torch.ones(50, 1)}, h, 0.1)
    with pytest.raises(InputError, match="'means' has shape"):
        information_gain({"means": torch.ones(49, 3)}, h, 0.1)


@pytest.mark.skipif(not numba_available(), reason="numba is not installed")
def test_compare_candidate_cost_script_alternates_the_two_checkouts(tmp_path: Path) -> None:
    """scripts/compare_candidate_cost.py (a ratio in docs/measured-figures.md): base and new children, alternately."""
    root = Path(__file__).resolve().parents[1]
    script = root / "scripts" / "compare_candidate_cost.py"
    out = tmp_path / "cmp.json"
    small = ["--rounds", "1", "--repeats", "3", "--surfels", "1500", "--width", "64", "--height", "48"]
    res = subprocess.run([sys.executable, str(script), str(root), str(root), *small, "--out", str(out)],
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr
    got = json.loads(out.read_text())
    assert [r["checkout"] for r in got["runs"]] == ["base", "new"]
    for r in got["runs"]:
        roi, rf = r["roi-gsurfisher"], r["fisherrf"]
        assert roi["train_fwd_bwd_ms"] > 0 and roi["roi_ms"] > 0 and roi["fisher_ms"] > 0 and rf["roi_ms"] < 0.01
        assert roi["ratio_candidate_over_train"] > roi["ratio_fisher_over_train"] > 0
    assert "candidate / training step" in res.stdout
    bad = subprocess.run([sys.executable, str(script), str(tmp_path), str(root)], capture_output=True, text=True)
    assert bad.returncode == 2 and "not a checkout" in bad.stderr


_WARM_CHILD = r"""
import json
import sys
sys.path.insert(0, sys.argv[1])
import roigsf_ros  # first: it sets OMP_WAIT_POLICY before torch loads
from roigsf_ros.nbv.warmup import compiled_signatures, warm_up_kernels
from roigsf_ros.render.numba_setup import set_numba_threads

set_numba_threads(2)
warm_up_kernels()
from roigsf_ros.nbv import roi
from roigsf_ros.nbv.config import RECOMMENDED_UNSEEN, NBVConfig
from roigsf_ros.nbv.scorer import NBVScorer
from roigsf_ros.perf import nbv

before = compiled_signatures()
print("LISTED", json.dumps(before))
scorer = NBVScorer()
st = nbv.build_state(2000, 80, 60, 4, 0.04, scorer)
for mode in ("roi-gsurfisher", "fisherrf"):
    for cands in (st.candidates[:1], st.candidates):
        scorer.score(st.surfel_map, st.h_train[mode], st.tsdf, st.train_poses, cands, st.intr, mode=mode)
recommended = NBVScorer(NBVConfig(**RECOMMENDED_UNSEEN))
res = recommended.score(st.surfel_map, st.h_train["roi-gsurfisher"], st.tsdf, st.train_poses, st.candidates, st.intr)
print("UNSEEN", res.timings_s["unseen"])
after = compiled_signatures()
new = {k: sorted(set(v) - set(before.get(k, []))) for k, v in after.items() if set(v) - set(before.get(k, []))}
print("LONE", len(roi._BATCH_KERNELS.dispatchers()["lone"].signatures))
print("NEW", new)
"""


@pytest.fixture(scope="module")
def warm_child() -> dict[str, str]:
    """What a fresh interpreter with two numba threads compiled in ``warm_up_kernels`` and after it (``_WARM_CHILD``).

    One run shared by the tests below (a warm cache: about 10 s; cold, the compile itself)."""
    if not numba_available():
        pytest.skip("no numba")
    res = subprocess.run([sys.executable, "-c", _WARM_CHILD, str(Path(__file__).resolve().parents[1])],
                         capture_output=True, text=True, timeout=900)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    lines = {ln.split(" ", 1)[0]: ln.split(" ", 1)[1] for ln in res.stdout.splitlines() if " " in ln}
    if int(lines["LONE"]) == 0:
        pytest.skip("numba runs one thread here: the lone-candidate ROI kernel is never used")
    return lines


def test_warm_up_compiles_every_kernel_a_planner_request_uses(warm_child: dict[str, str]) -> None:
    """After ``warm_up_kernels`` (what set-up and the planner run first), scoring one candidate alone and a window of
    them in both Fisher modes, and the window with the recommended unseen term (its carved grid), adds no kernel
    signature: on a fresh machine nothing compiles during a request. A fresh interpreter, two numba threads (the lone
    candidate's ROI kernel needs more threads than candidates)."""
    assert float(warm_child["UNSEEN"]) > 0  # the recommended variant did build and march its carved grid
    assert warm_child["NEW"] == "{}", warm_child["NEW"]


def test_kernel_signature_list_is_what_the_warm_up_compiles(warm_child: dict[str, str]) -> None:
    """The package's kernel signature list (what ``warmup --jobs N`` compiles on N processes before the warm-up) names
    exactly the kernels and argument types the real warm-up compiles: a list that drifted from the code would leave
    kernels to the one-core warm-up (a slower set-up) or compile signatures nothing calls."""
    got = json.loads(warm_child["LISTED"])
    listed = {row["kernel"]: sorted(row["signatures"]) for row in warmup.load_signature_list()}
    diff = {k: (listed.get(k), got.get(k)) for k in sorted(set(got) | set(listed)) if listed.get(k) != got.get(k)}
    assert not diff, (
        f"{warmup.SIGNATURES_PATH.name} differs from what the warm-up compiles (listed, compiled): {diff}; rewrite it "
        "with `.venv/bin/python scripts/kernel_compile_times.py --write-signatures` (a cold compile, about 150 s)"
    )
    assert all(float(row["compile_s"]) > 0 for row in warmup.load_signature_list())  # the split's weights


def test_split_by_cost_deals_every_row_once_into_balanced_shares() -> None:
    """``warmup --jobs N`` splits the cold compile by the listed compile times: the longest first, each to the lightest
    share so far; every kernel in exactly one share, no empty share, one share when asked for one."""
    rows = [{"kernel": f"m:G.k{i}", "compile_s": s, "signatures": []} for i, s in enumerate([16, 46, 5, 20, 19, 16, 3])]
    shares = warmup.split_by_cost(rows, 2)
    assert sorted(r["kernel"] for share in shares for r in share) == sorted(r["kernel"] for r in rows)
    assert [[r["compile_s"] for r in share] for share in shares] == [[46, 16], [20, 19, 16, 5, 3]]  # 62 s and 63 s
    assert len(warmup.split_by_cost(rows, 12)) == len(rows) and len(warmup.split_by_cost(rows, 1)) == 1


def test_kernel_signatures_read_back_as_numba_types() -> None:
    """Each listed signature (numba's repr of the argument types) reads back as the same types, and nothing but a
    tuple of numba types is accepted."""
    from numba.core import types

    rows = warmup.load_signature_list()
    assert rows and all(row["signatures"] for row in rows)
    for row in rows:
        for text in row["signatures"]:
            sig = warmup.parse_signature(text)
            assert repr(sig) == text and all(isinstance(t, types.Type) for t in sig)
    assert warmup.parse_signature("(Array(float32, 2, 'C', False, aligned=True), int64)") == (
        types.Array(types.float32, 2, "C"),
        types.int64,
    )
    for not_a_signature in ("int64", "(int64, 3)"):
        with pytest.raises(ValueError, match="not a signature tuple"):
            warmup.parse_signature(not_a_signature)
    with pytest.raises(NameError):
        warmup.parse_signature("(open('x'),)")  # no builtins


def test_parallel_compile_reports_a_bad_list_and_compiles_nothing(tmp_path: Path) -> None:
    """A missing, malformed or stale signature list is no error for set-up: the parallel compile reports it (naming
    the file or the kernel) and the warm-up after it compiles everything on one core."""
    missing = warmup.compile_in_parallel(2, tmp_path / "absent.json")
    assert missing["jobs"] == 0 and "absent.json" in missing["error"]
    bad = tmp_path / "bad.json"
    bad.write_text('{"kernels": [{"kernel": "no-colon"}]}')
    assert "bad.json: not a kernel signature list" in warmup.compile_in_parallel(2, bad)["error"]
    stale = tmp_path / "stale.json"
    stale.write_text(json.dumps({"kernels": [{"kernel": "roigsf_ros.render.fisher:_FISHER_KERNELS.gone",
                                              "compile_s": 1.0, "signatures": ["(int64,)"]}]}))  # fmt: skip
    res = warmup.compile_in_parallel(2, stale)
    assert res["jobs"] == 0 and "_FISHER_KERNELS.gone" in res["error"] and "stale" in res["error"]


@pytest.mark.skipif(not numba_available(), reason="no numba")
def test_parallel_compile_reports_a_failed_child(tmp_path: Path) -> None:
    """A compiling child that fails (here: a signature that is not one) is reported by what it was compiling and its
    exit status, while this process's own share still compiles (the warm-up after it redoes the rest)."""
    rows = sorted(warmup.load_signature_list(), key=lambda r: float(r["compile_s"]))[:2]
    bad = {**rows[0], "compile_s": 0.0, "signatures": ["(int64, 3)"]}  # the lighter share: the child's
    listed = tmp_path / "one_bad.json"
    listed.write_text(json.dumps({"kernels": [{**rows[1], "compile_s": 1.0}, bad]}))
    res = warmup.compile_in_parallel(2, listed)
    assert res["jobs"] == 2 and res["signatures"] == len(rows[1]["signatures"])
    assert f"compiling ['{bad['kernel']}'] exited 1" in res["error"]


_PARALLEL_CHILD = r"""
import json, sys
from pathlib import Path
sys.path.insert(0, sys.argv[1])
from numba.core import event
from roigsf_ros.nbv import warmup

path = Path(sys.argv[3])
if sys.argv[2] == "compile":
    print(json.dumps(warmup.compile_in_parallel(2, path)))
else:
    with event.install_recorder("numba:compile") as rec:
        n = warmup.compile_listed(warmup.load_signature_list(path))
    print(json.dumps({"signatures": n, "compiles": sum(1 for _, ev in rec.buffer if ev.is_start)}))
"""


@pytest.mark.skipif(not numba_available(), reason="no numba")
def test_parallel_compile_fills_the_cache_another_process_only_loads(tmp_path: Path) -> None:
    """``compile_in_parallel`` on 2 processes, into an empty numba cache, compiles each listed signature in one of
    them (the parent and a child of the same roigsf_ros copy); a later process then loads every one from the disk
    cache and compiles nothing. The list's three quickest kernels, to keep it short."""
    rows = sorted(warmup.load_signature_list(), key=lambda r: float(r["compile_s"]))[:3]
    listed = tmp_path / "quick.json"
    listed.write_text(json.dumps({"kernels": rows}))
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba_cache"))
    root = str(Path(__file__).resolve().parents[1])
    runs = []
    for step in ("compile", "load"):
        res = subprocess.run([sys.executable, "-c", _PARALLEL_CHILD, root, step, str(listed)], env=env,
                             capture_output=True, text=True, timeout=600)  # fmt: skip
        assert res.returncode == 0, res.stderr[-3000:]
        runs.append(json.loads(res.stdout.splitlines()[-1]))
    n = sum(len(r["signatures"]) for r in rows)
    assert runs[0] == {"jobs": 2, "seconds": runs[0]["seconds"], "signatures": n, "error": ""}
    assert runs[1] == {"signatures": n, "compiles": 0}


def test_installed_package_carries_the_kernel_signature_list() -> None:
    """Set-up compiles the *installed* copy (``python -m roigsf_ros.nbv.warmup --jobs N`` run outside the checkout),
    so the list must be package data of the installed copy, not only a file of the checkout."""
    probe = "import pathlib, roigsf_ros; print(pathlib.Path(roigsf_ros.__file__).parent)"
    res = subprocess.run([sys.executable, "-c", probe], cwd="/", capture_output=True, text=True, timeout=60)
    root = Path(__file__).resolve().parents[1]
    if res.returncode != 0 or Path(res.stdout.strip()) == root / "roigsf_ros":
        pytest.skip("roigsf_ros is not installed in this interpreter (run scripts/setup.sh)")
    installed = Path(res.stdout.strip()) / "nbv" / "kernel_signatures.json"
    assert installed.is_file(), f"{installed} missing: setup.py's package_data must carry it"


def test_warmup_seed_from_must_be_a_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--seed-from`` (set-up: the installed copy's roigsf_ros folder) names a missing folder in its error, before any
    kernel is compiled or loaded."""
    with pytest.raises(SystemExit) as exc:
        warmup.main(["--jobs", "1", "--seed-from", str(tmp_path / "no_such_copy")])
    assert exc.value.code == 2
    assert f"--seed-from: {tmp_path / 'no_such_copy'} is not a folder" in capsys.readouterr().err


def test_scoring_state_for_map_takes_the_maps_mesh_settings() -> None:
    """``ScoringState.for_map``: the scoring TSDF of ``score_views`` and the stream policies (the map's mesh voxel,
    its truncation at least a voxel, its depth range), overridable; the constructor's positional voxel, truncation and
    depth were easy to give in the wrong order, and each caller worked them out again."""
    from roigsf_ros.core.errors import InputError
    from roigsf_ros.mapping.mapper import MapperConfig

    cfg = MapperConfig(mesh_voxel_size_m=0.03, mesh_sdf_trunc_m=0.05, max_depth_m=6.0)
    state = ScoringState.for_map(cfg)
    assert (state.voxel_size_m, state.sdf_trunc_m, state.depth_max_m) == (0.03, 0.05, 6.0)
    assert state.config == NBVConfig() and state.train_fisher_cache is None
    assert ScoringState.for_map(cfg, voxel_size_m=0.08).sdf_trunc_m == 0.08  # a coarser voxel: truncated at one voxel
    kept = ScoringState.for_map(cfg, NBVConfig(mode="fisherrf"), 0.05, 0.2, cache_h_train=True)
    assert (kept.voxel_size_m, kept.sdf_trunc_m, kept.config.mode) == (0.05, 0.2, "fisherrf")
    assert kept.train_fisher_cache is not None
    with pytest.raises(InputError, match="config: expected a NBVConfig, got MapperConfig"):
        ScoringState.for_map(cfg, cfg)  # type: ignore[arg-type]
