"""The simulated Kinect v1 sensor (data/sensor.py): noise statistics, holes, determinism, poses, and a
simulated-sensor sequence mapped end to end through ``roigsf scene synth --sensor`` and ``roigsf map``."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from roigsf_ros.cli import main
from roigsf_ros.core.camera import POSE_RIGID_TOL, Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame
from roigsf_ros.data.replica import ReplicaSequence, load_traj, save_traj
from roigsf_ros.data.scene import MeshRenderer, look_at
from roigsf_ros.data.sensor import (
    KINECT_V1_INTRINSICS,
    SensorConfig,
    SensorModel,
    axial_sigma_m,
    measured_poses,
    orthonormality_error,
    projector_shadow,
    quantise_disparity,
    simulate_colour,
    simulate_depth,
)

K1 = KINECT_V1_INTRINSICS
FB = K1.fx * 0.075  # f * b of the Kinect v1 at 640 px (px m)
QUIET = dict(dropout_prob=0.0, disparity_step_px=0.0)  # only the axial noise on a plane


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def _plane(z: float, intr: Intrinsics = K1) -> np.ndarray:
    return np.full((intr.height, intr.width), z, np.float32)


# ------------------------------------------------------------------------------ noise statistics
@pytest.mark.parametrize("z", [0.8, 1.5, 2.5, 3.5])
def test_axial_noise_on_a_plane_matches_nguyen(z: float) -> None:
    """A fronto-parallel plane: zero-mean Gaussian depth error with std 0.0012 + 0.0019 (z - 0.4)^2 (to 2 %)."""
    depth, holes = simulate_depth(_plane(z), None, K1, _rng(), SensorConfig(**QUIET))
    assert holes.total == 0 and (depth > 0).all()
    err = depth.astype(np.float64) - z
    sigma = 0.0012 + 0.0019 * (z - 0.4) ** 2
    assert axial_sigma_m(z) == pytest.approx(sigma)
    assert err.std() == pytest.approx(sigma, rel=0.02)
    assert abs(err.mean()) < 5 * sigma / math.sqrt(err.size) + 1e-6  # float32 depth rounding
    # Gaussian: about 68.3 % within one sigma.
    assert (np.abs(err) < sigma).mean() == pytest.approx(0.683, abs=0.01)


@pytest.mark.parametrize("z", [1.0, 2.0, 3.0])
def test_disparity_quantisation_puts_depth_on_eighth_pixel_steps(z: float) -> None:
    """Depth takes only the values f b / (k / 8); the error's std is that of the noise plus the step's uniform."""
    depth, _ = simulate_depth(_plane(z), None, K1, _rng(1), SensorConfig(dropout_prob=0.0))
    k = FB / depth.astype(np.float64) * 8
    assert np.abs(k - np.round(k)).max() < 1e-3 * k.max() / 8  # float32 storage of the depth
    step = z**2 / FB / 8  # about 1.27 cm at 2 m
    expect = math.sqrt(axial_sigma_m(z) ** 2 + step**2 / 12)
    assert (depth - z).std() == pytest.approx(expect, rel=0.05)
    assert len(np.unique(depth)) < 40  # a few discrete levels, not a continuum
    # Off: the continuum comes back; 0 stays 0.
    assert np.array_equal(quantise_disparity(np.array([0.0, 2.0]), K1.fx, 0.075, 0.0), [0.0, 2.0])
    assert quantise_disparity(np.array([0.0]), K1.fx, 0.075, 0.125)[0] == 0.0


def test_noise_scales_with_the_render_size_as_one_sensor() -> None:
    """A 160 px render simulates the same 640 px sensor: the same quantisation steps in metres."""
    small = K1.resized(160, 120)
    depth, _ = simulate_depth(_plane(2.0, small), None, small, _rng(), SensorConfig(dropout_prob=0.0))
    k = FB / depth.astype(np.float64) * 8  # native f b, not the render's
    assert np.abs(k - np.round(k)).max() < 0.01


# ------------------------------------------------------------------------------------------ holes
def test_range_holes() -> None:
    cfg = SensorConfig(**QUIET)
    for z, expect in ((0.35, 0.0), (0.45, 1.0), (3.9, 1.0), (4.2, 0.0)):
        depth, holes = simulate_depth(_plane(z), None, K1, _rng(), cfg)
        assert (depth > 0).mean() == expect, z
        assert holes.out_of_range == (0 if expect else depth.size)


def test_depths_the_uint16_image_cannot_hold_are_holes_and_counted() -> None:
    """Huge noise or a range beyond the format's: the holes reported are those the written depth PNG has."""
    intr = Intrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5)  # uint16 at 6553.5: up to 10 m
    far = SensorConfig(**QUIET, max_range_m=20.0)
    depth, holes = simulate_depth(_plane(12.0, intr), None, intr, _rng(), far)
    assert (depth == 0).all() and holes.not_storable == holes.total == depth.size
    noisy = SensorConfig(**QUIET, axial_a_m=5.0)
    depth, holes = simulate_depth(_plane(2.0, intr), None, intr, _rng(), noisy)
    stored = np.round(depth.astype(np.float64) * intr.depth_scale)
    assert ((depth == 0) | ((stored >= 1) & (stored <= 65535))).all()  # every depth left fits the PNG
    assert holes.not_storable > 0 and holes.total == int((depth == 0).sum())
    assert SensorModel(noisy).describe()["hole_fractions"]["not_storable"] == 0.0  # nothing seen yet
    mm = Intrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5, depth_scale=1000.0)  # up to 65 m
    depth, holes = simulate_depth(_plane(12.0, mm), None, mm, _rng(), far)
    assert (depth > 0).all() and holes.not_storable == 0


