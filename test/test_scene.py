"""Ray-cast ground truth: office0 re-rendering vs the real frames, the procedural room, the CLI."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import open3d as o3d
import pytest

from roigsf_ros.cli import build_parser, main
from roigsf_ros.cli.scene import synth_intrinsics
from roigsf_ros.core.camera import Intrinsics, check_pose, load_cam_params
from roigsf_ros.core.errors import InputError
from roigsf_ros.data import scene
from roigsf_ros.data.replica import MAX_DEPTH_M, ReplicaSequence, load_traj
from roigsf_ros.data.scene import (
    REPLICA_PIXEL_OFFSET,
    ROOM_MAX,
    ROOM_MIN,
    MeshRenderer,
    load_mesh,
    render_sequence,
    surface_texture,
    synth_room,
    synth_trajectory,
)

SMALL = synth_intrinsics(160, 120)


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _leftovers(parent: Path) -> list[str]:
    """Hidden temp folders/files that atomic writes would leave behind on failure."""
    return [p.name for p in parent.iterdir() if p.name.startswith(".")]


def _grad_median(rgb: np.ndarray) -> float:
    """Median |Sobel x| of the grey image; Sobel's 3x3 kernel is about 8x the per-pixel step."""
    g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    return float(np.median(np.abs(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3))))


# ---------------------------------------------------------------------------------------------
# Renderer semantics on an analytic scene
# ---------------------------------------------------------------------------------------------


def _plane_mesh(z: float, colour_of_x: tuple[float, float]) -> o3d.geometry.TriangleMesh:
    """A 20 m square at world z (fronto-parallel to an identity camera), red linear in x."""
    v = np.array([[-10, -10, z], [10, -10, z], [10, 10, z], [-10, 10, z]], dtype=np.float64)
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector([[0, 1, 2], [0, 2, 3]]))
    a, b = colour_of_x
    m.vertex_colors = o3d.utility.Vector3dVector([[a + b * x, 0.4, 0.25] for x in v[:, 0]])
    return m


def test_depth_is_z_depth_and_rays_go_through_integer_pixel_centres() -> None:
    intr = Intrinsics(width=9, height=7, fx=3.0, fy=3.0, cx=4.0, cy=3.0)
    # Red = 0.45 + 0.04 x on the plane z = 2; the pixel at column u sees x = 2 (u - cx) / fx.
    renderer = MeshRenderer(_plane_mesh(2.0, (0.45, 0.04)), texture_strength=0.0)
    tilt = np.eye(4)
    tilt[:3, :3] = cv2.Rodrigues(np.array([0.0, 0.3, 0.0]))[0]  # yaw 0.3 rad: rays hit obliquely
    rgb, depth = renderer.render(np.eye(4), intr)
    # Every pixel sees the plane at z = 2 exactly (z-depth, not ray length).
    np.testing.assert_allclose(depth, 2.0, atol=1e-6)
    u = np.arange(intr.width)
    # Barycentric vertex colour at the hit, within 8-bit rounding; half a pixel off would be 3.4 levels.
    expected_red = (0.45 + 0.04 * 2.0 * (u - intr.cx) / intr.fx) * 255
    np.testing.assert_allclose(rgb[3, :, 0], expected_red, atol=0.51)
    assert np.all(rgb[..., 1] == 102) and np.all(rgb[..., 2] == 64)
    # Rotated camera: z-depth of the hit in the camera frame equals the rendered depth.
    d_tilt = renderer.render_depth(tilt, intr)
    dirs_w = scene.camera_rays(tilt, intr)[..., 3:].astype(np.float64)
    t = 2.0 / dirs_w[..., 2]  # ray parameter where the world ray meets z = 2
    hit_c = np.einsum("kj,hwk->hwj", tilt[:3, :3], dirs_w * t[..., None])  # R^T p
    np.testing.assert_allclose(d_tilt, hit_c[..., 2], rtol=1e-5)
    assert np.ptp(d_tilt) > 0.1  # not trivially constant
    # A half-pixel offset moves the sampled x by half a pixel's footprint.
    rgb_off, _ = renderer.render(np.eye(4), intr, pixel_offset=0.5)
    np.testing.assert_allclose(rgb_off[3, :, 0], (0.45 + 0.08 * (u + 0.5 - intr.cx) / intr.fx) * 255, atol=0.51)


