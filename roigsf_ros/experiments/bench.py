"""The NBV benchmark behind ``roigsf bench``: every policy on identical inputs, seeds and schedules.

Settings: ``stream`` (:func:`roigsf_ros.experiments.offline.run_offline` per policy and seed: frames in trajectory
order, the policy picks keyframes) and ``pool`` (:func:`roigsf_ros.experiments.pool.run_pool`: greedy selection
from a pool of views, FisherRF's "v20seq1"). Each run writes its own sub-folder
``runs/<label>/seed<k>/``; the benchmark adds, for a few held-out views of every run, the Eq. 17
pixel uncertainty and FisherRF's colour-Fisher uncertainty against the absolute depth error: their
AUSE (normalised, as FisherRF reports it, and raw in metres), a seeded random ordering's raw AUSE and
the Spearman correlation (see :func:`roigsf_ros.nbv.scorer.depth_error_ause` for why the normalised number
alone misleads). :func:`run_bench` writes ``results.json`` (every metric per run, mean/std over seeds,
parameters, versions, wall times), ``results.md`` and plots (see :mod:`roigsf_ros.experiments.report`);
:func:`rescore_ause` recomputes that study from a finished output folder's saved maps (no training). Both build the
whole folder under a hidden temporary name beside it and rename it into place once complete, so an interrupted or
failed bench leaves the folder as it was and a finished one holds nothing of the folder it replaced.

Policies are given as ``name[:key=value[:key=value...]]`` (e.g. ``roi-gsurfisher:window=12``); the
whole spec is the row label, so one policy can appear with several parameter sets.
"""

from __future__ import annotations

import fnmatch
import json
import logging
import os
import platform
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

import roigsf_ros
from roigsf_ros import evaluation
from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.config import Config
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import atomic_dir, check_writable, read_json, write_json
from roigsf_ros.core.frame import Frame, spread_indices
from roigsf_ros.data.bags import CameraTopics
from roigsf_ros.data.sources import FrameSource, is_bag, open_frames
from roigsf_ros.experiments.offline import EvalConfig, run_offline
from roigsf_ros.experiments.pool import POOL_POLICIES, PoolConfig, check_pool_params, run_pool, selectable_positions
from roigsf_ros.mapping.mapper import Mapper, MapperConfig
from roigsf_ros.nbv.scorer import NBVScorer, depth_error_ause, render_surfel_scalar, train_fisher
from roigsf_ros.policies.base import make_policy, parse_params, policy_names, unknown_policy
from roigsf_ros.policies.stream import StreamNBVPolicy
from roigsf_ros.render.rasterize import camera_tensors
from roigsf_ros.render.surfels import SurfelMap

log = logging.getLogger(__name__)

SETTINGS = ("stream", "pool")
"""Benchmark settings."""

STREAM_ONLY = ("gaus-slam", "every-n", "all")
"""Per-frame keyframe rules: they answer for the frame in hand and cannot score a pool of poses."""

SUMMARY_KEYS = (
    "n_keyframes",
    "psnr",
    "ssim",
    "depth_l1_cm",
    "test_scene_psnr",
    "test_scene_ssim",
    "test_scene_depth_l1_cm",
    "test_scene_psnr_covered",
    "test_scene_uncovered_pixel_fraction",
    "test_scene_uncovered_error_share",
    "test_scene_holes_unseen_share",
    "precision@1cm",
    "recall@1cm",
    "fscore@1cm",
    "precision@5cm",
    "recall@5cm",
    "fscore@5cm",
    "accuracy_cm",
    "completion_cm",
    "completion_ratio_5cm",
    "ause_eq17",
    "ause_fisherrf",
    "ause_raw_eq17",
    "ause_raw_fisherrf",
    "ause_raw_random",
    "ause_raw_eq17_cm",
    "ause_raw_fisherrf_cm",
    "ause_raw_random_cm",
    "rho_eq17",
    "rho_fisherrf",
    "map_size",
    "wall_s",
)
"""Metrics averaged over seeds in ``results.json``'s summary (those a run has)."""

AUSE_VIEW_KEYS = ("ause_eq17", "ause_fisherrf", "ause_raw_eq17", "ause_raw_fisherrf", "ause_raw_random",
                  "rho_eq17", "rho_fisherrf")  # fmt: skip
"""Per held-out view numbers of the AUSE study (raw AUSE in metres; ``rho``: Spearman vs |depth error|)."""


# ---------------------------------------------------------------------------------- policy specs
@dataclass(frozen=True)
class PolicySpec:
    """A policy of the benchmark: registered ``name``, its ``params`` and the row ``label`` (the spec text)."""

    name: str
    params: dict[str, Any] = field(default_factory=dict)
    label: str = ""


