r"""Observation-coverage bound on mesh recall for stream keyframe selection (issue 10), without mapping.

The mesh the mapper exports is fused from rendered depth at the keyframe poses only, so mesh recall at
``tau`` (R@5cm) is bounded by how much of the ground-truth surface the chosen keyframes observe. This
script measures that directly:

- GT samples: the GT mesh sampled exactly as the bench's recall does (``evaluation.sample_surface`` with
  ``EvalConfig.mesh_samples`` / ``seed``), culled to the samples some frame of the run sees
  (``evaluation.gt_visible_mask`` over all poses, ``MapperConfig.max_depth_m``): the recall denominator.
- Observed set of a frame: the GT samples within ``tau`` of a back-projected pixel of its valid input depth
  (``MapperConfig`` min/near/max depth; scipy ``cKDTree``).
- Coverage of a set of frames: the fraction of GT samples in the union of their observed sets.

Reported (table ``coverage.md`` and ``coverage.json``, written atomically under ``--out``): all frames;
every ``window``-th frame; an offline greedy max-coverage pick of the same count (frame 0 forced); the
stream oracle (frame 0, then from each trigger window of ``window`` frames the frame adding the most new
coverage given the earlier picks, the windows of ``StreamNBVPolicy``: frames 1..W, W+1..2W, ..., full
windows only), the same refined by coordinate ascent (each window's pick re-chosen given all the other
picks, until nothing changes), the stream oracle with ``--ref-window``; the offline greedy coverage
curve (frames needed for each ``--targets`` coverage); and, for every ``--bench`` folder of
``roigsf bench --setting stream``, each run's keyframes with their coverage next to the run's measured
recall, and for window policies the per-window coverage lost against a perfect window scorer. With
``--map NAME`` (oracle, ascent, cadence) that window-feasible set is also mapped (``run_offline`` with the
bench's defaults, each pick inserted at its window's trigger as a window policy would) and its measured
recall reported beside its coverage (about 2 min each; the coverage part alone takes under a minute).

    nice -n 19 .venv/bin/python scripts/coverage_bound.py --scene runs/office0_240_s5 --out runs/coverage_office0 \
        --bench runs/cov_bench/gaus-slam --bench runs/cov_bench/unseen --map ascent --map oracle --map cadence
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.fileio import atomic_path, write_json
from roigsf_ros.core.frame import Frame
from roigsf_ros.data.scene import camera_rays
from roigsf_ros.data.sources import open_frames
from roigsf_ros.evaluation.metrics import (
    as_legacy_mesh,
    gt_visible_mask,
    raycasting_scene,
    sample_surface,
    to_json_safe,
)
from roigsf_ros.experiments.offline import EvalConfig, run_offline
from roigsf_ros.mapping.mapper import MapperConfig
from roigsf_ros.policies.base import KeyframeMap, KeyframePolicy
from roigsf_ros.policies.stream import CandidateWindow

MAPPABLE = ("oracle", "ascent", "cadence")
"""Window-feasible sets ``--map`` can map: the stream oracle, its coordinate ascent, every window-th frame."""


@dataclass
class Scene:
    """Frames of a scene folder: ids (file numbers), z-depth [F, H, W], poses [F, 4, 4], intrinsics, GT mesh."""

    ids: list[int]
    depths: np.ndarray
    poses: np.ndarray
    intr: Intrinsics
    mesh_path: Path


def load_scene(path: Path) -> Scene:
    """Read every frame of a scene folder (``roigsf scene render`` output) with the library's loader."""
    source = open_frames(path)
    if source.gt_mesh_path is None:
        raise SystemExit(f"{path}: no mesh.ply (the ground truth) in the scene folder")
    ids, depths, poses = [], [], []
    for frame in source:
        ids.append(int(frame.index))
        depths.append(np.asarray(frame.depth_m, dtype=np.float32))
        poses.append(np.asarray(frame.T_wc, dtype=np.float64))
    return Scene(ids, np.stack(depths), np.stack(poses), source.intrinsics, Path(source.gt_mesh_path))


def gt_samples(scene: Scene, n_samples: int, seed: int, max_depth_m: float) -> tuple[np.ndarray, int]:
    """GT samples the recall counts (culled to what some pose observes, as ``mesh_metrics`` does); total drawn."""
    mesh = as_legacy_mesh(scene.mesh_path)
    pts = sample_surface(mesh, n_samples, seed)
    keep = gt_visible_mask(pts, raycasting_scene(mesh), scene.poses, scene.intr, max_depth_m=max_depth_m)
    return pts[keep], len(pts)