def test_grazing_incidence_holes_and_angle_dependent_noise() -> None:
    cfg = SensorConfig(**QUIET)
    cos = np.full((K1.height, K1.width), math.cos(math.radians(70.0)), np.float32)
    cos[:, 320:] = math.cos(math.radians(80.0))
    depth, holes = simulate_depth(_plane(2.0), cos, K1, _rng(), cfg)
    assert (depth[:, 322:] == 0).all() and holes.grazing == 480 * 320
    inner = depth[:, :318] - 2.0
    assert (depth[:, :318] > 0).all()
    # Nguyen's extra axial term beyond 60 deg: 0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2.
    th = math.radians(70.0)
    expect = axial_sigma_m(2.0) + 0.0001 / math.sqrt(2.0) * th**2 / (math.pi / 2 - th) ** 2
    assert inner.std() == pytest.approx(expect, rel=0.03)
    assert float(axial_sigma_m(2.0, math.radians(50.0))) == pytest.approx(axial_sigma_m(2.0))


def test_projector_shadow_band_is_the_disparity_difference_on_the_side_away_from_the_projector() -> None:
    """A 1 m box in front of a 2 m wall: a band of f b (1/1 - 1/2) = 19.7 px left of the box, nothing right of it."""
    z = _plane(2.0).astype(np.float64)
    z[200:300, 300:400] = 1.0
    shadow = projector_shadow(z, K1.fx, 0.075, side=1)
    cols = np.nonzero(shadow[250])[0]
    width = FB * (1 / 1.0 - 1 / 2.0)
    assert len(cols) == pytest.approx(width, abs=1) and cols.max() == 299  # ends at the box's left edge
    assert not shadow[:200].any() and not shadow[300:].any() and not shadow[:, 300:].any()
    mirrored = projector_shadow(z, K1.fx, 0.075, side=-1)
    assert np.nonzero(mirrored[250])[0].min() == 400 and len(np.nonzero(mirrored[250])[0]) == len(cols)
    assert not projector_shadow(z, K1.fx, 0.075, side=0).any()
    # A plane sloping away (no occluder) casts no shadow on itself.
    slope = 1.0 + 0.004 * np.arange(K1.width)[None, :] * np.ones((K1.height, 1))
    assert not projector_shadow(slope, K1.fx, 0.075).any()
    # Through the whole model: those pixels come out as holes, and the box's own pixels do not.
    depth, holes = simulate_depth(z.astype(np.float32), None, K1, _rng(), SensorConfig(**QUIET))
    assert (depth[250, 283:298] == 0).all() and holes.shadow == shadow.sum()
    assert (depth[205:295, 305:395] > 0).all()