BENCH_OUTPUT: dict[str, Any] = {"marks": ("results.json",), "what": "a bench's output", "own": ("runs/*/*",)}
"""What a bench's output folder is (:func:`roigsf_ros.core.fileio.check_replaceable`): results.json marks it, and its
runs (``runs/<label>/seed<k>/``, each with its metrics.json) are its own."""


def parse_policies(text: str, setting: str) -> list[PolicySpec]:
    """Policy specs from ``"a,b:key=value:key2=value2,..."``, checked against the registry and ``setting``."""
    if setting not in SETTINGS:
        raise InputError("--setting", f"unknown setting {setting!r} (choose from {', '.join(SETTINGS)})")
    specs: list[PolicySpec] = []
    identities: list[tuple[str, str]] = []  # each spec's policy and the parameters it runs with
    items = [s.strip() for s in str(text).split(",")]
    if not any(items):
        raise InputError("--policies", "no policy given")
    if not all(items):  # `random,` or `a,,b`: a policy left out by a slip, run without it
        raise InputError("--policies", f"{text!r} has an empty entry (a comma too many, or a policy left out)")
    for item in items:
        name, *pairs = [p.strip() for p in item.split(":")]
        params = parse_params(pairs, "--policies", f"{item!r}: expected name:key=value")
        if name not in policy_names():
            raise unknown_policy(name, where="--policies")
        if setting == "pool" and name not in POOL_POLICIES:
            raise InputError(
                "--policies",
                f"{name!r} is a stream-only rule (it cannot score a pool of poses); pool policies: "
                f"{', '.join(POOL_POLICIES)}",
            )
        if setting == "pool":
            check_pool_params(params)
        try:  # unknown, mistyped or out-of-range parameters fail here, before any work
            policy = make_policy(name, **params)
        except InputError as e:
            raise InputError("--policies", f"{item!r}: {e}") from e
        identity = _identity(name, policy)
        if identity in identities:  # one policy spelt twice (1 and 1.0, keys in another order, an alias) ran twice
            first = specs[identities.index(identity)].label
            twice = item if first == item else f"{first} and {item}"
            raise InputError("--policies", f"policy given twice: {twice} (the same policy and parameters)")
        identities.append(identity)
        specs.append(PolicySpec(name=name, params=params, label=item))
    return specs


def _identity(name: str, policy: Any) -> tuple[str, str]:
    """A policy and the parameters it runs with (its own ``params()``, defaults and aliases resolved; 1 and 1.0 one)."""
    params = {k: float(v) if isinstance(v, int) and not isinstance(v, bool) else v for k, v in policy.params().items()}
    return name, json.dumps(params, sort_keys=True, default=str)


def policy_identity(label: str) -> tuple[str, str]:
    """A spec label's policy and the parameters it runs with: ``every-n:n=4`` and ``every-n:every_n=4`` (an alias),
    ``x=1`` and ``x=1.0``, keys in any order, have one identity; InputError if the label names no policy that builds.
    """
    name, *pairs = [p.strip() for p in label.split(":")]
    return _identity(name, make_policy(name, **parse_params(pairs, label, "expected name:key=value")))


# ---------------------------------------------------------------------------------- uncertainty
def fisherrf_uncertainty_maps(
    scorer: NBVScorer,
    surfel_map: SurfelMap,
    train_poses: np.ndarray,
    eval_poses: Sequence[np.ndarray],
    intr: Intrinsics,
) -> list[np.ndarray]:
    """FisherRF's uncertainty map [H, W] at each of ``eval_poses``, as :meth:`NBVScorer.fisherrf_uncertainty`.

    The same quantity (colour Fisher of the training views plus the evaluated view, times the surfel's
    depth, composited) with the training views' Fisher computed once instead of once per evaluated view.
    """
    cfg = scorer.config
    if len(surfel_map) == 0:
        return [np.zeros((intr.height, intr.width)) for _ in eval_poses]
    params = [p for p in ("sh_dc", "sh_rest") if p != "sh_rest" or surfel_map.sh_rest is not None]
    h_train = train_fisher(surfel_map, train_poses, intr, ("color",), params, 1.0, cfg.near_m, cfg.far_m)
    out = []
    for T in eval_poses:
        h_view = train_fisher(surfel_map, [T], intr, ("color",), params, 1.0, cfg.near_m, cfg.far_m)
        per = sum((h_train[k] + h_view[k]).reshape(len(surfel_map), -1).sum(-1) for k in params)
        viewmat, _ = camera_tensors(T, intr, dtype=torch.float64)
        z = surfel_map.means.detach().double() @ viewmat[2, :3] + viewmat[2, 3]
        out.append(render_surfel_scalar(surfel_map, per.double() * z.clamp_min(0), T, intr, cfg.near_m, cfg.far_m))
    return out


