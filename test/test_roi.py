"""View ROI (Eq. 7-8): voxel weights, visibility (facing, frustum, occlusion), splatting, texture test."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import open3d as o3d
import pytest
import torch

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.data.scene import look_at
from roigsf_ros.evaluation.metrics import raycast_depth, raycasting_scene
from roigsf_ros.mapping.tsdf import SurfaceVoxels, TSDFVolume
from roigsf_ros.nbv.close_front import close_front_gain
from roigsf_ros.nbv.config import NBVConfig
from roigsf_ros.nbv.roi import (
    batch_roi,
    coverage_weight,
    footprint_weight,
    frustum_union,
    incidence_weight,
    view_roi,
    voxel_texture,
    voxel_visibility,
    voxel_weight,
)
from roigsf_ros.render.surfels import SH_C0, SurfelMap

CFG = NBVConfig()
INTR = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
UP = np.array([0.0, 0.0, 1.0])
EYE = np.eye(4)  # camera at the origin looking down +z (world = camera frame)


def plane_voxels(z: float, x_range: tuple, y_range: tuple, size: float = 0.02, normal_z: float = -1.0) -> SurfaceVoxels:
    """A one-layer grid of voxels on the plane z = const, normals along z (toward the origin for -1)."""
    xs = np.arange(x_range[0], x_range[1] + 1e-9, size)
    ys = np.arange(y_range[0], y_range[1] + 1e-9, size)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    c = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], axis=1)
    n = np.tile([0.0, 0.0, normal_z], (len(c), 1))
    return SurfaceVoxels(c, np.zeros(len(c), np.float32), np.ones(len(c), np.float32), n)


def cat_voxels(*vs: SurfaceVoxels) -> SurfaceVoxels:
    return SurfaceVoxels(*(np.concatenate(parts) for parts in zip(*vs, strict=True)))


# ------------------------------------------------------------------------------- weights
def test_incidence_weight_peaks_at_the_texture_dependent_preferred_angle() -> None:
    theta = np.arange(0.0, 89.5, 0.5)
    poor = incidence_weight(theta, np.zeros(theta.size, bool), CFG)
    rich = incidence_weight(theta, np.ones(theta.size, bool), CFG)
    assert theta[np.argmax(poor)] == 30.0 and theta[np.argmax(rich)] == 40.0
    assert poor.max() == pytest.approx(1.0) and np.all((poor > 0) & (poor <= 1))
    # Frontal and grazing views weigh less than the preferred angle, and the bump is symmetric.
    assert poor[theta == 0.0] < 0.5 and poor[theta == 85.0] < 0.01
    np.testing.assert_allclose(poor[theta == 20.0], poor[theta == 40.0])


def test_footprint_weight_peaks_at_two_and_a_half_pixels() -> None:
    fp = np.geomspace(0.1, 50.0, 2001)
    w = footprint_weight(fp, CFG)
    assert fp[np.argmax(w)] == pytest.approx(2.5, rel=0.01)
    # Symmetric in scale: half and double the preferred footprint weigh the same, exp(-1/2) for ln 2 width.
    np.testing.assert_allclose(footprint_weight(np.array([1.25, 5.0]), CFG), np.exp(-0.5), rtol=1e-3)
    assert footprint_weight(np.array([0.2]), CFG)[0] < 0.05 and footprint_weight(np.array([30.0]), CFG)[0] < 0.05


def test_coverage_favours_weakly_fused_voxels_and_combines_linearly() -> None:
    w = np.array([0.5, 1.0, 2.0, 10.0, 100.0])
    cover = coverage_weight(w)
    np.testing.assert_allclose(cover, [1.0, 1.0, 0.5, 0.1, 0.01])
    assert np.all(np.diff(cover) <= 0)
    theta, tex, fp = np.full(2, 30.0), np.zeros(2, bool), np.full(2, 2.5)
    total, wa, ws, _ = voxel_weight(theta, tex, fp, np.array([1.0, 1e9]), NBVConfig(mu=1.0))
    np.testing.assert_allclose(wa, 1.0)
    np.testing.assert_allclose(ws, 1.0)
    np.testing.assert_allclose(total, [2.0, 1.0], rtol=1e-6)  # (1 + mu W_cover), at most 1 + mu
    total_b, *_ = voxel_weight(np.full(2, 10.0), tex, fp, np.ones(2), NBVConfig(beta=2.0, mu=0.0))
    np.testing.assert_allclose(total_b, incidence_weight(np.full(2, 10.0), tex, CFG) ** 2)


# ---------------------------------------------------------------------------- visibility
def test_visibility_keeps_front_facing_in_frustum_voxels_only() -> None:
    front = plane_voxels(2.0, (-0.4, 0.4), (-0.3, 0.3))
    view = voxel_visibility(front, EYE, INTR, 0.02, CFG)
    assert len(view) == len(front.centres_m)
    np.testing.assert_allclose(view.z_m, 2.0)
    np.testing.assert_allclose(view.footprint_px, 50.0 * 0.02 / 2.0)
    assert np.all(view.cos_incidence > 0.95)
    # Back-facing: the same plane with its normals turned away from the camera.
    back = plane_voxels(2.0, (-0.4, 0.4), (-0.3, 0.3), normal_z=1.0)
    assert len(voxel_visibility(back, EYE, INTR, 0.02, CFG)) == 0
    # Outside the frustum: far to the side, behind the camera, closer than near, beyond far.
    side = plane_voxels(2.0, (3.0, 3.4), (-0.3, 0.3))
    behind = plane_voxels(-2.0, (-0.4, 0.4), (-0.3, 0.3), normal_z=1.0)
    too_near = plane_voxels(0.1, (-0.02, 0.02), (-0.02, 0.02))
    too_far = plane_voxels(CFG.far_m + 1.0, (-0.4, 0.4), (-0.3, 0.3))
    for vox in (side, behind, too_near, too_far):
        assert len(voxel_visibility(vox, EYE, INTR, 0.02, CFG)) == 0
    # Voxels with undefined (zero) normals never count as front-facing.
    zero_n = front._replace(normals=np.zeros_like(front.normals))
    assert len(voxel_visibility(zero_n, EYE, INTR, 0.02, CFG)) == 0


def test_voxels_behind_a_nearer_surface_are_occluded() -> None:
    far = plane_voxels(2.0, (-1.0, 1.0), (-0.7, 0.7))
    near = plane_voxels(1.0, (-0.6, 0.0), (-0.4, 0.4))  # covers the left half of the image
    vox = cat_voxels(far, near)
    n_far = len(far.centres_m)
    view = voxel_visibility(vox, EYE, INTR, 0.02, CFG)
    seen = np.zeros(len(vox.centres_m), bool)
    seen[view.index] = True
    assert seen[n_far:].all()  # the near plane is fully visible
    far_c = far.centres_m
    u = 50.0 * far_c[:, 0] / 2.0 + 31.5
    v = 50.0 * far_c[:, 1] / 2.0 + 23.5
    inside = (u >= -0.5) & (u < 63.5) & (v >= -0.5) & (v < 47.5)
    # Where a far voxel's ray crosses z = 1 m, well inside the near plane (hidden) or well clear of it (seen).
    xc, yc = far_c[:, 0] / 2.0, far_c[:, 1] / 2.0
    hidden_zone = inside & (xc > -0.6 + 0.04) & (xc < -0.04) & (np.abs(yc) < 0.4 - 0.04)
    clear_zone = inside & (xc > 0.04)
    assert hidden_zone.sum() > 100 and clear_zone.sum() > 100
    assert not seen[:n_far][hidden_zone].any()
    assert seen[:n_far][clear_zone].all()
    # Without the occluder the same far voxels are seen.
    alone = voxel_visibility(far, EYE, INTR, 0.02, CFG)
    seen_alone = np.zeros(n_far, bool)
    seen_alone[alone.index] = True
    assert seen_alone[hidden_zone].all()


# ------------------------------------------------------------------------------------ ROI
def test_roi_is_normalised_and_zero_outside_the_projected_surface() -> None:
    left = plane_voxels(2.0, (-2.0, -0.2), (-1.0, 1.0))  # x <= -0.2 m: image columns u <= 26.5
    roi = view_roi(left, 0.02, EYE, INTR, CFG)
    w = roi.weights
    assert w.shape == (48, 64) and np.all(np.isfinite(w))
    assert w.min() >= 0.0 and w.max() <= 1.0
    assert np.all(w[:, 28:] == 0.0)  # beyond the plane's edge (plus the 1 px kernel reach)
    assert np.all(w[:, :26] > 0.0)
    # Frontal at 2 m: W_angle at 0 deg (texture-poor, 30 deg preferred), footprint 0.5 px, cover 1 (weight 1).
    # Interior pixel (row 23, column 20): the ray's incidence angle on the plane, footprint 0.5 px, W_cover 1.
    theta = np.degrees(np.arctan(np.hypot((20 - 31.5) / 50.0, (23 - 23.5) / 50.0)))
    expected = incidence_weight(np.array([theta]), np.zeros(1, bool), CFG) * footprint_weight(np.array([0.5]), CFG)
    assert w[23, 20] == pytest.approx(expected[0], rel=0.03)
    assert roi.n_pixels == int((w > 0).sum()) and roi.mass == pytest.approx(w.sum())


def test_roi_weight_is_independent_of_voxel_density_but_follows_the_preferences() -> None:
    # The same plane sampled 2x denser gives the same interior ROI (a mean, not a sum, per pixel).
    sparse = view_roi(plane_voxels(2.0, (-1.0, 1.0), (-1.0, 1.0), 0.02), 0.02, EYE, INTR, CFG).weights
    dense = view_roi(plane_voxels(2.0, (-1.0, 1.0), (-1.0, 1.0), 0.01), 0.02, EYE, INTR, CFG).weights
    np.testing.assert_allclose(sparse[2:-2, 2:-2], dense[2:-2, 2:-2], rtol=0.02)
    # A plane at the preferred footprint distance (f * 0.02 / z = 2.5 px -> z = 0.4 m) outweighs one at 2 m.
    near = view_roi(plane_voxels(0.4, (-0.3, 0.3), (-0.3, 0.3)), 0.02, EYE, INTR, CFG).weights
    assert near[10:38, 10:54].mean() > 2 * sparse[10:38, 10:54].mean()
    # Nearer voxels get wider kernels: the plane at 0.4 m (2.5 px footprint) still tiles its image densely.
    assert np.all(near[4:44, 4:60] > 0)


def test_roi_of_a_fused_box_matches_its_silhouette() -> None:
    box = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0).translate((-0.5, -0.5, -0.5))
    scene = raycasting_scene(box)
    intr = Intrinsics(80, 60, 60.0, 60.0, 39.5, 29.5)
    vol = TSDFVolume(voxel_size_m=0.04)
    for k in range(6):
        a = 2 * np.pi * k / 6 + 0.2
        T = look_at(np.array([2.5 * np.cos(a), 2.5 * np.sin(a), 1.2 if k % 2 else -1.2]), np.zeros(3), UP)
        vol.integrate(raycast_depth(scene, T, intr), T, intr)
    vox = vol.surface_voxels()
    T = look_at(np.array([2.2, 1.0, 0.8]), np.zeros(3), UP)
    roi = view_roi(vox, vol.voxel_size_m, T, intr, CFG)
    sil = raycast_depth(scene, T, intr) > 0
    outside = cv2.distanceTransform((~sil).astype(np.uint8), cv2.DIST_L2, 5) > 2.0  # > 2 px off the silhouette
    on = roi.weights > 0
    # Projective-TSDF band artefacts at the box's edges put a few voxels off the surface: a tiny share of the mass.
    assert roi.weights[outside].sum() < 0.02 * roi.mass
    # ... and the ROI covers the silhouette: band voxels of 4 cm at ~2.5 m project ~1 px apart, so the
    # 1-px tent kernel leaves a few percent of interior pixels between voxel centres (96 % measured).
    assert (on & sil).sum() >= 0.95 * sil.sum()
    # Back faces (-x, -y, -z) do not contribute: hardly any seen voxel (TSDF-normal artefacts) lies inside one.
    seen = vox.centres_m[roi.view.index]
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        interior = (seen[:, axis] < -0.45) & np.all(np.abs(seen[:, others]) < 0.4, axis=1)
        assert interior.sum() <= 0.005 * len(seen)
    assert (seen[:, 0] > 0.45).sum() > 50 and (seen[:, 1] > 0.45).sum() > 50 and (seen[:, 2] > 0.45).sum() > 50


def _views_equal(a: object, b: object) -> None:
    np.testing.assert_array_equal(a.index, b.index)
    for f in ("u_px", "v_px", "z_m", "cos_incidence", "footprint_px"):
        np.testing.assert_allclose(getattr(a, f), getattr(b, f), rtol=1e-12, atol=1e-12, err_msg=f)
    if len(a) == 0:
        return
    oa, ob = np.lexsort(a.splat[:2]), np.lexsort(b.splat[:2])  # same entries, possibly in another order
    for x, y in zip(a.splat, b.splat, strict=True):
        np.testing.assert_allclose(x[oa], y[ob], rtol=1e-12, atol=1e-14)


def _box_voxels() -> tuple[SurfaceVoxels, Intrinsics]:
    """Surface voxels (4 cm) of a 1 m box fused from 4 views around it, and the 80x60 camera used."""
    box = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0).translate((-0.5, -0.5, -0.5))
    scene = raycasting_scene(box)
    intr = Intrinsics(80, 60, 60.0, 60.0, 39.5, 29.5)
    vol = TSDFVolume(voxel_size_m=0.04)
    for k in range(4):
        a = 2 * np.pi * k / 4 + 0.3
        T = look_at(np.array([2.5 * np.cos(a), 2.5 * np.sin(a), 1.0 if k % 2 else -1.0]), np.zeros(3), UP)
        vol.integrate(raycast_depth(scene, T, intr), T, intr)
    return vol.surface_voxels(), intr


def test_numba_visibility_equals_the_numpy_reference() -> None:
    pytest.importorskip("numba")
    vox, intr = _box_voxels()
    occluded = cat_voxels(plane_voxels(1.0, (-0.2, 0.2), (-0.2, 0.2)), plane_voxels(2.0, (-1.0, 1.0), (-1.0, 1.0)))
    cases = [
        (vox, look_at(np.array([2.2, 1.0, 0.8]), np.zeros(3), UP), intr),  # oblique, ~1 px footprints
        (vox, look_at(np.array([0.9, 0.3, 0.6]), np.zeros(3), UP), intr),  # close: wide splats, capped ones
        (vox, look_at(np.array([3.0, 0.0, 0.0]), np.array([6.0, 0.0, 0.0]), UP), intr),  # looking away: empty
        (occluded, EYE, INTR),  # a near patch hides part of a far plane
    ]
    for voxels, T, cam in cases:
        ref = voxel_visibility(voxels, T, cam, 0.04, CFG, backend="numpy")
        fast = voxel_visibility(voxels, T, cam, 0.04, CFG, backend="numba")
        _views_equal(fast, ref)
        w_ref = view_roi(voxels, 0.04, T, cam, CFG, view=ref).weights
        np.testing.assert_allclose(view_roi(voxels, 0.04, T, cam, CFG).weights, w_ref, rtol=1e-12, atol=1e-15)
    close = voxel_visibility(vox, cases[1][1], intr, 0.04, CFG)
    assert len(close) > 100 and close.footprint_px.max() > 2.0  # the wide-splat branch was exercised
    hidden = voxel_visibility(occluded, EYE, INTR, 0.04, CFG)
    assert 0 < len(hidden) < len(occluded.centres_m)
    with pytest.raises(InputError, match="backend"):
        voxel_visibility(vox, EYE, intr, 0.04, CFG, backend="cuda")


def test_batch_roi_equals_view_roi_and_close_front_candidate_by_candidate() -> None:
    """The candidates' ROI (Eq. 7-8) and I_vis (Eq. 14) in one parallel numba pass equal the per-candidate reference."""
    pytest.importorskip("numba")
    vox, intr = _box_voxels()
    rng = np.random.default_rng(3)
    m = len(vox.centres_m)
    textured, frontier, w_f = rng.random(m) < 0.4, rng.random(m) < 0.2, rng.random(m) * 0.5
    poses = np.stack([
        look_at(np.array([2.2, 1.0, 0.8]), np.zeros(3), UP),  # oblique
        look_at(np.array([0.9, 0.3, 0.6]), np.zeros(3), UP),  # close: wide splats, capped ones
        look_at(np.array([3.0, 0.0, 0.0]), np.array([6.0, 0.0, 0.0]), UP),  # looking away: empty
        look_at(np.array([-1.5, -1.8, -0.4]), np.zeros(3), UP),
        look_at(np.array([0.2, -2.0, 1.5]), np.array([0.0, 0.0, 0.3]), UP),
    ])  # fmt: skip
    for cfg in (CFG, replace(CFG, frontier_weight=0.5, beta=2.0, gamma=0.5, mu=0.5)):  # numba: W_a^b W_s^g as one exp
        fast = batch_roi(vox, 0.04, poses, intr, cfg, textured, frontier, w_f, backend="numba")
        ref = batch_roi(vox, 0.04, poses, intr, cfg, textured, frontier, w_f, backend="numpy")
        for i, T in enumerate(poses):
            r = view_roi(vox, 0.04, T, intr, cfg, textured, frontier=frontier)
            assert fast.n_visible_voxels[i] == ref.n_visible_voxels[i] == len(r.view)
            assert fast.n_pixels[i] == ref.n_pixels[i] == r.n_pixels
            np.testing.assert_allclose(fast.weights[i], r.weights, rtol=1e-12, atol=1e-15)
            np.testing.assert_allclose(ref.weights[i], r.weights, rtol=0, atol=0)
            assert fast.mass[i] == pytest.approx(r.mass, rel=1e-12, abs=1e-15)
            gain = close_front_gain(r.view, w_f)
            assert fast.close_front[i] == pytest.approx(gain, rel=1e-12) and ref.close_front[i] == pytest.approx(gain)
    assert fast.n_visible_voxels[2] == 0 and (fast.n_visible_voxels[[0, 1, 3, 4]] > 50).all()
    assert (fast.close_front[[0, 1, 3, 4]] > 0).all()
    union = frustum_union(vox, poses, intr, CFG)  # where texture is needed: in some candidate's frustum
    want = np.zeros(m, bool)
    for T in poses:
        want[voxel_visibility(vox, T, intr, 0.04, CFG, backend="numpy").index] = True
    assert (union >= want).all() and union[~want].any()
    one = frustum_union(vox, poses[1:2], intr, CFG)  # the close view: part of the box
    assert one.any() and not one.all() and (union >= one).all()
    ref = np.zeros(m, bool)
    for T in poses:  # in front within near..far and projecting into the image, as the ROI's frustum test
        pc = (vox.centres_m - T[:3, 3]) @ T[:3, :3]
        u, v = intr.fx * pc[:, 0] / pc[:, 2] + intr.cx, intr.fy * pc[:, 1] / pc[:, 2] + intr.cy
        ref |= (pc[:, 2] > CFG.near_m) & (pc[:, 2] <= CFG.far_m) & (u >= -0.5) & (u < 79.5) & (v >= -0.5) & (v < 59.5)
    np.testing.assert_array_equal(union, ref)
    no_wf = batch_roi(vox, 0.04, poses, intr, CFG)
    assert not no_wf.close_front.any() and no_wf.mass[0] > 0
    for i in (0, 1, 3):  # no texture given: every voxel texture-poor, as view_roi
        np.testing.assert_allclose(no_wf.weights[i], view_roi(vox, 0.04, poses[i], intr, CFG).weights,
                                   rtol=1e-12, atol=1e-15)  # fmt: skip
    with pytest.raises(InputError, match="fused_weight"):
        batch_roi(vox, 0.04, poses, intr, CFG, fused_weight=np.zeros(3))


