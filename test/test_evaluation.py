"""Image metrics, mesh metrics (with GT culling), AUSE and the comparison strip."""

from __future__ import annotations

import json
import math
import warnings
from types import SimpleNamespace

import cv2
import numpy as np
import open3d as o3d
import pytest
import torch
from skimage.metrics import structural_similarity

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.evaluation.metrics import (
    ause,
    depth_l1,
    gt_visible_mask,
    mesh_metrics,
    psnr,
    raycast_depth,
    render_metrics,
    sample_surface,
    save_comparison_strip,
    ssim,
    to_json_safe,
)


def grid_plane(x0: float, x1: float, y0: float, y1: float, z: float = 0.0, n: int = 20) -> o3d.geometry.TriangleMesh:
    """A flat [x0, x1] x [y0, y1] rectangle at height z, triangulated on an n x n grid, normal +z."""
    xs, ys = np.linspace(x0, x1, n + 1), np.linspace(y0, y1, n + 1)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    verts = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris))


def down_camera(x: float, y: float, height: float) -> np.ndarray:
    """Camera-to-world pose at (x, y, height) looking straight down -z (OpenCV axes)."""
    T = np.eye(4)
    T[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    T[:3, 3] = [x, y, height]
    return T


# ---------------------------------------------------------------------------------------------- images


def test_psnr_of_known_mse_and_input_forms() -> None:
    gt = np.zeros((8, 10, 3))
    pred = np.full((8, 10, 3), 0.1)  # MSE = 0.01 -> 20 dB
    assert psnr(pred, gt) == pytest.approx(20.0, abs=1e-9)
    assert psnr(gt, gt) == math.inf
    # uint8 inputs are divided by 255; torch channel-first inputs are accepted.
    assert psnr(np.full((8, 10, 3), 51, np.uint8), np.zeros((8, 10, 3), np.uint8)) == pytest.approx(
        -10 * math.log10(0.2**2)
    )
    assert psnr(torch.full((3, 8, 10), 0.1), torch.zeros(3, 8, 10)) == pytest.approx(20.0, abs=1e-5)
    with pytest.raises(InputError):
        psnr(np.zeros((8, 10, 3)), np.zeros((8, 11, 3)))


def test_ssim_identical_noisy_and_matches_skimage() -> None:
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.random((48, 64, 3)), (7, 7), 2.0)
    assert ssim(img, img) == pytest.approx(1.0)
    noisy = np.clip(img + rng.normal(0, 0.05, img.shape), 0, 1)
    value = ssim(noisy, img)
    assert value < 0.95
    direct = structural_similarity(
        noisy, img, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False
    )
    assert value == pytest.approx(direct, abs=1e-12)
    assert ssim(torch.from_numpy(noisy).permute(2, 0, 1), img) == pytest.approx(direct, abs=1e-6)


def test_depth_l1_ignores_invalid_ground_truth() -> None:
    gt = np.full((4, 5), 2.0)
    pred = np.full((4, 5), 2.5)
    gt[0, 0], gt[0, 1], gt[0, 2] = 0.0, np.nan, np.inf  # invalid GT: ignored even with huge errors
    pred[0, :3] = 100.0
    assert depth_l1(pred, gt) == pytest.approx(0.5)
    pred[1, 0] = 0.0  # a hole in the render counts with its full error unless valid_pred_only
    assert depth_l1(pred, gt) == pytest.approx((16 * 0.5 + 2.0) / 17)
    assert depth_l1(pred, gt, valid_pred_only=True) == pytest.approx(0.5)
    pred[1, 1] = np.nan  # a non-finite prediction is never counted
    assert np.isfinite(depth_l1(pred, gt))
    assert depth_l1(torch.from_numpy(pred), torch.from_numpy(gt)) == pytest.approx(depth_l1(pred, gt))
    with pytest.raises(InputError):
        depth_l1(pred, gt[:, :4])
    with pytest.raises(InputError):
        depth_l1(pred, np.zeros_like(gt))


# ---------------------------------------------------------------------------------------------- meshes