@dataclass
class UncertaintyStudy:
    """Per held-out view: the :data:`AUSE_VIEW_KEYS` of Eq. 17 and FisherRF's maps; maps of the first few views."""

    per_view: list[dict[str, Any]]
    maps: list[dict[str, Any]]

    def means(self) -> dict[str, float | None]:
        """Mean over the views of every :data:`AUSE_VIEW_KEYS` number (None where no view has it), raw also in cm."""
        out: dict[str, float | None] = {}
        for key in AUSE_VIEW_KEYS:
            vals = [v[key] for v in self.per_view if v.get(key) is not None and np.isfinite(v[key])]
            out[key] = float(np.mean(vals)) if vals else None
        for key in ("ause_raw_eq17", "ause_raw_fisherrf", "ause_raw_random"):
            out[f"{key}_cm"] = None if out[key] is None else 100.0 * out[key]
        return out


def study_views(candidates: Sequence[Frame], n_views: int) -> list[Frame]:
    """``n_views`` frames spread evenly over ``candidates`` (the held-out ones), without repeats."""
    if n_views <= 0 or not candidates:
        return []
    return _unique([candidates[i] for i in spread_indices(len(candidates), n_views)])


def uncertainty_study(
    mapper: Mapper,
    train_poses: np.ndarray,
    views: Sequence[Frame],
    n_maps: int,
    scorer: NBVScorer | None = None,
) -> UncertaintyStudy:
    """Eq. 17 uncertainty (training Fisher of the ROI modes) and FisherRF's map vs the depth error at ``views``.

    Depth error: |rendered depth (the mapper's ``eval_depth``) - the view's depth| where both are valid.
    Per view: normalised and raw AUSE of both maps, the raw AUSE of a seeded random pixel ordering (the
    same pixels for both maps, so one baseline) and both maps' Spearman rho. The first ``n_maps`` views
    keep their maps (rgb, depth error, both uncertainties) for the figure.
    """
    scorer = scorer or NBVScorer()
    m = mapper.map.detach()
    intr = mapper.intr
    per_view: list[dict[str, Any]] = []
    maps: list[dict[str, Any]] = []
    if len(m) == 0 or len(train_poses) == 0 or not views:
        return UncertaintyStudy(per_view, maps)
    h = scorer.train_fisher(m, train_poses, intr, mode="roi-gsurfisher")
    frr = fisherrf_uncertainty_maps(scorer, m, train_poses, [f.T_wc for f in views], intr)
    for i, (f, u_frr) in enumerate(zip(views, frr, strict=True)):
        u = scorer.uncertainty(m, h, f.T_wc, intr).u
        out = mapper.render(f.T_wc)
        depth = mapper.render_depth(out, mapper.config.eval_depth).cpu().numpy().astype(np.float64)
        gt = np.where(mapper.valid_depth_mask(f.depth_m), f.depth_m, 0.0).astype(np.float64)
        row: dict[str, Any] = {"frame": int(f.index)}
        try:
            a, b = depth_error_ause(u, depth, gt), depth_error_ause(u_frr, depth, gt)
            row |= {"ause_eq17": a["ause"], "ause_fisherrf": b["ause"]}
            row |= {"ause_raw_eq17": a["ause_raw"], "ause_raw_fisherrf": b["ause_raw"]}
            row |= {"ause_raw_random": a["ause_random_raw"], "n_pixels": a["n"]}
            row |= {"rho_eq17": _finite(a["spearman_rho"]), "rho_fisherrf": _finite(b["spearman_rho"])}
        except InputError as exc:  # no pixel with valid depths in this view
            row["error"] = str(exc)
        per_view.append(row)
        if i < n_maps:
            err = np.where((depth > 0) & (gt > 0), np.abs(depth - gt), np.nan)
            maps.append({"frame": int(f.index), "rgb": f.rgb, "depth_err_m": err, "u_eq17": u, "u_fisherrf": u_frr})
    return UncertaintyStudy(per_view, maps)


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


