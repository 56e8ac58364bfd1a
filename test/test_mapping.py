"""The mapper on a tiny ray-cast room: accuracy at a held-out pose, h_train, bad input, offline run, CLI."""

from __future__ import annotations

import json
import logging
import math
import warnings

import numpy as np
import open3d as o3d
import pytest
import torch

from roigsf_ros.cli import main as cli_main
from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame, resize_frame
from roigsf_ros.data.bags import write_bag
from roigsf_ros.data.replica import ReplicaSequence, write_replica
from roigsf_ros.data.sources import open_frames
from roigsf_ros.evaluation.metrics import psnr
from roigsf_ros.experiments.offline import EvalConfig, run_offline
from roigsf_ros.mapping import losses
from roigsf_ros.mapping.mapper import Mapper, MapperConfig, write_h_train
from roigsf_ros.policies.base import make_policy

INTR = Intrinsics(width=64, height=48, fx=52.0, fy=52.0, cx=31.5, cy=23.5)
ROOM_LO, ROOM_HI = np.array([-2.0, -1.5, 0.0]), np.array([2.0, 1.5, 2.5])


def room_mesh() -> o3d.geometry.TriangleMesh:
    """A 4 x 3 x 2.5 m box room with a 0.6 m cube standing on its floor."""
    room = o3d.geometry.TriangleMesh.create_box(*(ROOM_HI - ROOM_LO)).translate(ROOM_LO)
    cube = o3d.geometry.TriangleMesh.create_box(0.6, 0.6, 0.6).translate((0.8, -0.3, 0.0))
    mesh = room + cube
    mesh.compute_vertex_normals()
    return mesh


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def ray_cast(mesh: o3d.geometry.TriangleMesh, index: int, T_wc: np.ndarray) -> Frame:
    """Depth (z, metres) and a smooth procedural texture of the mesh seen from ``T_wc``."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float64)  # pixel centres at integers
    d_w = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)], -1) @ T_wc[:3, :3].T
    rays = np.concatenate([np.broadcast_to(T_wc[:3, 3], d_w.shape), d_w], -1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    hit = np.isfinite(t)
    p = T_wc[:3, 3] + d_w * np.where(hit, t, 0)[..., None]
    rgb = 0.5 + 0.35 * np.sin(np.stack([3 * p[..., 0] + 2 * p[..., 2], 4 * p[..., 1] - p[..., 0], 5 * p[..., 2]], -1))
    return Frame(index=index, rgb=(rgb * 255).astype(np.uint8), depth_m=np.where(hit, t, 0).astype(np.float32),
                 T_wc=T_wc)  # fmt: skip


def trajectory(n: int) -> list[np.ndarray]:
    """A slow pan from the +x wall over the cube to the +y wall, from near the room centre."""
    out = []
    for a in np.linspace(-0.35, 1.25, n):
        eye = np.array([-0.6, -0.4, 1.4]) + 0.1 * np.array([np.cos(a), np.sin(a), 0.0])
        out.append(look_at(eye, eye + np.array([np.cos(a), np.sin(a), -0.35])))
    return out


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    mesh = room_mesh()
    return [ray_cast(mesh, i, T) for i, T in enumerate(trajectory(7))]


def small_config(**kw: object) -> MapperConfig:
    base = dict(iters_per_keyframe=20, seed=3, mesh_voxel_size_m=0.04, mesh_sdf_trunc_m=0.12)
    return MapperConfig(**(base | kw))


def eval_at(mapper: Mapper, frame: Frame) -> tuple[float, float]:
    """PSNR (dB) and depth L1 (m) of the map at a frame's pose."""
    out = mapper.render(frame.T_wc)
    d = out.expected_depth().numpy()
    valid = frame.depth_m > 0
    return psnr(out.color.clamp(0, 1).numpy(), frame.rgb), float(np.abs(d - frame.depth_m)[valid].mean())


def test_mapping_fits_a_held_out_view_and_tracks_h_train(frames: list[Frame]) -> None:
    train, held_out = frames[0::2], frames[3]
    seeded = Mapper(INTR, small_config(track_h_train=False))
    for f in train:
        assert seeded.add_keyframe(f, optimise=False)
    mapper = Mapper(INTR, small_config())
    for f in train:
        assert mapper.add_keyframe(f)
        assert len(mapper._fisher_pending) == 1  # lazy: computed when h_train is next read
        # h_train follows the surfel set through every densify/prune.
        for k, h in mapper.h_train.items():
            assert h.shape == getattr(mapper.map, k).shape
    assert mapper.keyframe_ids == [0, 2, 4, 6]
    psnr0, _ = eval_at(seeded, held_out)
    psnr1, dl1_1 = eval_at(mapper, held_out)
    assert dl1_1 < 0.03, f"held-out depth L1 {dl1_1:.4f} m"
    assert psnr1 > psnr0 + 1.0, f"PSNR {psnr0:.2f} -> {psnr1:.2f}"
    assert psnr1 > 22.0
    stats = mapper.stats
    assert stats.keyframes_added == 4 and stats.steps == 4 * 20 and stats.steps_skipped_nonfinite == 0
    assert not mapper._fisher_pending

    # Surfels the training views see carry information; the Fisher is finite and non-negative.
    assert set(mapper.h_train) == {"means", "quats", "log_scales", "opacity_logits", "sh_dc"}
    seen = torch.zeros(mapper.n_surfels, dtype=torch.bool)
    for kf in mapper.keyframes:
        seen |= mapper.render(kf.T_wc).visible
    per_surfel = sum(h.reshape(mapper.n_surfels, -1).sum(-1) for h in mapper.h_train.values())
    assert all(bool(torch.isfinite(h).all()) and bool((h >= 0).all()) for h in mapper.h_train.values())
    assert float((per_surfel[seen] > 0).float().mean()) > 0.95
    assert float(per_surfel[~seen].abs().sum()) == 0.0 or float((per_surfel[~seen] > 0).float().mean()) < 0.5
    recomputed = mapper.recompute_h_train()
    assert all(recomputed[k].shape == getattr(mapper.map, k).shape for k in recomputed)
    assert float(recomputed["means"].sum()) > 0

    # Pruning keeps h_train aligned.
    with torch.no_grad():
        mapper.map.opacity_logits[:10] = -20.0
    n_before = mapper.n_surfels
    assert mapper.prune() >= 10
    assert mapper.n_surfels <= n_before - 10
    assert all(h.shape[0] == mapper.n_surfels for h in mapper.h_train.values())


