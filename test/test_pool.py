"""Pool (active reconstruction) setting: split, initial views, greedy picks = scorer argmax, seeds."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from roigsf_ros.cli.scene import synth_intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame
from roigsf_ros.data.scene import MeshRenderer, synth_room, synth_trajectory
from roigsf_ros.data.sources import MemoryFrameSource
from roigsf_ros.experiments.pool import (
    STREAM_TRIGGER_PARAMS,
    PoolConfig,
    ReplayPicks,
    farthest_point_views,
    pose_only,
    run_pool,
    split_pool,
)
from roigsf_ros.mapping.mapper import MapperConfig
from roigsf_ros.nbv.config import NBVConfig
from roigsf_ros.nbv.scorer import NBVScorer

INTR = synth_intrinsics(48, 36)
N_FRAMES = 32


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def source() -> MemoryFrameSource:
    """32 frames of the synthetic room at 48x36."""
    renderer = MeshRenderer(synth_room(0), texture_seed=0)
    frames = []
    for i, T in enumerate(synth_trajectory(0, N_FRAMES)):
        rgb, depth = renderer.render(T, INTR)
        frames.append(Frame(index=i, rgb=rgb, depth_m=depth, T_wc=T))
    return MemoryFrameSource(frames, INTR, "synth")


def mapper_config() -> MapperConfig:
    return MapperConfig(densify_stride=2, mesh_voxel_size_m=0.05, mesh_sdf_trunc_m=0.15)


def pool_config(**kw) -> PoolConfig:
    base = {"n_views": 6, "initial_iters": 6, "iters_per_view": 2, "mesh_checkpoints": (4,), "curve_test_views": 2}
    return PoolConfig(**(base | kw))


def test_farthest_point_views() -> None:
    c = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [10, 0, 0], [5, 0, 0]])
    assert farthest_point_views(c, 0, 3) == [0, 3, 4]  # 10 m away, then 5 m from both ends
    assert farthest_point_views(c, 2, 2) == [2, 3]
    assert farthest_point_views(c, 0, 9) == [0, 3, 4, 2, 1]  # capped at the number of centres
    with pytest.raises(InputError):
        farthest_point_views(c, 7, 2)


def test_split(source: MemoryFrameSource) -> None:
    poses = source.poses()
    s = split_pool(poses, PoolConfig(test_every=8, pool_stride=2, n_views=6))
    assert s.test == [0, 8, 16, 24]
    assert not set(s.test) & set(s.pool)
    assert s.pool == [i for i in range(N_FRAMES) if i % 8][::2]
    assert s.initial[0] == s.pool[0] and len(s.initial) == 4 and set(s.initial) <= set(s.pool)
    c = poses[:, :3, 3]
    for k in range(1, 4):  # each initial view maximises the distance to the ones before it
        d = [min(np.linalg.norm(c[p] - c[q]) for q in s.initial[:k]) for p in s.pool]
        assert np.isclose(min(np.linalg.norm(c[s.initial[k]] - c[q]) for q in s.initial[:k]), max(d))
    with pytest.raises(InputError, match="n_views"):
        split_pool(poses, PoolConfig(test_every=8, pool_stride=4, n_views=20))


def test_config_errors(source: MemoryFrameSource, tmp_path) -> None:
    with pytest.raises(InputError, match="not a pool policy"):
        PoolConfig(policy="gaus-slam")
    with pytest.raises(InputError, match="not a pool policy"):
        PoolConfig(policy="novelty")  # reads a candidate's captured depth
    with pytest.raises(InputError, match="novelty_weight"):
        PoolConfig(policy="roi-gsurfisher", policy_params={"novelty_weight": 1.0})
    with pytest.raises(InputError, match="lookahead"):
        PoolConfig(policy="roi-gsurfisher", policy_params={"lookahead": 4})
    with pytest.raises(InputError, match="n_views"):
        PoolConfig(n_views=3, n_initial=4)
    with pytest.raises(InputError, match="schedule"):
        PoolConfig(schedule="weekly")
    with pytest.raises(InputError, match="test_every"):
        PoolConfig(test_every=1)
    with pytest.raises(InputError, match="unknown parameter"):
        PoolConfig.from_dict({"n_view": 3})
    assert PoolConfig(schedule="epochs").steps(100, 5) == 500 and PoolConfig().steps(100, 5) == 100
    with pytest.raises(InputError, match="not found"):
        run_pool(source, pool_config(), mapper_config(), gt_mesh=tmp_path / "nope.ply")
    with pytest.raises(InputError, match="takes no parameter"):
        run_pool(source, pool_config(policy_params={"bogus": 1}), mapper_config())


def test_greedy_picks_are_scorer_argmax(source: MemoryFrameSource) -> None:
    """With W_f re-evaluated from every keyframe (``close_front_exact``) the policy's kept state scores exactly as the
    scorer does from scratch (by default each keyframe is folded into W_f once: a different, cheaper W_f)."""
    cfg = pool_config(policy="roi-gsurfisher", policy_params={"close_front_exact": True})
    expected: list[int] = []
    seen_images: list[int] = []

    def hook(mapper, policy, cand_positions, cand_poses) -> None:
        if not hasattr(policy, "_wrapped"):
            inner = policy.choose

            def checked(cands, m):
                seen_images.extend(f.rgb.size + f.depth_m.size for f in cands)
                return inner(cands, m)

            policy.choose, policy._wrapped = checked, True
        policy.sync_tsdf(mapper)
        res = NBVScorer(NBVConfig(mode="roi-gsurfisher")).score(
            mapper.map, mapper.h_train, policy.tsdf, mapper.keyframe_poses, cand_poses, mapper.intr
        )
        expected.append(cand_positions[res.best_index])

    res = run_pool(source, cfg, mapper_config(), on_select=hook)
    m = res.metrics
    chosen = m["chosen_positions"]
    assert len(chosen) == 6 == m["n_views"] and len(set(chosen)) == 6
    assert chosen[:4] == res.split.initial
    assert chosen[4:] == expected  # the greedy pick is the scorer's argmax on the same state
    assert not set(chosen) & set(res.split.test)
    assert seen_images and not any(seen_images)  # candidates reach the policy without images
    assert [p["n_views"] for p in m["curve"]] == [4, 5, 6]
    assert all(np.isfinite(p["test_psnr"]) for p in m["curve"])
    assert np.isfinite(m["psnr"]) and np.isfinite(m["ssim"]) and m["depth_l1_cm"] > 0


def test_carved_unseen_term_reaches_the_scorer_with_the_keyframes(source: MemoryFrameSource) -> None:
    """``unseen_source=carved`` as a policy parameter (``roigsf bench --policies roi-gsurfisher:unseen_weight=1:
    unseen_source=carved``): each pick is the scorer's argmax with the same options on the same map and keyframes,
    whose depth carves the grid (an empty keyframe list would leave every pixel unseen and U flat)."""
    params = {"close_front_exact": True, "unseen_weight": 1.0, "unseen_source": "carved"}
    cfg = pool_config(policy="roi-gsurfisher", policy_params=params)
    expected: list[int] = []
    spreads: list[float] = []

    def hook(mapper, policy, cand_positions, cand_poses) -> None:
        policy.sync_tsdf(mapper)
        res = NBVScorer(NBVConfig(mode="roi-gsurfisher", **params)).score(
            mapper.map, mapper.h_train, policy.tsdf, mapper.keyframe_poses, cand_poses, mapper.intr
        )
        expected.append(cand_positions[res.best_index])
        spreads.append(float(np.ptp(res.unseen[~res.flagged])))

    m = run_pool(source, cfg, mapper_config(), on_select=hook).metrics
    assert m["chosen_positions"][4:] == expected and m["policy_params"].items() >= params.items()
    assert not set(m["policy_params"]) & set(STREAM_TRIGGER_PARAMS)  # the stream's window decides nothing here
    assert all(s > 0.05 for s in spreads)  # U tells the candidates apart


def test_the_ablation_without_fisher_scores_as_the_scorer_and_recomputes_no_h_train(
    source: MemoryFrameSource, monkeypatch
) -> None:
    """``epsilon=0`` (issue 10's ablation of the fused score without z(F)): each pick is the scorer's argmax, and the
    pool spends nothing on the training Fisher the score no longer reads (the full score recomputes it each pick)."""
    from roigsf_ros.mapping.mapper import Mapper

    params = {"close_front_exact": True, "unseen_weight": 1.0, "unseen_source": "carved", "epsilon": 0.0}
    real = Mapper.recompute_h_train
    calls: list[int] = []
    monkeypatch.setattr(Mapper, "recompute_h_train", lambda self: calls.append(1) or real(self))
    expected: list[int] = []

    def hook(mapper, policy, cand_positions, cand_poses) -> None:
        policy.sync_tsdf(mapper)
        res = NBVScorer(NBVConfig(mode="roi-gsurfisher", **params)).score(
            mapper.map, None, policy.tsdf, mapper.keyframe_poses, cand_poses, mapper.intr
        )
        assert not res.fisher.any()
        expected.append(cand_positions[res.best_index])

    m = run_pool(source, pool_config(policy="roi-gsurfisher", policy_params=params), mapper_config(), on_select=hook)
    assert m.metrics["chosen_positions"][4:] == expected and calls == []
    full = pool_config(policy="roi-gsurfisher", policy_params=params | {"epsilon": 0.4})
    run_pool(source, full, mapper_config())
    assert len(calls) == 2  # one per pick of the full score


def test_seeds_reproduce_and_random_differs(source: MemoryFrameSource, tmp_path) -> None:
    cfg = pool_config(policy="random", n_views=8, seed=3)
    gt = tmp_path / "gt.ply"
    import open3d as o3d

    o3d.io.write_triangle_mesh(str(gt), synth_room(0))
    a = run_pool(source, replace(cfg, mesh_samples=2000), mapper_config(), tmp_path / "a", gt_mesh=gt).metrics
    b = run_pool(source, cfg, mapper_config()).metrics
    c = run_pool(source, replace(cfg, seed=4), mapper_config()).metrics
    assert a["chosen_positions"] == b["chosen_positions"] and a["psnr"] == b["psnr"]
    assert a["chosen_positions"][:4] == c["chosen_positions"][:4]  # initial views do not depend on the seed
    assert a["chosen_positions"][4:] != c["chosen_positions"][4:]
    assert a["config"]["seed"] == 3 and c["config"]["seed"] == 4
    assert "mesh" in a["curve"][0] and "mesh" in a["curve"][-1] and "recall@5cm" in a
    assert (tmp_path / "a" / "metrics.json").is_file() and (tmp_path / "a" / "mesh.ply").is_file()
    with pytest.raises(FileExistsError):
        run_pool(source, cfg, mapper_config(), tmp_path / "a")


def test_mesh_checkpoints_change_no_choice_and_no_final_figure(source: MemoryFrameSource, tmp_path) -> None:
    """Measuring the mesh at more view counts along a run (``mesh_checkpoints``) changes no pick and no final figure,
    with a policy that reads the map: so ``roigsf targets`` compares benches that differ only in it, and reads their
    curves for the views a candidate needs (``experiments.targets.views_to_match``)."""
    import open3d as o3d

    gt = tmp_path / "gt.ply"
    o3d.io.write_triangle_mesh(str(gt), synth_room(0))
    params = {"unseen_weight": 1.0, "unseen_source": "carved"}
    cfg = pool_config(policy="roi-gsurfisher", policy_params=params, n_views=7, mesh_samples=2000)
    a = run_pool(source, cfg, mapper_config(), gt_mesh=gt).metrics
    b = run_pool(source, replace(cfg, mesh_checkpoints=(4, 5, 6, 7)), mapper_config(), gt_mesh=gt).metrics
    assert [p["n_views"] for p in a["curve"] if "mesh" in p] == [4, 7]  # the checkpoints, and always the last view
    assert [p["n_views"] for p in b["curve"] if "mesh" in p] == [4, 5, 6, 7]
    assert a["chosen_positions"] == b["chosen_positions"]
    for key in ("psnr", "ssim", "depth_l1_m", "recall@5cm", "fscore@5cm", "precision@1cm"):
        assert a[key] == b[key], key
    assert [p["test_psnr"] for p in a["curve"]] == [p["test_psnr"] for p in b["curve"]]


def test_a_policy_object_replaces_the_named_policy(source: MemoryFrameSource) -> None:
    """``policy=`` (e.g. scripts/pool_bound.py's oracle replay) picks instead of ``config.policy``, in its order,
    and the metrics name it; the initial views stay the split's."""
    cfg = pool_config(policy="random", n_views=7)
    split = split_pool(np.stack([f.T_wc for f in source]), cfg)
    want = [p for p in reversed(split.pool) if p not in split.initial][:3]
    m = run_pool(source, cfg, mapper_config(), policy=ReplayPicks(want)).metrics
    assert m["chosen_positions"] == split.initial + want
    assert m["policy"] == "replay" and m["policy_params"] == {"frame_ids": want}
    with pytest.raises(InputError, match="none of the 1 replayed frame ids is a candidate"):
        ReplayPicks([N_FRAMES]).choose([pose_only(f) for f in source], None)


def test_pose_only() -> None:
    f = Frame(index=3, rgb=np.ones((4, 5, 3), np.uint8), depth_m=np.ones((4, 5), np.float32), T_wc=np.eye(4))
    p = pose_only(f)
    assert p.index == 3 and p.rgb.size == 0 and p.depth_m.size == 0 and np.array_equal(p.T_wc, f.T_wc)