# ---------------------------------------------------------------------------------------- config
@dataclass(frozen=True)
class BenchConfig(Config):
    """What ``roigsf bench`` runs: scene, setting, policies, seeds, sizes and the shared configs."""

    scene: Path
    setting: str
    policies: list[PolicySpec]
    seeds: int = 1
    gt_mesh: Path | None = None
    size: tuple[int | None, int | None] | None = None
    """Frame size (one side None: it follows the scene's aspect ratio); None: the scene's own."""
    stride: int = 1
    max_frames: int | None = None
    mapper: MapperConfig = field(default_factory=MapperConfig)
    pool: PoolConfig = field(default_factory=PoolConfig)
    eval_every: int = 1
    """Stream: evaluate every this-many-th non-keyframe."""
    uncertainty_views: int = 6
    """Held-out views per run for the AUSE study (0: none)."""
    uncertainty_maps: int = 3
    """Of those, views whose maps are drawn (seed 0 of each policy)."""
    test_scene: Path | None = None
    """Stream: frames no policy sees (same camera; resized like the scene), evaluated for every run: one test set
    for all policies, where the non-keyframes differ from one policy to the next."""
    topics: CameraTopics | None = None
    """How a bag scene (and a bag test scene) is read: topics, transports, pose from a topic or TF, as ``roigsf map``'s
    camera options say (a robot's bag: ``--realsense``); None: the default names, raw images."""
    cam: Path | None = None
    """A Replica folder's camera file when it has no ``cam_params.json`` (the test scene's too; a bag: refused)."""
    allow_partial: bool = False
    """Read a Replica folder whose ``traj.txt`` holds more poses than its frames (a partial download)."""

    def validate(self) -> BenchConfig:
        """Self, or InputError naming the bad field."""
        if self.setting not in SETTINGS:
            raise InputError("--setting", f"unknown setting {self.setting!r} (choose from {', '.join(SETTINGS)})")
        if isinstance(self.seeds, bool) or int(self.seeds) != self.seeds or self.seeds < 1:
            raise InputError("--seeds", f"must be a positive integer, got {self.seeds!r}")
        if not self.policies:
            raise InputError("--policies", "no policy given")
        if self.setting == "pool":
            bad = [p.name for p in self.policies if p.name not in POOL_POLICIES]
            if bad:
                raise InputError("--policies", f"stream-only rule(s) {', '.join(bad)} in the pool setting")
        if not Path(self.scene).exists():
            raise InputError(self.scene, "no such bag or scene folder")
        if self.gt_mesh is not None:
            evaluation.check_gt_mesh(self.gt_mesh)
        for name in ("eval_every", "stride"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"--{name.replace('_', '-')}", f"must be at least 1, got {getattr(self, name)}")
        if self.test_scene is not None:
            if self.setting != "stream":
                raise InputError("--test-scene", "stream setting only (the pool holds out its own test views)")
            if not Path(self.test_scene).exists():
                raise InputError(self.test_scene, "no such bag or scene folder (--test-scene)")
        if self.uncertainty_views < 0 or self.uncertainty_maps < 0:
            raise InputError("--uncertainty-views", "must be >= 0")
        self.mapper.validate()
        return self

    def source(self) -> FrameSource:
        """The frame source every run reads (the same frames, sizes and stride for all)."""
        return open_frames(self.scene, size=self.size, stride=self.stride, max_frames=self.max_frames,
                           topics=self.topics, cam=self.cam, allow_partial=self.allow_partial)  # fmt: skip

    def test_source(self) -> FrameSource | None:
        """The test scene's frames at the scene's size (all of them), or None."""
        if self.test_scene is None:
            return None
        cam = self.cam if not is_bag(self.test_scene) else None  # a bag test scene beside a folder: its camera_info
        return open_frames(self.test_scene, size=self.size, topics=self.topics, cam=cam,
                           allow_partial=self.allow_partial)  # fmt: skip


def versions() -> dict[str, str]:
    """Versions of the package and the libraries that decide the numbers."""
    import open3d

    return {
        "roigsf_ros": roigsf_ros.__version__,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "open3d": open3d.__version__,
        "torch_threads": str(torch.get_num_threads()),
        "machine": platform.machine(),
    }


# -------------------------------------------------------------------------------------- one run
def _stream_run(cfg: BenchConfig, spec: PolicySpec, seed: int, run_dir: Path, gt: Path | None) -> dict[str, Any]:
    """One stream run (run_offline) and its uncertainty study; returns the run record."""
    source = cfg.source()
    policy = make_policy(spec.name, **spec.params)
    if isinstance(policy, StreamNBVPolicy) and "seed" not in spec.params:
        policy = make_policy(spec.name, **(spec.params | {"seed": seed}))
    mcfg = replace(cfg.mapper, seed=seed)
    metrics = run_offline(source, policy, mcfg, run_dir, gt_mesh=gt, eval_config=EvalConfig(eval_every=cfg.eval_every),
                          progress=False, overwrite=True, test_source=cfg.test_source())  # fmt: skip
    frames = list(source)
    kf = set(metrics["keyframe_ids"])
    positions = {int(f.index): i for i, f in enumerate(frames)}
    chosen = [positions[i] for i in metrics["keyframe_ids"] if i in positions]
    held_out = [f for f in frames if int(f.index) not in kf]
    record: dict[str, Any] = {"chosen_positions": chosen, "test_positions": []}
    study = None
    if cfg.uncertainty_views and held_out:
        t0 = time.perf_counter()
        mapper = Mapper.load(run_dir, mcfg)
        views = study_views(held_out, cfg.uncertainty_views)
        study = uncertainty_study(mapper, mapper.loaded_keyframe_poses, views, cfg.uncertainty_maps)
        record["uncertainty_s"] = time.perf_counter() - t0
    return _finish(record, metrics, study, np.stack([f.T_wc for f in frames]))