def test_bad_input_is_masked_skipped_or_refused(frames: list[Frame], caplog: pytest.LogCaptureFixture) -> None:
    mapper = Mapper(INTR, small_config(iters_per_keyframe=3))
    f0 = frames[0]
    # An empty map renders nothing, meshes to nothing and optimises to a no-op.
    assert mapper.render_alpha(f0.T_wc).max() == 0.0
    assert float(mapper.render(f0.T_wc).alpha.max()) == 0.0
    assert mapper.optimise(3) == {}
    assert len(mapper.mesh(poses=[f0.T_wc]).triangles) == 0

    caplog.set_level(logging.WARNING, logger="roigsf_ros.mapping.mapper")
    nan_depth = Frame(index=10, rgb=f0.rgb, depth_m=np.full_like(f0.depth_m, np.nan), T_wc=f0.T_wc)
    zero_depth = Frame(index=11, rgb=f0.rgb, depth_m=np.zeros_like(f0.depth_m), T_wc=f0.T_wc)
    far_depth = Frame(index=12, rgb=f0.rgb, depth_m=np.full_like(f0.depth_m, 1e4), T_wc=f0.T_wc)
    for bad in (nan_depth, zero_depth, far_depth):
        assert not mapper.add_keyframe(bad)
    assert mapper.stats.frames_skipped_no_depth == 3 and mapper.n_surfels == 0 and not mapper.keyframes
    assert mapper.stats.invalid_depth_pixels == 3 * INTR.width * INTR.height
    assert "no valid depth" in caplog.text
    # each says what it saw: nothing usable, or values out of range with a hint for millimetres given as metres
    assert "frame 10: no valid depth (every value NaN, infinite, zero or negative; valid is min_depth_m" in caplog.text
    assert "frame 12: no valid depth (finite values 1e+04-1e+04 m, outside min_depth_m" in caplog.text
    assert "millimetres given as metres?" in caplog.text

    # Partly broken depth: the bad pixels are masked and counted, the map stays finite.
    depth = f0.depth_m.copy()
    depth[:10] = np.nan
    depth[10:14] = 0.0
    depth[14:16] = -1.0
    depth[16:18] = np.inf
    partial = Frame(index=13, rgb=f0.rgb, depth_m=depth, T_wc=f0.T_wc)
    assert mapper.add_keyframe(partial)
    assert mapper.stats.invalid_depth_pixels == 3 * INTR.width * INTR.height + 18 * INTR.width
    assert all(bool(torch.isfinite(t).all()) for t in mapper.map.parameters())

    # Not a rigid transform / wrong image size: a clear InputError, nothing added.
    n = mapper.n_surfels
    sheared = f0.T_wc.copy()
    sheared[0, 1] += 0.3
    with pytest.raises(InputError, match="rigid"):
        mapper.add_keyframe(Frame(index=14, rgb=f0.rgb, depth_m=f0.depth_m, T_wc=sheared))
    nan_pose = f0.T_wc.copy()
    nan_pose[0, 3] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        mapper.add_keyframe(Frame(index=15, rgb=f0.rgb, depth_m=f0.depth_m, T_wc=nan_pose))
    with pytest.raises(InputError, match="shape"):
        mapper.add_keyframe(Frame(index=16, rgb=f0.rgb[:20], depth_m=f0.depth_m[:20], T_wc=f0.T_wc))
    with pytest.raises(InputError, match="rigid"):
        mapper.render(sheared)
    # Colour as floats is [0, 1]: a 0-255 image given as floats would be clipped to white, so it is refused, as is an
    # integer type other than uint8 (a uint16 image); floats in [0, 1] are taken.
    rgb_255 = f0.rgb.astype(np.float32)
    with pytest.raises(InputError, match=r"frame 17: colour floats reach 2\d\d: floats must be in \[0, 1\]"):
        mapper.add_keyframe(Frame(index=17, rgb=rgb_255, depth_m=f0.depth_m, T_wc=f0.T_wc))
    with pytest.raises(InputError, match="frame 18: colour has dtype uint16"):
        mapper.add_keyframe(Frame(index=18, rgb=f0.rgb.astype(np.uint16), depth_m=f0.depth_m, T_wc=f0.T_wc))
    assert mapper.n_surfels == n and len(mapper.keyframes) == 1
    fresh = Mapper(INTR, small_config(iters_per_keyframe=1))
    assert fresh.add_keyframe(Frame(index=19, rgb=rgb_255 / 255.0, depth_m=f0.depth_m, T_wc=f0.T_wc))
    assert torch.equal(fresh.keyframes[0].rgb_u8.cpu(), torch.from_numpy(f0.rgb))

    # A step whose loss is not finite is skipped and counted; no NaN reaches the map.
    before = {k: t.clone() for k, t in mapper.map.named_parameters().items()}
    real_loss = mapper.keyframe_loss
    mapper.keyframe_loss = lambda out, kf: (real_loss(out, kf)[0] * float("nan"), {})
    mapper.optimise(2)
    mapper.keyframe_loss = real_loss
    assert mapper.stats.steps_skipped_nonfinite == 2
    assert all(torch.equal(before[k], t) for k, t in mapper.map.named_parameters().items())

    # Non-finite surfels (e.g. a corrupted load) are removed by pruning and counted.
    with torch.no_grad():
        mapper.map.means[0, 0] = float("nan")
    mapper.prune()
    assert mapper.stats.surfels_removed_nonfinite == 1
    assert all(bool(torch.isfinite(t).all()) for t in mapper.map.parameters())