def test_rays_missing_the_mesh_give_zero_depth_and_black() -> None:
    intr = Intrinsics(width=8, height=6, fx=4.0, fy=4.0, cx=3.5, cy=2.5)
    renderer = MeshRenderer(_plane_mesh(2.0, (0.5, 0.0)))
    away = np.diag([1.0, -1.0, -1.0, 1.0])  # looking along -z, away from the plane
    rgb, depth = renderer.render(away, intr)
    assert depth.dtype == np.float32 and depth.shape == (6, 8) and np.all(depth == 0)
    assert rgb.dtype == np.uint8 and rgb.shape == (6, 8, 3) and np.all(rgb == 0)
    with pytest.raises(InputError, match="rigid"):
        renderer.render(np.diag([2.0, 1.0, 1.0, 1.0]), intr)


def test_surface_texture_is_deterministic_bounded_and_smooth() -> None:
    pts = np.random.default_rng(0).uniform(-3.0, 3.0, (20000, 3))
    tex = surface_texture(pts, seed=1)
    assert tex.shape == (20000, 3) and tex.dtype == np.float32
    np.testing.assert_array_equal(tex, surface_texture(pts, seed=1))
    assert np.abs(tex - surface_texture(pts, seed=2)).mean() > 0.05
    # Brightness modulation roughly 0.6-1.3 (5th-95th percentile), with some hue variation.
    lo, hi = np.percentile(tex, [5, 95])
    assert 0.55 < lo < 0.75 and 1.1 < hi < 1.35
    assert np.percentile(np.abs(tex[:, 0] / tex[:, 1] - 1), 90) > 0.03
    # A surface property: continuous in space (1 mm away changes little), not per-pixel noise.
    assert np.abs(surface_texture(pts + 1e-3, seed=1) - tex).max() < 0.05
    np.testing.assert_array_equal(surface_texture(pts, seed=1, strength=0.0), 1.0)
    half = surface_texture(pts, seed=1, strength=0.5)
    np.testing.assert_allclose(half, 1.0 + 0.5 * (tex - 1.0), atol=1e-6)


# ---------------------------------------------------------------------------------------------
# office0: the renderer reproduces the real Replica depth
# ---------------------------------------------------------------------------------------------


def test_office0_render_matches_real_depth(office0: Path) -> None:
    seq = ReplicaSequence(office0 / "office0", allow_partial=True)
    assert (seq.intrinsics.width, seq.intrinsics.height) == (1200, 680)
    renderer = MeshRenderer(load_mesh(office0 / "office0_mesh.ply"))
    for k in range(len(seq)):
        frame = seq.frame(k)
        depth = renderer.render_depth(frame.T_wc, seq.intrinsics, pixel_offset=REPLICA_PIXEL_OFFSET)
        valid = (depth > 0) & (frame.depth_m > 0)
        assert valid.mean() > 0.99
        err = np.abs(depth - frame.depth_m)[valid]
        assert np.median(err) < 1e-3, f"frame {k}: median depth error {np.median(err) * 1e3:.2f} mm"
        assert (err < 0.02).mean() > 0.99
        if k == 0:
            # Replica's renderer sampled pixel u at u + 0.5 with the published cx = 599.5: the nominal
            # integer-centre rays are half a pixel off, which shows as several times the error.
            nominal = np.abs(renderer.render_depth(frame.T_wc, seq.intrinsics) - frame.depth_m)[valid]
            assert np.median(nominal) > 3 * np.median(err)


def test_load_mesh_errors_name_the_file(tmp_path: Path, capfd: Any) -> None:
    with pytest.raises(InputError, match="not found") as exc:
        load_mesh(tmp_path / "nope.ply")
    assert "nope.ply" in str(exc.value)
    junk = tmp_path / "junk.ply"
    junk.write_text("this is not a mesh\n")
    with pytest.raises(InputError, match="no triangles") as exc:
        load_mesh(junk)
    assert "junk.ply" in str(exc.value)
    points = tmp_path / "points.ply"  # vertices only: a point cloud
    points.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                      "property float z\nend_header\n0 0 0\n")  # fmt: skip
    with pytest.raises(InputError, match="no triangles"):
        load_mesh(points)
    # Our error says it; Open3D's warnings ("Read PLY failed", "appears to be a PointCloud") printed before it did not
    out, err = capfd.readouterr()
    assert "Open3D WARNING" not in out + err


# ---------------------------------------------------------------------------------------------
# The procedural room and trajectory
# ---------------------------------------------------------------------------------------------


