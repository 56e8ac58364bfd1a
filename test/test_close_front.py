"""Close-front scoring (Eq. 11-14): per-voxel best training observation, candidate gain, memory alignment."""

from __future__ import annotations

import numpy as np
import pytest

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.data.scene import look_at
from roigsf_ros.mapping.tsdf import SurfaceVoxels
from roigsf_ros.nbv.close_front import CloseFrontMemory, close_front_gain, observation_weight, voxel_keys
from roigsf_ros.nbv.config import NBVConfig
from roigsf_ros.nbv.roi import voxel_visibility

CFG = NBVConfig()
INTR = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
VS = 0.02
IMG_UP = np.array([0.0, -1.0, 0.0])  # with this "up", look_at along +z gives the identity rotation


def plane_voxels(z: float, half: float, normal_z: float = -1.0) -> SurfaceVoxels:
    """A square one-layer patch of voxels on z = const centred on the z axis, normals along z."""
    xs = np.arange(-half, half + 1e-9, VS)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    c = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], axis=1)
    n = np.tile([0.0, 0.0, normal_z], (len(c), 1))
    return SurfaceVoxels(c, np.zeros(len(c), np.float32), np.ones(len(c), np.float32), n)


def cam(eye: tuple, target: tuple = (0.0, 0.0, 2.0)) -> np.ndarray:
    return look_at(np.array(eye, float), np.array(target, float), IMG_UP)


PATCH = plane_voxels(2.0, 0.1)  # a 0.2 m patch 2 m in front of the origin, facing it
TRAIN = cam((0.0, 0.0, -1.0))  # frontal, 3 m away


def test_observation_weight_is_cos_over_depth() -> None:
    view = voxel_visibility(PATCH, TRAIN, INTR, VS, CFG)
    assert len(view) == len(PATCH.centres_m)
    w = observation_weight(view)
    d = PATCH.centres_m[view.index] - TRAIN[:3, 3]
    np.testing.assert_allclose(w, (d[:, 2] / np.linalg.norm(d, axis=1)) / d[:, 2], rtol=1e-9)
    assert w.max() == pytest.approx(1 / 3.0, rel=1e-6)


def test_closer_frontal_candidate_beats_a_farther_oblique_one_and_a_repeat_scores_zero() -> None:
    mem = CloseFrontMemory(VS, CFG)
    assert mem.add_view(PATCH, TRAIN, INTR) == len(PATCH.centres_m)
    w_f = mem.fused_weight(PATCH)
    np.testing.assert_allclose(w_f, observation_weight(voxel_visibility(PATCH, TRAIN, INTR, VS, CFG)), rtol=1e-12)

    def gain(T: np.ndarray) -> float:
        return close_front_gain(voxel_visibility(PATCH, T, INTR, VS, CFG), w_f)

    close_front = cam((0.0, 0.0, 1.0))  # 1 m, frontal
    a = np.radians(60.0)
    far_oblique = cam((2.5 * np.sin(a), 0.0, 2.0 - 2.5 * np.cos(a)))  # 2.5 m, 60 deg off the normal
    mid_oblique = cam((1.2 * np.sin(a), 0.0, 2.0 - 1.2 * np.cos(a)))  # 1.2 m, 60 deg
    g_close, g_far, g_mid = gain(close_front), gain(far_oblique), gain(mid_oblique)
    n = len(PATCH.centres_m)
    assert g_close == pytest.approx(n * (1.0 - 1.0 / 3.0), rel=0.02)
    assert g_far == 0.0  # cos/z = 0.5/2.5 < 1/3 everywhere: no improvement
    assert g_close > g_mid > g_far
    assert gain(TRAIN) == 0.0  # the training view itself adds nothing
    # Nothing seen: looking away, or from behind the patch.
    assert gain(cam((0.0, 0.0, 1.0), (0.0, 0.0, -5.0))) == 0.0
    assert gain(cam((0.0, 0.0, 3.0))) == 0.0
    assert close_front_gain(voxel_visibility(PATCH, close_front, INTR, VS, CFG), np.zeros(n)) > g_close


def test_incremental_memory_equals_recomputation_and_follows_a_growing_voxel_set() -> None:
    poses = [TRAIN, cam((0.5, 0.0, 0.5)), cam((-0.3, 0.2, 0.8))]
    mem = CloseFrontMemory(VS, CFG)
    for T in poses:
        mem.add_view(PATCH, T, INTR)
    exact = CloseFrontMemory.from_poses(PATCH, poses, INTR, VS, CFG)
    np.testing.assert_array_equal(mem.fused_weight(PATCH), exact.fused_weight(PATCH))
    assert len(mem.poses) == 3 and len(mem) == len(PATCH.centres_m)
    # The TSDF grows and reorders its voxels: old values follow their voxels, new voxels start unobserved.
    extra = plane_voxels(2.0, 0.2)
    new = ~np.isin(voxel_keys(extra.centres_m, VS), voxel_keys(PATCH.centres_m, VS))
    grown = SurfaceVoxels(*(np.concatenate([a, b[new]]) for a, b in zip(PATCH, extra, strict=True)))
    perm = np.random.default_rng(0).permutation(len(grown.centres_m))
    shuffled = SurfaceVoxels(*(a[perm] for a in grown))
    w = mem.fused_weight(shuffled)
    n_old = len(PATCH.centres_m)
    np.testing.assert_array_equal(w[np.argsort(perm)][:n_old], mem.fused_weight(PATCH))
    assert np.all(w[np.argsort(perm)][n_old:] == 0.0)
    # A new keyframe updates old and new voxels alike.
    mem.add_view(shuffled, cam((0.0, 0.0, 1.5)), INTR)
    assert np.all(mem.fused_weight(PATCH) >= exact.fused_weight(PATCH))
    assert mem.fused_weight(shuffled).min() > 0.0


