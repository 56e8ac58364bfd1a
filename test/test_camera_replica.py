"""Intrinsics, poses and the Replica layout reader/writer (bad input included)."""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from roigsf_ros.core.camera import (
    Intrinsics,
    check_pose,
    load_cam_params,
    load_pose,
    matrix_to_quat_xyzw,
    pose_from_position_quat,
    quat_xyzw_to_matrix,
)
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame
from roigsf_ros.data.replica import ReplicaSequence, load_traj, write_replica

INTR = Intrinsics(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5)


def _random_pose(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    T = np.eye(4)
    T[:3, :3] = quat_xyzw_to_matrix(q / np.linalg.norm(q))
    T[:3, 3] = rng.normal(size=3)
    return T


def _frames(n: int, seed: int = 0) -> list[Frame]:
    rng = np.random.default_rng(seed)
    return [
        Frame(
            index=i,
            rgb=cv2.resize(rng.integers(0, 256, (3, 4, 3), dtype=np.uint8), (INTR.width, INTR.height)),
            depth_m=rng.uniform(0.3, 5.0, (INTR.height, INTR.width)).astype(np.float32),
            T_wc=_random_pose(rng),
        )
        for i in range(n)
    ]


@pytest.fixture
def seq_dir(tmp_path: Path) -> Path:
    out = tmp_path / "scene"
    write_replica(out, INTR, _frames(3))
    return out


def test_resized_intrinsics_keep_pixel_centres_aligned() -> None:
    replica = Intrinsics(1200, 680, 600.0, 600.0, 599.5, 339.5)
    small = replica.resized(240, 136)
    assert (small.fx, small.fy, small.cx, small.cy) == (120.0, 120.0, 119.5, 67.5)
    # The image centre stays the principal point's counterpart at any scale.
    assert replica.resized(600, 340).cx == pytest.approx(299.5)


def test_load_cam_params_errors_name_the_file(tmp_path: Path) -> None:
    p = tmp_path / "cam.json"
    p.write_text(json.dumps({"camera": {"w": 10, "h": 10, "fx": 5.0, "fy": 5.0, "cx": 4.5}}))
    with pytest.raises(InputError, match=r"cam\.json.*cy"):
        load_cam_params(p)
    p.write_text("{not json")
    with pytest.raises(InputError, match=r"cam\.json"):
        load_cam_params(p)
    p.write_text(json.dumps({"camera": {"w": 10, "h": 10, "fx": -5.0, "fy": 5.0, "cx": 4.5, "cy": 4.5}}))
    with pytest.raises(InputError, match="invalid"):
        load_cam_params(p)
    with pytest.raises(InputError, match="not found"):
        load_cam_params(tmp_path / "missing.json")


def test_quaternion_round_trip_and_pose_checks() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        T = _random_pose(rng)
        q = matrix_to_quat_xyzw(T[:3, :3])
        np.testing.assert_allclose(quat_xyzw_to_matrix(q), T[:3, :3], atol=1e-12)
        np.testing.assert_allclose(pose_from_position_quat(T[:3, 3], q), T, atol=1e-12)
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(InputError, match="rigid"):
        check_pose(bad, "traj.txt:7")
    bad = np.eye(4)
    bad[1, 3] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        check_pose(bad, "here")
    # a pose in GPS/UTM metres (one such keyframe stopped every later planner request): refused as the pose it is
    far = np.eye(4)
    far[0, 3] = 1e6
    with pytest.raises(InputError, match=r"^/camera/pose @ 5 ns: pose position \[1000000.0, 0.0, 0.0\] m is 1000000 m"):
        check_pose(far, "/camera/pose @ 5 ns")
    far[0, 3] = 9_000.0  # a large site is still mapped
    assert check_pose(far, "here")[0, 3] == 9_000.0
    with pytest.raises(InputError, match="unit quaternion"):
        quat_xyzw_to_matrix(np.array([0.0, 0.0, 0.0, 2.0]))


def test_write_read_round_trip(seq_dir: Path) -> None:
    frames = _frames(3)
    seq = ReplicaSequence(seq_dir)
    assert len(seq) == 3 and seq.intrinsics == INTR
    for k, fr in enumerate(seq):
        assert fr.index == k
        np.testing.assert_array_equal(fr.T_wc, frames[k].T_wc)  # traj.txt keeps full precision
        # uint16 PNG quantises depth to 1 / 6553.5 m.
        assert np.abs(fr.depth_m - frames[k].depth_m).max() <= 0.5 / 6553.5 + 1e-6
        assert np.abs(fr.rgb.astype(int) - frames[k].rgb).mean() < 3  # JPEG of a smooth image


def test_layout_variants(seq_dir: Path, tmp_path: Path) -> None:
    # The `results` folder itself is accepted; cam_params.json may live in the parent (Replica download).
    assert len(ReplicaSequence(seq_dir / "results")) == 3
    dataset = tmp_path / "Replica"
    shutil.copytree(seq_dir, dataset / "office9")
    (dataset / "office9" / "cam_params.json").rename(dataset / "cam_params.json")
    seq = ReplicaSequence(dataset / "office9", size=(16, 12))
    assert seq.intrinsics == INTR.resized(16, 12)
    assert seq.frame(0).rgb.shape == (12, 16, 3) and seq.frame(0).depth_m.shape == (12, 16)
    # The download's root given instead of a scene: the error names its scene folders.
    (dataset / "notes").mkdir()
    shutil.copytree(seq_dir, dataset / "room0")
    with pytest.raises(InputError, match=r"it holds scene folder\(s\) office9, room0: give one of them \(e\.g\. "):
        ReplicaSequence(dataset)
    with pytest.raises(InputError, match=r"NICE-SLAM Replica layout\)$"):  # no scene below: no hint
        ReplicaSequence(dataset / "notes")


def test_traj_count_mismatch_is_an_error_unless_partial(seq_dir: Path) -> None:
    traj = seq_dir / "traj.txt"
    traj.write_text(traj.read_text() + traj.read_text().splitlines(keepends=True)[0])
    with pytest.raises(InputError, match=r"traj\.txt.*4 poses.*3 frames"):
        ReplicaSequence(seq_dir)
    assert len(ReplicaSequence(seq_dir, allow_partial=True)) == 3
    traj.write_text("".join(traj.read_text().splitlines(keepends=True)[:2]))
    with pytest.raises(InputError, match=r"traj\.txt.*frame number 2"):
        ReplicaSequence(seq_dir, allow_partial=True)


def test_bad_pose_line_is_named(seq_dir: Path) -> None:
    traj = seq_dir / "traj.txt"
    lines = traj.read_text().splitlines()
    values = lines[1].split()
    values[0] = "3.0"  # scales the rotation: not rigid
    lines[1] = " ".join(values)
    traj.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"traj\.txt:2: .*rigid"):
        load_traj(traj)
    lines[1] = " ".join(values[:15])
    traj.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"traj\.txt:2: .*15 values"):
        load_traj(traj)