def test_synth_room_is_deterministic_and_reasonably_sized() -> None:
    a, b, c = synth_room(0), synth_room(0), synth_room(1)
    np.testing.assert_array_equal(np.asarray(a.vertices), np.asarray(b.vertices))
    np.testing.assert_array_equal(np.asarray(a.vertex_colors), np.asarray(b.vertex_colors))
    np.testing.assert_array_equal(np.asarray(a.triangles), np.asarray(b.triangles))
    assert not np.array_equal(np.asarray(a.vertex_colors)[:100], np.asarray(c.vertex_colors)[:100])
    assert 10_000 < len(a.triangles) < 100_000
    np.testing.assert_allclose(a.get_min_bound(), ROOM_MIN, atol=1e-9)
    np.testing.assert_allclose(a.get_max_bound(), ROOM_MAX, atol=1e-9)
    # Walls are subdivided and their vertex colours vary (not one flat colour per wall).
    wall = np.abs(np.asarray(a.vertices)[:, 0] - ROOM_MIN[0]) < 1e-9
    assert wall.sum() > 500 and np.asarray(a.vertex_colors)[wall].std(axis=0).max() > 0.01


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_synth_trajectory_is_smooth_safe_and_sees_the_room(seed: int) -> None:
    poses = synth_trajectory(seed, 100)
    assert poses.shape == (100, 4, 4) and poses.dtype == np.float64
    for i, T in enumerate(poses):
        check_pose(T, f"pose {i}", tol=1e-9)
    pos = poses[:, :3, 3]
    assert np.all(pos[:, :2] >= ROOM_MIN[:2] + 0.5) and np.all(pos[:, :2] <= ROOM_MAX[:2] - 0.5)
    assert np.all((pos[:, 2] >= 1.2) & (pos[:, 2] <= 1.7))
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert steps.max() < 0.15  # smooth: under 15 cm between consecutive frames of a 100-frame loop
    rel = np.einsum("nji,njk->nik", poses[:-1, :3, :3], poses[1:, :3, :3])
    angles = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert angles.max() < 15.0
    # The loop goes round the centre (covers all four quadrants) and the view direction varies.
    quads = set(zip((pos[:, 0] > 0).tolist(), (pos[:, 1] > 0).tolist(), strict=True))
    assert len(quads) == 4
    # Every ray hits (closed room) and no surface is closer than 0.4 m (never inside furniture).
    renderer = MeshRenderer(synth_room(seed), texture_strength=0.0)
    tiny = synth_intrinsics(40, 30)
    depths = np.stack([renderer.render_depth(T, tiny) for T in poses])
    assert depths.min() > 0.4 and depths.max() < MAX_DEPTH_M


@pytest.fixture(scope="module")
def synth_dirs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Seed 0 rendered twice and seed 1 once: 6 frames at 160x120."""
    root = tmp_path_factory.mktemp("synth")
    out = {}
    for name, seed in (("a", 0), ("b", 0), ("c", 1)):
        out[name] = render_sequence(
            synth_room(seed), synth_trajectory(seed, 6), SMALL, root / name, texture_seed=seed, progress=False
        )
    return out


def test_synth_render_is_byte_identical_for_a_seed(synth_dirs: dict[str, Path]) -> None:
    a, b, c = (_files(synth_dirs[k]) for k in "abc")
    expected = {"traj.txt", "cam_params.json", "mesh.ply", "render.json"}
    expected |= {f"results/{kind}{i:06d}.{ext}" for i in range(6) for kind, ext in (("frame", "jpg"), ("depth", "png"))}
    assert set(a) == expected
    assert a == b
    for name in ("traj.txt", "mesh.ply", "results/frame000000.jpg", "results/depth000000.png"):
        assert a[name] != c[name], name


def test_synth_frames_are_textured_full_and_on_the_mesh(synth_dirs: dict[str, Path]) -> None:
    root = synth_dirs["a"]
    seq = ReplicaSequence(root)
    assert seq.intrinsics == SMALL
    mesh = load_mesh(root / "mesh.ply")
    flat = MeshRenderer(mesh, texture_strength=0.0)
    raycast = o3d.t.geometry.RaycastingScene()
    raycast.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    u, v = np.meshgrid(np.arange(SMALL.width), np.arange(SMALL.height))
    for frame in seq:
        # Closed room: every pixel has a valid depth.
        assert np.all(frame.depth_m > 0.3) and np.all(frame.depth_m < MAX_DEPTH_M)
        # Texture: the median horizontal grey gradient is at least ~1 grey level per pixel (Sobel
        # about 8x the step) and 3x the untextured render's, whose gradient is only at object edges
        # and 8-bit rounding. Photometric Fisher information needs this everywhere, not at edges.
        g_tex = _grad_median(frame.rgb)
        g_flat = _grad_median(flat.render(frame.T_wc, SMALL)[0])
        assert g_tex >= 8.0 and g_tex >= 3.0 * g_flat, (g_tex, g_flat)
        # Back-projected depth lies on the ground-truth mesh (well within the 1 mm requirement).
        d = frame.depth_m.astype(np.float64)
        p_c = np.stack([(u - SMALL.cx) / SMALL.fx * d, (v - SMALL.cy) / SMALL.fy * d, d], -1).reshape(-1, 3)
        p_w = p_c @ frame.T_wc[:3, :3].T + frame.T_wc[:3, 3]
        dist = raycast.compute_distance(o3d.core.Tensor(p_w.astype(np.float32))).numpy()
        # Half a PNG step is 0.076 mm of z; along oblique rays and in float32 that stays under 0.25 mm.
        assert dist.max() < 2.5e-4, dist.max()


def test_render_sequence_failure_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = {"n": 0}
    real_render = MeshRenderer.render

    def failing_render(self: MeshRenderer, *args: object, **kwargs: object) -> tuple[np.ndarray, np.ndarray]:
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("simulated crash mid-sequence")
        return real_render(self, *args, **kwargs)

    monkeypatch.setattr(MeshRenderer, "render", failing_render)
    with pytest.raises(RuntimeError, match="simulated"):
        render_sequence(synth_room(0), synth_trajectory(0, 5), synth_intrinsics(32, 24), tmp_path / "out")
    assert list(tmp_path.iterdir()) == []


def test_render_sequence_progress_is_the_callers_choice(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``progress=True`` draws the bar wherever stderr goes, as every other library call does (bags, mapping); the
    command line passes it on a terminal only. The review found the scene renderer checking for a terminal itself,
    so a library caller's ``progress=True`` in a notebook or a log drew nothing."""
    render_sequence(synth_room(0), synth_trajectory(0, 2), synth_intrinsics(16, 12), tmp_path / "a", progress=True)
    assert "render a" in capsys.readouterr().err
    render_sequence(synth_room(0), synth_trajectory(0, 2), synth_intrinsics(16, 12), tmp_path / "b", progress=False)
    assert "render b" not in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------