def test_sample_surface_is_area_weighted_and_seeded() -> None:
    # Two triangles of areas 0.5 and 1.5 (disjoint, in the z = 0 plane).
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [8, 0, 0], [5, 1, 0]], float)
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector([[0, 1, 2], [3, 4, 5]])
    )
    pts = sample_surface(mesh, 40_000, seed=3)
    assert np.mean(pts[:, 0] >= 5) == pytest.approx(0.75, abs=0.01)
    small = pts[pts[:, 0] < 5]
    assert np.all(small[:, 0] + small[:, 1] <= 1 + 1e-9) and np.all(small >= -1e-12)
    # Uniform inside the triangle: the centroid of the samples is the triangle's centroid.
    assert small[:, :2].mean(0) == pytest.approx([1 / 3, 1 / 3], abs=0.01)
    np.testing.assert_array_equal(pts, sample_surface(mesh, 40_000, seed=3))
    assert not np.array_equal(pts, sample_surface(mesh, 40_000, seed=4))


def test_mesh_metrics_self_is_perfect() -> None:
    box = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 0.5)
    m = mesh_metrics(box, box, n_samples=20_000)
    for key in ("precision@1cm", "recall@1cm", "fscore@1cm", "precision@5cm", "recall@5cm", "fscore@5cm"):
        assert m[key] == 1.0, key
    assert m["accuracy_cm"] < 1e-3 and m["completion_cm"] < 1e-3
    assert m["completion_ratio_5cm"] == 1.0
    assert m["n_pred_samples"] == m["n_gt_samples"] == 20_000 and m["gt_observed_fraction"] == 1.0


def test_mesh_metrics_warns_of_unit_mistakes() -> None:
    """A walk: thresholds in cm given as metres were reported as ``@100cm``/``@500cm``, and a ground truth in
    millimetres against a map in metres gave recall 0, both without a word. Each is warned about; metres are not."""
    box = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 0.5)
    with pytest.warns(RuntimeWarning, match=r"taus_m \[5.0\] are metres \(500 cm\)"):
        mesh_metrics(box, box, taus_m=(0.01, 5.0), n_samples=2_000)
    mm = o3d.geometry.TriangleMesh.create_box(1000.0, 2000.0, 500.0)
    with pytest.warns(RuntimeWarning, match=r"1000x apart: meshes in different units"):
        mesh_metrics(box, mm, n_samples=2_000)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh_metrics(box, o3d.geometry.TriangleMesh.create_box(0.2, 0.2, 0.2), n_samples=2_000)  # 10x: a part


def test_mesh_metrics_shifted_by_3cm() -> None:
    gt = grid_plane(0, 2, 0, 1)
    pred = grid_plane(0, 2, 0, 1, z=0.03)
    m = mesh_metrics(pred, gt, taus_m=(0.01, 0.025, 0.05), n_samples=20_000)
    assert m["precision@1cm"] == 0.0 and m["recall@1cm"] == 0.0 and m["fscore@1cm"] == 0.0
    assert m["precision@2.5cm"] == 0.0
    assert m["precision@5cm"] == 1.0 and m["recall@5cm"] == 1.0 and m["fscore@5cm"] == 1.0
    assert m["accuracy_cm"] == pytest.approx(3.0, abs=1e-3)
    assert m["completion_cm"] == pytest.approx(3.0, abs=1e-3)
    assert m["completion_ratio_5cm"] == 1.0


def test_mesh_metrics_half_reconstruction_and_culling() -> None:
    gt = grid_plane(0, 2, 0, 1)
    half = grid_plane(0, 1, 0, 1)
    m = mesh_metrics(half, gt, n_samples=40_000)
    assert m["precision@1cm"] == 1.0
    assert m["recall@1cm"] == pytest.approx(0.505, abs=0.01)  # x < 1.01 of a 2 m wide plane
    assert m["completion_ratio_5cm"] == pytest.approx(0.525, abs=0.01)
    assert m["completion_cm"] > 10.0

    # Cameras 1 m above the plane that only see x in [0.05, 0.95]: recall against the observed GT is 1.
    intr = Intrinsics(90, 100, 100.0, 100.0, 44.5, 49.5)  # half-width 0.45 m, half-height 0.5 m at 1 m
    poses = np.stack([down_camera(0.5, 0.5, 1.0), down_camera(0.5, 0.4, 1.0)])
    culled = mesh_metrics(half, gt, n_samples=40_000, observed_poses=poses, intr=intr)
    assert culled["recall@1cm"] == 1.0 and culled["completion_ratio_5cm"] == 1.0
    assert culled["precision@1cm"] == 1.0  # precision is still against the full GT
    assert culled["gt_observed_fraction"] == pytest.approx(0.45, abs=0.01)
    assert culled["n_gt_samples"] == pytest.approx(0.45 * 40_000, rel=0.03)
    with pytest.raises(InputError):
        mesh_metrics(half, gt, observed_poses=poses)  # intrinsics missing