def test_a_blank_line_among_the_poses_is_refused_not_skipped(seq_dir: Path) -> None:
    """Line k is frame k's pose: a blank line in the middle used to be skipped, so every later frame took the next
    frame's pose without a word (session 60's walk). Blank lines at the end stay harmless."""
    traj = seq_dir / "traj.txt"
    lines = traj.read_text().splitlines()
    traj.write_text("\n".join(lines) + "\n\n\n")
    assert len(load_traj(traj)) == len(lines)
    traj.write_text("\n".join([lines[0], "", *lines[1:]]) + "\n")
    with pytest.raises(InputError, match=r"traj\.txt:2: blank line among the poses"):
        ReplicaSequence(seq_dir)


def test_a_camera_field_that_is_no_number_is_named(seq_dir: Path) -> None:
    cam = json.loads((seq_dir / "cam_params.json").read_text())
    cam["camera"]["fy"] = "abc"
    (seq_dir / "cam_params.json").write_text(json.dumps(cam))
    with pytest.raises(InputError, match=r"cam_params\.json: camera field 'fy' is not a number: 'abc'"):
        ReplicaSequence(seq_dir)
    for key, value, said in (("fy", True, "is not a number: True"), ("w", 64.9, "is not a whole number of pixels")):
        cam["camera"]["fy"] = 5.0
        cam["camera"][key] = value  # JSON true was read as 1.0, 64.9 as 64: a run on wrong intrinsics
        (seq_dir / "cam_params.json").write_text(json.dumps(cam))
        with pytest.raises(InputError, match=rf"camera field '{key}' {said}"):
            ReplicaSequence(seq_dir)


def _kinect_like(T: np.ndarray, rng: np.random.Generator, off: float) -> np.ndarray:
    """``T`` with its rotation off orthonormal by about ``off`` (KinectFusion poses in 7-Scenes/ScanNet)."""
    bad = T.copy()
    bad[:3, :3] += rng.uniform(-off, off, (3, 3))
    return bad