def test_speckle_dropouts_and_lateral_noise_at_edges_only() -> None:
    z = _plane(2.0)
    z[:, 320:] = 1.5  # a step edge between columns 319 and 320
    cfg = SensorConfig(axial_a_m=0.0, axial_b_m_per_m2=0.0, axial_angle_term=False, disparity_step_px=0.0,
                       projector_side=0)  # fmt: skip
    depth, holes = simulate_depth(z, None, K1, _rng(3), cfg)
    assert holes.dropout / holes.pixels == pytest.approx(0.01, abs=0.002)  # 1 % +- 5 binomial sigma
    assert holes.total == holes.dropout and holes.shadow == 0
    # No axial noise: every depth is exact except where lateral noise copied the other side's (at the edge).
    changed = (depth != z) & (depth > 0)
    cols = np.nonzero(changed.any(axis=0))[0]
    assert changed.sum() > 100  # jagged: about a quarter of the 960 edge pixels cross over
    assert cols.min() >= 317 and cols.max() <= 322
    assert set(np.unique(depth[changed])) <= {np.float32(1.5), np.float32(2.0)}


def test_simulated_depth_is_deterministic_per_seed_and_frame() -> None:
    renderer = MeshRenderer(o3d.geometry.TriangleMesh.create_box(1, 1, 1).translate((-0.5, -0.5, 1.5)))
    intr = K1.resized(160, 120)
    T = look_at(np.array([0.3, -0.2, 0.0]), np.array([0.0, 0.0, 2.0]), np.array([0.0, -1.0, 0.0]))
    rgb, depth, cos = renderer.render_with_incidence(T, intr)
    ideal = Frame(index=5, rgb=rgb, depth_m=depth, T_wc=T)
    a = SensorModel(seed=7).frame(ideal, intr, cos)
    b = SensorModel(seed=7).frame(ideal, intr, cos)
    c = SensorModel(seed=8).frame(ideal, intr, cos)
    assert np.array_equal(a.depth_m, b.depth_m) and np.array_equal(a.rgb, b.rgb)
    assert not np.array_equal(a.depth_m, c.depth_m)
    # Each frame draws from its own stream: another frame seen before does not change this one.
    model = SensorModel(seed=7)
    model.frame(Frame(index=4, rgb=rgb, depth_m=depth, T_wc=T), intr, cos)
    assert np.array_equal(model.frame(ideal, intr, cos).depth_m, a.depth_m)
    assert model.holes.pixels == 2 * depth.size


def test_render_with_incidence_gives_the_angle_to_the_surface_normal() -> None:
    """A wall seen 60 deg off its normal: |cos| = 0.5 on the optical axis; the same colour and depth as render()."""
    wall = o3d.geometry.TriangleMesh.create_box(10, 10, 0.01).translate((-5, -5, 2.0))
    renderer = MeshRenderer(wall)
    intr = Intrinsics(width=41, height=31, fx=30.0, fy=30.0, cx=20.0, cy=15.0)
    a = math.radians(60.0)
    T = np.eye(4)
    T[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
    rgb, depth, cos = renderer.render_with_incidence(T, intr)
    assert cos[15, 20] == pytest.approx(0.5, abs=1e-4)
    rgb2, depth2 = renderer.render(T, intr)
    assert np.array_equal(rgb, rgb2) and np.array_equal(depth, depth2)
    assert (cos[depth == 0] == 0).all()


# ----------------------------------------------------------------------------------------- colour
def test_colour_noise_then_jpeg() -> None:
    flat = np.full((96, 128, 3), 120, np.uint8)
    no_jpeg = simulate_colour(flat, _rng(), SensorConfig(jpeg_quality=0))
    assert (no_jpeg.astype(float) - 120).std() == pytest.approx(2.0, rel=0.05)
    out = simulate_colour(flat, _rng(), SensorConfig())
    assert out.shape == flat.shape and out.dtype == np.uint8
    assert not np.array_equal(out, no_jpeg)  # JPEG changed it (smooths the noise)
    assert 0 < (out.astype(float) - 120).std() < 2.0
    with pytest.raises(InputError):
        simulate_colour(flat.astype(np.float32), _rng())


# ------------------------------------------------------------------------------------------ poses
def _loop(n: int) -> np.ndarray:
    poses = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = np.array([1.5 * math.cos(a), 1.5 * math.sin(a), 1.2])
        poses.append(look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0])))
    return np.stack(poses)