def test_view_sampling() -> None:
    cfg = MapperConfig(views_per_iteration=3, newest_keyframe_prob=0.5, keyframe_window=4, seed=1)
    mapper = Mapper(INTR, cfg)
    mapper.keyframes = [None] * 10  # only the count matters to the sampler
    draws = [mapper._pick_views(newest=9) for _ in range(300)]
    assert all(len(d) == 3 and len(set(d)) == 3 and set(d) <= {6, 7, 8, 9} for d in draws)
    assert 0.7 < np.mean([9 in d for d in draws]) < 0.95  # 1 - 0.5^3 minus draws that ran out of others
    mapper.keyframes = [None]
    assert mapper._pick_views(newest=0) == [0]
    uniform = Mapper(INTR, MapperConfig(views_per_iteration=1, seed=2))
    uniform.keyframes = [None] * 5
    counts = np.bincount([uniform._pick_views(newest=None)[0] for _ in range(500)], minlength=5)
    assert counts.min() > 60  # every keyframe gets drawn


def test_losses_basics() -> None:
    torch.manual_seed(0)
    img = torch.rand(20, 24, 3)
    assert float(losses.ssim(img, img)) == pytest.approx(1.0, abs=1e-5)
    assert float(losses.ssim(img, torch.rand(20, 24, 3))) < 0.2
    assert float(losses.colour_loss(img, img)) == pytest.approx(0.0, abs=1e-5)
    # Normals of a fronto-parallel plane face the camera (-z); a tilted plane's normal matches.
    plane = torch.full((INTR.height, INTR.width), 2.0)
    n = losses.depth_to_normal_cam(plane, INTR)
    assert torch.allclose(n[1:-1, 1:-1], torch.tensor([0.0, 0.0, -1.0]).expand(46, 62, 3), atol=1e-5)
    valid = torch.zeros_like(plane, dtype=torch.bool)
    valid[5:10] = True
    assert float(losses.depth_l1(plane + 0.1, plane, valid)) == pytest.approx(0.1, abs=1e-6)
    assert float(losses.depth_l1(plane, plane, torch.zeros_like(valid))) == 0.0


class FrameList:
    """The FrameSource protocol over a list: intrinsics, len, re-iterable frames."""

    intrinsics = INTR

    def __init__(self, frames: list[Frame]) -> None:
        self.frames = frames

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self):
        return iter(self.frames)


def test_run_offline_writes_everything_and_save_load(frames: list[Frame], tmp_path) -> None:
    gt = tmp_path / "gt.ply"
    o3d.io.write_triangle_mesh(str(gt), room_mesh())
    out = tmp_path / "run"
    metrics = run_offline(
        FrameList(frames),
        make_policy("every-n", n=2),
        small_config(iters_per_keyframe=8, final_iters=4, weight_distortion=100.0),
        out,
        gt_mesh=gt,
        eval_config=EvalConfig(mesh_samples=20_000, strip_frames=2),
        progress=False,
    )
    for name in ("metrics.json", "mesh.ply", "map.ply", "strip.png", "keyframes.json"):
        assert (out / name).is_file(), name
    on_disk = json.loads((out / "metrics.json").read_text())
    required = [
        "psnr", "ssim", "depth_l1_m", "n_frames", "n_keyframes", "keyframe_ids", "wall_s", "map_size",
        "n_eval_frames", "precision@1cm", "recall@1cm", "fscore@1cm", "precision@5cm", "recall@5cm",
        "fscore@5cm", "accuracy_cm", "completion_cm", "completion_ratio_5cm", "gt_culling",
    ]  # fmt: skip
    assert not [k for k in required if k not in on_disk]
    assert on_disk["n_frames"] == 7 and on_disk["keyframe_ids"] == [0, 2, 4, 6] and on_disk["n_keyframes"] == 4
    assert on_disk["n_eval_frames"] == 3  # the non-keyframes 1, 3, 5
    assert on_disk["map_size"] == metrics["map_size"] > 0
    assert on_disk["psnr"] > 20 and on_disk["depth_l1_m"] < 0.05
    assert on_disk["precision@5cm"] > 0.8 and on_disk["recall@5cm"] > 0.8
    assert math.isfinite(on_disk["wall_s"])
    with pytest.raises(FileExistsError):
        run_offline(FrameList(frames), make_policy("all"), small_config(), out, progress=False)

    loaded = Mapper.load(out)
    assert loaded.n_surfels == metrics["map_size"]
    assert loaded.loaded_keyframe_ids == [0, 2, 4, 6]
    assert loaded.config.iters_per_keyframe == 8 and loaded.config.weight_distortion == 100.0
    a = loaded.render(frames[3].T_wc).alpha
    assert float(a.mean()) > 0.9
    assert len(loaded.mesh().triangles) > 100  # meshed at the saved keyframe poses
    # Policy "all" never read the training Fisher, so it is not computed only to be saved (test below for a map that
    # has it). Without it, the running h_train lacks the loaded keyframes (no images saved), zeros that ranked views
    # wrongly, without a word; reading it warns (once), and the policies recompute it from the poses.
    assert not (out / "h_train.npz").exists() and not loaded.h_train_complete
    with pytest.warns(RuntimeWarning, match=r"not of the 4 read by load\(\).*h_train=None"):
        h = loaded.h_train
    assert all(float(v.abs().sum()) == 0.0 for v in h.values())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loaded.h_train  # noqa: B018 - once per mapper
    assert make_policy("roi-gsurfisher")._h_train(loaded) is None


def test_a_map_whose_fisher_was_read_saves_it_and_a_save_never_leaves_another_maps(
    frames: list[Frame], tmp_path
) -> None:
    """Two walks' findings: (1) `roigsf map --policy roi-gsurfisher` never wrote ``h_train.npz``: the newest keyframe's
    lazy Fisher pass was still pending at the save, so the README's "saved when the run computed it" never held for a
    Fisher run; (2) saving a map into a folder holding another map's ``h_train.npz`` left it there, and ``Mapper.load``
    then refused the folder ("array 'means' has shape ...")."""
    out = tmp_path / "run"
    run_offline(FrameList(frames[:4]), make_policy("roi-gsurfisher", window=2), small_config(iters_per_keyframe=2),
                out, progress=False)  # fmt: skip
    assert (out / "h_train.npz").is_file()
    assert Mapper.load(out).h_train_complete  # a resumed Fisher run scores views as the saved one
    mapper = Mapper(INTR, small_config(iters_per_keyframe=2))
    for f in frames[:2]:
        mapper.add_keyframe(f)
    mapper.save(tmp_path / "map")  # never read: not computed only to be saved
    assert not (tmp_path / "map" / "h_train.npz").exists()
    mapper.h_train  # noqa: B018 - read once, as a Fisher policy does
    mapper.add_keyframe(frames[2])  # its Fisher pass pending
    assert not mapper.h_train_computed and mapper.h_train_to_save
    mapper.save(tmp_path / "map")
    assert Mapper.load(tmp_path / "map").h_train_complete
    other = Mapper(INTR, small_config(iters_per_keyframe=2))
    other.add_keyframe(frames[4])
    other.save(tmp_path / "map")  # over the first map: its h_train.npz is not this map's
    assert not (tmp_path / "map" / "h_train.npz").exists()
    write_h_train(tmp_path / "map" / "h_train.npz", mapper.h_train)  # put there by hand: said, with the way out
    with pytest.raises(InputError, match=r"another map's\? without the file the map loads"):
        Mapper.load(tmp_path / "map")
    (tmp_path / "map" / "h_train.npz").unlink()
    assert Mapper.load(tmp_path / "map").n_surfels == other.n_surfels