def observed_sets(scene: Scene, gt: np.ndarray, tau_m: float, lo_m: float, hi_m: float) -> np.ndarray:
    """Bool [F, N]: GT sample n lies within ``tau_m`` of a back-projected valid depth pixel of frame f."""
    obs = np.zeros((len(scene.ids), len(gt)), dtype=bool)
    for f, (depth, T) in enumerate(zip(scene.depths, scene.poses, strict=True)):
        valid = np.isfinite(depth) & (depth > lo_m) & (depth <= hi_m)
        if not valid.any():
            continue
        rays = camera_rays(T, scene.intr)[valid].astype(np.float64)
        pts = rays[:, :3] + depth[valid, None].astype(np.float64) * rays[:, 3:]
        lo, hi = pts.min(axis=0) - tau_m, pts.max(axis=0) + tau_m
        cand = np.flatnonzero(np.all((gt >= lo) & (gt <= hi), axis=1))
        if cand.size == 0:
            continue
        dist, _ = cKDTree(pts).query(gt[cand], k=1, distance_upper_bound=tau_m)
        obs[f, cand[dist < tau_m]] = True
    return obs


def coverage(obs: np.ndarray, picks: list[int]) -> float:
    """Fraction of GT samples observed by at least one of the frames ``picks`` (positions)."""
    if not picks:
        return 0.0
    return float(np.count_nonzero(obs[picks].any(axis=0))) / obs.shape[1]


def offline_greedy(obs: np.ndarray, k_max: int, first: int = 0) -> tuple[list[int], list[float]]:
    """Greedy max coverage: ``first`` then the frame adding the most new samples, up to ``k_max`` or no gain.

    Returns the picks in order and the coverage after each one.
    """
    n = obs.shape[1]
    picks = [first]
    rem = obs[:, ~obs[first]]  # frames x still-uncovered samples
    covered = n - rem.shape[1]
    curve = [covered / n]
    while len(picks) < k_max and rem.shape[1] > 0:
        gains = np.count_nonzero(rem, axis=1)
        best = int(np.argmax(gains))
        if gains[best] == 0:
            break
        picks.append(best)
        covered += int(gains[best])
        curve.append(covered / n)
        rem = rem[:, ~rem[best]]
    return picks, curve


def trigger_windows(n_frames: int, window: int, partial_tail: bool = False) -> list[list[int]]:
    """``StreamNBVPolicy``'s candidate windows (positions): 1..W, W+1..2W, ...; a short last one only if asked."""
    out = [list(range(s, min(s + window, n_frames))) for s in range(1, n_frames, window)]
    return out if partial_tail or not out or len(out[-1]) == window else out[:-1]


def stream_oracle(obs: np.ndarray, windows: list[list[int]], first: int = 0) -> list[int]:
    """A perfect window scorer: ``first``, then per window the frame adding the most given the earlier picks."""
    picks = [first]
    covered = obs[first].copy()
    for win in windows:
        gains = np.count_nonzero(obs[win] & ~covered, axis=1)
        best = win[int(np.argmax(gains))]
        picks.append(best)
        covered |= obs[best]
    return picks


def refine_windows(obs: np.ndarray, picks: list[int], windows: list[list[int]], max_rounds: int = 20) -> list[int]:
    """Coordinate ascent under the window constraint: re-choose each window's pick given all others (picks[0] kept)."""
    picks = list(picks)
    for _ in range(max_rounds):
        changed = False
        for w, win in enumerate(windows):
            others = picks[: w + 1] + picks[w + 2 :]
            covered = obs[others].any(axis=0)
            gains = np.count_nonzero(obs[win] & ~covered, axis=1)
            best = win[int(np.argmax(gains))]
            if gains[win.index(best)] > gains[win.index(picks[w + 1])]:
                picks[w + 1] = best
                changed = True
        if not changed:
            break
    return picks


