"""The pool (active reconstruction) setting of the NBV experiments, as FisherRF's "v20seq1".

A posed RGB-D sequence is split into held-out **test views** (every ``test_every``-th frame, never
selectable) and a **pool** (the rest, optionally every ``pool_stride``-th of them). Training starts
from ``n_initial`` views: the first pool frame plus the pool frames whose camera centres are
farthest from those already chosen (farthest-point sampling). Then, greedily, at a fixed training
schedule, the policy scores the *poses* of every remaining pool frame (their images are never
shown to it: candidates are passed as pose-only frames) and the best one is added, until
``n_views`` views.

The schedule is explicit (:class:`PoolConfig`): ``initial_iters`` optimiser steps after the
initial views, ``iters_per_view`` steps after each added view, ``final_iters`` at the end. With
``schedule="epochs"`` these counts are epochs, multiplied by the current number of training views
(FisherRF adds a view every 100 epochs: iterations 400, 900, 1500, 2200, ...).

Policies (by name): ``roi-gsurfisher``, ``roi-fisher``, ``close-front``, ``fisherrf`` (the
:class:`roigsf_ros.nbv.scorer.NBVScorer` modes) and ``random`` (a seeded uniform pick); the selection itself
is :meth:`roigsf_ros.policies.stream.StreamNBVPolicy.choose`, so the TSDF is fused from the map's
*rendered* depth at the chosen views exactly as in the stream setting. After every added view the
run records the mean test-view PSNR and, at ``mesh_checkpoints`` view counts and with a GT mesh,
the mesh metrics, so quality-versus-views curves exist.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import open3d as o3d

from roigsf_ros import evaluation
from roigsf_ros.core.config import Config
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import atomic_dir, check_run_output, write_json
from roigsf_ros.core.frame import Frame, spread_indices
from roigsf_ros.data.sources import FrameSequence, check_frame_source
from roigsf_ros.mapping.mapper import Mapper, MapperConfig
from roigsf_ros.nbv.config import ROI_MODES, NBVConfig
from roigsf_ros.policies.base import make_policy
from roigsf_ros.policies.stream import StreamNBVPolicy

log = logging.getLogger(__name__)

POOL_POLICIES = ("roi-gsurfisher", "roi-fisher", "close-front", "fisherrf", "random")
"""Policies valid in the pool setting (the per-frame rules gaus-slam, every-n, all are stream-only)."""

SCHEDULES = ("fixed", "epochs")
"""``fixed``: step counts as given; ``epochs``: counts times the current number of training views."""


STREAM_TRIGGER_PARAMS = ("window", "trigger_every", "trigger", "adaptive_ratio", "adaptive_history",
                         "adaptive_max_gap", "budget_every", "budget_burst")  # fmt: skip
"""A stream policy's parameters of when it decides, which the pool setting has no use for."""


def check_pool_params(params: dict[str, Any]) -> None:
    """InputError for policy parameters that need a candidate's images (the pool scores poses only), or that decide
    when a stream frame is judged (:data:`STREAM_TRIGGER_PARAMS`).
    """
    for name, off in (("novelty_weight", 0), ("lookahead", 0), ("novelty_measure", "area")):
        value = params.get(name)
        if value is not None and value != off:
            raise InputError(name, "reads a candidate's captured depth: stream setting only (the pool scores "
                             "views before they are taken, from their poses)")  # fmt: skip
    for name in STREAM_TRIGGER_PARAMS:  # accepted and kept in the label, they changed nothing
        if name in params:
            raise InputError(name, "decides when a stream frame becomes a keyframe: stream setting only (the pool "
                             "adds one view per step; --pool-set n_views sets how many)")  # fmt: skip