def test_gt_visible_mask_occlusion_and_range() -> None:
    # Two parallel planes: the camera above sees the upper one; the lower one is hidden behind it.
    upper = grid_plane(0, 1, 0, 1, z=0.5)
    lower = grid_plane(0, 1, 0, 1, z=0.0)
    both = upper + lower
    intr = Intrinsics(64, 64, 40.0, 40.0, 31.5, 31.5)
    pose = down_camera(0.5, 0.5, 1.5)
    pts_up = sample_surface(upper, 2000, seed=0)
    pts_low = sample_surface(lower, 2000, seed=1)
    vis = gt_visible_mask(np.concatenate([pts_up, pts_low]), both, [pose], intr)
    assert vis[:2000].all() and not vis[2000:].any()
    # Without the occluder, the lower plane is seen; beyond max depth it is not.
    assert gt_visible_mask(pts_low, lower, [pose], intr).all()
    assert not gt_visible_mask(pts_low, lower, [pose], intr, max_depth_m=1.4).any()
    # A camera looking away sees nothing.
    away = pose.copy()
    away[:3, :3] = np.diag([1.0, 1.0, 1.0])  # looking up +z
    assert not gt_visible_mask(pts_up, upper, [away], intr).any()


def test_mesh_metrics_empty_prediction_is_json_safe() -> None:
    gt = grid_plane(0, 1, 0, 1)
    m = mesh_metrics(o3d.geometry.TriangleMesh(), gt, n_samples=5_000)
    assert m["precision@1cm"] == 0.0 and m["recall@1cm"] == 0.0 and m["fscore@5cm"] == 0.0
    assert m["completion_ratio_5cm"] == 0.0 and m["n_pred_samples"] == 0
    assert math.isinf(m["accuracy_cm"]) and math.isinf(m["completion_cm"])
    safe = to_json_safe(m)
    assert safe["accuracy_cm"] is None and safe["completion_cm"] is None and safe["recall@5cm"] == 0.0
    json.dumps(safe, allow_nan=False)
    assert to_json_safe({"a": np.float32(np.nan), "b": np.arange(2), "c": (np.int64(3), np.bool_(True))}) == {
        "a": None,
        "b": [0, 1],
        "c": [3, True],
    }
    with pytest.raises(InputError):
        mesh_metrics(gt, o3d.geometry.TriangleMesh())  # empty ground truth


def test_mesh_metrics_deterministic_in_seed() -> None:
    gt = o3d.geometry.TriangleMesh.create_sphere(0.5, resolution=20)
    pred = o3d.geometry.TriangleMesh.create_sphere(0.51, resolution=12)
    a = mesh_metrics(pred, gt, n_samples=10_000, seed=7)
    assert a == mesh_metrics(pred, gt, n_samples=10_000, seed=7)
    b = mesh_metrics(pred, gt, n_samples=10_000, seed=8)
    assert a != b
    assert a["accuracy_cm"] == pytest.approx(b["accuracy_cm"], rel=0.05)


# ---------------------------------------------------------------------------------------------- AUSE


def test_ause_perfect_random_reversed() -> None:
    rng = np.random.default_rng(0)
    err = rng.random(50_000)
    perfect = ause(err, err)
    assert perfect["ause"] == pytest.approx(0.0, abs=1e-12) and perfect["ause_raw"] == pytest.approx(0.0, abs=1e-12)
    assert perfect["ratios"][0] == 0.0 and perfect["ratios"][-1] == pytest.approx(0.999)
    assert len(perfect["curve_oracle"]) == 100 and perfect["curve_oracle"].max() == pytest.approx(1.0)
    informative = ause(err * np.exp(rng.normal(0, 0.5, err.size)), err)["ause"]
    random = ause(rng.random(err.size), err)
    reversed_ = ause(-err, err)
    assert 0.0 < informative < 0.15
    assert random["ause"] > 0.4  # a flat curve against the oracle's fall
    assert reversed_["ause"] > informative and reversed_["ause"] >= random["ause"]
    assert reversed_["ause_raw"] > 1.5 * random["ause_raw"]
    # torch inputs and non-finite pairs are accepted (the latter dropped).
    unc = torch.from_numpy(err.copy())
    unc[0] = float("nan")
    assert ause(unc, err)["ause"] == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(InputError):
        ause(err[:10], err)


