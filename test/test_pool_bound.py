"""scripts/pool_bound.py: how much of the true surface a pool bench's candidates can see, and the oracle's pick."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from conftest import load_script

from roigsf_ros.cli.scene import synth_intrinsics
from roigsf_ros.data.scene import render_sequence, synth_room, synth_trajectory
from roigsf_ros.data.sources import open_frames
from roigsf_ros.experiments.pool import PoolConfig, run_pool
from roigsf_ros.mapping.mapper import MapperConfig
from roigsf_ros.mapping.observed_space import FREE, OCCUPIED, UNKNOWN, ObservedSpace

pb = load_script("pool_bound")

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_greedy_pick_forces_the_initial_views_then_adds_the_most_unseen_then_fills() -> None:
    """Rows 2 and 0 forced; row 3 adds 3 unseen samples (row 1 only 2, shared with row 3); then nothing adds, so
    the lowest row not taken fills the budget."""
    obs = np.zeros((5, 8), dtype=bool)
    for r, cols in {0: [0], 1: [4, 5], 2: [1], 3: [3, 4, 5], 4: []}.items():
        obs[r, cols] = True
    assert pb.greedy_pick(obs, [2, 0], 3) == [2, 0, 3]
    assert pb.greedy_pick(obs, [2, 0], 5) == [2, 0, 3, 1, 4]
    assert pb.greedy_pick(obs, [2, 0, 2], 2) == [2, 0]


def test_swaps_find_the_pair_greedy_misses_and_keep_the_forced_rows() -> None:
    """Rows 1 = {0..3}, 2 = {0, 1, 4}, 3 = {2, 3, 5}, row 0 forced (sample 6): greedy takes row 1 then row 2 (ties to
    the lowest), 6 of 7; swapping row 1 for row 3 covers all 7. The forced row stays, whatever it adds; a pick no swap
    improves is returned as it was."""
    obs = np.zeros((4, 7), dtype=bool)
    for r, cols in {0: [6], 1: [0, 1, 2, 3], 2: [0, 1, 4], 3: [2, 3, 5]}.items():
        obs[r, cols] = True
    greedy = pb.greedy_pick(obs, [0], 3)
    assert greedy == [0, 1, 2] and pb.cb.coverage(obs, greedy) == 6 / 7
    swapped = pb.swap_refine(obs, greedy, 1)
    assert swapped == [0, 3, 2] and pb.cb.coverage(obs, swapped) == 1.0
    assert pb.swap_refine(obs, [1, 2, 3], 1) == [1, 2, 3]  # row 1 forced: nothing better for the others
    assert pb.swap_refine(obs, swapped, 1) == swapped


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthetic room (24 frames at 48x36) and a two-seed `random` pool bench of 6 views on it."""
    tmp = tmp_path_factory.mktemp("pool_bound")
    scene = tmp / "scene"
    render_sequence(synth_room(0), synth_trajectory(0, 24), synth_intrinsics(48, 36), scene, progress=False)
    o3d.io.write_triangle_mesh(str(scene / "mesh.ply"), synth_room(0))
    pcfg = PoolConfig(policy="random", n_views=6, initial_iters=6, iters_per_view=2, mesh_checkpoints=(6,),
                      curve_test_views=1, mesh_samples=3000)  # fmt: skip
    mcfg = MapperConfig(densify_stride=2, mesh_voxel_size_m=0.05, mesh_sdf_trunc_m=0.15)
    runs = []
    for seed in (0, 1):
        cfg = PoolConfig.from_dict(pcfg.to_dict() | {"seed": seed})
        m = run_pool(open_frames(scene), cfg, mcfg, gt_mesh=scene / "mesh.ply").metrics
        runs.append({"label": "random", "seed": seed, "chosen_positions": m["chosen_positions"], "metrics": m})
    out = tmp / "bench"
    out.mkdir()
    results = {"setting": "pool", "scene": str(scene), "gt_mesh": str(scene / "mesh.ply"), "size": None,
               "stride": 1, "max_frames": None, "pool_config": pcfg.to_dict(), "mapper_config": mcfg.to_dict(),
               "runs": runs}  # fmt: skip
    (out / "results.json").write_text(json.dumps(results))
    return out