def _pool_run(cfg: BenchConfig, spec: PolicySpec, seed: int, run_dir: Path, gt: Path | None) -> dict[str, Any]:
    """One pool run (run_pool) and its uncertainty study over the test views; returns the run record."""
    pcfg = replace(cfg.pool, policy=spec.name, policy_params=dict(spec.params), seed=seed)
    res = run_pool(cfg.source(), pcfg, cfg.mapper, run_dir, gt_mesh=gt, overwrite=True)
    record: dict[str, Any] = {"chosen_positions": res.metrics["chosen_positions"], "test_positions": res.split.test}
    study = None
    if cfg.uncertainty_views:
        t0 = time.perf_counter()
        views = study_views([res.frames[i] for i in res.split.test], cfg.uncertainty_views)
        study = uncertainty_study(res.mapper, res.mapper.keyframe_poses, views, cfg.uncertainty_maps)
        record["uncertainty_s"] = time.perf_counter() - t0
    return _finish(record, res.metrics, study, np.stack([f.T_wc for f in res.frames]))


def _unique(frames: list[Frame]) -> list[Frame]:
    seen: set[int] = set()
    return [f for f in frames if not (f.index in seen or seen.add(f.index))]


def _finish(record: dict[str, Any], metrics: dict[str, Any], study: UncertaintyStudy | None,
            poses: np.ndarray) -> dict[str, Any]:  # fmt: skip
    """Merge the run's metrics with the AUSE means; keep the maps and the trajectory for the plots."""
    record["metrics"] = dict(metrics)
    if study is not None:
        record["metrics"] |= study.means()
        record["uncertainty_per_view"] = study.per_view
    record["_maps"] = study.maps if study is not None else []
    record["_trajectory"] = poses
    return record


# ----------------------------------------------------------------------------------- aggregation
def summarise(runs: list[dict[str, Any]], labels: list[str]) -> dict[str, dict[str, Any]]:
    """Mean, std (population) and count over seeds of every :data:`SUMMARY_KEYS` metric, per label."""
    out: dict[str, dict[str, Any]] = {}
    for label in labels:
        mine = [r["metrics"] for r in runs if r["label"] == label]
        row: dict[str, Any] = {}
        for key in SUMMARY_KEYS:
            vals = [float(m[key]) for m in mine if m.get(key) is not None]
            if vals:
                row[key] = {"mean": float(np.mean(vals)), "std": float(np.std(vals)), "n": len(vals)}
        out[label] = row
    return out


def pool_curves(runs: list[dict[str, Any]], labels: list[str]) -> dict[str, list[dict[str, Any]]]:
    """Per label and view count: mean/std over seeds of the test PSNR and (at checkpoints) recall/F at 5 cm."""
    out: dict[str, list[dict[str, Any]]] = {}
    for label in labels:
        by_n: dict[int, dict[str, list[float]]] = {}
        for r in (r for r in runs if r["label"] == label):
            for p in r["metrics"].get("curve", []):
                d = by_n.setdefault(int(p["n_views"]), {})
                if p.get("test_psnr") is not None:
                    d.setdefault("test_psnr", []).append(float(p["test_psnr"]))
                for k in ("recall@5cm", "fscore@5cm", "precision@5cm", "recall@1cm", "fscore@1cm"):
                    if p.get("mesh", {}).get(k) is not None:
                        d.setdefault(k, []).append(float(p["mesh"][k]))
        rows = []
        for n in sorted(by_n):
            row: dict[str, Any] = {"n_views": n}
            for k, v in by_n[n].items():
                row[k] = {"mean": float(np.mean(v)), "std": float(np.std(v)), "n": len(v)}
            rows.append(row)
        out[label] = rows
    return out