def test_poses_are_off_orthonormal_in_range_and_the_loader_re_orthonormalises(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    true = _loop(40)
    written = measured_poses(true, seed=3)
    dev = np.array([orthonormality_error(T[:3, :3]) for T in written])
    assert dev.min() >= 1e-4 * (1 - 1e-6) and dev.max() <= 4e-4 * (1 + 1e-6)
    assert dev.max() - dev.min() > 1.5e-4  # spread over the range, not one value
    assert np.array_equal(written[:, :3, 3], true[:, :3, 3]) and np.array_equal(written[:, 3], true[:, 3])
    assert np.array_equal(measured_poses(true, seed=3), written)
    assert not np.array_equal(measured_poses(true, seed=4), written)
    assert dev.max() < POSE_RIGID_TOL

    save_traj(tmp_path / "traj.txt", written)
    with caplog.at_level(logging.WARNING):
        loaded = load_traj(tmp_path / "traj.txt")
    assert sum("re-orthonormalised" in r.getMessage() for r in caplog.records) == 1  # one warning per file
    for T_true, T in zip(true, loaded, strict=True):
        assert orthonormality_error(T[:3, :3]) < 1e-12 and np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
        assert np.abs(T[:3, :3] - T_true[:3, :3]).max() < 1e-3  # the rotation error is about the deviation


def test_drift_is_a_random_walk_along_the_path() -> None:
    true = _loop(200)  # about 9.4 m of path
    cfg = SensorConfig(drift_trans_m_per_sqrt_m=0.01, drift_rot_deg_per_sqrt_m=0.2)
    runs = np.stack([measured_poses(true, seed=s, config=cfg) for s in range(12)])
    err = np.linalg.norm(runs[:, :, :3, 3] - true[None, :, :3, 3], axis=-1)  # [seed, frame]
    assert (err[:, 0] == 0).all()
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(true[:, :3, 3], axis=0), axis=1))])
    rms_end = math.sqrt((err[:, -1] ** 2).mean())
    assert rms_end == pytest.approx(0.01 * math.sqrt(3 * path[-1]), rel=0.5)  # 3 axes, 12 seeds
    assert math.sqrt((err[:, 20] ** 2).mean()) < rms_end


def test_sensor_config_is_validated_and_named() -> None:
    with pytest.raises(InputError, match="dropout_prob"):
        SensorConfig(dropout_prob=1.5)
    with pytest.raises(InputError, match="pose_ortho_dev_max"):
        SensorConfig(pose_ortho_dev_max=0.05)
    # A min/max pair out of order names both fields: either may be the one the user set.
    with pytest.raises(InputError, match=r"^min_range_m, max_range_m: .* got 5.0 and 4.0"):
        SensorConfig(min_range_m=5.0)
    with pytest.raises(InputError, match=r"^pose_ortho_dev_min, pose_ortho_dev_max: .* got 0.0005 and 0.0004"):
        SensorConfig(pose_ortho_dev_min=5e-4)
    with pytest.raises(InputError, match=r"^max_range_m: must be a finite number"):
        SensorConfig(max_range_m=math.inf)
    with pytest.raises(InputError, match="unknown sensor"):
        SensorModel.named("realsense")
    assert SensorModel.named("kinect", seed=2, dropout_prob=0.05).config.dropout_prob == 0.05