def test_depth_mostly_out_of_range_is_warned_once_and_noted_under_the_run(
    frames: list[Frame], caplog: pytest.LogCaptureFixture
) -> None:
    """A walk: ``scale: 1000`` in a Replica cam_params.json (depth 6.55x too far) masked 93 % of every frame beyond
    ``max_depth_m`` and `roigsf map` gave F@5cm 0.000 without a word. The mapper counts the out-of-range values,
    warns once, and the run's table says so; holes (zero depth) are not counted as out of range."""
    from dataclasses import asdict

    from roigsf_ros.cli import metric_notes

    mapper = Mapper(INTR, small_config(iters_per_keyframe=1))
    with caplog.at_level(logging.WARNING, logger="roigsf_ros.mapping.mapper"):
        for f in frames[:2]:
            far = f.depth_m * 20.0  # 1-3 m read as 20-60 m
            far[:4] = 0.0  # and a few holes
            mapper.add_keyframe(Frame(f.index, f.rgb, far, f.T_wc))
    said = [r.getMessage() for r in caplog.records if "depth values are outside" in r.getMessage()]
    assert len(said) == 1 and "a depth scale off" in said[0], said
    stats = {f"mapper_{k}": v for k, v in asdict(mapper.stats).items()}
    assert stats["mapper_depth_pixels"] == 2 * INTR.width * INTR.height
    assert stats["mapper_depth_out_of_range_pixels"] == stats["mapper_invalid_depth_pixels"] - 2 * 4 * INTR.width
    assert any("depth values were outside min_depth_m..max_depth_m" in n for n in metric_notes(stats))
    holes = Mapper(INTR, small_config(iters_per_keyframe=1))
    hollow = frames[0].depth_m.copy()
    hollow[: INTR.height * 3 // 4] = 0.0  # most of the frame without depth: a sensor's holes, no scale error
    holes.add_keyframe(Frame(0, frames[0].rgb, hollow, frames[0].T_wc))
    stats = {f"mapper_{k}": v for k, v in asdict(holes.stats).items()}
    assert stats["mapper_depth_out_of_range_pixels"] == 0 and not metric_notes(stats)


def test_a_resumed_map_scores_views_as_the_saved_one(frames: list[Frame], tmp_path) -> None:
    """``save-map`` then ``load-map`` changed the NBV scores (a walk: Fisher 2.287e7 -> 9.883e6 for one candidate):
    the running training Fisher was not saved, and the loaded map's was recomputed from the poses under another
    rule. ``h_train.npz`` now travels with the map, so the scores are the same; a damaged one is named."""
    from roigsf_ros.nbv.state import score_views

    mapper = Mapper(INTR, small_config(iters_per_keyframe=3))
    for f in frames[:3]:
        mapper.add_keyframe(f)
    candidates = [f.T_wc for f in frames[3:6]]
    before = score_views(mapper, candidates)
    mapper.save(tmp_path / "map")
    loaded = Mapper.load(tmp_path / "map")
    after = score_views(loaded, candidates)
    np.testing.assert_allclose(after.fisher, before.fisher, rtol=1e-5)
    np.testing.assert_allclose(after.fused, before.fused, rtol=1e-5, atol=1e-6)
    loaded.save(tmp_path / "again")  # load then save keeps it
    for k, v in np.load(tmp_path / "map" / "h_train.npz").items():
        np.testing.assert_array_equal(np.load(tmp_path / "again" / "h_train.npz")[k], v)
    h = dict(np.load(tmp_path / "map" / "h_train.npz"))
    for bad, words in (({**h, "means": h["means"][:-1]}, r"array 'means' has shape"),
                       ({**h, "means": np.full_like(h["means"], np.nan)}, "not finite and >= 0"),
                       ({k: v for k, v in h.items() if k != "means"}, r"no array 'means'")):  # fmt: skip
        np.savez(tmp_path / "map" / "h_train.npz", **bad)
        with pytest.raises(InputError, match=rf"^{tmp_path / 'map' / 'h_train.npz'}: .*{words}"):
            Mapper.load(tmp_path / "map")
    np.savez(tmp_path / "map" / "h_train.npz", **{k: v for k, v in h.items() if k != "means"})  # a config of its own
    assert not Mapper.load(tmp_path / "map", config=small_config(iters_per_keyframe=3)).h_train_complete  # recomputed
    (tmp_path / "map" / "h_train.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a readable training-Fisher file"):
        Mapper.load(tmp_path / "map")


@pytest.mark.parametrize(
    ("returns", "error"),
    [
        ("none", r"observe\(\) returned NoneType, not a list"),
        ("frame", r"observe\(\) returned Frame, not a list"),
        ("int", r"observe\(\) returned a int among its frames, not a Frame"),
        ("twice", r"observe\(\) named frame 0 twice in one answer"),
        ("again", r"observe\(\) named frame 0 again"),
        ("finish", r"finish\(\) named frame 0 again"),
    ],
)
def test_a_policy_that_returns_no_list_of_new_frames_is_named(
    frames: list[Frame], tmp_path, monkeypatch: pytest.MonkeyPatch, returns: str, error: str
) -> None:
    """What a policy's ``observe``/``finish`` returns is checked: a wrong type failed deep in the mapper, and a frame
    named twice was inserted twice, its keyframe id twice in keyframes.json and its Fisher counted twice."""
    from roigsf_ros.policies import base

    monkeypatch.setattr(base, "_REGISTRY", dict(base._REGISTRY))  # registered for this test only

    @base.register_policy("test-bad")
    class Bad(base.KeyframePolicy):
        def __init__(self, returns: str = "none") -> None:
            self.returns, self.first = returns, None

        def observe(self, frame, keyframe_map):
            self.first = self.first or frame
            if frame.index < 2:
                if self.returns == "raise" and frame.index == 1:
                    raise RuntimeError("the policy's own bug")
                return {"none": None, "frame": frame, "int": [3], "twice": [frame, frame]}.get(self.returns, [frame])
            return [self.first] if self.returns == "again" else []

        def finish(self, keyframe_map):
            return [self.first] if self.returns == "finish" else []

    out = tmp_path / "run"
    with pytest.raises(InputError, match=error) as info:
        run_offline(FrameList(frames), make_policy("test-bad", returns=returns), small_config(), out, progress=False)
    assert info.value.where == "keyframe policy 'test-bad'" and not out.exists()
    if returns == "none":  # a policy that raises: its own traceback, with a note naming the policy and the frame
        with pytest.raises(RuntimeError, match="the policy's own bug") as raised:
            raising = make_policy("test-bad", returns="raise")
            run_offline(FrameList(frames), raising, small_config(), out, progress=False)
        assert raised.value.__notes__ == ["in keyframe policy 'test-bad': observe() of frame 1"] and not out.exists()


def test_score_views_scores_a_built_and_a_loaded_map_alike(frames: list[Frame], tmp_path) -> None:
    """``nbv.score_views``: candidate poses scored against a Mapper in one call, with the recommended settings too; a
    map from ``Mapper.load`` (no keyframe images, its poses in ``map_keyframes``) scores as the map it was saved from
    with H_train recomputed (a walk gave ``keyframe_poses``, empty there, and got zeros and "no TSDF given")."""
    from roigsf_ros.nbv import RECOMMENDED_UNSEEN, NBVConfig, score_views

    mapper = Mapper(INTR, small_config(iters_per_keyframe=8, track_h_train=False))  # H_train recomputed in both
    for f in frames[::2]:
        mapper.add_keyframe(f)
    mapper.save(tmp_path / "map")
    loaded = Mapper.load(tmp_path / "map")
    assert len(loaded.keyframe_poses) == 0 and len(loaded.map_keyframes()[1]) == 4
    candidates = np.stack([f.T_wc for f in frames[1::2]])
    for config in (None, NBVConfig(**RECOMMENDED_UNSEEN)):
        built = score_views(mapper, candidates, config)
        again = score_views(loaded, candidates, config)
        assert built.reason == again.reason == "" and np.isfinite(again.fused).all() and np.ptp(again.fused) > 0
        np.testing.assert_allclose(again.fused, built.fused, rtol=1e-5, atol=1e-9)
        assert list(again.ranking) == list(built.ranking)


def test_the_library_names_a_researchers_easy_mistakes(frames: list[Frame], tmp_path) -> None:
    """A sixty-fourth-session walk of the Python API: each of these went through silently or failed deep inside on a
    missing attribute; now each is an error naming the argument (or, for an empty map, a reason that fits)."""
    from roigsf_ros.evaluation.metrics import ssim
    from roigsf_ros.experiments.pool import PoolConfig, run_pool
    from roigsf_ros.nbv import RECOMMENDED_UNSEEN, NBVConfig, score_views
    from roigsf_ros.render.rasterize import rasterize_surfels, render_map
    from roigsf_ros.render.surfels import surfels_from_rgbd

    f = frames[0]
    mapper = Mapper(INTR, small_config(iters_per_keyframe=0, track_h_train=False))
    mapper.add_keyframe(f)
    candidates = np.stack([g.T_wc for g in frames[1:4]])
    with pytest.raises(InputError, match=r"^config: expected a NBVConfig, got mappingproxy: give NBVConfig\(\*\*it\)"):
        score_views(mapper, candidates, RECOMMENDED_UNSEEN)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="top_k"):
        score_views(mapper, candidates, top_k=0)  # was taken as the default 5
    empty = score_views(Mapper(INTR, small_config()), candidates, NBVConfig(**RECOMMENDED_UNSEEN))
    assert "no TSDF given" not in empty.reason and "no keyframe fused into it" in empty.reason, empty.reason
    with pytest.raises(InputError, match=r"^surfel_map: expected a SurfelMap \(a Mapper's is mapper.map\), got Mapper"):
        render_map(mapper, f.T_wc, INTR)
    with pytest.raises(InputError, match=r"^intr: expected an Intrinsics, got NoneType"):
        render_map(mapper.map, f.T_wc, None)  # type: ignore[arg-type]
    scaled = f.T_wc.copy()
    scaled[:3, :3] *= 2.0
    for bad, words in ((np.full((4, 4), np.nan), "non-finite"), (scaled, "not orthonormal")):
        with pytest.raises(InputError, match=f"^T_wc: pose.*{words}"):  # rendered an empty or warped image
            render_map(mapper.map, bad, INTR)
    view = torch.as_tensor(np.linalg.inv(f.T_wc), dtype=torch.float32)
    m = mapper.map
    with pytest.raises(ValueError, match=r"^viewmat must be a torch.Tensor, got ndarray"):
        rasterize_surfels(m.means, m.quats, m.scales(), m.opacities(), m.colors(), view.numpy(),
                          torch.as_tensor(INTR.K, dtype=torch.float32), INTR.width, INTR.height)  # fmt: skip
    as_floats = f.rgb.astype(np.float32)  # 0-255 as floats: clipped to a white map / a 2 dB PSNR before
    with pytest.raises(InputError, match=r"^rgb: colour floats reach 2\d\d: floats must be in \[0, 1\]"):
        surfels_from_rgbd(as_floats, f.depth_m, f.T_wc, INTR)
    with pytest.raises(InputError, match=r"^pred_rgb: colour floats have median \d+"):
        psnr(as_floats, f.rgb)
    assert psnr(f.rgb.astype(np.float32) / 255.0, f.rgb) > 40  # floats in [0, 1] as before
    with pytest.raises(InputError, match=r"SSIM needs images of at least 11x11 px .* got 8x8"):
        ssim(f.rgb[:8, :8], f.rgb[:8, :8])
    with pytest.raises(InputError, match=r"^intr: expected an Intrinsics"):
        Mapper(None)  # type: ignore[arg-type]  # failed at the first keyframe
    (tmp_path / "file").write_text("in the way")
    with pytest.raises(InputError, match="cannot create the map folder"):
        mapper.save(tmp_path / "file" / "map")
    with pytest.raises(InputError, match=r"^source: expected a frame sequence, got str: open a folder or bag with"):
        run_offline(str(tmp_path), make_policy("all"), small_config(), tmp_path / "out")  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"^source: expected a frame sequence, got PosixPath"):
        run_pool(tmp_path, PoolConfig(), small_config())  # type: ignore[arg-type]
    with pytest.raises(InputError, match="is a file, not a scene folder"):
        open_frames(tmp_path / "file")