# -------------------------------------------------------------------------------------------- run
def run_bench(cfg: BenchConfig, out_dir: str | Path, overwrite: bool = False, progress: bool = True,
              command: str | None = None) -> dict[str, Any]:  # fmt: skip
    """Run every policy for every seed; write runs/, results.json, results.md and the plots into ``out_dir``.

    The whole folder is built under a hidden temporary name beside ``out_dir`` (``.NAME.tmp-*``, removed on an error
    or Ctrl-C) and renamed to ``out_dir`` once all of it is written; with ``overwrite`` an existing ``out_dir`` is
    replaced only then, so an interrupted bench leaves it as it was and a finished one leaves no file of it. Runs
    are not reused: every run is made anew. Returns the results dict.
    """
    from roigsf_ros.experiments import report as bench_report  # matplotlib only when a benchmark runs

    cfg.validate()
    out = Path(out_dir)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: already exists (overwrite=True replaces it)")
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    source = cfg.source()
    if cfg.setting == "pool":  # now, not inside the first run (run_pool's split_pool checks it too)
        selectable_positions(len(source), cfg.pool, where="--pool-set n_views")
    gt = cfg.gt_mesh if cfg.gt_mesh is not None else source.gt_mesh_path
    t0 = time.perf_counter()
    runs: list[dict[str, Any]] = []
    labels = [p.label for p in cfg.policies]
    total = len(labels) * cfg.seeds
    reads = [p for p in (cfg.scene, cfg.gt_mesh, cfg.test_scene, source.gt_mesh_path) if p is not None]
    with atomic_dir(out, overwrite, inputs=reads, **BENCH_OUTPUT) as tmp:
        if progress:
            print(f"writing into {tmp}, renamed to {out} when the bench is complete", flush=True)
        for spec in cfg.policies:
            for seed in range(cfg.seeds):
                rel = Path("runs") / _slug(spec.label) / f"seed{seed}"
                if progress:
                    print(
                        f"[{len(runs) + 1}/{total}] {cfg.setting} {spec.label} seed {seed} -> {out / rel}", flush=True
                    )
                t_run = time.perf_counter()
                fn = _stream_run if cfg.setting == "stream" else _pool_run
                record = fn(cfg, spec, seed, tmp / rel, gt)
                record |= {"label": spec.label, "policy": spec.name, "params": spec.params, "seed": seed,
                           "dir": rel.as_posix(), "run_wall_s": time.perf_counter() - t_run}  # fmt: skip
                runs.append(record)
                if progress:
                    m = record["metrics"]
                    print(f"    views {m.get('n_keyframes')}  PSNR {_fmt(m.get('psnr'))}  R@5cm "
                          f"{_fmt(m.get('recall@5cm'))}  {record['run_wall_s']:.0f} s", flush=True)  # fmt: skip

        results: dict[str, Any] = {
            "setting": cfg.setting,
            "scene": str(cfg.scene),
            "scene_resolved": str(Path(cfg.scene).resolve()),  # for a rescore run from another working directory
            "gt_mesh": str(gt) if gt is not None else None,
            "command": command,
            "seeds": list(range(cfg.seeds)),
            "size": [source.intrinsics.width, source.intrinsics.height],  # as resized (a side given alone: derived)
            "stride": cfg.stride,
            "max_frames": cfg.max_frames,
            "n_frames": len(source),
            "policies": [{"label": p.label, "name": p.name, "params": p.params} for p in cfg.policies],
            "mapper_config": cfg.mapper.to_dict(),
            "pool_config": cfg.pool.to_dict() if cfg.setting == "pool" else None,
            "eval_every": cfg.eval_every if cfg.setting == "stream" else None,
            "test_scene": str(cfg.test_scene) if cfg.test_scene is not None else None,
            "camera_topics": source.camera_topics.record() if source.camera_topics is not None else None,  # a bag's
            "tf_child_frame_note": source.tf_child_frame_note or None,  # the poses are not the images': say so
            "cam": str(cfg.cam) if cfg.cam is not None else None,  # a rescore reads the folder with these two
            "allow_partial": cfg.allow_partial,
            "uncertainty_views": cfg.uncertainty_views,
            "uncertainty_maps": cfg.uncertainty_maps,
            "versions": versions(),
            "summary": summarise(runs, labels),
            "curves": pool_curves(runs, labels) if cfg.setting == "pool" else None,
            "runs": [{k: v for k, v in r.items() if not k.startswith("_")} for r in runs],
        }
        results["wall_s"] = time.perf_counter() - t0
        results = evaluation.to_json_safe(results)
        bench_report.write_report(tmp, results, runs)
        write_json(tmp / "results.json", results)
    return results


# ------------------------------------------------------------------------------------ read back
def read_results(
    folder: str | Path, setting: str | None = None, fields: Sequence[str] = (), run_fields: Sequence[str] = ()
) -> dict[str, Any]:
    """``folder/results.json`` of a finished bench, for the scripts that read one: InputError naming the file and the
    first of ``fields`` missing or empty, another ``setting`` than the one asked, or a run without one of
    ``run_fields``.
    """
    path = Path(folder) / "results.json"
    res = read_json(path, "not found (not a finished `roigsf bench` output folder)")
    if setting is not None and res.get("setting") != setting:
        raise InputError(path, f"setting is {res.get('setting')!r}, not {setting!r}")
    for key in fields:
        if not res.get(key):
            raise InputError(path, f"field {key!r} is missing or empty")
    if run_fields:
        runs = res.get("runs")
        if not isinstance(runs, list):
            raise InputError(path, "field 'runs' is missing or not a list")
        for i, run in enumerate(runs):
            missing = [k for k in run_fields if not isinstance(run, dict) or k not in run]
            if missing:
                raise InputError(path, f"runs[{i}] has no field {missing[0]!r}")
    return res