def test_real_sensor_poses_are_reorthonormalised_with_one_warning(
    seq_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    rng = np.random.default_rng(7)
    exact = [_random_pose(rng) for _ in range(20)]
    kinect = [_kinect_like(T, rng, 2e-4) for T in exact]
    devs = [np.abs(T[:3, :3].T @ T[:3, :3] - np.eye(3)).max() for T in kinect]
    assert 1e-4 < max(devs) < 1e-3  # as far off as real KinectFusion trajectories
    traj = seq_dir / "traj.txt"
    traj.write_text("".join(" ".join(f"{v:.8f}" for v in T.reshape(-1)) + "\n" for T in kinect))
    with caplog.at_level(logging.WARNING, logger="roigsf_ros"):
        poses = load_traj(traj)
        load_traj(traj)  # the same source again: no second warning
    assert len(poses) == 20
    for T, want in zip(poses, exact, strict=True):
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(T, want, atol=2e-3)
    warned = [r for r in caplog.records if "orthonormal" in r.getMessage()]
    assert len(warned) == 1 and str(traj) in warned[0].getMessage()
    # every loader goes through the same function: a lone matrix, and check_pose for library callers
    # (the file holds 8 decimals, hence 1e-7)
    np.testing.assert_allclose(load_pose(kinect[0], "field", source="test"), poses[0], atol=1e-7)
    np.testing.assert_allclose(check_pose(kinect[0], "T_wc"), poses[0], atol=1e-7)


@pytest.mark.parametrize("decimals", [6, 8])
def test_poses_off_only_by_print_rounding_are_reorthonormalised_without_a_warning(
    decimals: int, seq_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A traj.txt of exact rotations printed to 6 or 8 decimals is off by ~1e-6 or ~1e-8: no warning, still exact."""
    rng = np.random.default_rng(9)
    exact = [_random_pose(rng) for _ in range(50)]
    traj = seq_dir / "traj.txt"
    traj.write_text("".join(" ".join(f"{v:.{decimals}f}" for v in T.reshape(-1)) + "\n" for T in exact))
    written = np.loadtxt(traj).reshape(-1, 4, 4)
    assert max(np.abs(T[:3, :3].T @ T[:3, :3] - np.eye(3)).max() for T in written) > 1e-9  # re-orthonormalised
    with caplog.at_level(logging.WARNING, logger="roigsf_ros"):
        poses = load_traj(traj)
    assert not [r for r in caplog.records if "orthonormal" in r.getMessage()]
    for T in poses:
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)


def test_clearly_non_rigid_poses_are_refused_naming_the_line(seq_dir: Path) -> None:
    rng = np.random.default_rng(8)
    good = _random_pose(rng)
    mirrored = good.copy()
    mirrored[:3, 0] *= -1  # orthonormal but det -1: a reflection
    for bad, why in ((_kinect_like(good, rng, 5e-2), "not orthonormal"), (mirrored, "det")):
        traj = seq_dir / "traj.txt"
        traj.write_text("".join(" ".join(f"{v:.12f}" for v in T.reshape(-1)) + "\n" for T in (good, bad, good)))
        with pytest.raises(InputError, match=rf"traj\.txt:2: .*{why}"):
            load_traj(traj)
    with pytest.raises(InputError, match=r"^poses\[3\]: .*det -1 < 0 \(a reflection"):
        load_pose(mirrored, "poses[3]")
    zero = good.copy()
    zero[:3, :3] = 0.0  # an all-zero rotation read as "det 0 <= 0 (a reflection ...)"
    with pytest.raises(InputError, match=r"^poses\[3\]: pose rotation is singular \(det 0; all zero\?\)"):
        load_pose(zero, "poses[3]")


def test_missing_unreadable_and_mismatched_images(seq_dir: Path) -> None:
    (seq_dir / "results" / "depth000001.png").unlink()
    with pytest.raises(InputError, match=r"depth000001\.png.*missing"):
        ReplicaSequence(seq_dir)
    cv2.imwrite(str(seq_dir / "results" / "depth000001.png"), np.zeros((24, 32, 3), np.uint8))
    with pytest.raises(InputError, match=r"depth000001\.png.*uint16"):
        ReplicaSequence(seq_dir).frame(1)
    (seq_dir / "results" / "frame000002.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(InputError, match=r"frame000002\.jpg.*unreadable"):
        ReplicaSequence(seq_dir).frame(2)
    cv2.imwrite(str(seq_dir / "results" / "depth000000.png"), np.zeros((10, 10), np.uint16))
    with pytest.raises(InputError, match=r"depth000000\.png: depth image is 10x10 but .* say 32x24"):
        ReplicaSequence(seq_dir).frame(0)  # the wrong-size depth file is named, not the colour file


def test_wrong_size_colour_is_blamed_on_the_colour_file(seq_dir: Path) -> None:
    cv2.imwrite(str(seq_dir / "results" / "frame000001.jpg"), np.zeros((10, 12, 3), np.uint8))
    with pytest.raises(InputError, match=r"frame000001\.jpg: colour image is 12x10 but .* say 32x24"):
        ReplicaSequence(seq_dir).frame(1)


@pytest.mark.parametrize("name", ["frame000001.jpg", "depth000001.png", "frame000001.png"])
def test_truncated_images_are_refused_naming_the_file(seq_dir: Path, name: str) -> None:
    path = seq_dir / "results" / name
    if name == "frame000001.png":  # a PNG colour frame instead of the JPEG
        (seq_dir / "results" / "frame000001.jpg").unlink()
        cv2.imwrite(str(path), _frames(2)[1].rgb)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])  # a copy or download cut short
    seq = ReplicaSequence(seq_dir)
    with pytest.raises(InputError, match=rf"{name.replace('.', r'[.]')}: .*truncated"):
        seq.frame(1)
    assert seq.frame(0).rgb.shape == (24, 32, 3)  # the intact frames still read


def test_office0_sample_is_readable(office0: Path, caplog: pytest.LogCaptureFixture) -> None:
    with pytest.raises(InputError, match="2000 poses"):
        ReplicaSequence(office0 / "office0")
    with caplog.at_level("WARNING"):
        seq = ReplicaSequence(office0 / "office0", allow_partial=True)
    said = "4 frames on disk of the 2000 poses in traj.txt; reading those (a partial download, accepted)"
    assert said in caplog.text
    assert len(seq) == 4 and seq.intrinsics.width == 1200 and seq.intrinsics.height == 680
    fr = seq.frame(3)
    assert fr.rgb.shape == (680, 1200, 3) and fr.depth_m.dtype == np.float32
    assert 0.1 < float(np.median(fr.depth_m)) < 10.0
    # its ground truth beside it, NICE-SLAM's layout: what roigsf map scores against without --gt-mesh
    from roigsf_ros.data.sources import open_frames

    assert open_frames(office0 / "office0", allow_partial=True).gt_mesh_path == office0 / "office0_mesh.ply"


def test_intrinsics_no_camera_could_have_are_refused_where_they_are_made() -> None:
    """A negative width built a Mapper and failed later as numpy's "negative dimensions"; a NaN focal length or a
    width of 0 scored every view 0 ("no candidate sees any surface"). The library's Intrinsics now refuses them."""
    good = Intrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5)
    for change, what in (
        ({"width": -1}, "width and height"),
        ({"height": 0}, "width and height"),
        ({"width": 64.5}, "width and height"),
        ({"fx": float("nan")}, "fx, fy and depth_scale"),
        ({"fy": 0.0}, "fx, fy and depth_scale"),
        ({"depth_scale": -1.0}, "fx, fy and depth_scale"),
        ({"cx": float("inf")}, "cx and cy"),
    ):
        with pytest.raises(InputError, match=rf"^intrinsics: {what}"):
            replace(good, **change)
    assert replace(good, cx=-3.0).cx == -3.0  # a principal point outside the image is a camera (a crop)


def test_a_frame_missing_between_others_is_named_and_a_flat_folder_is_read(
    seq_dir: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """One missing ``frame000001.jpg`` of three was reported as ``traj.txt: has 3 poses but results/ holds 2
    frames ... --allow-partial``, and following that advice mapped the others without a word about it. A partial
    download stops early, a gap is a frame lost: named (an error; with allow_partial a warning). A flat folder
    (images beside traj.txt and cam_params.json, no results/) was read with its parent as the sequence root."""
    flat = tmp_path / "flat"
    shutil.copytree(seq_dir / "results", flat)
    for name in ("traj.txt", "cam_params.json"):
        shutil.copy(seq_dir / name, flat / name)
    assert len(ReplicaSequence(flat)) == 3 and ReplicaSequence(flat).root == flat
    (flat / "traj.txt").write_text("".join((seq_dir / "traj.txt").read_text().splitlines(keepends=True)[:2]))
    with pytest.raises(InputError, match=r"too few: flat/ holds frame number 2"):  # it said "results/ holds"
        ReplicaSequence(flat)
    (seq_dir / "results" / "frame000001.jpg").unlink()
    (seq_dir / "results" / "depth000001.png").unlink()
    with pytest.raises(InputError, match=r"results: 1 frame\(s\) missing between frame 0 and frame 2: frame000001"):
        ReplicaSequence(seq_dir)
    with caplog.at_level(logging.WARNING):  # left out on purpose: read, with a word about it
        assert ReplicaSequence(seq_dir, allow_partial=True).indices == [0, 2]
    assert "1 frame(s) missing between frame 0 and frame 2: frame000001.jpg" in caplog.text