def test_the_demo_says_against_what_its_recall_is_taken(frames: list[Frame], tmp_path) -> None:
    """``roigsf demo``'s report takes the mesh metrics as ``roigsf map`` does (:func:`run_mesh_metrics`): the GT culled
    to what every frame's pose observes, and says so in ``gt_culling`` (its metrics.json did not say)."""
    from roigsf_ros import evaluation
    from roigsf_ros.cli.demo import evaluate_map
    from roigsf_ros.data.bags import BagFrame

    gt = tmp_path / "gt.ply"
    o3d.io.write_triangle_mesh(str(gt), room_mesh())
    mapper = Mapper(INTR, small_config(iters_per_keyframe=8, weight_distortion=100.0))
    for f in frames[::2]:
        mapper.add_keyframe(f)
    # the nodes name a keyframe by its frame's stamp: a bag whose stamps are the frame numbers
    bag = [BagFrame(f.index, f.rgb, f.depth_m, f.T_wc, INTR) for f in frames]
    ev = EvalConfig(mesh_samples=20_000, strip_frames=2)
    metrics, rows, mesh = evaluate_map(mapper, bag, gt, ev)
    assert metrics["n_keyframes"] == 4 and metrics["keyframes_in_bag"] == 4 and len(rows) == 2
    assert metrics["gt_culling"].startswith("GT samples culled") and metrics["gt_mesh"] == str(gt)
    poses = np.stack([f.T_wc for f in frames])
    kwargs = {"taus_m": ev.mesh_taus_m, "n_samples": ev.mesh_samples, "seed": ev.seed}
    culled = evaluation.mesh_metrics(mesh, gt, observed_poses=poses, intr=INTR,
                                     cull_max_depth_m=mapper.config.max_depth_m, **kwargs)  # fmt: skip
    whole = evaluation.mesh_metrics(mesh, gt, **kwargs)
    assert metrics["recall@5cm"] == culled["recall@5cm"] > whole["recall@5cm"]
    unculled, _, _ = evaluate_map(mapper, bag, gt, EvalConfig(mesh_samples=20_000, cull_gt_to_observed=False))
    assert unculled["gt_culling"].startswith("none") and unculled["recall@5cm"] == whole["recall@5cm"]


