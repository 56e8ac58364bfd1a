"""`roigsf bench`: policy specs, bad input, the uncertainty maps, and small pool / stream benchmarks end to end."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from roigsf_ros.cli import main
from roigsf_ros.cli.scene import synth_intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame
from roigsf_ros.data.scene import render_sequence, synth_room, synth_trajectory
from roigsf_ros.data.sources import open_frames
from roigsf_ros.evaluation import render_metrics
from roigsf_ros.experiments import bench as bench_module
from roigsf_ros.experiments import report as report_module
from roigsf_ros.experiments.bench import (
    BenchConfig,
    PolicySpec,
    fisherrf_uncertainty_maps,
    parse_policies,
    rescore_ause,
    uncertainty_study,
)
from roigsf_ros.experiments.report import AUSE_CAVEAT, TABLE_COLUMNS, cell, parse_markdown_table
from roigsf_ros.mapping.mapper import Mapper, MapperConfig
from roigsf_ros.nbv.scorer import NBVScorer
from roigsf_ros.policies import parse_value
from roigsf_ros.policies.base import make_policy

MAPPER_SET = ["--set", "densify_stride=2", "--set", "mesh_voxel_size_m=0.05", "--set", "mesh_sdf_trunc_m=0.15",
              "--set", "iters_per_keyframe=2"]  # fmt: skip


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A `roigsf scene synth`-style folder: 24 frames of the synthetic room at 48x36 with its mesh.ply."""
    out = tmp_path_factory.mktemp("bench") / "room"
    render_sequence(synth_room(0), synth_trajectory(0, 24), synth_intrinsics(48, 36), out, progress=False)
    return out


def test_parse_policies() -> None:
    specs = parse_policies("gaus-slam, roi-gsurfisher:window=12:epsilon=0.5,random", "stream")
    assert [s.label for s in specs] == ["gaus-slam", "roi-gsurfisher:window=12:epsilon=0.5", "random"]
    assert specs[1] == PolicySpec("roi-gsurfisher", {"window": 12, "epsilon": 0.5}, specs[1].label)
    assert parse_value("true") is True and parse_value("3") == 3 and parse_value("x") == "x"
    assert parse_value("1e+3") == 1000.0 and parse_value("means + quats") == ("means", "quats")
    spec = parse_policies("roi-gsurfisher:fisher_params=means+quats+log_scales+opacity_logits", "pool")[0]
    assert make_policy(spec.name, **spec.params).config.fisher_params == (
        "means", "quats", "log_scales", "opacity_logits"
    )  # fmt: skip
    with pytest.raises(InputError, match="fisher_params"):
        parse_policies("roi-gsurfisher:fisher_params=means+colour", "pool")
    with pytest.raises(InputError, match="unknown policy 'nope'"):
        parse_policies("random,nope", "pool")
    for slip in ("random,", "random,,fisherrf"):  # ran `random` alone, or without a policy, without a word
        with pytest.raises(InputError, match=r"has an empty entry \(a comma too many, or a policy left out\)"):
            parse_policies(slip, "pool")
    with pytest.raises(InputError, match="stream-only"):
        parse_policies("random,gaus-slam", "pool")
    with pytest.raises(InputError, match="stream-only"):
        parse_policies("every-n:n=3", "pool")
    with pytest.raises(InputError, match="stream-only"):  # novelty reads captured depth: a pool view has none yet
        parse_policies("novelty", "pool")
    with pytest.raises(InputError, match=r"novelty_weight.*stream setting only"):
        parse_policies("roi-gsurfisher:unseen_weight=1:novelty_weight=1", "pool")
    with pytest.raises(InputError, match=r"novelty_measure.*stream setting only"):
        parse_policies("roi-fisher:novelty_measure=pixels", "pool")
    assert parse_policies("roi-gsurfisher:novelty_weight=1,novelty:window=5", "stream")[1].params == {"window": 5}
    with pytest.raises(InputError, match="takes no parameter"):
        parse_policies("fisherrf:windows=3", "pool")
    with pytest.raises(InputError, match="expected name:key=value"):
        parse_policies("fisherrf:window", "pool")
    with pytest.raises(InputError, match="given twice"):
        parse_policies("random,random", "pool")
    with pytest.raises(InputError, match="setting"):
        parse_policies("random", "batch")


def test_bench_config_errors(scene: Path, tmp_path: Path) -> None:
    specs = parse_policies("random", "pool")
    with pytest.raises(InputError, match="seeds"):
        BenchConfig(scene=scene, setting="pool", policies=specs, seeds=0).validate()
    with pytest.raises(InputError, match="ground-truth mesh not found"):
        BenchConfig(scene=scene, setting="pool", policies=specs, gt_mesh=tmp_path / "x.ply").validate()
    with pytest.raises(InputError, match="no such"):
        BenchConfig(scene=tmp_path / "none", setting="pool", policies=specs).validate()
    with pytest.raises(InputError, match="stream-only"):
        BenchConfig(scene=scene, setting="pool", policies=[PolicySpec("all")]).validate()