# ---------------------------------------------------------------------------------------- rescore
def _read_results(out: Path) -> dict[str, Any]:
    """``out/results.json`` of a finished bench, checked for what :func:`rescore_ause` needs."""
    path = out / "results.json"
    results = read_json(path, "not found (not a finished `roigsf bench` output folder)")
    needed = ("setting", "scene", "size", "stride", "max_frames", "n_frames", "policies", "mapper_config", "runs")
    missing = [k for k in needed if k not in results]
    if missing:
        raise InputError(path, f"missing field(s) {', '.join(missing)}")
    if results["setting"] not in SETTINGS:
        raise InputError(path, f"unknown setting {results['setting']!r}")
    for i, r in enumerate(results["runs"]):
        lacking = [k for k in ("label", "seed", "dir", "metrics") if k not in r]
        if lacking:
            raise InputError(path, f"runs[{i}] lacks {', '.join(lacking)}")
    return results


def _bench_scene(results: dict[str, Any]) -> Path:
    """The bench's scene: its ``scene`` as given if that exists from here, else ``scene_resolved``, the absolute path
    the bench recorded (a relative ``scene`` is of the bench's working directory); else ``scene``, for the error.
    """
    given = Path(results["scene"])
    resolved = results.get("scene_resolved")
    if not given.exists() and isinstance(resolved, str) and resolved and Path(resolved).exists():
        return Path(resolved)
    return given


def bench_topics(results: dict[str, Any]) -> CameraTopics | None:
    """How the bench read its bag (``camera_topics`` of its results.json; None: the defaults, as before it was kept);
    InputError naming the field when it is not what :class:`CameraTopics` takes.
    """
    given = results.get("camera_topics")
    if given is None:
        return None
    try:
        return CameraTopics(**given)
    except (TypeError, InputError) as exc:
        raise InputError("results.json", f"field 'camera_topics': {exc}") from None


def _open_bench_frames(results: dict[str, Any], scene: Path) -> list[Frame]:
    """The frames the bench ran on: its scene, stride and frame cap, resized only if it was."""
    stride, max_frames = int(results["stride"]), results["max_frames"]
    reading: dict[str, Any] = {"topics": bench_topics(results), "allow_partial": bool(results.get("allow_partial"))}
    reading["cam"] = results.get("cam") if not is_bag(scene) else None
    source = open_frames(scene, stride=stride, max_frames=max_frames, **reading)
    want = (int(results["size"][0]), int(results["size"][1]))
    if (source.intrinsics.width, source.intrinsics.height) != want:
        source = open_frames(scene, size=want, stride=stride, max_frames=max_frames, **reading)
    frames = list(source)
    if len(frames) != int(results["n_frames"]):
        raise InputError(scene, f"{len(frames)} frames (stride {stride}) but the bench ran on {results['n_frames']}")
    return frames