def test_cli_map(frames: list[Frame], tmp_path, capsys: pytest.CaptureFixture) -> None:
    scene = tmp_path / "scene"
    write_replica(scene, INTR, frames[:4])
    o3d.io.write_triangle_mesh(str(scene / "mesh.ply"), room_mesh())
    src = open_frames(scene, stride=2)
    assert len(src) == 2 and src.gt_mesh_path == scene / "mesh.ply" and len(list(src)) == 2
    run = tmp_path / "run"
    rc = cli_main(["map", str(scene), "--policy", "every-n", "--every-n", "1", "--out", str(run),
                   "--width", "32", "--height", "24", "--iters-per-keyframe", "2", "--no-progress",
                   "--set", "mesh_voxel_size_m=0.05", "--set", "mesh_sdf_trunc_m=0.15"])  # fmt: skip
    assert rc == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["n_keyframes"] == 4 and "precision@5cm" in metrics  # GT mesh found beside the frames
    assert metrics["config"]["mesh_voxel_size_m"] == 0.05
    assert "keyframes" in capsys.readouterr().out
    # --test-scene: frames the policy never sees, evaluated on the final map
    between = tmp_path / "between"
    write_replica(between, INTR, frames[4:6])
    rc = cli_main(["map", str(scene), "--policy", "every-n", "--every-n", "2", "--out", str(tmp_path / "run_t"),
                   "--width", "32", "--height", "24", "--iters-per-keyframe", "2", "--no-progress",
                   "--test-scene", str(between), "--set", "mesh_voxel_size_m=0.05",
                   "--set", "mesh_sdf_trunc_m=0.15"])  # fmt: skip
    assert rc == 0
    m_t = json.loads((tmp_path / "run_t" / "metrics.json").read_text())
    assert m_t["test_scene_frames"] == 2 and m_t["test_scene"] == str(between)
    assert np.isfinite(m_t["test_scene_psnr"]) and 0.0 <= m_t["test_scene_uncovered_error_share"] <= 1.0
    assert "test-scene PSNR" in capsys.readouterr().out

    assert cli_main(["map", str(tmp_path / "missing"), "--out", str(tmp_path / "r2")]) == 2
    assert cli_main(["map", str(scene), "--out", str(run)]) == 2  # exists, no --overwrite
    assert cli_main(["map", str(scene), "--out", str(tmp_path / "r3"), "--policy", "nope"]) == 2
    assert cli_main(["map", str(scene), "--out", str(tmp_path / "r4"), "--set", "lr_means=abc"]) == 2
    assert cli_main(["map", str(scene), "--out", str(tmp_path / "r5"), "--window", "3"]) == 2  # gaus-slam: no window
    assert cli_main(["map", str(scene), "--out", str(tmp_path / "r6"), "--policy", "random", "--window", "0"]) == 2
    assert "error" in capsys.readouterr().err
    assert not any((tmp_path / f"r{k}").exists() for k in range(2, 7))