def test_cli_synth_round_trip(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "room"
    args = ["scene", "synth", "--out", str(out), "--seed", "3", "--frames", "4", "--width", "64", "--height", "48"]
    assert main(args) == 0
    seq = ReplicaSequence(out)
    intr = synth_intrinsics(64, 48)
    assert len(seq) == 4 and seq.intrinsics == intr
    assert (intr.fx, intr.cx, intr.cy) == (0.8 * 64, 31.5, 23.5)
    np.testing.assert_array_equal(seq.poses, synth_trajectory(3, 4))
    assert seq.frame(0).rgb.shape == (48, 64, 3)
    assert (out / "mesh.ply").is_file()
    assert "wrote 4 frames" in capsys.readouterr().out
    # Existing output: refused without --overwrite, replaced with it.
    assert main(args) == 2
    assert "already exists" in capsys.readouterr().err
    assert main([*args[:-4], "--width", "32", "--height", "24", "--overwrite"]) == 0
    assert ReplicaSequence(out).intrinsics.width == 32
    assert _leftovers(tmp_path) == []


def test_cli_render_office0_subsampled(office0: Path, tmp_path: Path) -> None:
    out = tmp_path / "office0_small"
    args = [
        "scene", "render", "--mesh", str(office0 / "office0_mesh.ply"), "--traj", str(office0 / "office0" / "traj.txt"),
        "--cam", str(office0 / "cam_params.json"), "--out", str(out), "--width", "120", "--height", "68",
        "--stride", "500", "--max-frames", "3", "--texture-strength", "0.5",
    ]  # fmt: skip
    assert main(args) == 0
    seq = ReplicaSequence(out)
    assert len(seq) == 3
    assert seq.intrinsics == load_cam_params(office0 / "cam_params.json").resized(120, 68)
    np.testing.assert_array_equal(seq.poses, load_traj(office0 / "office0" / "traj.txt")[[0, 500, 1000]])
    for frame in seq:
        assert (frame.depth_m > 0).mean() > 0.99 and frame.rgb.std() > 10
    assert len(load_mesh(out / "mesh.ply").triangles) == 50_000


@pytest.fixture
def small_inputs(tmp_path: Path) -> dict[str, Path]:
    """A tiny mesh, a 3-pose traj.txt and a cam_params.json in tmp_path/in."""
    src = tmp_path / "in"
    src.mkdir()
    o3d.io.write_triangle_mesh(str(src / "mesh.ply"), _plane_mesh(3.0, (0.5, 0.01)))
    poses = np.stack([np.eye(4)] * 3)
    poses[:, 0, 3] = [0.0, 0.1, 0.2]
    (src / "traj.txt").write_text("".join(" ".join(map(str, T.ravel())) + "\n" for T in poses))
    intr = Intrinsics(width=16, height=12, fx=10.0, fy=10.0, cx=7.5, cy=5.5)
    (src / "cam.json").write_text(json.dumps(intr.to_replica_json()))
    return {"mesh": src / "mesh.ply", "traj": src / "traj.txt", "cam": src / "cam.json"}


def _render_args(inputs: dict[str, Path], out: Path, *extra: str) -> list[str]:
    return [
        "scene", "render", "--mesh", str(inputs["mesh"]), "--traj", str(inputs["traj"]),
        "--cam", str(inputs["cam"]), "--out", str(out), *extra,
    ]  # fmt: skip


def test_cli_render_small_inputs_work(small_inputs: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert main(_render_args(small_inputs, out)) == 0
    seq = ReplicaSequence(out)
    assert len(seq) == 3
    np.testing.assert_allclose(seq.frame(2).depth_m, 3.0, atol=1e-4)


def test_cli_render_offset_takes_the_poses_between(
    small_inputs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--offset K --stride S`` renders poses K, K + S, ...: a test set between another render's frames."""
    out = tmp_path / "between"
    assert main(_render_args(small_inputs, out, "--stride", "2", "--offset", "1")) == 0
    np.testing.assert_array_equal(ReplicaSequence(out).poses, load_traj(small_inputs["traj"])[1::2])
    assert main(_render_args(small_inputs, tmp_path / "bad", "--stride", "2", "--offset", "2")) == 2
    assert "--offset" in capsys.readouterr().err and not (tmp_path / "bad").exists()


@pytest.mark.parametrize(
    ("bad_line", "what"),
    [
        ("2 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1", "rigid"),  # scaled rotation
        ("1 0 0 nan 0 1 0 0 0 0 1 0 0 0 0 1", "non-finite"),
    ],
)
def test_cli_render_bad_traj_line(
    small_inputs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], bad_line: str, what: str
) -> None:
    lines = small_inputs["traj"].read_text().splitlines()
    lines[1] = bad_line
    small_inputs["traj"].write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    assert main(_render_args(small_inputs, out)) == 2
    err = capsys.readouterr().err
    assert f"{small_inputs['traj']}:2" in err and what in err
    assert err.count("\n") == 1  # one line, no traceback
    assert not out.exists() and _leftovers(tmp_path) == []


def test_cli_render_bad_inputs(
    small_inputs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    # Missing mesh file.
    missing = dict(small_inputs, mesh=tmp_path / "in" / "absent.ply")
    assert main(_render_args(missing, out)) == 2
    assert "absent.ply" in capsys.readouterr().err
    # Camera JSON without fx.
    cam = tmp_path / "in" / "cam_nofx.json"
    cam.write_text('{"camera": {"w": 16, "h": 12, "fy": 10, "cx": 7.5, "cy": 5.5}}')
    assert main(_render_args(dict(small_inputs, cam=cam), out)) == 2
    err = capsys.readouterr().err
    assert "cam_nofx.json" in err and "fx" in err
    # Bad numbers.
    for extra, name in (
        (["--stride", "0"], "--stride"),
        (["--max-frames", "0"], "--max-frames"),
        (["--height", "-3"], "--height"),  # (--width alone is fine: the height keeps the aspect ratio)
        (["--width", "0", "--height", "10"], "--width"),
        (["--texture-strength", "-1"], "--texture-strength"),
    ):
        assert main(_render_args(small_inputs, out, *extra)) == 2
        assert name in capsys.readouterr().err
    assert not out.exists() and _leftovers(tmp_path) == []
    # Existing output without --overwrite is refused and left untouched.
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert main(_render_args(small_inputs, out)) == 2
    assert "already exists" in capsys.readouterr().err
    assert (out / "keep.txt").read_text() == "mine"
    # Synth with bad counts.
    assert main(["scene", "synth", "--out", str(tmp_path / "s"), "--frames", "0"]) == 2
    assert "--frames" in capsys.readouterr().err
    # a walk: the suite's minimum was said as "n_frames", the sensor's unknown field without the fields, a pool
    # field's range without --pool-set
    assert main(["scene", "synth", "--kind", "suite", "--out", str(tmp_path / "s"), "--frames", "8"]) == 2
    assert "error: --frames: the suite's walk needs >= 10 frames, got 8" in capsys.readouterr().err
    assert (
        main(["scene", "synth", "--sensor", "kinect", "--sensor-set", "jpeg_qualty=50", "--out", str(tmp_path / "s")])
        == 2
    )
    err = capsys.readouterr().err
    assert "SensorConfig field (did you mean jpeg_quality?): native_width_px, " in err, err
    bench = [
        "bench",
        "--scene",
        str(tmp_path),
        "--setting",
        "pool",
        "--policies",
        "random",
        "--out",
        str(tmp_path / "b"),
    ]
    assert main([*bench, "--pool-set", "n_views=0"]) == 2
    assert "error: --pool-set n_views: must be" in capsys.readouterr().err
    assert main(["scene", "synth", "--out", str(tmp_path / "s"), "--width", "-4"]) == 2
    assert not (tmp_path / "s").exists() and _leftovers(tmp_path) == []


def _subparser(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices[name]


def test_cli_help_documents_every_option() -> None:
    scene_parser = _subparser(build_parser(), "scene")
    for name in ("render", "synth"):
        parser = _subparser(scene_parser, name)
        options = [a for a in parser._actions if a.option_strings and "--help" not in a.option_strings]
        assert len(options) >= 6
        for action in options:
            assert action.help and len(action.help.split()) >= 3, f"scene {name} {action.option_strings}"
        assert "--overwrite" in parser.format_help()


def test_texture_strength_zero_gives_plain_vertex_colours() -> None:
    mesh = synth_room(0)
    T = synth_trajectory(0, 1)[0]
    flat, _ = MeshRenderer(mesh, texture_strength=0.0).render(T, SMALL)
    tex, _ = MeshRenderer(mesh, texture_strength=1.0).render(T, SMALL)
    assert np.abs(flat.astype(int) - tex.astype(int)).mean() > 10
    with pytest.raises(InputError, match="texture_strength"):
        MeshRenderer(mesh, texture_strength=float("nan"))


def test_synth_object_scene_is_an_orbit_around_primitives_with_an_empty_background(tmp_path: Path) -> None:
    """``scene synth --kind object``: the object-centric NBV scene; every view sees the object and some sky."""
    out = tmp_path / "obj"
    assert main(["scene", "synth", "--kind", "object", "--frames", "6", "--width", "48", "--out", str(out)]) == 0
    seq = ReplicaSequence(out)
    assert len(seq) == 6 and (seq.intrinsics.width, seq.intrinsics.height) == (48, 36)
    mesh = o3d.io.read_triangle_mesh(str(out / "mesh.ply"))
    lo, hi = mesh.get_min_bound(), mesh.get_max_bound()
    assert np.all(hi[:2] <= 0.81) and np.all(lo[:2] >= -0.81) and lo[2] >= -0.05 and hi[2] < 0.6
    centre = np.zeros(3)
    for frame in seq:
        valid = frame.depth_m > 0
        assert 0.05 < valid.mean() < 0.95  # the object and the empty background
        eye = frame.T_wc[:3, 3]
        assert 0.8 < np.linalg.norm(eye[:2] - centre[:2]) < 1.5 and 0.1 < eye[2] < 1.0
    again = scene.synth_object(0)
    assert np.array_equal(np.asarray(again.vertices), np.asarray(scene.synth_object(0).vertices))
    assert not np.array_equal(np.asarray(again.vertices), np.asarray(scene.synth_object(1).vertices))


def _views_seeing(mesh: o3d.geometry.TriangleMesh, poses: np.ndarray, point: list[float]) -> int:
    """How many camera centres of ``poses`` see ``point`` (the first hit of the ray from the centre is the point)."""
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    eyes = poses[:, :3, 3]
    d = np.asarray(point) - eyes
    dist = np.linalg.norm(d, axis=1)
    rays = np.concatenate([eyes, d / dist[:, None]], 1).astype(np.float32)
    t_hit = rs.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return int((np.abs(t_hit - dist) < 1e-3).sum())


def _dome_scene(
    tmp_path: Path, kind: str, make: Callable[[int], o3d.geometry.TriangleMesh]
) -> tuple[o3d.geometry.TriangleMesh, np.ndarray]:
    """Checks ``scene synth --kind kind`` and the mesh ``make`` builds (on the 0.8 m disc, under 0.6 m, the same for
    seed 0 every time, another for seed 1); returns the seed-0 mesh and the 120 dome poses of the benchmark.
    """
    out = tmp_path / kind
    assert main(["scene", "synth", "--kind", kind, "--frames", "6", "--width", "48", "--out", str(out)]) == 0
    assert len(ReplicaSequence(out)) == 6
    mesh = make(0)
    lo, hi = mesh.get_min_bound(), mesh.get_max_bound()
    assert np.all(hi[:2] <= 0.81) and np.all(lo[:2] >= -0.81) and lo[2] >= -0.05 and hi[2] < 0.6
    assert np.array_equal(np.asarray(mesh.vertices), np.asarray(make(0).vertices))
    assert not np.array_equal(np.asarray(mesh.vertices), np.asarray(make(1).vertices))
    return mesh, scene.dome_trajectory(120)


def test_synth_clutter_hides_the_cabinet_insides_from_most_views(tmp_path: Path) -> None:
    """``scene synth --kind clutter-dome``: the occluded NBV scene; a cabinet's inside is seen by few of the views."""
    mesh, poses = _dome_scene(tmp_path, "clutter-dome", scene.synth_clutter)
    for turn in range(4):  # each cabinet's floor and back, inside; its roof and the middle box's top, outside
        c, s = np.cos(turn * np.pi / 2), np.sin(turn * np.pi / 2)
        inside = [_views_seeing(mesh, poses, [r * c, r * s, z]) for r, z in ((0.6, 0.0), (0.4801, 0.15))]
        assert max(inside) <= 12, (turn, inside)  # at most 10 % of the hemisphere's views
        assert _views_seeing(mesh, poses, [0.6 * c, 0.6 * s, 0.35]) >= 40
    assert _views_seeing(mesh, poses, [0.0, 0.0, 0.55]) >= 60


def test_synth_shelf_hides_the_shelf_backs_and_the_crate_from_most_views(tmp_path: Path) -> None:
    """``scene synth --kind shelf-dome``: the tuning scene of the NBV options; its occluded parts are seen by few
    of the hemisphere's views, their occluders by many, and it is not the clutter scene.
    """
    mesh, poses = _dome_scene(tmp_path, "shelf-dome", scene.synth_shelf)
    for back in ([-0.14, -0.3001, 0.12], [0.10, -0.3001, 0.36]):  # inside two compartments
        assert _views_seeing(mesh, poses, back) <= 8
    assert _views_seeing(mesh, poses, [0.0, -0.44, 0.5201]) >= 40  # the shelf's top
    assert _views_seeing(mesh, poses, [0.39, 0.12, 0.1601]) <= 30  # the crate's top, under the table
    assert _views_seeing(mesh, poses, [0.39, 0.12, 0.2701]) >= 60  # the table's top
    assert len(mesh.vertices) != len(scene.synth_clutter(0).vertices)


def test_synth_bins_hides_the_bin_floors_the_tunnel_and_the_crate_from_most_views(tmp_path: Path) -> None:
    """``scene synth --kind bins-dome``: the object scene made after the NBV options were fixed; what its bins, tunnel
    and screen hide is seen by few of the hemisphere's views, their tops by many, and it is neither earlier scene.
    """
    mesh, poses = _dome_scene(tmp_path, "bins-dome", scene.synth_bins)
    assert _views_seeing(mesh, poses, [0.19, 0.19, 0.0301]) <= 20  # a corner of the big bin's floor
    assert _views_seeing(mesh, poses, [0.30, 0.151, 0.2601]) >= 60  # its rim
    assert _views_seeing(mesh, poses, [0.0, -0.12, 0.0001]) <= 15  # the tunnel's floor, halfway in
    assert _views_seeing(mesh, poses, [0.0, -0.12, 0.1701]) >= 60  # its roof
    assert _views_seeing(mesh, poses, [0.35, -0.5201, 0.11]) <= 5  # the crate's face towards the screen
    assert _views_seeing(mesh, poses, [0.35, -0.44, 0.2201]) >= 60  # the crate's top
    for other in (scene.synth_clutter(0), scene.synth_shelf(0)):
        assert not np.array_equal(np.asarray(mesh.vertices), np.asarray(other.vertices))


def test_synth_dining_hides_the_cabinet_inside_and_the_wedge_under_the_plank(tmp_path: Path) -> None:
    """``scene synth --kind dining-dome``: the object scene made after every NBV option was fixed (fiftieth session);
    the cabinet's inside past its half-open door and the wedge under the leaning plank are seen by few of the
    hemisphere's views, the tops around them by many, and it is none of the earlier scenes.
    """
    mesh, poses = _dome_scene(tmp_path, "dining-dome", scene.synth_dining)
    assert _views_seeing(mesh, poses, [-0.42, -0.1001, 0.12]) <= 5  # the cabinet's inner back, lower compartment
    assert _views_seeing(mesh, poses, [-0.42, -0.2, 0.0301]) <= 8  # its floor
    assert _views_seeing(mesh, poses, [-0.42, -0.23, 0.4601]) >= 60  # its top
    assert _views_seeing(mesh, poses, [-0.42, -0.0699, 0.08]) <= 20  # its outer back, under the plank
    assert 20 <= _views_seeing(mesh, poses, [0.07, 0.15, 0.2301]) <= 60  # a chair's seat, under the table top
    assert _views_seeing(mesh, poses, [0.25, 0.15, 0.4301]) >= 60  # the table's top
    v = np.asarray(mesh.vertices)
    assert np.hypot(v[:, 0], v[:, 1]).max() <= 0.8 + 1e-9  # everything stands on the disc
    for other in (scene.synth_clutter(0), scene.synth_shelf(0), scene.synth_bins(0)):
        assert not np.array_equal(np.asarray(mesh.vertices), np.asarray(other.vertices))


def test_synth_object_dome_views_the_objects_from_a_hemisphere(tmp_path: Path) -> None:
    """``scene synth --kind object-dome``: the same objects, every view sees them, from 10-75 deg elevation."""
    out = tmp_path / "dome"
    assert main(["scene", "synth", "--kind", "object-dome", "--frames", "8", "--width", "48", "--out", str(out)]) == 0
    seq = ReplicaSequence(out)
    assert len(seq) == 8
    elev, azim = [], []
    for frame in seq:
        assert (frame.depth_m > 0).mean() > 0.05  # the object is in view
        rel = frame.T_wc[:3, 3] - np.array([0.0, 0.0, 0.1])
        r = np.linalg.norm(rel)
        assert 1.0 - 1e-9 <= r <= 1.3 + 1e-9
        elev.append(np.degrees(np.arcsin(rel[2] / r)))
        azim.append(np.degrees(np.arctan2(rel[1], rel[0])))
    assert min(elev) >= 10.0 and max(elev) <= 75.0 and np.all(np.diff(elev) > 0)  # rising along the sequence
    assert len({round(a) for a in azim}) == 8  # golden-angle azimuths: no two views from one direction


def test_synth_suite_joins_two_rooms_by_a_doorway_the_walk_goes_through(tmp_path: Path) -> None:
    """``scene synth --kind suite``: two rooms and a doorway; the loop of the first room, the walk through the doorway
    and the loop of the second are smooth, never inside anything, and every ray hits (a closed suite)."""
    out = tmp_path / "suite"
    assert main(["scene", "synth", "--kind", "suite", "--frames", "12", "--width", "48", "--out", str(out)]) == 0
    assert len(ReplicaSequence(out)) == 12
    mesh = scene.synth_suite(7)
    assert np.array_equal(np.asarray(mesh.vertices), np.asarray(scene.synth_suite(7).vertices))
    np.testing.assert_allclose(mesh.get_min_bound(), scene.ROOM_MIN, atol=1e-9)
    np.testing.assert_allclose(mesh.get_max_bound(), scene.ROOM_MAX + scene.SUITE_OFFSET_M, atol=1e-9)
    door_x, wall_y = scene.suite_door_x(7), float(scene.ROOM_MAX[1])
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    rays = [[door_x, wall_y - 1.0, 1.0, 0.0, 1.0, 0.0], [door_x + 0.6, wall_y - 1.0, 1.0, 0.0, 1.0, 0.0]]
    t_hit = rs.cast_rays(o3d.core.Tensor(np.array(rays, dtype=np.float32)))["t_hit"].numpy()
    assert t_hit[0] > 2.0 and t_hit[1] == pytest.approx(1.0, abs=1e-4)  # through the doorway; beside it, the wall
    for seed in range(12):  # no furniture the walk (at 1.4 m) could meet stands in the doorway's passage
        door = scene.suite_door_x(seed)
        assert scene._suite_passage_counts(scene._suite_furniture(seed), door - scene.SUITE_DOOR_M[0] / 2)[0] == 0

    poses = scene.suite_trajectory(7, 400)
    for i, T in enumerate(poses):
        check_pose(T, f"pose {i}", tol=1e-9)
    pos = poses[:, :3, 3]
    assert np.all(pos[:168, 1] < wall_y - 0.5) and np.all(pos[232:, 1] > wall_y + 0.5)  # one room, then the other
    crossing = np.argmax(pos[:, 1] > wall_y)
    assert abs(pos[crossing, 0] - door_x) < 1e-9 and abs(pos[crossing, 2] - 1.4) < 1e-9  # through the doorway
    assert np.linalg.norm(np.diff(pos, axis=0), axis=1).max() < 0.1
    rel = np.einsum("nji,njk->nik", poses[:-1, :3, :3], poses[1:, :3, :3])
    assert np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1))).max() < 6.0
    renderer = MeshRenderer(mesh, texture_strength=0.0)
    depths = np.stack([renderer.render_depth(T, synth_intrinsics(40, 30)) for T in poses[::2]])
    assert depths.min() > 0.3 and depths.max() < MAX_DEPTH_M