def test_views_that_do_not_see_a_voxel_leave_its_weight_alone() -> None:
    near = plane_voxels(1.0, 0.3)  # hides the patch from the origin
    vox = SurfaceVoxels(*(np.concatenate([a, b]) for a, b in zip(PATCH, near, strict=True)))
    mem = CloseFrontMemory(VS, CFG)
    mem.add_view(vox, np.eye(4), INTR)
    w = mem.fused_weight(vox)
    n = len(PATCH.centres_m)
    assert np.all(w[:n] == 0.0)  # occluded
    assert np.all(w[n:] > 0.0)
    mem.add_view(vox, cam((0.0, 0.0, 5.0), (0.0, 0.0, 0.0)), INTR)  # behind both: back-facing
    np.testing.assert_array_equal(mem.fused_weight(vox), w)


def test_voxel_keys_and_bad_input() -> None:
    c = np.array([[0.0, 0.0, 0.0], [0.02, -0.04, 0.06], [-0.02, 0.04, -0.06]])
    keys = voxel_keys(c, VS)
    assert len(np.unique(keys)) == 3
    np.testing.assert_array_equal(voxel_keys(c + 0.004, VS), keys)  # rounding to the lattice
    with pytest.raises(InputError, match="beyond"):
        voxel_keys(np.array([[1e5, 0.0, 0.0]]), VS)
    with pytest.raises(InputError, match="voxel_size_m"):
        CloseFrontMemory(-1.0, CFG)
    mem = CloseFrontMemory(VS, CFG)
    with pytest.raises(InputError, match="rigid"):
        mem.add_view(PATCH, np.diag([1.0, 1.0, 2.0, 1.0]), INTR)
    empty = SurfaceVoxels(np.zeros((0, 3)), np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros((0, 3)))
    assert mem.add_view(empty, TRAIN, INTR) == 0
    assert mem.fused_weight(empty).shape == (0,)
    assert np.all(mem.fused_weight(PATCH) == 0.0)


def _plane_rgbd(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth [H, W] of the square z = 2, |x|, |y| <= 0.6 seen from ``T`` (0 where the ray misses it), black colour."""
    u, v = np.meshgrid(np.arange(INTR.width, dtype=float), np.arange(INTR.height, dtype=float))
    d = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)], -1) @ T[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (2.0 - T[2, 3]) / d[..., 2]  # the camera-frame z of the hit (the camera ray has z = 1)
    hit = T[:3, 3] + t[..., None] * d
    ok = (t > 0) & (np.abs(hit[..., 0]) <= 0.6) & (np.abs(hit[..., 1]) <= 0.6)
    return np.where(ok, t, 0.0).astype(np.float32), np.zeros((INTR.height, INTR.width, 3), np.uint8)


def test_scoring_state_folds_each_new_keyframe_into_w_f_once_or_rebuilds_it_when_exact() -> None:
    """Issue 12: W_f was rebuilt from every keyframe pose at each TSDF update (O(keyframes x voxels) per window)."""
    from dataclasses import replace

    from roigsf_ros.nbv.state import ScoringState

    poses = np.stack([cam((-0.5, 0.0, 0.6), (-0.3, 0.0, 2.0)), cam((0.5, 0.0, 0.6), (0.3, 0.0, 2.0)),
                      cam((0.0, 0.4, 1.0), (0.0, 0.45, 2.0))])  # fmt: skip
    for exact in (False, True):
        state = ScoringState(replace(CFG, close_front_exact=exact), VS, 0.08, 10.0)
        state.sync(_plane_rgbd, poses[:2], INTR)
        surf1, mem1 = state.products(poses[:2], INTR, close_front=True)
        ref1 = CloseFrontMemory.from_poses(surf1, poses[:2], INTR, VS, CFG)
        np.testing.assert_array_equal(mem1.fused_weight(surf1), ref1.fused_weight(surf1))
        state.sync(_plane_rgbd, poses, INTR)
        surf2, mem2 = state.products(poses, INTR, close_front=True)
        assert len(surf2.centres_m) > len(surf1.centres_m)  # the third keyframe saw new surface
        assert state.products(poses, INTR, close_front=True)[1] is mem2  # no work without a new keyframe
        if exact:
            want = CloseFrontMemory.from_poses(surf2, poses, INTR, VS, CFG)
            assert (state.close_front_builds, state.close_front_views_added) == (2, 0)
        else:
            want = CloseFrontMemory.from_poses(surf1, poses[:2], INTR, VS, CFG)
            want.add_view(surf2, poses[2], INTR)
            assert (state.close_front_builds, state.close_front_views_added) == (1, 1)
        np.testing.assert_array_equal(mem2.fused_weight(surf2), want.fused_weight(surf2))
        assert (mem2.fused_weight(surf2) > 0).mean() > 0.5