def test_resize_keeps_pixel_centres_aligned() -> None:
    src = Intrinsics(width=48, height=36, fx=40.0, fy=40.0, cx=23.5, cy=17.5)
    dst = src.resized(16, 12)  # factor 3: destination pixel j is centred on source pixel 3j + 1
    depth = np.tile(np.arange(48, dtype=np.float32), (36, 1)) + 100 * np.arange(36, dtype=np.float32)[:, None]
    frame = Frame(index=0, rgb=np.zeros((36, 48, 3), np.uint8), depth_m=depth, T_wc=np.eye(4))
    out = resize_frame(frame, dst)
    jj, ii = np.meshgrid(np.arange(16), np.arange(12))
    np.testing.assert_array_equal(out.depth_m, depth[3 * ii + 1, 3 * jj + 1])
    assert dst.cx == pytest.approx((src.cx - 1) / 3)  # the same point: source centre 1 -> destination 0


def test_open_frames_from_a_bag(frames: list[Frame], tmp_path) -> None:
    scene = tmp_path / "scene"
    write_replica(scene, INTR, frames[:5])
    bag = tmp_path / "bag"
    write_bag(ReplicaSequence(scene), bag, progress=False)
    src = open_frames(bag, size=(32, 24), stride=2, max_frames=2)
    assert src.kind == "bag" and len(src) == 2 and src.gt_mesh_path is None
    assert (src.intrinsics.width, src.intrinsics.height) == (32, 24)
    assert src.intrinsics.fx == pytest.approx(INTR.fx / 2)
    got = list(src)
    assert [f.index for f in got] == [0, 2]
    assert got[1].rgb.shape == (24, 32, 3) and got[1].depth_m.shape == (24, 32)
    np.testing.assert_allclose(got[1].T_wc, frames[2].T_wc, atol=1e-6)
    assert len(open_frames(bag)) == 5
    with pytest.raises(InputError):
        open_frames(bag, stride=0)
    with pytest.raises(InputError):
        open_frames(tmp_path / "nothing-here")


@pytest.fixture(scope="module")
def saved_map(frames: list[Frame], tmp_path_factory: pytest.TempPathFactory):
    """A saved one-keyframe map folder (no optimisation) and its keyframes.json contents."""
    mapper = Mapper(INTR, small_config(iters_per_keyframe=0))
    assert mapper.add_keyframe(frames[0], optimise=False)
    out = tmp_path_factory.mktemp("saved") / "map"
    mapper.save(out)
    return out, json.loads((out / "keyframes.json").read_text())


def _edit(meta: dict, path: str, value: object) -> dict:
    """A deep copy of ``meta`` with the dotted ``path`` set to ``value`` (``...`` deletes it)."""
    meta = json.loads(json.dumps(meta))
    *parents, last = path.split(".")
    node = meta
    for key in parents:
        node = node[key]
    if value is ...:
        del node[last]
    else:
        node[last] = value
    return meta


_BAD_META = [
    (lambda m: [m], "JSON object"),  # a list instead of an object
    (lambda m: _edit(m, "intrinsics", ...), "'intrinsics'"),
    (lambda m: _edit(m, "intrinsics", [64, 48]), "'intrinsics'"),
    (lambda m: _edit(m, "intrinsics.fx", ...), "'intrinsics.fx' is missing"),
    (lambda m: _edit(m, "intrinsics.focal", 50.0), "'intrinsics.focal' is unknown"),
    (lambda m: _edit(m, "intrinsics.width", "sixty-four"), "'intrinsics.width'"),
    (lambda m: _edit(m, "intrinsics.width", 64.5), "'intrinsics.width'"),
    (lambda m: _edit(m, "intrinsics.height", None), "'intrinsics.height'"),
    (lambda m: _edit(m, "intrinsics.fy", -1.0), "'intrinsics.fy'"),
    (lambda m: _edit(m, "keyframe_ids", ["zero"]), "'keyframe_ids'"),
    (lambda m: _edit(m, "keyframe_ids", [0, 1]), "'keyframe_poses' has 1 poses for 2"),
    (lambda m: _edit(m, "keyframe_poses", [[1, 2, 3]]), "'keyframe_poses[0]'"),
    (lambda m: _edit(m, "keyframe_poses", [[[1, 2], [3]]]), "'keyframe_poses[0]'"),
    (lambda m: _edit(m, "keyframe_poses", [(2 * np.eye(4)).tolist()]), "'keyframe_poses[0]'"),
    (lambda m: _edit(m, "keyframe_poses", 7), "'keyframe_poses'"),
    (lambda m: _edit(m, "config", [1, 2]), "config"),
    (lambda m: _edit(m, "config.no_such_field", 1), "no_such_field"),
    (lambda m: _edit(m, "config.iters_per_keyframe", "many"), "'iters_per_keyframe'"),
    (lambda m: _edit(m, "config.near_m", -1.0), "'near_m'"),
    (lambda m: _edit(m, "config.fisher_params", ["nope"]), "fisher_params"),
    (lambda m: _edit(m, "config.device", "quantum"), "'device'"),
]


@pytest.mark.parametrize(
    ("device", "problem"),
    [("quantum", "not a torch device"), ("meta", "only cpu and cuda"), ("cuda:99", "CUDA device")],
)
def test_an_unusable_device_is_refused_naming_the_field(device: str, problem: str) -> None:
    """Not deep inside the first render (torch's AssertionError without CUDA): at the config, naming the field."""
    with pytest.raises(InputError) as exc:
        MapperConfig(device=device)
    msg = str(exc.value)
    assert msg.startswith(f"mapper.device: '{device}'") and problem in msg, msg
    assert MapperConfig(device="cpu:0").device == "cpu:0"


@pytest.mark.parametrize(("corrupt", "field"), _BAD_META)
def test_load_of_a_malformed_keyframes_json_names_the_file_and_field(saved_map, tmp_path, corrupt, field) -> None:
    src, meta = saved_map
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "map.ply").write_bytes((src / "map.ply").read_bytes())
    (bad / "keyframes.json").write_text(json.dumps(corrupt(meta)))
    with pytest.raises(InputError) as exc:  # never KeyError/TypeError/AttributeError
        Mapper.load(bad)
    msg = str(exc.value)
    assert msg.startswith(str(bad / "keyframes.json")) and field in msg, msg