def window_losses(obs: np.ndarray, picks: list[int], windows: list[list[int]]) -> list[dict[str, Any]] | None:
    """Per window, for a policy with one pick per window (picks[0] the first frame): coverage it lost.

    ``regret``: new coverage of the window's best frame minus that of the policy's pick, both given the
    policy's own earlier picks (what a perfect scorer would have gained at that trigger). ``swap_gain``:
    the policy's final coverage gain if only this window's pick were replaced by the best one given all
    its other picks. None if the picks do not fall one per window.
    """
    n = obs.shape[1]
    later = sorted(picks[1:])
    if len(later) != len(windows) or any(p not in win for p, win in zip(later, windows, strict=True)):
        return None
    seq = [picks[0], *later]
    out = []
    covered = obs[seq[0]].copy()
    total = coverage(obs, seq)
    for w, win in enumerate(windows):
        gains = np.count_nonzero(obs[win] & ~covered, axis=1)
        pick = seq[w + 1]
        best = win[int(np.argmax(gains))]
        others = obs[seq[: w + 1] + seq[w + 2 :]].any(axis=0)
        swap_gains = np.count_nonzero(obs[win] & ~others, axis=1)
        swap_best = pick if swap_gains[win.index(pick)] == swap_gains.max() else win[int(np.argmax(swap_gains))]
        out.append(
            {
                "window": w,
                "frames": [win[0], win[-1]],
                "pick": pick,
                "best": best,
                "regret": float(gains.max() - gains[win.index(pick)]) / n,
                "swap_best": swap_best,
                "swap_gain": float(np.count_nonzero(others | obs[swap_best])) / n - total,
            }
        )
        covered |= obs[pick]
    return out


class ScheduledPicks(KeyframePolicy):
    """Replays given keyframe ids: the first frame at once, the others at their window's trigger.

    The timing of ``StreamNBVPolicy`` (:class:`CandidateWindow`): a pick of frames 1..W is inserted
    when frame W arrives, so the mapper sees it when a window policy's pick would be inserted.
    """

    name = "scheduled-picks"

    def __init__(self, ids: list[int], window: int) -> None:
        self.ids = {int(i) for i in ids}
        self.window = int(window)
        self.candidates = CandidateWindow(self.window)

    def reset(self) -> None:
        """Forget the window."""
        self.candidates.reset()

    def observe(self, frame: Frame, keyframe_map: KeyframeMap) -> list[Frame]:
        """The first frame; at a trigger the window's frames among ``ids``."""
        due, first = self.candidates.push(frame)
        if first:
            return due
        hits = [f for f in due if int(f.index) in self.ids]
        for f in hits:
            self.candidates.remove(f)
        return hits

    def params(self) -> dict[str, Any]:
        """The ids and the window."""
        return {"ids": sorted(self.ids), "window": self.window}


def map_picks(scene_path: Path, ids: list[int], window: int, out_dir: Path) -> dict[str, Any]:
    """Map the scene with exactly these keyframes (bench defaults: MapperConfig, EvalConfig); its metrics."""
    source = open_frames(scene_path)
    policy = ScheduledPicks(ids, window)
    return run_offline(
        source, policy, MapperConfig(), out_dir, gt_mesh=source.gt_mesh_path, eval_config=EvalConfig(),
        progress=False, overwrite=True,
    )  # fmt: skip


def read_bench(path: Path) -> list[dict[str, Any]]:
    """The stream runs of a ``roigsf bench`` folder: label, seed, keyframe ids and measured mesh metrics."""
    results = json.loads((path / "results.json").read_text())
    runs = []
    for rec in results.get("runs", []):
        m = rec.get("metrics", {})
        ids = m.get("keyframe_ids")
        if ids is None:
            kf = path / str(rec.get("dir", "")) / "keyframes.json"
            ids = json.loads(kf.read_text())["keyframe_ids"] if kf.is_file() else None
        if ids is None:
            continue
        runs.append(
            {
                "bench": str(path),
                "label": rec.get("label", m.get("policy")),
                "seed": rec.get("seed"),
                "keyframe_ids": [int(i) for i in ids],
                "recall@5cm": m.get("recall@5cm"),
                "recall@1cm": m.get("recall@1cm"),
                "n_gt_samples": m.get("n_gt_samples"),
            }
        )
    return runs


def frames_to_reach(curve: list[float], target: float) -> int | None:
    """Smallest number of greedy frames whose coverage reaches ``target`` (None: never)."""
    hit = [i for i, c in enumerate(curve) if c >= target - 1e-12]
    return hit[0] + 1 if hit else None