@dataclass(frozen=True)
class PoolConfig(Config):
    """Every knob of the pool setting; the field names are the ROS parameter names."""

    policy: str = "roi-gsurfisher"
    """Selection policy, one of :data:`POOL_POLICIES`."""
    policy_params: dict[str, Any] = field(default_factory=dict)
    """Extra parameters of the policy (see :class:`roigsf_ros.policies.stream.StreamNBVPolicy`: epsilon,
    delta, fisher_downsample, voxel_size_m, ...); window/trigger_every have no meaning here."""
    n_views: int = 20
    """Training views at the end (initial ones included)."""
    n_initial: int = 4
    """Initial views: the first pool frame plus farthest-point camera centres."""
    test_every: int = 8
    """Frames at positions 0, k, 2k, ... of the sequence are held-out test views (never selectable)."""
    pool_stride: int = 1
    """Keep every this-many-th of the remaining frames as the pool."""
    schedule: str = "fixed"
    """How the step counts below are read, one of :data:`SCHEDULES`."""
    initial_iters: int = 100
    """Optimiser steps (or epochs) after the initial views."""
    iters_per_view: int = 30
    """Optimiser steps (or epochs) after each added view."""
    final_iters: int = 0
    """Refinement steps (or epochs) over all views at the end (0: none)."""
    newest_first: bool = True
    """After an addition, steps prefer the new view (the mapper's newest_keyframe_prob); False: uniform."""
    recompute_h_train: bool = True
    """Recompute the training Fisher of every view under the current map before each selection
    (FisherRF does); False keeps the mapper's running sum (each view's Fisher at its insertion)."""
    seed: int = 0
    """Seed of the mapper and of the random policy."""
    mesh_checkpoints: tuple[int, ...] = (4, 8, 12, 16, 20)
    """View counts at which the mesh metrics are recorded (with a GT mesh); the final count always is."""
    curve_test_views: int = 0
    """Test views evaluated after each addition for the PSNR curve, evenly spread (0: all)."""
    mesh_samples: int = 100_000
    """Points sampled on each mesh for the mesh metrics."""
    mesh_taus_m: tuple[float, ...] = (0.01, 0.05)
    """Distance thresholds of precision / recall / F-score."""
    cull_gt_to_observed: bool = True
    """Cull the GT mesh to what the whole sequence's cameras observe before recall/completion."""

    def validate(self) -> PoolConfig:
        """Self, or InputError naming the first field out of range."""
        if self.policy not in POOL_POLICIES:
            raise InputError("policy", f"{self.policy!r} is not a pool policy (choose from {', '.join(POOL_POLICIES)})")
        check_pool_params(self.policy_params)
        if self.schedule not in SCHEDULES:
            raise InputError("schedule", f"unknown schedule {self.schedule!r} (choose from {', '.join(SCHEDULES)})")
        for name, lo in (("n_initial", 1), ("test_every", 2), ("pool_stride", 1), ("mesh_samples", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or v < lo:
                raise InputError(name, f"must be an integer >= {lo}, got {v!r}")
        for name in ("initial_iters", "iters_per_view", "final_iters", "curve_test_views", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or v < 0:
                raise InputError(name, f"must be an integer >= 0, got {v!r}")
        if isinstance(self.n_views, bool) or int(self.n_views) != self.n_views or self.n_views < self.n_initial:
            raise InputError("n_views", f"must be an integer >= n_initial ({self.n_initial}), got {self.n_views!r}")
        if any(int(c) != c or c < 1 for c in self.mesh_checkpoints):
            raise InputError("mesh_checkpoints", f"must be positive view counts, got {self.mesh_checkpoints}")
        if not self.mesh_taus_m or not all(np.isfinite(t) and t > 0 for t in self.mesh_taus_m):
            raise InputError("mesh_taus_m", f"must be positive metres, got {self.mesh_taus_m}")
        return self

    def steps(self, n_iters: int, n_views: int) -> int:
        """Optimiser steps of a phase of ``n_iters`` with ``n_views`` training views under the schedule."""
        return int(n_iters) * (int(n_views) if self.schedule == "epochs" else 1)


# ------------------------------------------------------------------------------------------ split
@dataclass(frozen=True)
class PoolSplit:
    """Positions (0-based, in sequence order) of the test views, the pool and the initial views."""

    test: list[int]
    pool: list[int]
    initial: list[int]


def farthest_point_views(centres_m: np.ndarray, first: int, n: int) -> list[int]:
    """``n`` row indices of ``centres_m`` [M, 3]: ``first``, then each time the one farthest from those chosen.

    Distance to the chosen set is the minimum Euclidean distance; ties go to the lowest index.
    """
    c = np.asarray(centres_m, dtype=np.float64).reshape(-1, 3)
    if not 0 <= first < len(c):
        raise InputError("first", f"index {first} outside the {len(c)} centres")
    chosen = [int(first)]
    d = np.linalg.norm(c - c[first], axis=1)
    while len(chosen) < min(n, len(c)):
        d_masked = d.copy()
        d_masked[chosen] = -np.inf
        nxt = int(np.argmax(d_masked))
        chosen.append(nxt)
        d = np.minimum(d, np.linalg.norm(c - c[nxt], axis=1))
    return chosen


def selectable_positions(n_frames: int, config: PoolConfig, where: str = "pool") -> list[int]:
    """Positions of the pool of a sequence of ``n_frames``: not test views, every ``pool_stride``-th of the rest.

    InputError naming ``where`` when they are fewer than ``n_views``: known from the frame count alone, so a bench
    checks it before any run starts.
    """
    pool = [i for i in range(n_frames) if i % config.test_every][:: config.pool_stride]
    if len(pool) < config.n_views:
        raise InputError(
            where,
            f"{len(pool)} selectable frames (of {n_frames}; test_every={config.test_every}, "
            f"pool_stride={config.pool_stride}) but n_views={config.n_views}",
        )
    return pool


def split_pool(poses: np.ndarray, config: PoolConfig) -> PoolSplit:
    """Test views, pool and initial views of a sequence of ``poses`` [N, 4, 4] under ``config``."""
    n = len(poses)
    test = list(range(0, n, config.test_every))
    pool = selectable_positions(n, config)
    centres = np.asarray(poses, dtype=np.float64)[pool, :3, 3]
    initial = [pool[j] for j in farthest_point_views(centres, 0, config.n_initial)]
    return PoolSplit(test=test, pool=pool, initial=initial)


def pose_only(frame: Frame) -> Frame:
    """A copy of ``frame`` without its images (empty arrays): what a policy may see of a candidate."""
    return Frame(
        index=frame.index, rgb=np.zeros((0, 0, 3), np.uint8), depth_m=np.zeros((0, 0), np.float32), T_wc=frame.T_wc
    )


def make_pool_policy(config: PoolConfig) -> StreamNBVPolicy:
    """The selection policy of ``config`` (seeded with ``config.seed`` unless its params give a seed)."""
    params = {"seed": config.seed} | dict(config.policy_params)
    policy = make_policy(config.policy, **params)
    if not isinstance(policy, StreamNBVPolicy):  # defensive: PoolConfig already checks the name
        raise InputError("policy", f"{config.policy!r} cannot score candidate poses (stream-only rule)")
    return policy


# -------------------------------------------------------------------------------------------- run
@dataclass
class PoolResult:
    """A finished pool run: its metrics (as written to metrics.json), the trained mapper and the frames."""

    metrics: dict[str, Any]
    mapper: Mapper
    frames: list[Frame]
    split: PoolSplit


class PoolPolicy(Protocol):
    """What :func:`run_pool` asks of a selection policy: a :class:`StreamNBVPolicy`, or :class:`ReplayPicks` (given
    views, e.g. ``scripts/pool_bound.py``'s coverage oracle).
    """

    mode: str | None
    """Scoring mode; ``roi-gsurfisher`` and ``roi-fisher`` make the run keep the training Fisher current."""

    def reset(self) -> None:
        """Forget every earlier run."""

    def choose(self, candidates: list[Frame], keyframe_map: Mapper) -> int:
        """Index into ``candidates`` (pose-only frames) of the view to add next."""

    def params(self) -> dict[str, Any]:
        """The policy's parameters, as the run's metrics record them."""


class ReplayPicks:
    """A pool policy that adds given frames in the given order (by frame id): an oracle's picks or a hand-chosen set,
    mapped under the pool's schedule.
    """

    name = "replay"
    mode: str | None = None

    def __init__(self, frame_ids: Sequence[int]) -> None:
        self.frame_ids = [int(i) for i in frame_ids]

    def reset(self) -> None:
        """Nothing is kept between runs."""

    def choose(self, candidates: list[Frame], keyframe_map: Mapper) -> int:
        """The first of the frame ids still among the candidates; InputError when none is."""
        by_id = {int(f.index): i for i, f in enumerate(candidates)}
        for fid in self.frame_ids:
            if fid in by_id:
                return by_id[fid]
        raise InputError("candidates", f"none of the {len(self.frame_ids)} replayed frame ids is a candidate")

    def params(self) -> dict[str, Any]:
        """The replayed frame ids, in order."""
        return {"frame_ids": self.frame_ids}


SelectHook = Callable[[Mapper, PoolPolicy, list[int], np.ndarray], None]
"""``hook(mapper, policy, candidate_positions, candidate_poses [M, 4, 4])``, called before each selection."""


def _test_image_metrics(mapper: Mapper, frames: Sequence[Frame], with_ssim: bool) -> dict[str, float | None]:
    """Mean PSNR (and SSIM, depth L1) of the map rendered at ``frames``' poses against their images."""
    m = evaluation.render_metrics(mapper.render_rgb_depth, frames, mapper.valid_depth_mask, with_ssim).means()
    keys = ("psnr", "ssim", "depth_l1_m", "depth_l1_cm") if with_ssim else ("psnr",)
    return {k: m[k] for k in keys}  # type: ignore[misc]


def run_pool(
    source: FrameSequence,
    config: PoolConfig,
    mapper_config: MapperConfig | None = None,
    out_dir: str | Path | None = None,
    gt_mesh: str | Path | None = None,
    overwrite: bool = False,
    on_select: SelectHook | None = None,
    policy: PoolPolicy | None = None,
) -> PoolResult:
    """Run the pool setting on a sequence; write ``metrics.json``, ``mesh.ply``, ``map.ply``, ``keyframes.json``.

    ``mapper_config``'s seed is replaced by ``config.seed``. ``out_dir`` None writes nothing. The metrics
    hold the split, the chosen view positions and frame ids in order, the per-addition ``curve`` (views,
    test PSNR, surfels, seconds of scoring and training, mesh metrics at checkpoints) and the final
    test-view PSNR / SSIM / depth L1 and mesh metrics. ``policy`` selects instead of ``config.policy`` (the
    metrics then name it by its ``name`` attribute); ``config.seed`` still seeds the mapper.
    """
    t_start = time.perf_counter()
    check_frame_source(source, "source")
    evaluation.check_eval_size(source.intrinsics)
    gt_path = Path(gt_mesh) if gt_mesh is not None else None
    if gt_path is not None:
        evaluation.check_gt_mesh(gt_path)
    keep: dict[str, Any] = {}
    if out_dir is not None:
        reads = (getattr(source, "path", None), gt_path)
        keep = check_run_output(out_dir, overwrite, "a pool run's output", reads, ("metrics.json",))
    mcfg = replace(mapper_config or MapperConfig(), seed=config.seed)
    policy_name = config.policy if policy is None else str(getattr(policy, "name", type(policy).__name__))
    if policy is None:
        policy = make_pool_policy(config)
    policy.reset()
    frames = list(source)
    if not frames:
        raise InputError("source", "no frames")
    poses = np.stack([f.T_wc for f in frames])
    split = split_pool(poses, config)
    intr = source.intrinsics
    test_frames = [frames[i] for i in split.test]
    n_curve = config.curve_test_views or len(test_frames)  # 0: all of them
    curve_frames = [test_frames[i] for i in spread_indices(len(test_frames), n_curve)]
    mapper = Mapper(intr, mcfg)

    visible_cache: dict[str, np.ndarray] = {}

    def observed(points: np.ndarray) -> np.ndarray:
        """GT samples seen from the sequence's poses; the samples are the same at every checkpoint, so once."""
        if "points" not in visible_cache or not np.array_equal(visible_cache["points"], points):
            assert gt_path is not None
            visible_cache["points"] = points.copy()
            visible_cache["mask"] = evaluation.gt_visible_mask(points, gt_path, poses, intr, mcfg.max_depth_m)
        return visible_cache["mask"]

    def mesh_metrics() -> dict[str, Any]:
        assert gt_path is not None
        return evaluation.mesh_metrics(
            mapper.mesh(),
            gt_path,
            taus_m=config.mesh_taus_m,
            n_samples=config.mesh_samples,
            seed=config.seed,
            cull_max_depth_m=mcfg.max_depth_m,
            gt_point_filter=observed if config.cull_gt_to_observed else None,
        )

    chosen: list[int] = []
    skipped: list[int] = []
    curve: list[dict[str, Any]] = []
    t_train = t_score = t_eval = 0.0

    def record(score_s: float, train_s: float) -> None:
        nonlocal t_eval
        t0 = time.perf_counter()
        n = len(mapper.keyframes)
        point: dict[str, Any] = {"n_views": n, "view": chosen[-1] if chosen else None, "n_surfels": mapper.n_surfels}
        point["test_psnr"] = _test_image_metrics(mapper, curve_frames, with_ssim=False)["psnr"]
        point["score_s"], point["train_s"] = score_s, train_s
        if gt_path is not None and (n in config.mesh_checkpoints or n == config.n_views):
            point["mesh"] = mesh_metrics()
        t_eval += time.perf_counter() - t0
        curve.append(point)

    # Initial views, then the initial training phase.
    t0 = time.perf_counter()
    for pos in split.initial:
        if mapper.add_keyframe(frames[pos], optimise=False):
            chosen.append(pos)
        else:
            skipped.append(pos)
    if not chosen:
        raise InputError("pool", "no initial view has valid depth")
    mapper.optimise(config.steps(config.initial_iters, len(chosen)), newest=None)
    mapper.prune()
    dt = time.perf_counter() - t0
    t_train += dt
    record(0.0, dt)

    remaining = [p for p in split.pool if p not in chosen and p not in skipped]
    nbv_config = getattr(policy, "config", None)
    uses_h_train = policy.mode in ROI_MODES and (
        not isinstance(nbv_config, NBVConfig) or nbv_config.uses_fisher(policy.mode)
    )
    while len(mapper.keyframes) < config.n_views and remaining:
        t0 = time.perf_counter()
        if config.recompute_h_train and uses_h_train and mcfg.track_h_train:
            mapper.recompute_h_train()
        cand_poses = poses[remaining]
        if on_select is not None:
            on_select(mapper, policy, list(remaining), cand_poses.copy())
        pick = policy.choose([pose_only(frames[p]) for p in remaining], mapper)
        pos = remaining.pop(pick)
        score_s = time.perf_counter() - t0
        t_score += score_s
        t0 = time.perf_counter()
        if not mapper.add_keyframe(frames[pos], optimise=False):
            skipped.append(pos)
            log.warning("pool frame %d has no valid depth; skipped", frames[pos].index)
            continue
        chosen.append(pos)
        newest = len(mapper.keyframes) - 1 if config.newest_first else None
        mapper.optimise(config.steps(config.iters_per_view, len(chosen)), newest=newest)
        mapper.prune()
        dt = time.perf_counter() - t0
        t_train += dt
        record(score_s, dt)
    if config.final_iters:
        t0 = time.perf_counter()
        mapper.refine(config.steps(config.final_iters, len(chosen)))
        t_train += time.perf_counter() - t0

    t0 = time.perf_counter()
    metrics: dict[str, Any] = {
        "setting": "pool",
        "policy": policy_name,
        # what chose the views: a stream policy's window and trigger decide nothing here (check_pool_params)
        "policy_params": {k: v for k, v in policy.params().items() if k not in STREAM_TRIGGER_PARAMS},
        "n_frames": len(frames),
        "n_test_views": len(split.test),
        "n_pool": len(split.pool),
        "n_views": len(mapper.keyframes),
        "n_keyframes": len(mapper.keyframes),
        "initial_positions": split.initial,
        "chosen_positions": chosen,
        "chosen_frame_ids": [int(frames[p].index) for p in chosen],
        "skipped_positions": skipped,
        "test_positions": split.test,
        "map_size": mapper.n_surfels,
        "eval_on": "held-out test views",
    }
    metrics |= _test_image_metrics(mapper, test_frames, with_ssim=True)
    mesh = mapper.mesh()
    if gt_path is not None:
        last = curve[-1]
        if config.final_iters == 0 and "mesh" in last:
            metrics |= last["mesh"]
        else:
            metrics |= mesh_metrics()
        metrics["gt_mesh"] = str(gt_path)
    t_eval += time.perf_counter() - t0
    metrics["curve"] = curve
    metrics["train_s"] = t_train
    metrics["score_s"] = t_score
    metrics["eval_s"] = t_eval
    metrics["wall_s"] = time.perf_counter() - t_start
    metrics["pool_config"] = config.to_dict()
    metrics["config"] = mcfg.to_dict()
    metrics |= {f"mapper_{k}": v for k, v in asdict(mapper.stats).items()}  # as a stream run's (depth_scale_note)
    metrics = evaluation.to_json_safe(metrics)
    if out_dir is not None:
        with atomic_dir(out_dir, overwrite, **keep) as tmp:
            mapper.save(tmp)
            if not o3d.io.write_triangle_mesh(str(tmp / "mesh.ply"), mesh):
                raise OSError(f"{Path(out_dir) / 'mesh.ply'}: open3d could not write the mesh")
            write_json(tmp / "metrics.json", metrics)
    return PoolResult(metrics=metrics, mapper=mapper, frames=frames, split=split)


__all__ = [
    "POOL_POLICIES",
    "SCHEDULES",
    "STREAM_TRIGGER_PARAMS",
    "PoolConfig",
    "PoolPolicy",
    "PoolResult",
    "PoolSplit",
    "ReplayPicks",
    "check_pool_params",
    "farthest_point_views",
    "make_pool_policy",
    "pose_only",
    "run_pool",
    "selectable_positions",
    "split_pool",
]