def test_map_load_errors_name_the_file(saved_map, tmp_path) -> None:
    src, meta = saved_map
    assert Mapper.load(src).loaded_keyframe_ids == meta["keyframe_ids"]  # the intact folder loads
    folder = tmp_path / "m"
    folder.mkdir()
    (folder / "keyframes.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match=r"m/map\.ply: PLY file not found"):
        Mapper.load(folder)
    (folder / "map.ply").write_bytes((src / "map.ply").read_bytes()[:-10])
    with pytest.raises(InputError, match=r"m/map\.ply: truncated"):
        Mapper.load(folder)
    (folder / "keyframes.json").write_text("{truncated")
    with pytest.raises(InputError, match=r"m/keyframes\.json: cannot read"):
        Mapper.load(folder)
    with pytest.raises(InputError, match=r"nothing: no such map folder"):  # the folder, not its keyframes.json
        Mapper.load(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match=r"empty/keyframes\.json: not found"):
        Mapper.load(tmp_path / "empty")


def test_sparse_adam_numba_matches_torch() -> None:
    """The numba sparse Adam (CPU) and the torch one (other devices) update the same rows alike."""
    from roigsf_ros.mapping.mapper import _SparseAdam

    shapes = {"means": (50, 3), "quats": (50, 4), "opacity_logits": (50,)}
    results = []
    for use_numba in (True, False):
        params = {
            k: torch.randn(*s, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
            for k, s in shapes.items()
        }
        adam = _SparseAdam({"means": 1e-2, "quats": 2e-3, "opacity_logits": 5e-2})
        adam.sync(params)
        for step in range(4):
            rows = torch.randperm(50, generator=torch.Generator().manual_seed(step))[:30]
            for p in params.values():
                p.grad = torch.randn(p.shape, generator=torch.Generator().manual_seed(10 + step), dtype=torch.float64)
            if use_numba:
                adam.step(params, rows)
            else:
                import roigsf_ros.mapping.mapper as mm

                saved = mm._numba_rows_ok
                mm._numba_rows_ok = lambda *a: False
                try:
                    adam.step(params, rows)
                finally:
                    mm._numba_rows_ok = saved
        results.append((params, adam))
    (pa, aa), (pb, ab) = results
    assert torch.equal(aa.t, ab.t)
    for k in shapes:
        assert torch.allclose(pa[k], pb[k], rtol=1e-12, atol=1e-14), k
        assert torch.allclose(aa.m[k], ab.m[k], rtol=1e-12, atol=1e-14)
        assert torch.allclose(aa.v[k], ab.v[k], rtol=1e-12, atol=1e-14)


def test_gradient_check_sees_non_finite_rows() -> None:
    from roigsf_ros.mapping.mapper import Mapper

    p = {"means": torch.zeros(10, 3, requires_grad=True)}
    p["means"].grad = torch.zeros(10, 3)
    assert Mapper._grads_finite(p, torch.tensor([1, 2, 3]))
    p["means"].grad[2, 1] = float("nan")
    assert not Mapper._grads_finite(p, torch.tensor([1, 2, 3]))
    p["means"].grad[2, 1] = float("inf")
    assert not Mapper._grads_finite(p, torch.tensor([2]))


def test_a_loaded_map_saved_again_keeps_its_keyframes_and_adds_the_new_ones(frames: list[Frame], tmp_path) -> None:
    """`Mapper.load(d).save(d2)` writes d's keyframe ids and poses (was: none), a keyframe inserted after the load goes
    after them, and the shared map's save writes the same keyframes.json (one list: `Mapper.map_keyframes`)."""
    from roigsf_ros.nodes.shared_map import SharedMapper

    def ids_poses(folder) -> tuple[list[int], np.ndarray]:
        meta = json.loads((folder / "keyframes.json").read_text())
        return meta["keyframe_ids"], np.asarray(meta["keyframe_poses"])

    mapper = Mapper(INTR, small_config(iters_per_keyframe=0))
    for k in (0, 2, 4):
        assert mapper.add_keyframe(frames[k], optimise=False)
    mapper.save(tmp_path / "a")
    ids_a, poses_a = ids_poses(tmp_path / "a")
    assert ids_a == [0, 2, 4]

    loaded = Mapper.load(tmp_path / "a")
    loaded.save(tmp_path / "b")
    ids_b, poses_b = ids_poses(tmp_path / "b")
    assert ids_b == ids_a
    np.testing.assert_array_equal(poses_b, poses_a)

    assert loaded.add_keyframe(frames[6], optimise=False)
    loaded.save(tmp_path / "c")
    ids_c, poses_c = ids_poses(tmp_path / "c")
    assert ids_c == [0, 2, 4, 6]
    np.testing.assert_array_equal(poses_c, np.concatenate([poses_a, frames[6].T_wc[None]]))
    assert Mapper.load(tmp_path / "c").loaded_keyframe_ids == [0, 2, 4, 6]

    shared = SharedMapper(loaded.config)
    shared.mapper = loaded
    shared.save(tmp_path / "d")
    ids_d, poses_d = ids_poses(tmp_path / "d")
    assert ids_d == ids_c
    np.testing.assert_array_equal(poses_d, poses_c)


def test_run_offline_names_an_argument_of_the_wrong_kind(frames: list[Frame], tmp_path) -> None:
    """``run_offline(config={...})`` and ``run_offline(policy="gaus-slam")`` failed as bare AttributeErrors deep in
    the mapper; the library's own errors named the CLI's flags only (``--stride``)."""
    scene = tmp_path / "scene"
    write_replica(scene, INTR, frames[:2])
    source = open_frames(scene)
    with pytest.raises(InputError, match=r"^config: must be a MapperConfig .*got a dict"):
        run_offline(source, make_policy("all"), {"iters_per_keyframe": 2}, tmp_path / "a", progress=False)  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"^policy: must be a keyframe policy .*got 'gaus-slam'"):
        run_offline(source, "gaus-slam", small_config(), tmp_path / "b", progress=False)  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"^stride \(--stride\): must be at least 1"):
        open_frames(scene, stride=0)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