def markdown(report: dict[str, Any]) -> str:
    """The report as a markdown table (rows) plus the greedy curve and the per-window losses."""
    lines = [
        f"# Observation coverage at {report['tau_m'] * 100:g} cm: {report['scene']}",
        "",
        f"GT samples (culled to observed, the recall denominator): {report['n_gt_culled']} of "
        f"{report['n_gt_drawn']}; frames: {report['n_frames']}",
        "",
        "| set | keyframes | coverage | measured R@5cm | coverage - R@5cm |",
        "|---|---:|---:|---:|---:|",
    ]
    for row in report["rows"]:
        r = row.get("recall@5cm")
        gap = f"{row['coverage'] - r:.4f}" if r is not None else ""
        rec = f"{r:.4f}" if r is not None else ""
        lines.append(f"| {row['name']} | {row['n']} | {row['coverage']:.4f} | {rec} | {gap} |")
    lines += ["", "Offline greedy (frame 0 first): frames needed for a coverage", ""]
    lines += [f"- {t}: {k}" for t, k in report["greedy_frames_to_reach"].items()]
    lines += ["", "Offline greedy coverage at k frames: " + ", ".join(
        f"k={k}: {c:.4f}" for k, c in report["greedy_coverage_at"].items()
    )]  # fmt: skip
    for name, losses in report["window_losses"].items():
        top = sorted(losses, key=lambda d: (-d["swap_gain"], -d["regret"]))[:10]
        lines += [
            "",
            f"Windows where {name} loses most coverage (swap gain: final coverage gained by re-choosing only this "
            "window's pick given all its other picks; regret: best new coverage in the window minus its pick's, "
            "given its own earlier picks)",
            "",
        ]
        lines += [
            "| window | frames | pick | best | regret | swap best | swap gain |",
            "|---:|---|---:|---:|---:|---:|---:|",
        ]
        for d in top:
            lines.append(
                f"| {d['window']} | {d['frames'][0]}-{d['frames'][1]} | {d['pick']} | {d['best']} | "
                f"{d['regret']:.4f} | {d['swap_best']} | {d['swap_gain']:.4f} |"
            )
    lines += ["", "Wall times (s): " + ", ".join(f"{k} {v:.1f}" for k, v in report["wall_s"].items()), ""]
    return "\n".join(lines)