def test_batch_roi_of_a_lone_camera_split_over_its_voxels(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fewer cameras than threads: each camera's voxels split into blocks (any number) give the reference's ROI."""
    pytest.importorskip("numba")
    from roigsf_ros.nbv import roi as roi_mod

    vox, intr = _box_voxels()
    rng = np.random.default_rng(4)
    m = len(vox.centres_m)
    textured, frontier, w_f = rng.random(m) < 0.4, rng.random(m) < 0.2, rng.random(m) * 0.5
    poses = [look_at(np.array([2.2, 1.0, 0.8]), np.zeros(3), UP), look_at(np.array([0.9, 0.3, 0.6]), np.zeros(3), UP),
             look_at(np.array([3.0, 0.0, 0.0]), np.array([6.0, 0.0, 0.0]), UP)]  # fmt: skip
    cfg = replace(CFG, frontier_weight=0.5, mu=0.5)
    monkeypatch.setattr(roi_mod, "_LONE_MIN_VOXELS", 0)
    for parts in (2, 3, 7):
        monkeypatch.setattr(roi_mod, "n_threads", lambda parts=parts: parts)
        for T in poses:
            fast = batch_roi(vox, 0.04, T[None], intr, cfg, textured, frontier, w_f, backend="numba")
            ref = batch_roi(vox, 0.04, T[None], intr, cfg, textured, frontier, w_f, backend="numpy")
            assert fast.n_visible_voxels[0] == ref.n_visible_voxels[0]
            assert fast.n_pixels[0] == ref.n_pixels[0]
            np.testing.assert_allclose(fast.weights, ref.weights, rtol=1e-12, atol=1e-15)
            assert fast.mass[0] == pytest.approx(ref.mass[0], rel=1e-12, abs=1e-15)
            assert fast.close_front[0] == pytest.approx(ref.close_front[0], rel=1e-12, abs=1e-15)
        assert fast.n_visible_voxels[0] == 0  # the last pose looks away
    one = batch_roi(vox, 0.04, poses[0][None], intr, cfg, textured, frontier, w_f)
    assert one.n_visible_voxels[0] > 50 and one.mass[0] > 0  # the first pose sees the box


def test_numba_voxel_weights_equal_eq7_from_grazing_to_frontal_and_tiny_to_huge_footprints() -> None:
    """The kernels' Eq. 7 (vectorised arccos and exp, scratch rows) against Eq. 7 in extended precision and against
    :func:`voxel_weight` (numpy's) where its factors have not underflowed, over the weight's whole range: incidence
    cosines from back-facing to frontal, footprints from below the 1e-12 clamp to 1e8 px (weights under 1e-180),
    any fusion weight, texture and frontier."""
    pytest.importorskip("numba")
    from roigsf_ros.nbv import roi as roi_mod

    roi_mod._BATCH_KERNELS["batch"]  # compiles the helpers as the kernels use them
    rng = np.random.default_rng(7)
    n, m = 20_000, 30_000
    cos = np.concatenate([rng.uniform(-0.2, 1.0, n - 5), [0.0, 1.0, -1.0, 1e-9, 0.5]])
    fp = np.geomspace(1e-14, 1e8, n)[rng.permutation(n)]
    geo = np.column_stack([np.zeros(n), np.zeros(n), np.ones(n), cos, fp])
    rows = rng.integers(0, m, n)
    tsdf_w, textured, frontier = rng.uniform(0, 30, m), rng.random(m) < 0.4, rng.random(m) < 0.2
    for cfg in (CFG, replace(CFG, frontier_weight=0.5, beta=2.0, gamma=0.5, mu=0.5)):
        prm = np.array([cfg.angle_pref_texture_poor_deg, cfg.angle_pref_texture_rich_deg, cfg.angle_sigma_deg,
                        cfg.footprint_pref_px, cfg.footprint_sigma_ln, cfg.beta, cfg.gamma, cfg.mu,
                        cfg.frontier_weight])  # fmt: skip
        out = np.full((4, n), np.nan)
        roi_mod._voxel_weights(geo, rows, n, tsdf_w, textured, frontier, prm, cfg.frontier_weight > 0, *out)
        theta = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        numpy_w = voxel_weight(theta, textured[rows], fp, tsdf_w[rows], cfg)[0]
        factor = (1.0 + cfg.mu / np.maximum(tsdf_w[rows], 1.0)) * (
            (1.0 + cfg.frontier_weight * frontier[rows]) / (1.0 + cfg.frontier_weight)
        )
        if cfg.frontier_weight > 0:
            numpy_w = numpy_w * (1.0 + cfg.frontier_weight * frontier[rows]) / (1.0 + cfg.frontier_weight)
        # numpy's W_angle^beta W_scale^gamma underflows factor by factor (W_scale = 0 where the product is 1e-170):
        # Eq. 7 as one exp in extended precision is the reference everywhere, numpy's where it has not underflowed
        L = np.longdouble
        ta = (np.degrees(np.arccos(np.clip(cos, -1.0, 1.0).astype(L))) - np.where(textured[rows], prm[1], prm[0])) / L(
            prm[2]
        )
        tf = np.log(np.maximum(fp, 1e-12).astype(L) / L(prm[3])) / L(prm[4])
        exact = (np.exp(-0.5 * (L(prm[5]) * ta * ta + L(prm[6]) * tf * tf)) * factor.astype(L)).astype(np.float64)
        assert exact.min() < 1e-180 and exact.max() > 0.5 and (numpy_w == 0).any()  # the range was covered
        np.testing.assert_allclose(out[0], exact, rtol=1e-12, atol=1e-300)
        big = numpy_w > 1e-100  # below, its factors can be subnormal (a few digits)
        np.testing.assert_allclose(out[0][big], numpy_w[big], rtol=1e-12)


# ---------------------------------------------------------------------------------- texture
def _patch_map(rng: np.random.Generator, x0: float, noisy: bool) -> SurfelMap:
    g = np.stack(np.meshgrid(np.arange(0, 0.4, 0.01), np.arange(0, 0.4, 0.01), indexing="ij"), -1).reshape(-1, 2)
    means = np.column_stack([g[:, 0] + x0, g[:, 1], np.full(len(g), 2.0)])
    col = rng.uniform(0.1, 0.9, (len(g), 3)) if noisy else np.full((len(g), 3), 0.5)
    n = len(g)
    z = lambda *s: torch.zeros(*s, dtype=torch.float64)  # noqa: E731
    quats = z(n, 4)
    quats[:, 0] = 1.0
    return SurfelMap(torch.tensor(means), quats, z(n, 2) - 4.0, z(n), torch.tensor((col - 0.5) / SH_C0))


def test_texture_test_separates_textured_from_flat_surface() -> None:
    rng = np.random.default_rng(0)
    smap = SurfelMap.cat([_patch_map(rng, 0.0, noisy=True), _patch_map(rng, 1.0, noisy=False)])
    centres = np.array([[0.2, 0.2, 2.0], [1.2, 0.2, 2.0], [5.0, 5.0, 5.0]])
    tex = voxel_texture(centres, smap, 0.02, CFG)
    np.testing.assert_array_equal(tex, [True, False, False])  # noisy, flat, no surfels nearby
    assert not voxel_texture(centres, None, 0.02, CFG).any()
    assert not voxel_texture(centres, SurfelMap.empty(dtype=torch.float64), 0.02, CFG).any()
    only = np.array([True, False, True])  # classified voxels equal the full test's; the others come back False
    np.testing.assert_array_equal(voxel_texture(centres, smap, 0.02, CFG, only=only), [True, False, False])
    np.testing.assert_array_equal(voxel_texture(centres, smap, 0.02, CFG, only=~only), [False, False, False])
    with pytest.raises(InputError, match="only"):
        voxel_texture(centres, smap, 0.02, CFG, only=np.ones(2, bool))


# -------------------------------------------------------------------------------- bad input
def test_roi_bad_inputs() -> None:
    vox = plane_voxels(2.0, (-0.2, 0.2), (-0.2, 0.2))
    with pytest.raises(InputError, match="textured"):
        view_roi(vox, 0.02, EYE, INTR, CFG, textured=np.zeros(3, bool))
    with pytest.raises(InputError, match="voxel_size_m"):
        view_roi(vox, 0.0, EYE, INTR, CFG)
    bad = EYE.copy()
    bad[0, 0] = 2.0
    with pytest.raises(InputError, match="rigid"):
        view_roi(vox, 0.02, bad, INTR, CFG)
    empty = SurfaceVoxels(np.zeros((0, 3)), np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros((0, 3)))
    roi = view_roi(empty, 0.02, EYE, INTR, CFG)
    assert roi.weights.shape == (48, 64) and not roi.weights.any() and roi.n_pixels == 0


def test_frontier_mask_marks_the_edge_of_the_observed_surface_and_weights_it() -> None:
    """Beyond the paper: a wall seen once, frontally, at 2 m. Its frontier voxels (a never-observed 6-neighbour)
    lie at the edge of the view's footprint, not inside; frontier_weight raises their share of the ROI."""
    from roigsf_ros.data.scene import MeshRenderer

    wall = o3d.geometry.TriangleMesh.create_box(6.0, 6.0, 0.05).translate((-3.0, -3.0, 2.0))
    T = look_at(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0]))
    rgb, depth = MeshRenderer(wall).render(T, INTR)
    tsdf = TSDFVolume(voxel_size_m=0.04, sdf_trunc_m=0.16)
    tsdf.integrate(depth, T, INTR, rgb)
    vox = tsdf.surface_voxels()
    fr = tsdf.frontier_mask(vox)
    assert fr.shape == (len(vox.centres_m),) and 0 < fr.sum() < 0.3 * len(fr)
    u = INTR.fx * vox.centres_m[:, 0] / vox.centres_m[:, 2] + INTR.cx  # camera at the origin looking +z
    v = INTR.fy * vox.centres_m[:, 1] / vox.centres_m[:, 2] + INTR.cy
    border = np.minimum.reduce([u + 0.5, INTR.width - 0.5 - u, v + 0.5, INTR.height - 0.5 - v])
    assert np.mean(border[fr] < 3.0) > 0.9  # frontier voxels: at the edge of the observed footprint
    assert np.mean(fr[border > 4.0]) < 0.02  # inside it: (almost) none
    # In the ROI: with frontier_weight, frontier voxels weigh (1 + f) times the others; 0 = the paper's weights.
    cand = look_at(np.array([0.5, 0.3, 0.2]), np.array([0.0, 0.0, 2.0]), np.array([0.0, -1.0, 0.0]))
    paper = view_roi(vox, 0.04, cand, INTR, NBVConfig(), frontier=fr)
    boosted = view_roi(vox, 0.04, cand, INTR, NBVConfig(frontier_weight=3.0), frontier=fr)
    np.testing.assert_allclose(paper.voxel_weight, view_roi(vox, 0.04, cand, INTR, NBVConfig()).voxel_weight)
    f_in = fr[boosted.view.index]
    assert f_in.any() and (~f_in).any()
    ratio = boosted.voxel_weight / paper.voxel_weight
    np.testing.assert_allclose(ratio[f_in], 1.0)
    np.testing.assert_allclose(ratio[~f_in], 0.25)
    assert boosted.weights.max() <= 1.0
    with pytest.raises(InputError):
        NBVConfig(frontier_weight=-1.0)