# ----------------------------------------------------------------------------------- end to end
def test_simulated_sensor_sequence_maps_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``scene synth --sensor kinect`` -> ``roigsf map``: no pose refused, holes masked and counted, finite metrics."""
    scene = tmp_path / "room"
    args = ["scene", "synth", "--out", str(scene), "--seed", "2", "--frames", "24", "--width", "160",
            "--sensor", "kinect", "--sensor-seed", "5"]  # fmt: skip
    assert main(args) == 0
    assert "simulated kinect sensor (seed 5)" in capsys.readouterr().out
    info = json.loads((scene / "render.json").read_text())["sensor"]
    assert info["name"] == "kinect" and info["hole_fractions"]["total"] > 0.01
    assert 1e-4 * (1 - 1e-6) <= info["pose_orthonormality_error"][0] <= info["pose_orthonormality_error"][1] <= 4e-4
    raw = np.loadtxt(scene / "traj.txt").reshape(-1, 4, 4)
    assert min(orthonormality_error(T[:3, :3]) for T in raw) >= 1e-4 * (1 - 1e-6)  # what a real tracker writes
    np.testing.assert_allclose(ReplicaSequence(scene).poses, load_traj(scene / "traj_gt.txt"), atol=1e-3)

    ideal = tmp_path / "ideal"  # the same sequence without the sensor: image metrics against it
    assert main(["scene", "synth", "--out", str(ideal), "--seed", "2", "--frames", "24", "--width", "160"]) == 0

    run = tmp_path / "run"
    cmd = ["map", str(scene), "--policy", "every-n", "--every-n", "2", "--out", str(run), "--width", "64",
           "--stride", "4", "--iters-per-keyframe", "3", "--no-progress", "--no-h-train", "--set",
           "mesh_voxel_size_m=0.05", "--set", "mesh_sdf_trunc_m=0.15", "--eval-against", str(ideal)]  # fmt: skip
    short = tmp_path / "short"
    assert main(["scene", "synth", "--out", str(short), "--frames", "8", "--width", "32"]) == 0
    assert main([*cmd[:-1], str(short)]) == 2  # 2 frames against 6: refused before mapping
    assert "eval_source" in capsys.readouterr().err and not run.exists()
    assert main(cmd) == 0
    m = json.loads((run / "metrics.json").read_text())
    assert m["eval_against"] == str(ideal)
    assert m["n_frames"] == 6 and m["frames_skipped_bad_pose"] == 0 and m["n_keyframes"] == 3
    assert m["mapper_frames_skipped_no_depth"] == 0
    # Holes arrive as 0 depth, are masked and counted: at least the 1 % dropouts of every keyframe.
    assert m["mapper_invalid_depth_pixels"] >= 0.005 * m["n_keyframes"] * 64 * 48
    assert m["n_eval_frames"] == 3 and m["eval_frames_without_gt_depth"] == 0
    for key in ("psnr", "depth_l1_cm", "precision@5cm", "recall@5cm", "precision@1cm", "recall@1cm"):
        assert math.isfinite(m[key]), key
    assert m["precision@5cm"] > 0.5 and m["psnr"] > 10


def test_cli_sensor_options(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base = ["scene", "synth", "--frames", "2", "--width", "32"]
    assert main([*base, "--out", str(tmp_path / "a"), "--sensor-set", "dropout_prob=0.1"]) == 2
    assert "needs --sensor" in capsys.readouterr().err
    assert main([*base, "--out", str(tmp_path / "b"), "--sensor", "kinect", "--sensor-set", "nope=1"]) == 2
    assert main([*base, "--out", str(tmp_path / "c"), "--sensor", "kinect", "--sensor-set", "dropout_prob=2"]) == 2
    assert "dropout_prob" in capsys.readouterr().err
    assert main([*base, "--out", str(tmp_path / "e"), "--sensor", "kinect", "--sensor-set", "dropout_prob=x"]) == 2
    assert "--sensor-set dropout_prob: cannot parse 'x'" in capsys.readouterr().err  # the option given, not --set
    assert not any((tmp_path / n).exists() for n in "abce")
    out = tmp_path / "d"
    assert main([*base, "--out", str(out), "--sensor", "kinect", "--sensor-set", "drift_trans_m_per_sqrt_m=0.02"]) == 0
    info = json.loads((out / "render.json").read_text())["sensor"]
    assert info["config"]["drift_trans_m_per_sqrt_m"] == 0.02 and info["pose_position_error_m_max"] > 0


def test_cli_render_named_kinect_camera(office0: Path, tmp_path: Path) -> None:
    """``scene render --cam kinect-v1 --sensor kinect`` on office0: a 640x480 Kinect-like sequence, read back."""
    out = tmp_path / "o0"
    rc = main(["scene", "render", "--mesh", str(office0 / "office0_mesh.ply"), "--traj",
               str(office0 / "office0" / "traj.txt"), "--cam", "kinect-v1", "--out", str(out), "--stride", "700",
               "--max-frames", "2", "--width", "320", "--sensor", "kinect"])  # fmt: skip
    assert rc == 0
    seq = ReplicaSequence(out)
    assert seq.intrinsics == K1.resized(320, 240)
    frame = seq.frame(1)
    assert 0.005 < (frame.depth_m == 0).mean() < 0.5
    np.testing.assert_allclose(seq.poses, load_traj(office0 / "office0" / "traj.txt")[[0, 700]], atol=1e-3)