def test_all_pool_views_bound_every_choice_and_the_oracle_is_replayed(bench: Path, tmp_path: Path) -> None:
    """Per seed: all pool views cover at least what any chosen set covers; the greedy pick starts with the bench's
    initial views and covers at least the random run's views, and its refinement by swaps keeps them and covers at
    least the greedy pick; the rows --map-rows names are mapped (the replay adds exactly the picks, or the script
    raises) and measured, the other not; the bench run's own metrics are carried over; the GT sample counts are the
    bench's (the script raises otherwise)."""
    assert pb.main([str(bench), "--out", str(tmp_path / "b"), "--map", "--map-rows", "all,greedy"]) == 0
    report = json.loads((tmp_path / "b" / "bound.json").read_text())
    results = json.loads((bench / "results.json").read_text())
    assert [s["seed"] for s in report["seeds"]] == [0, 1]
    for s, run in zip(report["seeds"], results["runs"], strict=True):
        every, greedy, swaps, mine = s["rows"]
        assert every["n"] == report["n_pool"] and greedy["n"] == 6 == mine["n"] == swaps["n"]
        assert greedy["positions"][:4] == report["initial_positions"] == run["metrics"]["initial_positions"]
        assert swaps["positions"][:4] == greedy["positions"][:4]
        assert every["coverage"] >= swaps["coverage"] >= greedy["coverage"] >= mine["coverage"] > 0.3
        assert "recall@5cm" not in swaps  # not among --map-rows
        assert mine["recall@5cm"] == run["metrics"]["recall@5cm"] and mine["positions"] == run["chosen_positions"]
        assert s["n_gt"] == run["metrics"]["n_gt_samples"]
        for row in (every, greedy):
            assert 0 < row["recall@5cm"] <= 1 and np.isfinite(row["psnr"])
    assert (tmp_path / "b" / "bound.md").read_text().count("\n| ") == 5  # the header and four rows
    assert (tmp_path / "b" / "maps" / "greedy_seed1" / "mesh.ply").is_file()