def test_ause_normalisation_rewards_a_reversed_ranking() -> None:
    """Heavy-tailed errors: the reversed map's normalised AUSE beats random; raw AUSE and rho expose it."""
    rng = np.random.default_rng(1)
    err = rng.lognormal(0.0, 1.0, 20_000)
    informative = ause(err * np.exp(rng.normal(0, 0.5, err.size)), err)
    random = ause(rng.random(err.size), err)
    reversed_ = ause(-err, err)
    assert reversed_["ause"] < 0.5 * random["ause"]  # the inversion the normalisation causes
    assert reversed_["ause_raw"] > 2.0 * reversed_["ause_random_raw"]
    assert reversed_["spearman_rho"] == pytest.approx(-1.0)
    assert informative["ause_raw"] < 0.2 * informative["ause_random_raw"] and informative["spearman_rho"] > 0.8
    # the seeded random baseline: the same for every map of the same errors, near an actual random map's
    assert random["ause_random_raw"] == informative["ause_random_raw"] == reversed_["ause_random_raw"]
    assert random["ause_raw"] == pytest.approx(random["ause_random_raw"], rel=0.15)
    assert abs(random["spearman_rho"]) < 0.05
    assert ause(-err, err, random_seed=1)["ause_random_raw"] != reversed_["ause_random_raw"]
    assert reversed_["n"] == err.size
    flat = ause(np.zeros(err.size), err)
    assert np.isnan(flat["spearman_rho"]) and np.isfinite(flat["ause_raw"])


# ---------------------------------------------------------------------------------------------- strip


def test_save_comparison_strip(tmp_path: object) -> None:
    rng = np.random.default_rng(0)
    rows = []
    for _ in range(2):
        depth_in = rng.uniform(0.5, 3.0, (30, 40)).astype(np.float32)
        depth_in[0, 0] = 0.0
        rows.append(
            (
                rng.integers(0, 255, (30, 40, 3), dtype=np.uint8),
                torch.from_numpy(rng.random((3, 30, 40))),
                depth_in,
                depth_in + 0.1,
            )
        )
    path = tmp_path / "strip.png"
    grid = save_comparison_strip(path, rows)
    img = cv2.imread(str(path))
    assert img.shape == (60, 160, 3) and grid.shape == (60, 160, 3)
    np.testing.assert_array_equal(img[..., ::-1], grid)
    # The first input tile below the label band is the input image, unchanged; invalid depth is black.
    np.testing.assert_array_equal(grid[20:30, :40], rows[0][0][20:30])
    assert grid[30, 80].tolist() == [0, 0, 0]
    assert [p.name for p in tmp_path.iterdir()] == ["strip.png"]


def test_raycast_depth_of_a_plane() -> None:
    intr = Intrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
    depth = raycast_depth(grid_plane(-5, 5, -5, 5), down_camera(0.0, 0.0, 2.0), intr)
    assert depth.shape == (24, 32) and np.allclose(depth, 2.0, atol=1e-5)


def test_render_metrics_splits_the_error_between_holes_and_the_rest() -> None:
    """With ``covered``, the squared colour error is split between uncovered pixels and the rest."""
    gt = np.full((4, 5, 3), 128, np.uint8)
    pred = np.full((4, 5, 3), 128 / 255 + 0.1)  # every pixel off by 0.1 per channel ...
    pred[0, :2] = 0.0  # ... except two holes, rendered black
    covered = np.ones((4, 5), bool)
    covered[0, :2] = False
    frame = SimpleNamespace(rgb=gt, depth_m=np.ones((4, 5)), T_wc=np.eye(4))

    def render(T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return pred, np.ones((4, 5))

    m = render_metrics(render, [frame, frame], lambda d: d > 0, False, covered=lambda T_wc: covered).means()
    hole_err, rest_err = 2 * 3 * (128 / 255) ** 2, 18 * 3 * 0.1**2
    assert m["uncovered_pixel_fraction"] == pytest.approx(2 / 20)
    assert m["uncovered_error_share"] == pytest.approx(hole_err / (hole_err + rest_err))
    assert m["psnr_covered"] == pytest.approx(20.0)  # MSE 0.01 over the covered pixels
    assert m["psnr"] == pytest.approx(-10 * math.log10((hole_err + rest_err) / 60))
    assert "uncovered_error_share" not in render_metrics(render, [frame], lambda d: d > 0, False).means()