def test_a_broken_ground_truth_mesh_is_refused_before_any_work(
    scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--gt-mesh`` that is truncated, holds no triangle, is a point cloud or has a NaN vertex: ``roigsf map`` mapped
    every frame and ``roigsf bench`` trained its first run before failing as "gt_mesh: ground-truth mesh has no
    surface" (a NaN vertex passed); now refused first, naming the file, and no run starts."""
    import open3d as o3d

    box = o3d.geometry.TriangleMesh.create_box()
    good = tmp_path / "good.ply"
    o3d.io.write_triangle_mesh(str(good), box)
    cloud = o3d.geometry.PointCloud(box.vertices)
    nan_box = o3d.geometry.TriangleMesh(box)
    nan_box.vertices[0] = [float("nan"), 0.0, 0.0]
    broken = {"truncated.ply": good.read_bytes()[:-40], "text.ply": b"not a mesh\n"}
    for name, data in broken.items():
        (tmp_path / name).write_bytes(data)
    o3d.io.write_point_cloud(str(tmp_path / "cloud.ply"), cloud)
    o3d.io.write_triangle_mesh(str(tmp_path / "nan.ply"), nan_box)
    for name in ("truncated.ply", "text.ply", "cloud.ply", "nan.ply"):
        mesh = tmp_path / name
        for args in (["map", str(scene), "--policy", "every-n", "--out", str(tmp_path / "m")],
                     ["bench", "--scene", str(scene), "--setting", "pool", "--policies", "random",
                      "--out", str(tmp_path / "b")]):  # fmt: skip
            assert main([*args, "--gt-mesh", str(mesh)]) == 2, name
            err = capsys.readouterr().err
            assert f"{mesh}: " in err and any(w in err for w in ("triangles", "non-finite", "truncated")), err
    assert not (tmp_path / "m").exists() and not (tmp_path / "b").exists()


def test_an_image_too_small_to_evaluate_is_refused_before_any_work(
    scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``roigsf map --width 4`` mapped every frame, then failed in skimage's SSIM ("win_size exceeds image extent");
    ``roigsf bench`` the same after its first run. Both now refuse a side under 11 px first, and write nothing."""
    for args in (["map", str(scene), "--policy", "every-n", "--out", str(tmp_path / "m")],
                 ["bench", "--scene", str(scene), "--setting", "pool", "--policies", "random", "--out",
                  str(tmp_path / "b")]):  # fmt: skip
        assert main([*args, "--width", "10"]) == 2
        err = capsys.readouterr().err
        assert "10x" in err and "at least 11 px a side" in err and "mapping:" not in err, err
    assert not (tmp_path / "m").exists() and not (tmp_path / "b").exists()


def test_cli_bad_input(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base = ["bench", "--scene", str(scene), "--setting", "pool", "--out", str(tmp_path / "o")]
    for extra, msg in (
        (["--policies", "roi-gsurfisher,bogus"], "unknown policy 'bogus'"),
        (["--policies", "evry-n,random"], "--policies: unknown policy 'evry-n' (did you mean 'every-n'?); choose one"),
        (["--policies", "gaus-slam"], "stream-only"),
        (["--policies", "random", "--seeds", "0"], "--seeds"),
        (["--policies", "random", "--gt-mesh", str(tmp_path / "m.ply")], "ground-truth mesh not found"),
        (["--policies", "random", "--set", "nope=1"], "--set nope=1"),
        (["--policies", "random", "--pool-set", "seed=1"], "--pool-set seed=1"),
    ):
        assert main(base + extra) == 2
        assert msg in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_fisherrf_maps_match_scorer(scene: Path) -> None:
    src = open_frames(scene)
    frames = list(src)
    mapper = Mapper(src.intrinsics, MapperConfig(densify_stride=3, iters_per_keyframe=2))
    for f in frames[:3]:
        mapper.add_keyframe(f)
    scorer = NBVScorer()
    train = mapper.keyframe_poses
    evals = [frames[5].T_wc, frames[9].T_wc]
    fast = fisherrf_uncertainty_maps(scorer, mapper.map, train, evals, src.intrinsics)
    for T, u in zip(evals, fast, strict=True):
        ref = scorer.fisherrf_uncertainty(mapper.map, T, src.intrinsics, [*train, T])
        assert u.max() > 0 and np.allclose(u, ref, rtol=1e-6, atol=1e-9 * ref.max())
    study = uncertainty_study(mapper, train, [frames[5], frames[9]], n_maps=1, scorer=scorer)
    assert len(study.per_view) == 2 and len(study.maps) == 1
    assert all(0 <= v["ause_eq17"] <= 1 and 0 <= v["ause_fisherrf"] <= 1 for v in study.per_view)
    assert study.means()["ause_eq17"] == pytest.approx(np.mean([v["ause_eq17"] for v in study.per_view]))
    for v in study.per_view:  # raw AUSE in metres, one random baseline per view, rank correlations
        assert v["ause_raw_random"] > 0 and v["n_pixels"] > 0
        assert -1 <= v["rho_eq17"] <= 1 and -1 <= v["rho_fisherrf"] <= 1
    means = study.means()
    assert means["ause_raw_random_cm"] == pytest.approx(100 * np.mean([v["ause_raw_random"] for v in study.per_view]))


def check_md_matches_json(out: Path) -> dict:
    res = json.loads((out / "results.json").read_text())
    md = (out / "results.md").read_text()
    assert AUSE_CAVEAT in md
    table = parse_markdown_table(md)
    assert list(table) == [p["label"] for p in res["policies"]]
    for label, row in table.items():
        for header, key, fmt in TABLE_COLUMNS:
            if header in row:
                assert row[header] == cell(res["summary"][label], key, fmt)
            else:  # left out only when empty by construction: no test scene
                assert key.startswith("test_scene_") and not res.get("test_scene"), header
                assert cell(res["summary"][label], key, fmt) == "-"
    assert any("test scene" in header for header in next(iter(table.values()))) == bool(res.get("test_scene"))
    return res


def test_pool_bench_end_to_end(scene: Path, tmp_path: Path) -> None:
    out = tmp_path / "pool"
    argv = ["bench", "--scene", str(scene), "--setting", "pool", "--policies", "close-front,random", "--seeds", "2",
            "--out", str(out), "--no-progress", "--uncertainty-views", "2", "--uncertainty-maps", "1",
            "--pool-set", "n_views=6", "--pool-set", "initial_iters=4", "--pool-set", "iters_per_view=2",
            "--pool-set", "mesh_checkpoints=4,6", "--pool-set", "mesh_samples=3000", *MAPPER_SET]  # fmt: skip
    assert main(argv) == 0
    for name in ("results.json", "results.md", "quality_vs_views.png", "chosen_views.png",
                 "uncertainty_close-front.png", "uncertainty_random.png"):  # fmt: skip
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    res = check_md_matches_json(out)
    assert res["setting"] == "pool" and res["seeds"] == [0, 1] and res["pool_config"]["n_views"] == 6
    assert all(r["metrics"]["mapper_depth_pixels"] > 0 for r in res["runs"])  # the mapper's counters, as a stream's
    runs = res["runs"]
    assert len(runs) == 4 and {(r["label"], r["seed"]) for r in runs} == {(p, s) for p in ("close-front", "random")
                                                                         for s in (0, 1)}  # fmt: skip
    for r in runs:
        m = json.loads((out / r["dir"] / "metrics.json").read_text())
        assert m["chosen_positions"] == r["metrics"]["chosen_positions"] and m["config"]["seed"] == r["seed"]
        assert not set(m["chosen_positions"]) & set(m["test_positions"])
        assert r["metrics"]["ause_eq17"] is not None and r["metrics"]["ause_fisherrf"] is not None
    for label in ("close-front", "random"):
        vals = [r["metrics"]["recall@5cm"] for r in runs if r["label"] == label]
        s = res["summary"][label]["recall@5cm"]
        assert s["mean"] == pytest.approx(np.mean(vals)) and s["std"] == pytest.approx(np.std(vals)) and s["n"] == 2
        curve = res["curves"][label]
        assert [c["n_views"] for c in curve] == [4, 5, 6] and "recall@5cm" in curve[0] and "recall@5cm" in curve[2]
    # close-front ignores the seed beyond the mapper's; random's picks depend on it
    picks = {(r["label"], r["seed"]): r["metrics"]["chosen_positions"] for r in runs}
    assert picks[("random", 0)] != picks[("random", 1)]
    assert main(argv) == 2  # --out exists
    check_targets(out, res, "close-front", "random")
    check_rescore(out, res)


def check_targets(out: Path, res: dict, candidate: str, other: str) -> None:
    """`roigsf targets` reads a real bench's results.json: its checks hold the summary's means and stds."""
    verdict_path = out / "targets.json"
    assert main(["targets", f"{out}#{candidate}", "--against", f"{out}#{other}", "--out", str(verdict_path)]) == 0
    verdict = json.loads(verdict_path.read_text())
    assert verdict["setting"] == res["setting"] and verdict["checks"] and verdict["config_differences"] == {}
    for check in verdict["checks"]:
        key = "n_keyframes" if check["what"].startswith("keyframes") else check["what"].split(" ")[0]
        assert check["candidate"]["mean"] == res["summary"][candidate][key]["mean"]
        assert check["other"]["std"] == res["summary"][other][key]["std"]
        assert len(check["seed_margins"]) == len(res["seeds"])  # the keyframes to spare too, seed by seed


def check_rescore(out: Path, res: dict) -> None:
    """`--rescore-ause` from the saved runs reproduces the study bit for bit and replaces stale numbers."""
    stale = json.loads((out / "results.json").read_text())
    for r in stale["runs"]:  # an older results.json: wrong normalised AUSE, no raw / random / rho numbers
        r["metrics"]["ause_eq17"] = 99.0
        r["uncertainty_per_view"] = [{"frame": v["frame"], "ause_eq17": 99.0} for v in r["uncertainty_per_view"]]
        for key in ("ause_raw_random", "rho_eq17", "rho_fisherrf", "ause_raw_eq17_cm"):
            r["metrics"].pop(key, None)
    stale.pop("uncertainty_maps")
    (out / "results.json").write_text(json.dumps(stale))
    (out / "results.md").write_text("stale")
    assert main(["bench", "--rescore-ause", "--out", str(out), "--no-progress"]) == 0
    new = check_md_matches_json(out)
    assert new["ause_rescore"]["wall_s"] > 0 and new["uncertainty_maps"] == 3
    for a, b in zip(res["runs"], new["runs"], strict=True):
        assert a["dir"] == b["dir"] and a["uncertainty_per_view"] == b["uncertainty_per_view"]
        assert a["metrics"] == b["metrics"]
    assert new["summary"] == res["summary"]
    assert (out / "uncertainty_random.png").stat().st_size > 0


def test_rescore_bad_input(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "--rescore-ause", "--out", str(tmp_path)]) == 2
    assert "results.json: not found" in capsys.readouterr().err
    assert main(["bench", "--rescore-ause", "--policies", "random", "--out", str(tmp_path)]) == 2
    assert "not used with --rescore-ause" in capsys.readouterr().err
    assert main(["bench", "--out", str(tmp_path / "x")]) == 2
    assert "--scene --setting --policies: required" in capsys.readouterr().err
    (tmp_path / "results.json").write_text(json.dumps({"setting": "pool", "scene": str(scene)}))
    with pytest.raises(InputError, match="missing field"):
        rescore_ause(tmp_path)


def test_stream_bench_end_to_end(scene: Path, tmp_path: Path) -> None:
    out = tmp_path / "stream"
    policies = "every-n:n=6,random:window=6,novelty:window=6:lookahead=6"
    argv = ["bench", "--scene", str(scene), "--setting", "stream", "--policies", policies, "--out", str(out),
            "--no-progress", "--uncertainty-views", "2", "--max-frames", "14", *MAPPER_SET]  # fmt: skip
    assert main(argv) == 0
    res = check_md_matches_json(out)
    assert res["n_frames"] == 14 and res["curves"] is None
    # a walk: a wrong depth scale was said on stderr only; results.md says it when a run's counters show it
    run = res["runs"][0]
    assert run["metrics"]["mapper_depth_pixels"] > 0 and "depth scale off" not in (out / "results.md").read_text()
    doctored = run | {"metrics": run["metrics"] | {"mapper_depth_pixels": 10, "mapper_depth_out_of_range_pixels": 9}}
    assert "**90% of the keyframes' depth values were outside" in report_module.markdown(res | {"runs": [doctored]})
    every = next(r for r in res["runs"] if r["label"] == "every-n:n=6")
    assert every["metrics"]["keyframe_ids"] == [0, 6, 12] and every["chosen_positions"] == [0, 6, 12]
    assert res["summary"]["every-n:n=6"]["n_keyframes"]["mean"] == 3
    # deciding one window late: the second trigger decides the first window, the end of the sequence the rest
    late = next(r for r in res["runs"] if r["label"] == "novelty:window=6:lookahead=6")["metrics"]
    assert len(late["keyframe_ids"]) == 3 and 1 <= late["keyframe_ids"][1] <= 6
    assert late["policy_params"]["lookahead"] == 6
    assert (out / "chosen_views.png").is_file() and (out / "uncertainty_every-n_n_6.png").is_file()
    check_targets(out, res, "novelty:window=6:lookahead=6", "every-n:n=6")
    rescored = rescore_ause(out, progress=False)
    assert [r["uncertainty_per_view"] for r in rescored["runs"]] == [r["uncertainty_per_view"] for r in res["runs"]]
    # the saved map folder must be the run's: other keyframes are refused
    kf_path = out / every["dir"] / "keyframes.json"
    kf = json.loads(kf_path.read_text())
    kf["keyframe_ids"] = [0, 6, 13]
    kf_path.write_text(json.dumps(kf))
    with pytest.raises(InputError, match="keyframes differ"):
        rescore_ause(out, progress=False)


def unseen_hole_share(mapper: Mapper, frames: list[Frame], keyframes: list[Frame]) -> float:
    """Of the test frames' hole pixels with depth, the share whose voxel (2.5 cm) lies farther than 5 cm plus half a
    voxel from every voxel of the keyframes' valid depth: a k-d tree over the keyframes' own frames."""
    from scipy.spatial import cKDTree

    from roigsf_ros.core.camera import depth_points_w

    def voxels(f: Frame, mask: np.ndarray) -> np.ndarray:
        return np.floor(depth_points_w(f.depth_m, f.T_wc, mapper.intr, mask) / 0.025)

    tree = cKDTree(np.concatenate([voxels(k, mapper.valid_depth_mask(k.depth_m)) for k in keyframes]))
    n = unseen = 0
    for f in frames:
        hole = ~mapper.covered_mask(f.T_wc) & mapper.valid_depth_mask(f.depth_m)
        d, _ = tree.query(voxels(f, hole), k=1)
        n, unseen = n + len(d), unseen + int(np.count_nonzero(d > (0.05 + 0.0125) / 0.025 + 1e-9))
    return unseen / n if n else 0.0


def test_stream_bench_test_scene(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--test-scene``: every run is also evaluated on frames no policy sees, the same frames for all policies."""
    test_scene = tmp_path / "between"
    poses = synth_trajectory(0, 48)[1::8]  # 6 poses of the room's loop, off the mapped ones
    render_sequence(synth_room(0), poses, synth_intrinsics(48, 36), test_scene, progress=False)
    out = tmp_path / "stream"
    argv = ["bench", "--scene", str(scene), "--setting", "stream", "--policies", "every-n:n=6,every-n:n=3",
            "--out", str(out), "--no-progress", "--uncertainty-views", "0", "--max-frames", "12",
            "--test-scene", str(test_scene), *MAPPER_SET]  # fmt: skip
    assert main(argv) == 0
    res = check_md_matches_json(out)
    assert res["test_scene"] == str(test_scene) and "frames no policy sees" in (out / "results.md").read_text()
    frames = list(open_frames(test_scene))
    by_id = {f.index: f for f in open_frames(scene)}
    shares: list[float] = []
    for run in res["runs"]:
        m = run["metrics"]
        assert m["test_scene_frames"] == 6 and m["test_scene_frames_skipped_bad_pose"] == 0
        mapper = Mapper.load(out / run["dir"])  # the saved map, evaluated here on the same frames
        again = render_metrics(mapper.render_rgb_depth, frames, mapper.valid_depth_mask,
                               covered=mapper.covered_mask).means()  # fmt: skip
        assert m["test_scene_psnr"] == pytest.approx(again["psnr"], abs=1e-6)
        assert m["test_scene_psnr_covered"] == pytest.approx(again["psnr_covered"], abs=1e-6)
        assert m["test_scene_uncovered_error_share"] == pytest.approx(again["uncovered_error_share"], abs=1e-9)
        assert 0.0 <= m["test_scene_uncovered_pixel_fraction"] < 0.5
        assert m["test_scene_depth_l1_cm"] == pytest.approx(again["depth_l1_cm"], abs=1e-6)
        assert m["test_scene_psnr"] != pytest.approx(m["psnr"], abs=1e-3)  # not the non-keyframes' numbers
        shares.append(m["test_scene_holes_unseen_share"])
        assert shares[-1] == pytest.approx(unseen_hole_share(mapper, frames, [by_id[i] for i in m["keyframe_ids"]]))
    assert shares[0] > 0.0 and shares[0] != shares[1]  # some holes are unseen surface, and it depends on the keyframes
    assert res["summary"]["every-n:n=3"]["test_scene_psnr"]["n"] == 1
    # the pool holds out its own views; another camera is refused before any run
    with pytest.raises(InputError, match="stream setting only"):
        BenchConfig(scene=scene, setting="pool", policies=[PolicySpec("random")], test_scene=test_scene).validate()
    small = tmp_path / "small"
    render_sequence(synth_room(0), poses[:2], synth_intrinsics(40, 30), small, progress=False)
    argv[argv.index(str(test_scene))] = str(small)
    argv[argv.index(str(out))] = str(tmp_path / "o2")
    assert main(argv) == 2
    assert "camera differs" in capsys.readouterr().err and not (tmp_path / "o2").exists()


# ------------------------------------------------------------------ interrupted and replaced outputs
def tiny_bench_argv(scene: Path, out: Path, policies: str, seeds: int, *extra: str) -> list[str]:
    """A stream bench of 8 frames, 2 steps per keyframe and one held-out view per run (about a second a run)."""
    return ["bench", "--scene", str(scene), "--setting", "stream", "--policies", policies, "--seeds", str(seeds),
            "--out", str(out), "--no-progress", "--max-frames", "8", "--uncertainty-views", "1",
            "--uncertainty-maps", "1", *MAPPER_SET, *extra]  # fmt: skip


@pytest.fixture(scope="module")
def old_bench(scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished bench of two policies and two seeds (tests copy it; it stays as built)."""
    out = tmp_path_factory.mktemp("old") / "bench"
    assert main(tiny_bench_argv(scene, out, "every-n:n=4,every-n:n=6", 2)) == 0
    return out


def snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every file (hidden ones too) under ``folder`` with its bytes, and every folder (None)."""
    return {str(p.relative_to(folder)): p.read_bytes() if p.is_file() else None for p in sorted(folder.rglob("*"))}


def interrupt_after(fn: Callable, calls: int = 1) -> Callable:
    """``fn`` that raises KeyboardInterrupt (a Ctrl-C) once it has returned ``calls`` times."""
    done: list[int] = []

    def wrapped(*args: object, **kwargs: object) -> object:
        if len(done) >= calls:
            raise KeyboardInterrupt
        done.append(1)
        result = fn(*args, **kwargs)
        if len(done) >= calls:
            raise KeyboardInterrupt
        return result

    return wrapped


def overwrite_argv(scene: Path, out: Path) -> list[str]:
    """``--overwrite`` of :func:`old_bench` (copied to ``out``) by a bench of one policy, one seed, other settings."""
    return tiny_bench_argv(scene, out, "every-n:n=4", 1, "--set", "iters_per_keyframe=3", "--overwrite")


def test_interrupted_overwrite_keeps_the_old_bench(
    scene: Path, old_bench: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C during ``--overwrite`` (after a run, or while the report is drawn) leaves the old bench byte for byte."""
    out = tmp_path / "bench"
    shutil.copytree(old_bench, out)
    before = snapshot(out)
    with monkeypatch.context() as m:  # once the first run of the new bench is written
        m.setattr(bench_module, "_stream_run", interrupt_after(bench_module._stream_run))
        assert main(overwrite_argv(scene, out)) == 130
    assert snapshot(out) == before
    with monkeypatch.context() as m:  # after results.md, before the plots and results.json
        m.setattr(report_module, "plot_chosen_views", interrupt_after(report_module.plot_chosen_views, 0))
        assert main(overwrite_argv(scene, out)) == 130
    assert snapshot(out) == before
    assert [p.name for p in tmp_path.iterdir()] == ["bench"]  # no temporary folder left beside it


def test_a_key_given_twice_in_a_policy_spec_is_warned(caplog: pytest.LogCaptureFixture) -> None:
    """A walk of the figures: ``$F2:unseen_weight=2`` (F2 holds ``unseen_weight=1``), as the documented commands write
    F3, ran F3 without a word, under a label that reads both weights. The later value is still the one used (those
    commands re-make their figures), now with a warning naming the key and both values."""
    from roigsf_ros.experiments.bench import parse_policies

    f2 = "roi-gsurfisher:unseen_weight=1:unseen_source=carved:unseen_measure=rays"
    with caplog.at_level("WARNING", logger="roigsf_ros"):
        (spec,) = parse_policies(f"{f2}:unseen_weight=2", "pool")
    assert spec.params["unseen_weight"] == 2 and spec.label == f"{f2}:unseen_weight=2"
    assert "--policies: unseen_weight given twice (1, then 2): the later is used" in caplog.text, caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="roigsf_ros"):
        parse_policies(f2, "pool")
    assert not caplog.records


def test_a_policy_spelt_twice_and_a_setting_s_unused_options_are_refused(scene: Path) -> None:
    """A walk ran ``roi-gsurfisher:unseen_weight=1,roi-gsurfisher:unseen_weight=1.0`` as two rows (and the keys in
    another order, and every-n's alias ``n``), took ``window`` and ``trigger_every`` in the pool setting and
    ``--pool-set`` in the stream one, each changing nothing, without a word."""
    from roigsf_ros.experiments.bench import parse_policies

    for text in ("roi-gsurfisher:unseen_weight=1,roi-gsurfisher:unseen_weight=1.0",
                 "roi-gsurfisher:epsilon=0.5:delta=0.5,roi-gsurfisher:delta=0.5:epsilon=0.5",
                 "every-n:n=4,every-n:every_n=4"):  # fmt: skip
        setting = "stream" if text.startswith("every-n") else "pool"
        with pytest.raises(InputError, match=r"^--policies: policy given twice: .* and .* \(the same policy and"):
            parse_policies(text, setting)
    with pytest.raises(InputError, match=r"^--policies: policy given twice: random \(the same"):
        parse_policies("random,random", "pool")
    assert len(parse_policies("roi-gsurfisher:unseen_weight=1,roi-gsurfisher:unseen_weight=2", "pool")) == 2
    with pytest.raises(InputError, match="unseen_weight"):  # read as 25 by Python's numbers, and taken
        parse_policies("roi-gsurfisher:unseen_weight=2_5", "pool")
    for spec in ("roi-gsurfisher:window=13", "roi-gsurfisher:trigger_every=3"):
        with pytest.raises(InputError, match="decides when a stream frame becomes a keyframe: stream setting only"):
            parse_policies(spec, "pool")
    argv = tiny_bench_argv(scene, scene.parent / "never", "every-n:n=4", 1, "--pool-set", "n_views=5")
    assert main(argv) == 2 and not (scene.parent / "never").exists()


def test_overwrite_never_replaces_the_scene_or_a_folder_of_other_things(
    scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk ran ``roigsf bench --scene X --out X --overwrite`` (rc 0: the scene was gone, and ``--out PARENT`` took
    a notes file with it) and ``roigsf map X --out X --overwrite`` (its mesh.ply replaced by the reconstruction while
    it said "mesh metrics against X/mesh.ply"). Now both are refused before any work, naming the folder, and
    ``--overwrite`` replaces only an earlier output of the same command or an empty folder."""
    work = tmp_path / "work"
    shutil.copytree(scene, work / "scene")
    (work / "notes.txt").write_text("mine")
    before = snapshot(work)
    for out in (work / "scene", work):
        assert main(tiny_bench_argv(work / "scene", out, "every-n:n=4", 1, "--overwrite")) == 2
        assert "which this command reads: writing there would delete it" in capsys.readouterr().err
        assert main(["map", str(work / "scene"), "--out", str(out), "--overwrite", "--max-frames", "2"]) == 2
        assert "which this command reads: writing there would delete it" in capsys.readouterr().err
    other = tmp_path / "other"
    other.mkdir()
    (other / "thesis.tex").write_text("mine")
    assert main(tiny_bench_argv(work / "scene", other, "every-n:n=4", 1, "--overwrite")) == 2
    assert "is a folder without results.json, not a bench's output: only a bench's output" in capsys.readouterr().err
    assert snapshot(work) == before and (other / "thesis.tex").read_text() == "mine"


def test_overwrite_leaves_no_file_of_the_old_bench(scene: Path, old_bench: Path, tmp_path: Path) -> None:
    """A completed ``--overwrite`` leaves only what the new bench wrote: no run, seed or plot of the old one."""
    out = tmp_path / "bench"
    shutil.copytree(old_bench, out)
    assert main(overwrite_argv(scene, out)) == 0
    res = check_md_matches_json(out)
    assert res["mapper_config"]["iters_per_keyframe"] == 3 and [r["dir"] for r in res["runs"]] == [
        "runs/every-n_n_4/seed0"
    ]
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_dir()) == [
        "runs", "runs/every-n_n_4", "runs/every-n_n_4/seed0"
    ]  # fmt: skip
    assert sorted(p.name for p in out.iterdir() if p.is_file()) == [
        "chosen_views.png", "quality_vs_views.png", "results.json", "results.md", "uncertainty_every-n_n_4.png"
    ]  # fmt: skip
    assert [p.name for p in tmp_path.iterdir()] == ["bench"]


def test_interrupted_bench_leaves_no_output(scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C while the report is drawn (results.md already written) leaves no --out and no temporary folder."""
    out = tmp_path / "bench"
    monkeypatch.setattr(report_module, "plot_quality", interrupt_after(report_module.plot_quality, 0))
    argv = tiny_bench_argv(scene, out, "every-n:n=6", 1)
    argv[argv.index("--uncertainty-views") + 1] = "0"
    assert main(argv) == 130
    assert list(tmp_path.iterdir()) == []


def test_rescore_replaces_the_report_only_when_complete(
    old_bench: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An interrupted ``--rescore-ause`` leaves the bench byte for byte; a completed one keeps the runs and other files
    and leaves no plot of the old report (here: with no maps drawn, no uncertainty plot)."""
    out = tmp_path / "bench"
    shutil.copytree(old_bench, out)
    (out / "notes.txt").write_text("mine")
    before = snapshot(out)
    argv = ["bench", "--rescore-ause", "--out", str(out), "--no-progress", "--uncertainty-maps", "0"]
    with monkeypatch.context() as m:  # Ctrl-C after results.md, before the plots and results.json
        m.setattr(report_module, "plot_chosen_views", interrupt_after(report_module.plot_chosen_views, 0))
        assert main(argv) == 130
    assert snapshot(out) == before
    assert [p.name for p in tmp_path.iterdir()] == ["bench"]
    assert main(argv) == 0
    res = check_md_matches_json(out)
    assert res["uncertainty_maps"] == 0 and res["ause_rescore"]["wall_s"] > 0
    after = snapshot(out)
    kept = {k: v for k, v in before.items() if k.startswith("runs") or k == "notes.txt"}
    assert {k: v for k, v in after.items() if k in kept} == kept
    assert sorted(set(after) - set(kept)) == ["chosen_views.png", "quality_vs_views.png", "results.json", "results.md"]
    assert [p.name for p in tmp_path.iterdir()] == ["bench"]


# ------------------------------------------------------------------ paths, early checks, report wording
def test_rescore_finds_a_relative_scene_from_another_working_directory(
    scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """results.json keeps ``scene`` as given and records ``scene_resolved``, which a rescore from elsewhere uses."""
    out = tmp_path / "bench"
    monkeypatch.chdir(scene.parent)
    assert main(tiny_bench_argv(Path(scene.name), out, "every-n:n=6", 1)) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["scene"] == scene.name and res["scene_resolved"] == str(scene.resolve())
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    capsys.readouterr()
    assert main(["bench", "--rescore-ause", "--out", str(out), "--no-progress"]) == 0  # was: scene not found
    assert json.loads((out / "results.json").read_text())["ause_rescore"]["scene"] == str(scene.resolve())
    res = json.loads((out / "results.json").read_text())
    res["scene_resolved"] = str(tmp_path / "moved")  # neither path exists: the error as before
    (out / "results.json").write_text(json.dumps(res))
    assert main(["bench", "--rescore-ause", "--out", str(out), "--no-progress"]) == 2
    assert f"{scene.name}: scene of the bench not found (pass --scene" in capsys.readouterr().err


def test_pool_larger_than_the_scene_is_refused_before_any_run(
    scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--pool-set n_views`` above the selectable frames fails up front (it was refused inside the first run)."""

    def no_run(*_args: object, **_kw: object) -> None:
        raise AssertionError("a run started")

    monkeypatch.setattr(bench_module, "_pool_run", no_run)
    out = tmp_path / "o"
    argv = ["bench", "--scene", str(scene), "--setting", "pool", "--policies", "random", "--out", str(out)]
    assert main([*argv, "--pool-set", "n_views=500"]) == 2
    captured = capsys.readouterr()
    assert captured.err == (
        "roigsf bench: error: --pool-set n_views: 21 selectable frames (of 24; test_every=8, pool_stride=1) "
        "but n_views=500\n"
    )
    assert captured.out == "" and list(tmp_path.iterdir()) == []  # no run, no temporary folder


def test_pool_report_says_image_metrics() -> None:
    results = {"setting": "pool", "seeds": [0], "scene": "s", "n_frames": 24, "size": [48, 36], "stride": 1,
               "wall_s": 1.0, "policies": [], "summary": {}, "curves": None,
               "pool_config": {"n_views": 6, "n_initial": 4, "test_every": 8, "pool_stride": 1, "schedule": "fixed",
                               "initial_iters": 4, "iters_per_view": 2, "final_iters": 0}}  # fmt: skip
    md = report_module.markdown(results)
    assert "- image metrics over the held-out test views; #views = training views" in md and "images" not in md


def test_the_quality_plot_ticks_whole_view_counts(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Four views measured at 1-4 were ticked at 1.0, 1.5, 2.0, ...: half a view. The x axis ticks counts only."""
    saved = []
    monkeypatch.setattr(report_module, "_save", lambda fig, path: saved.append(fig))
    curve = [{"n_views": n, "test_psnr": {"mean": 20.0 + n, "std": 0.1}} for n in (1, 2, 3, 4)]
    results = {"setting": "pool", "gt_mesh": None, "policies": [{"label": "random"}], "curves": {"random": curve}}
    report_module.plot_quality(results, tmp_path / "q.png")
    ticks = [t for ax in saved[0].axes for t in ax.get_xticks() if 1 <= t <= 4]
    assert ticks and all(float(t).is_integer() for t in ticks), ticks


def test_the_report_says_how_many_views_the_ause_study_held_out_where_fewer_than_asked() -> None:
    """A 4-frame stream bench's results.md said "AUSE ... on 6 held-out views per run" for runs scored on 2 and 3
    (all their non-keyframes): the number asked, not the number used."""
    runs = [
        {"label": "gaus-slam", "uncertainty_per_view": [{}] * 2},
        {"label": "random", "uncertainty_per_view": [{}] * 3},
    ]
    said = report_module._ause_views({"uncertainty_views": 6, "runs": runs})
    assert said == "6 held-out views per run (fewer where a run had fewer to hold out: gaus-slam 2, random 3)"
    full = [{"label": "a", "uncertainty_per_view": [{}] * 6}]
    assert report_module._ause_views({"uncertainty_views": 6, "runs": full}) == "6 held-out views per run"