def test_bad_benches_are_named(bench: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A stream bench, a bench of another pool and a missing folder: exit 2, the file and the field named."""
    results = json.loads((bench / "results.json").read_text())
    stream = tmp_path / "stream"
    stream.mkdir()
    (stream / "results.json").write_text(json.dumps(results | {"setting": "stream"}))
    other = tmp_path / "other"
    other.mkdir()
    (other / "results.json").write_text(json.dumps(results | {"pool_config": results["pool_config"] | {"n_views": 5}}))
    for args, words in (([stream], ("stream/results.json", "setting")), ([bench, other], ("other/results.json",
                        "pool_config")), ([tmp_path / "nope"], ("nope", "results.json"))):  # fmt: skip
        assert pb.main([*map(str, args), "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err
        assert all(w in err for w in words), err
    assert pb.main([str(bench), "--out", str(tmp_path / "x"), "--map", "--map-rows", "greedy,best"]) == 2
    assert "--map-rows" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_unseen_vs_gain_compares_each_count_with_the_true_gain_of_the_first_pick(bench: Path, tmp_path: Path) -> None:
    """scripts/unseen_vs_gain.py: the gains it ranks against are the true coverage steps (the best one equals the
    largest increase any candidate gives the initial views' coverage), each count's pick gains at most the best, the
    back faces' share of the area count is a share, and every candidate of the pool is scored."""
    uv = load_script("unseen_vs_gain")
    assert uv.main([str(bench), "--out", str(tmp_path / "g"), "--seeds", "1"]) == 0
    report = json.loads((tmp_path / "g" / "unseen_vs_gain.json").read_text())
    (s,) = report["seeds"]
    setup = pb.load_pool(json.loads((bench / "results.json").read_text()), bench)
    _gt, obs, _n = pb.observed(setup, 1, 0.05)
    initial = [setup.row_of[p] for p in setup.split.initial]
    rows = [setup.row_of[p] for p in setup.split.pool if p not in setup.split.initial]
    base = pb.cb.coverage(obs, initial)
    assert s["best_gain"] == pytest.approx(max(pb.cb.coverage(obs, [*initial, r]) - base for r in rows), abs=1e-12)
    assert s["candidates"] == len(rows) and s["best_gain"] > 0
    for name in uv.RHO_COUNTS:
        r = s[name]
        assert 0 <= r["gain_of_pick"] <= s["best_gain"] and 0 <= r["gain_of_max_u"] <= s["best_gain"]
        assert all(np.isnan(v) or -1 <= v <= 1 for v in (r["rho_u"], r["rho_fused"]))
    assert 0 <= s["back_share_at_max_area"] <= 1 and 0 <= s["back_share_all"] <= 1
    assert (tmp_path / "g" / "unseen_vs_gain.md").read_text().count("\n| 1 | ") == len(uv.RHO_COUNTS) == 6


def test_unseen_spread_records_each_scoring_call_and_restores_the_scorer(bench: Path, tmp_path: Path) -> None:
    """scripts/unseen_spread.py: one record per pick after the initial views (the pool's only scoring calls), each
    with U's spread over the scored candidates and the pick's U inside its range; the scorer is unwrapped afterwards,
    even when the bench fails."""
    from roigsf_ros.nbv.scorer import NBVScorer

    us = load_script("unseen_spread")
    original = NBVScorer.score
    scene = bench.parent / "scene"
    args = ["--scene", str(scene), "--setting", "pool", "--seeds", "1", "--overwrite", "--set", "densify_stride=2",
            "--set", "mesh_voxel_size_m=0.05", "--set", "mesh_sdf_trunc_m=0.15", "--pool-set", "n_views=6",
            "--pool-set", "initial_iters=6", "--pool-set", "iters_per_view=2", "--pool-set", "mesh_samples=3000",
            "--policies", "roi-gsurfisher:unseen_weight=1", "--out", str(tmp_path / "b")]  # fmt: skip
    assert us.main(["--out", str(tmp_path / "spread.json"), "--", *args]) == 0
    assert NBVScorer.score is original
    calls = json.loads((tmp_path / "spread.json").read_text())["calls"]
    assert len(calls) == 2  # 6 views, 4 of them initial
    for c in calls:
        assert c["candidates"] > 2 and c["u_std"] >= 0
        assert c["u_min"] <= c["u_mean"] <= c["u_max"] and c["u_min"] <= c["u_of_pick"] <= c["u_max"]
    assert us.main(["--out", str(tmp_path / "bad.json"), "--", "--scene", str(tmp_path / "nope"), "--setting",
                    "pool", "--policies", "random", "--out", str(tmp_path / "c")]) != 0  # fmt: skip
    assert NBVScorer.score is original and not (tmp_path / "bad.json").exists()


def test_carve_from_captured_carves_the_frames_depth_and_restores_the_scorer(
    bench: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """scripts/carve_from_captured.py: its carve is ObservedSpace.carve of the matched frames' depth (no return: free
    up to far_m), it runs at each pick of a carved variant's pool run with every keyframe matched exactly, a pose no
    frame has is refused naming the scene, and the scorer's carve is restored, even when the bench fails."""
    from roigsf_ros.core.errors import InputError
    from roigsf_ros.data.replica import ReplicaSequence
    from roigsf_ros.mapping.observed_space import ObservedSpace
    from roigsf_ros.nbv import NBVConfig
    from roigsf_ros.nbv import unseen as unseen_module

    cc = load_script("carve_from_captured")
    scene = bench.parent / "scene"
    frame = ReplicaSequence.frame

    def with_a_hole(self: ReplicaSequence, k: int) -> object:  # the room has a wall behind every pixel: add no-returns
        f = frame(self, k)
        f.depth_m[:12, :16] = 0.0
        return f

    monkeypatch.setattr(ReplicaSequence, "frame", with_a_hole)
    seq = ReplicaSequence(scene)
    cfg = NBVConfig(unseen_voxel_m=0.1)
    lo, hi = np.array([-3.0, -3.0, -1.0]), np.array([3.0, 3.0, 3.0])
    log = {"calls": 0, "max_pose_error": 0.0}
    poses = seq.poses[[0, 7]]
    got = cc.captured_carver(scene, log)(None, poses, seq.intrinsics, lo, hi, cfg)
    depth = np.stack([seq.frame(k).depth_m.astype(np.float64) for k in (0, 7)])
    want = ObservedSpace.carve(lo, hi, 0.1, poses, np.where(depth > 0, depth, np.inf), seq.intrinsics, cfg.far_m)
    assert np.array_equal(got.state, want.state) and log == {"calls": 1, "max_pose_error": 0.0}
    holes_unknown = ObservedSpace.carve(lo, hi, 0.1, poses, depth, seq.intrinsics, cfg.far_m)
    assert not np.array_equal(got.state, holes_unknown.state)  # the no-returns carve free space
    monkeypatch.undo()
    moved = poses.copy()
    moved[0, 0, 3] += 0.01
    with pytest.raises(InputError, match="no frame has the keyframe pose"):
        cc.captured_carver(scene, log)(None, moved, seq.intrinsics, lo, hi, cfg)

    original = unseen_module.carved_space
    args = ["--scene", str(scene), "--setting", "pool", "--seeds", "1", "--overwrite", "--set", "densify_stride=2",
            "--set", "mesh_voxel_size_m=0.05", "--set", "mesh_sdf_trunc_m=0.15", "--pool-set", "n_views=6",
            "--pool-set", "initial_iters=6", "--pool-set", "iters_per_view=2", "--pool-set", "mesh_samples=3000",
            "--policies", "roi-gsurfisher:unseen_weight=1:unseen_source=carved",
            "--out", str(tmp_path / "b")]  # fmt: skip
    assert cc.main(["--out", str(tmp_path / "calls.json"), "--", *args]) == 0
    assert unseen_module.carved_space is original
    report = json.loads((tmp_path / "calls.json").read_text())
    assert report["calls"] == 2 and report["max_pose_error"] == 0.0  # 6 views, 4 of them initial
    assert (tmp_path / "b" / "results.json").is_file()
    assert cc.main(["--out", str(tmp_path / "bad.json"), "--", "--scene", str(tmp_path / "nope"), "--setting",
                    "pool", "--policies", "random", "--out", str(tmp_path / "c")]) != 0  # fmt: skip
    assert unseen_module.carved_space is original and not (tmp_path / "bad.json").exists()


def test_late_handover_picks_as_fisherrf_from_the_given_view_and_restores_the_policy(
    bench: Path, tmp_path: Path
) -> None:
    """scripts/late_handover.py: handing over from the first pick, the variant's bench chooses exactly the views a
    `fisherrf` bench of the same seed chooses; handing over at view 5 of 6 leaves the first pick to the variant and
    the second to FisherRF; the policy's ``choose`` is restored, even when the bench fails."""
    from roigsf_ros.policies.stream import StreamNBVPolicy

    lh = load_script("late_handover")
    original = StreamNBVPolicy.choose
    scene = bench.parent / "scene"
    args = ["--scene", str(scene), "--setting", "pool", "--seeds", "1", "--overwrite", "--set", "densify_stride=2",
            "--set", "mesh_voxel_size_m=0.05", "--set", "mesh_sdf_trunc_m=0.15", "--pool-set", "n_views=6",
            "--pool-set", "initial_iters=6", "--pool-set", "iters_per_view=2",
            "--pool-set", "mesh_samples=3000"]  # fmt: skip
    variant = "roi-gsurfisher:unseen_weight=1:unseen_source=carved"

    def chosen(out: Path, policy: str) -> list[int]:
        runs = json.loads((out / "results.json").read_text())["runs"]
        return next(r["chosen_positions"] for r in runs if r["label"] == policy)

    assert lh.main(["--after", "4", "--log", str(tmp_path / "all.json"), "--", *args, "--policies", variant,
                    "--out", str(tmp_path / "all")]) == 0  # fmt: skip
    assert StreamNBVPolicy.choose is original
    assert json.loads((tmp_path / "all.json").read_text())["picks"] == {"fisherrf": 2}
    from roigsf_ros.cli import main as roigsf_main

    assert roigsf_main(["bench", *args, "--policies", f"fisherrf,{variant}", "--out", str(tmp_path / "ref")]) == 0
    assert chosen(tmp_path / "all", variant) == chosen(tmp_path / "ref", "fisherrf")
    assert chosen(tmp_path / "ref", variant) != chosen(tmp_path / "ref", "fisherrf")  # else the check shows nothing
    assert lh.main(["--after", "5", "--log", str(tmp_path / "late.json"), "--", *args, "--policies", variant,
                    "--out", str(tmp_path / "late")]) == 0  # fmt: skip
    assert json.loads((tmp_path / "late.json").read_text())["picks"] == {"roi-gsurfisher": 1, "fisherrf": 1}
    assert chosen(tmp_path / "late", variant)[:5] == chosen(tmp_path / "ref", variant)[:5]
    assert lh.main(["--after", "4", "--log", str(tmp_path / "bad.json"), "--", "--scene", str(tmp_path / "nope"),
                    "--setting", "pool", "--policies", variant, "--out", str(tmp_path / "c")]) != 0  # fmt: skip
    assert StreamNBVPolicy.choose is original and not (tmp_path / "bad.json").exists()


def test_pick_regret_follows_the_replayed_run_pick_by_pick(bench: Path, tmp_path: Path) -> None:
    """scripts/pick_regret.py: each pick's gain is the true coverage step the run's next view adds (their sum plus the
    initial views' coverage is the run's coverage), no pick gains more than the best candidate, the first pick's
    candidates are the pool less the initial views; with --pixels U's unseen pixels are split into new and not new, each
    by its stretch, and the gain by where its samples lie in the carved grid; a bench whose run of the label chose other
    views is refused."""
    pr = load_script("pick_regret")
    label = "roi-gsurfisher:unseen_weight=1:unseen_source=carved"
    assert pr.main([str(bench), "--out", str(tmp_path / "r"), "--label", label, "--seeds", "1", "--pixels"]) == 0
    (s,) = json.loads((tmp_path / "r" / "pick_regret.json").read_text())["seeds"]
    setup = pb.load_pool(json.loads((bench / "results.json").read_text()), bench)
    _gt, obs, _n = pb.observed(setup, 1, 0.05)
    initial = [setup.row_of[p] for p in setup.split.initial]
    chosen = [setup.row_of[p] for p in s["chosen"]]
    assert chosen[:4] == initial and len(chosen) == 6 and len(s["picks"]) == 2
    assert s["picks"][0]["candidates"] == len(setup.split.pool) - 4 == s["picks"][1]["candidates"] + 1
    steps = [pb.cb.coverage(obs, chosen[: 4 + k]) - pb.cb.coverage(obs, chosen[: 3 + k]) for k in (1, 2)]
    assert [p["gain_of_pick"] for p in s["picks"]] == pytest.approx(steps, abs=1e-12)
    assert s["coverage"] == pytest.approx(pb.cb.coverage(obs, chosen), abs=1e-12)
    for p in s["picks"]:
        assert 0 <= p["gain_of_pick"] <= p["best_gain"] and 0 <= p["gain_of_max_u"] <= p["best_gain"]
        px = p["pixels"]  # --pixels: U recomputed from the carved grid matched the scorer's (the script raises if not)
        in_bins = sum(px["stretch_true_unseen"]) + sum(px["stretch_false_unseen"])
        assert px["true_unseen"] + px["false_unseen"] == in_bins
        assert px["true_unseen"] + px["missed_new"] > 0 and 0 <= p["gain_of_max_u_star"] <= p["best_gain"]
        # every gained sample lies in one class: the split adds up to the pick's gain and the best candidate's
        assert sum(p["gain_split_pick"].values()) == pytest.approx(p["gain_of_pick"], abs=1e-12)
        assert sum(p["gain_split_best"].values()) == pytest.approx(p["best_gain"], abs=1e-12)
        assert 0 <= p["gain_of_edges"] <= p["best_gain"]  # U_sf in place of U picks some candidate
        assert 0 <= p["gain_of_rays"] <= p["best_gain"] and 0 <= p["gain_of_max_u_ray"] <= p["best_gain"]  # U_ray
        assert 0 <= p["gain_of_rank"] <= p["best_gain"]  # the rank fusion rebuilt the scorer's fusion (else raises)
        assert 0 <= p["gain_of_div"] <= p["best_gain"] and 0 <= p["gain_of_max_div"] <= p["best_gain"]
    results = json.loads((bench / "results.json").read_text())
    wrong = {"label": label, "seed": 1, "chosen_positions": s["chosen"][:4] + s["chosen"][:3:-1], "metrics": {}}
    other = tmp_path / "other"
    other.mkdir()
    (other / "results.json").write_text(json.dumps(results | {"runs": [*results["runs"], wrong]}))
    with pytest.raises(RuntimeError, match="the replay chose"):
        pr.measure(other, label, [1], 0.05)


def test_sample_classes_tell_held_surface_unknown_free_and_outside() -> None:
    """pick_regret.sample_classes: a point within one cell of an occupied cell is held surface, whatever its own
    cell; else its own cell's state decides (unknown, free); a point outside the grid is outside."""
    pr = load_script("pick_regret")
    state = np.full((6, 3, 3), UNKNOWN, dtype=np.uint8)
    state[3:, :, :] = FREE
    state[0, 1, 1] = OCCUPIED
    space = ObservedSpace(lo_m=np.zeros(3), voxel_m=0.1, state=state)
    pts = np.array([[0.05, 0.15, 0.15], [0.15, 0.15, 0.15], [0.25, 0.15, 0.15], [0.45, 0.15, 0.15], [0.7, 0.1, 0.1]])
    classes = [pr.SAMPLE_CLASSES[c] for c in pr.sample_classes(space, pr.near_occupied(space), pts)]
    assert classes == ["held", "held", "unknown", "free", "outside"]


def test_rank_fusion_lets_no_one_term_outvote_the_others_and_checks_the_fusion_it_replaces() -> None:
    """pick_regret.rank_fused: one candidate's Fisher far above the rest wins the z-score fusion although another
    candidate is best on close-front and U; over ranks that one wins. Flagged candidates score -inf; a fused score that
    is not epsilon z(F) + delta z(C) + w z(U) is refused."""
    pr = load_script("pick_regret")
    z = pr.scorer_module.zscore
    f = np.array([50.0, 1, 2, 3, 4, 5, 6, 7, 8])
    c = np.array([0.5, 0.6, 0.4, 0.3, 0.5, 0.2, 0.1, 0.45, 0.0])
    u = np.array([0.3, 0.4, 0.2, 0.1, 0.25, 0.15, 0.05, 0.35, 0.0])
    ok = np.arange(9) < 8  # the last one flagged
    fused = np.zeros(9)
    fused[ok] = 0.4 * z(f[ok]) + 0.6 * z(c[ok]) + z(u[ok])
    s = {
        "fisher": f,
        "close_front": c,
        "u": u,
        "fused": fused,
        "epsilon": 0.4,
        "delta": 0.6,
        "w": 1.0,
        "min_std": 0.0,
        "cf_min_std": 0.0,
    }
    assert int(np.argmax(fused)) == 0
    ranked = pr.rank_fused(s, ok)
    assert int(np.argmax(ranked)) == 1 and ranked[8] == -np.inf and np.isfinite(ranked[ok]).all()
    with pytest.raises(RuntimeError, match="not epsilon"):
        pr.rank_fused(s | {"w": 2.0}, ok)


def test_pose_diversity_is_the_nearest_view_in_distance_over_the_pool_scale_plus_the_turn() -> None:
    """pick_regret.pose_diversity: a candidate at a taken view scores 0; one 2 L away looking the same way scores 2;
    one at a view turned by 90 degrees scores 1 (1 - cos); the minimum over the views decides. pool_scale is the median
    nearest-neighbour distance of the positions."""
    pr = load_script("pick_regret")

    def pose(x: float, yaw_deg: float) -> np.ndarray:
        t = np.deg2rad(yaw_deg)
        T = np.eye(4)
        T[:3, :3] = [[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]]  # optical axis (sin, 0, cos)
        T[0, 3] = x
        return T

    seen = np.stack([pose(0.0, 0.0), pose(10.0, 0.0)])
    cands = np.stack([pose(0.0, 0.0), pose(1.0, 0.0), pose(10.0, 90.0), pose(5.0, 180.0)])
    d = pr.pose_diversity(cands, seen, 0.5)
    assert d == pytest.approx([0.0, 2.0, 1.0, 10.0 + 2.0])
    assert pr.pool_scale(np.array([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [7.0, 0, 0]])) == pytest.approx(1.5)