def rescore_ause(out_dir: str | Path, scene: str | Path | None = None, uncertainty_views: int | None = None,
                 uncertainty_maps: int | None = None, progress: bool = True) -> dict[str, Any]:  # fmt: skip
    """Recompute the AUSE study of a finished bench from its saved runs; rewrite results.json / .md / plots.

    Nothing is trained: each run's ``map.ply`` and keyframe poses (``keyframes.json``) are loaded, the
    training Fisher (h_train) is recomputed from those poses, and the same held-out views as
    :func:`run_bench` chose (pool: the test views, stream: the non-keyframes) are read from the scene
    (``scene`` overrides the path stored in results.json). Every other metric is kept; the run records'
    AUSE numbers and ``uncertainty_per_view``, the summary and the report are replaced, and ``ause_rescore``
    records when, how long and with which versions. The new folder (the old one's files, hard-linked, but its
    report; the new report) is built beside it and swapped in once complete, so results.json, results.md and the
    plots are always of one study: an interrupted rescore leaves the folder as it was. Returns the results.
    """
    from roigsf_ros.experiments import report as bench_report

    out = Path(out_dir)
    out = out.resolve() if out.is_symlink() else out  # rescore where the bench is; the link keeps pointing at it
    if not out.is_dir():
        raise InputError(out, "no such bench output folder")
    check_writable(out)  # the new folder is built beside it: fail now rather than after the study
    t0 = time.perf_counter()
    results = _read_results(out)
    scene_path = Path(scene) if scene is not None else _bench_scene(results)
    if not scene_path.exists():
        raise InputError(scene_path, "scene of the bench not found (pass --scene to point at it)")
    frames = _open_bench_frames(results, scene_path)
    n_views = int(results.get("uncertainty_views") or 6) if uncertainty_views is None else int(uncertainty_views)
    n_maps = int(results.get("uncertainty_maps", 3)) if uncertainty_maps is None else int(uncertainty_maps)
    if n_views < 1 or n_maps < 0:
        raise InputError("--uncertainty-views", f"need >= 1 view and >= 0 maps, got {n_views}, {n_maps}")
    mcfg = MapperConfig.from_dict(results["mapper_config"])
    positions = {int(f.index): i for i, f in enumerate(frames)}
    trajectory = np.stack([f.T_wc for f in frames])
    scorer = NBVScorer()
    runs: list[dict[str, Any]] = []
    for k, rec in enumerate(results["runs"]):
        run_dir = out / rec["dir"]
        if progress:
            print(f"[{k + 1}/{len(results['runs'])}] rescoring {rec['label']} seed {rec['seed']}", flush=True)
        t_run = time.perf_counter()
        mapper = Mapper.load(run_dir, replace(mcfg, seed=int(rec["seed"])))
        if (mapper.intr.width, mapper.intr.height) != (frames[0].rgb.shape[1], frames[0].rgb.shape[0]):
            raise InputError(run_dir / "keyframes.json", "its image size differs from the bench's frames")
        m = rec["metrics"]
        expected = m.get("keyframe_ids") if results["setting"] == "stream" else m.get("chosen_frame_ids")
        if expected is not None and sorted(mapper.loaded_keyframe_ids) != sorted(int(i) for i in expected):
            raise InputError(run_dir / "keyframes.json", "its keyframes differ from the run's record in results.json")
        if results["setting"] == "pool":
            bad = [i for i in rec.get("test_positions", []) if not 0 <= int(i) < len(frames)]
            if bad or not rec.get("test_positions"):
                raise InputError(out / "results.json", f"{rec['dir']}: no valid test_positions")
            candidates = [frames[int(i)] for i in rec["test_positions"]]
        else:
            kf = {int(i) for i in mapper.loaded_keyframe_ids}
            candidates = [f for f in frames if int(f.index) not in kf]
        views = study_views(candidates, n_views)
        keep_maps = n_maps if rec["seed"] == 0 else 0  # only seed 0 is drawn
        study = uncertainty_study(mapper, mapper.loaded_keyframe_poses, views, keep_maps, scorer)
        rec["metrics"] = {k2: v for k2, v in m.items() if not k2.startswith(("ause_", "rho_"))}  # stale study
        rec["metrics"] |= study.means()
        rec["uncertainty_per_view"] = study.per_view
        rec["uncertainty_s"] = time.perf_counter() - t_run
        chosen = rec.get("chosen_positions")
        if chosen is None:  # stream records before chosen_positions: from the keyframe ids
            chosen = [positions[i] for i in mapper.loaded_keyframe_ids if i in positions]
        runs.append(rec | {"chosen_positions": chosen, "_maps": study.maps, "_trajectory": trajectory})
    labels = [p["label"] for p in results["policies"]]
    results["runs"] = [{k: v for k, v in r.items() if not k.startswith("_")} for r in runs]
    results["summary"] = summarise(runs, labels)
    results["uncertainty_views"], results["uncertainty_maps"] = n_views, n_maps
    results["ause_rescore"] = {"at": time.strftime("%Y-%m-%d %H:%M:%S %z"), "wall_s": time.perf_counter() - t0,
                               "scene": str(scene_path), "versions": versions()}  # fmt: skip
    results = evaluation.to_json_safe(results)
    with atomic_dir(out, overwrite=True) as tmp:
        _link_all_but_report(out, tmp, bench_report.REPORT_FILES)
        bench_report.write_report(tmp, results, runs)
        write_json(tmp / "results.json", results)
    return results


def _link_all_but_report(src: Path, dst: Path, report_files: Sequence[str]) -> None:
    """Copy bench folder ``src`` into ``dst`` but its results.json and report (``report_files``, glob patterns at the
    top level), as hard links where the file system allows: no map is copied, and no plot of the old report stays.
    """

    def link(a: str, b: str) -> None:
        try:
            os.link(a, b)
        except OSError:
            shutil.copy2(a, b)

    def ignore(folder: str, names: list[str]) -> set[str]:
        if Path(folder) != src:
            return set()
        return {n for n in names if any(fnmatch.fnmatchcase(n, p) for p in ("results.json", *report_files))}

    shutil.copytree(src, dst, symlinks=True, ignore=ignore, copy_function=link, dirs_exist_ok=True)


def _slug(label: str) -> str:
    """A folder name for a policy label (``:`` and ``=`` become ``_``)."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in label)


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


__all__ = [
    "AUSE_VIEW_KEYS",
    "BENCH_OUTPUT",
    "SETTINGS",
    "STREAM_ONLY",
    "SUMMARY_KEYS",
    "BenchConfig",
    "PolicySpec",
    "UncertaintyStudy",
    "bench_topics",
    "fisherrf_uncertainty_maps",
    "parse_policies",
    "policy_identity",
    "pool_curves",
    "read_results",
    "rescore_ause",
    "run_bench",
    "study_views",
    "summarise",
    "uncertainty_study",
]