def main() -> None:
    """Parse the arguments, measure, write ``coverage.json`` and ``coverage.md``, print the table."""
    ev, mc = EvalConfig(), MapperConfig()
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", type=Path, default=Path("runs/office0_240_s5"), help="scene folder")
    ap.add_argument("--out", type=Path, default=Path("runs/coverage_office0"), help="output folder")
    ap.add_argument("--bench", type=Path, action="append", default=[], help="roigsf bench --setting stream folder")
    ap.add_argument("--tau", type=float, default=0.05, help="distance threshold (m), as in R@5cm")
    ap.add_argument("--window", type=int, default=13, help="trigger window (frames) of the budget")
    ap.add_argument("--ref-window", type=int, default=9, help="a second window for reference")
    ap.add_argument("--targets", default="0.981,0.985,0.991", help="coverages for the greedy curve")
    ap.add_argument("--n-samples", type=int, default=ev.mesh_samples, help="GT samples drawn (bench default)")
    ap.add_argument("--seed", type=int, default=ev.seed, help="sampling seed (bench default)")
    ap.add_argument(
        "--map",
        action="append",
        default=[],
        choices=MAPPABLE,
        help="also map this window-feasible set (bench defaults, picks inserted at their triggers) and report its "
        "measured recall (about 2 min each; repeatable)",
    )
    args = ap.parse_args()

    wall: dict[str, float] = {}
    t0 = time.perf_counter()
    scene = load_scene(args.scene)
    n_frames = len(scene.ids)
    wall["load_frames"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    gt, n_drawn = gt_samples(scene, args.n_samples, args.seed, mc.max_depth_m)
    wall["gt_sampling_culling"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    lo = max(mc.min_depth_m, mc.near_m)
    obs = observed_sets(scene, gt, args.tau, lo, mc.max_depth_m)
    wall["observed_sets"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    pos = {fid: p for p, fid in enumerate(scene.ids)}
    win = trigger_windows(n_frames, args.window)
    win_tail = trigger_windows(n_frames, args.window, partial_tail=True)
    ref_win = trigger_windows(n_frames, args.ref_window)
    k = len(win) + 1
    targets = [float(t) for t in args.targets.split(",") if t.strip()]
    greedy, curve = offline_greedy(obs, n_frames)
    oracle = stream_oracle(obs, win)
    oracle_refined = refine_windows(obs, oracle, win)
    oracle_tail = stream_oracle(obs, win_tail)
    oracle_ref = stream_oracle(obs, ref_win)
    oracle_ref_refined = refine_windows(obs, oracle_ref, ref_win)
    pickable = list(range(win[-1][-1] + 1)) if win else [0]
    cadence = list(range(0, n_frames, args.window))
    fits = len(cadence) == k and all(c in w for c, w in zip(cadence[1:], win, strict=True))
    cadence_refined = refine_windows(obs, cadence, win) if fits else None
    wall["selection"] = time.perf_counter() - t0

    def row(name: str, picks: list[int], **extra: Any) -> dict[str, Any]:
        return {"name": name, "n": len(picks), "coverage": coverage(obs, picks), "picks": sorted(picks), **extra}

    rows = [
        row(f"all {n_frames} frames", list(range(n_frames))),
        row(f"all frames a W={args.window} window policy can pick (0..{pickable[-1]})", pickable),
        row(f"every {args.window}th frame (0, {args.window}, ...)", cadence),
        row(f"offline greedy, {k} frames (0 forced)", greedy[:k]),
        row(f"stream oracle, windows of {args.window} (full windows only)", oracle),
        row(f"stream oracle W={args.window} + coordinate ascent in windows", oracle_refined),
        *([row(f"every {args.window}th + coordinate ascent in windows", cadence_refined)] if cadence_refined else []),
        row(f"stream oracle W={args.window} incl. partial last window", oracle_tail),
        row(f"stream oracle, windows of {args.ref_window}", oracle_ref),
        row(f"stream oracle W={args.ref_window} + coordinate ascent in windows", oracle_ref_refined),
    ]
    named = {"oracle": oracle, "ascent": oracle_refined, "cadence": cadence}
    for name in args.map:
        t0 = time.perf_counter()
        ids = [scene.ids[p] for p in named[name]]
        m = map_picks(args.scene, ids, args.window, args.out / "maps" / name)
        wall[f"map_{name}"] = time.perf_counter() - t0
        if sorted(m["keyframe_ids"]) != sorted(ids):
            print(f"warning: mapping {name}: keyframes {m['keyframe_ids']} differ from the picks {ids}")
        picks = [pos[i] for i in m["keyframe_ids"] if i in pos]
        rows.append(row(f"mapped: {name} (this script)", picks, **{"recall@5cm": m["recall@5cm"],
                                                                   "recall@1cm": m["recall@1cm"]}))  # fmt: skip

    losses: dict[str, list[dict[str, Any]]] = {}
    bench_runs: list[dict[str, Any]] = []
    for b in args.bench:
        for run in read_bench(b):
            picks = [pos[i] for i in run["keyframe_ids"] if i in pos]
            name = f"{run['label']} seed {run['seed']} ({b.name})"
            rows.append(row(name, picks, **{"recall@5cm": run["recall@5cm"], "recall@1cm": run["recall@1cm"]}))
            if run["n_gt_samples"] is not None and run["n_gt_samples"] != len(gt):
                print(f"warning: {name}: bench counted {run['n_gt_samples']} GT samples, here {len(gt)}")
            wl = window_losses(obs, picks, win) if picks and picks[0] == 0 else None
            if wl is not None:
                losses[name] = wl
            bench_runs.append(run | {"name": name})

    report = {
        "scene": str(args.scene),
        "tau_m": args.tau,
        "n_frames": n_frames,
        "n_gt_drawn": n_drawn,
        "n_gt_culled": len(gt),
        "depth_range_m": [lo, mc.max_depth_m],
        "window": args.window,
        "ref_window": args.ref_window,
        "rows": rows,
        "greedy_order": greedy,
        "greedy_curve": curve,
        "greedy_frames_to_reach": {f"{t:g}": frames_to_reach(curve, t) for t in targets},
        "greedy_coverage_at": {str(n): curve[min(n, len(curve)) - 1] for n in (k, len(ref_win) + 1, 160)},
        "window_losses": losses,
        "bench_runs": bench_runs,
        "wall_s": wall,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "coverage.json", to_json_safe(report))
    text = markdown(report)
    with atomic_path(args.out / "coverage.md") as tmp:
        tmp.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
