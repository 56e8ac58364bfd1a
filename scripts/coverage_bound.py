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

Reported (table ``coverage.md`` and ``coverage.json``, written atomically under ``--out``): all frames; every
``window``-th frame; an offline greedy max-coverage pick of the same count (frame 0 forced); the stream oracle
(frame 0, then from each trigger window of ``window`` frames the frame adding the most new coverage given the
earlier picks, the windows of ``StreamNBVPolicy``: frames 1..W, W+1..2W, ..., full windows only); the same
deciding one window late (:func:`delayed_oracle`); the stream policies' own ``lookahead`` rule with the true
coverage (:func:`lookahead_oracle`, ``--lookahead`` frames); the stream oracle refined by coordinate ascent (each
window's pick re-chosen given all the other picks, until nothing changes: hindsight, not causal); the stream
oracle with ``--ref-window``; two causal adaptive oracles, not one pick per window: the threshold oracle
(:func:`threshold_picks`: frame 0, then every frame whose new coverage reaches a threshold, a keyframe as it
arrives; the smallest threshold for each ``--threshold-budgets`` count found by bisection) and the
budget-trigger oracle (:func:`budget_oracle`: ``StreamNBVPolicy``'s ``trigger="budget"`` with the GT new
coverage as score and gain, one per ``--budget-ratios`` value); the offline greedy coverage curve (frames needed
for each ``--targets`` coverage); and, for every ``--bench`` folder of ``roigsf bench --setting stream``, each
run's keyframes with their coverage next to the run's measured recall, F@5cm and PSNR, and for window policies
the per-window coverage lost against a perfect window scorer. With ``--map NAME`` (oracle, delayed, lookahead,
ascent, cadence, threshold, budget) that set is also mapped (``run_offline`` with the bench's defaults or
``--set``, each pick inserted when its policy would insert it: at its window's trigger (a window late for
``delayed``, as many as the lookahead spans for ``lookahead``), on arrival for the threshold oracle at the
``--window`` budget, at its trigger for every budget oracle) and its measured recall, F@5cm and PSNR reported
beside its coverage (under a minute each here; the coverage part alone takes about 30 s).

    nice -n 19 .venv/bin/python scripts/coverage_bound.py --scene runs/office0_240_s5 --out runs/coverage_office0 \
        --bench runs/cov_bench/gaus-slam --bench runs/cov_bench/unseen --bench runs/cov_bench/gaus-slam_tau0.1 \
        --bench runs/cov_bench/gaus-slam_tau0.14 --bench runs/cov_bench/gaus-slam_tau0.15 --map ascent \
        --map oracle --map delayed --map cadence --map threshold --map budget
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from roigsf_ros.cli.bench import parse_overrides
from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import atomic_path, read_json, write_json
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

MAPPABLE = ("oracle", "delayed", "lookahead", "ascent", "cadence", "threshold", "budget")
"""Sets ``--map`` can map: the window-feasible stream oracle, one-window-late oracle, lookahead-rule oracle,
coordinate ascent and every window-th frame (inserted at their triggers), and the causal threshold oracle (at the
threshold for the window budget; each pick inserted as it arrives) and budget-trigger oracle (each pick inserted at
its trigger)."""


METRICS = ("recall@5cm", "recall@1cm", "fscore@5cm", "psnr")
"""Measured metrics a row carries when it was mapped (here or by a bench)."""


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


def depth_points(
    depth_m: np.ndarray, T_wc: np.ndarray, intr: Intrinsics, lo_m: float, hi_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """World points [N, 3] (float64) of the pixels of a z-depth map [H, W] in (lo_m, hi_m], and that mask [H, W]."""
    valid = np.isfinite(depth_m) & (depth_m > lo_m) & (depth_m <= hi_m)
    rays = camera_rays(T_wc, intr)[valid].astype(np.float64)
    return rays[:, :3] + depth_m[valid, None].astype(np.float64) * rays[:, 3:], valid


def observed_sets(scene: Scene, gt: np.ndarray, tau_m: float, lo_m: float, hi_m: float) -> np.ndarray:
    """Bool [F, N]: GT sample n lies within ``tau_m`` of a back-projected valid depth pixel of frame f."""
    obs = np.zeros((len(scene.ids), len(gt)), dtype=bool)
    for f, (depth, T) in enumerate(zip(scene.depths, scene.poses, strict=True)):
        pts, valid = depth_points(depth, T, scene.intr, lo_m, hi_m)
        if not valid.any():
            continue
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


def offline_greedy(obs: np.ndarray, k_max: int, first: int | Sequence[int] = 0) -> tuple[list[int], list[float]]:
    """Greedy max coverage: ``first`` (a frame, or frames forced in order) then the frame adding the most new
    samples, up to ``k_max`` or no gain.

    Returns the picks in order and the coverage after each one (one value for all forced frames together).
    """
    n = obs.shape[1]
    picks = [int(first)] if isinstance(first, int | np.integer) else list(dict.fromkeys(int(f) for f in first))
    rem = obs[:, ~obs[picks].any(axis=0)]  # frames x still-uncovered samples
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


def delayed_oracle(obs: np.ndarray, windows: list[list[int]], first: int = 0) -> list[int]:
    """A window scorer deciding one window late: window t's pick is chosen once window t+1 has been seen.

    Its score is the new coverage (given the earlier picks) that no frame of window t+1 sees, ties broken by
    the plain new coverage: surface the next window shows again is left to it. Causal with a delay of one
    window (a candidate buffer of two windows, one keyframe per window); the last window decides alone.
    """
    picks = [first]
    covered = obs[first].copy()
    for t, win in enumerate(windows):
        new = obs[win] & ~covered
        plain = np.count_nonzero(new, axis=1).astype(np.float64)
        if t + 1 < len(windows):
            later = obs[windows[t + 1]].any(axis=0)
            score = np.count_nonzero(new & ~later, axis=1) + plain / (plain.max() + 1.0)
        else:
            score = plain
        best = win[int(np.argmax(score))]
        picks.append(best)
        covered |= obs[best]
    return picks


def lookahead_oracle(obs: np.ndarray, windows: list[list[int]], lookahead: int, first: int = 0) -> list[int]:
    """The stream policies' ``lookahead`` rule with the true coverage: window t's pick is the frame f of the window
    with the most new coverage plus the most that one of the ``lookahead`` frames after the window would still add
    after f (both given the earlier picks), decided once those frames are in (``lookahead_new_voxels``' rule, with
    ground truth instead of the frames' voxels). Ties to the earliest frame.
    """
    n = obs.shape[0]
    picks = [first]
    covered = obs[first].copy()
    for win in windows:
        later = obs[win[-1] + 1 : min(n, win[-1] + 1 + lookahead)]
        best, best_score = win[0], -1
        for f in win:
            after = covered | obs[f]
            score = np.count_nonzero(obs[f] & ~covered)
            if len(later):
                score += int(np.count_nonzero(later & ~after, axis=1).max())
            if score > best_score:
                best, best_score = f, score
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


def threshold_picks(obs: np.ndarray, min_new: int, first: int = 0) -> list[int]:
    """Causal threshold oracle: ``first``, then each later frame, as it arrives, if it observes at least ``min_new``
    GT samples that no earlier pick observes (its new coverage >= ``min_new`` / N).
    """
    picks = [first]
    covered = obs[first].copy()
    for f in range(first + 1, obs.shape[0]):
        if np.count_nonzero(obs[f] & ~covered) >= min_new:
            picks.append(f)
            covered |= obs[f]
    return picks


def threshold_for(obs: np.ndarray, k_max: int) -> tuple[int, list[int]]:
    """Bisection: the smallest ``min_new`` (a count of GT samples) whose :func:`threshold_picks` has <= ``k_max``
    frames, and those picks. Assumes the count falls as the threshold rises (checked: a warning if not).
    """
    lo, hi = 1, obs.shape[1] + 1  # n(hi) = 1 <= k_max; find the smallest c with n(c) <= k_max
    if len(threshold_picks(obs, lo)) <= k_max:
        return lo, threshold_picks(obs, lo)
    while hi - lo > 1:  # invariant: n(lo) > k_max >= n(hi)
        mid = (lo + hi) // 2
        if len(threshold_picks(obs, mid)) <= k_max:
            hi = mid
        else:
            lo = mid
    picks = threshold_picks(obs, hi)
    above = [c for c in range(hi + 1, min(hi + 200, obs.shape[1] + 1)) if len(threshold_picks(obs, c)) > k_max]
    if above:
        print(f"warning: threshold for <= {k_max} keyframes is not monotone: {above[0]} gives more again")
    return hi, picks


def budget_oracle(
    obs: np.ndarray,
    window: int,
    trigger_every: int,
    budget_every: float,
    burst: float = 3.0,
    ratio: float = 1.0,
    history: int = 8,
    first: int = 0,
) -> tuple[list[int], dict[int, int], float]:
    """``StreamNBVPolicy``'s ``trigger="budget"`` with the GT new coverage as both score and gain.

    Replays ``CandidateWindow`` (the last ``window`` frames not chosen, a trigger every ``trigger_every`` frames
    after the first) and ``observe`` / ``_accept``: each frame after the first earns 1 / ``budget_every`` of a
    keyframe (at most ``burst`` banked); a trigger with less than one banked is skipped unscored; otherwise the
    window's frame with the most new coverage (given the keyframes inserted so far; ties: the oldest) is
    inserted if its gain reaches ``ratio`` x the median of the last ``history`` triggers' gains (the first two
    always), or if the next trigger would overflow the bank; every scored trigger's gain enters the history.
    Returns the picks in insertion order (``first`` first), per pick the position at which it is inserted, and the
    keyframes still banked at the end.
    """
    picks, when = [first], {first: first}
    covered = obs[first].copy()
    buffer: deque[int] = deque(maxlen=window)
    gains: deque[float] = deque(maxlen=history)
    tokens, since = 0.0, 0
    for f in range(first + 1, obs.shape[0]):
        buffer.append(f)
        since += 1
        tokens = min(tokens + 1.0 / budget_every, burst)
        if since < trigger_every:
            continue
        since = 0
        if tokens < 1.0 - 1e-9:
            continue
        cand = list(buffer)
        new = np.count_nonzero(obs[cand] & ~covered, axis=1)
        best = int(np.argmax(new))
        g = float(new[best]) / obs.shape[1]
        ok = len(gains) < 2 or g >= ratio * float(np.median(gains))
        ok = ok or tokens + trigger_every / budget_every > burst + 1e-9
        gains.append(g)
        if not ok:
            continue
        tokens -= 1.0
        buffer.remove(cand[best])
        picks.append(cand[best])
        when[cand[best]] = f
        covered |= obs[cand[best]]
    return picks, when, tokens


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
    """Replays given keyframe ids: the first frame at once, the others when a window policy would insert them.

    The timing of ``StreamNBVPolicy`` (:class:`CandidateWindow`): a pick of frames 1..W is inserted when
    frame W arrives (the window's trigger); with ``delay`` d, at the trigger d windows later, except that
    the pick of window ``last_window`` (no later trigger comes) is inserted at its own trigger.
    """

    name = "scheduled-picks"

    def __init__(self, ids: list[int], window: int, delay: int = 0, last_window: int | None = None) -> None:
        self.ids = {int(i) for i in ids}
        self.window, self.delay, self.last_window = int(window), int(delay), last_window
        self.reset()

    def reset(self) -> None:
        """Forget the frames seen."""
        self._seen = 0
        self._held: list[tuple[int, Frame]] = []  # (window of the frame, frame)

    def observe(self, frame: Frame, keyframe_map: KeyframeMap) -> list[Frame]:
        """The first frame; at a trigger the held picks whose insertion is due."""
        self._seen += 1
        if self._seen == 1:
            return [frame]
        w = (self._seen - 2) // self.window  # arrival 2..W+1 is window 0
        if int(frame.index) in self.ids:
            self._held.append((w, frame))
        if (self._seen - 1) % self.window:
            return []
        due = [f for fw, f in self._held if fw <= w - self.delay or fw == self.last_window]
        self._held = [(fw, f) for fw, f in self._held if not (fw <= w - self.delay or fw == self.last_window)]
        return due

    def params(self) -> dict[str, Any]:
        """The ids, the window and the delay."""
        return {"ids": sorted(self.ids), "window": self.window, "delay": self.delay}


class TimedPicks(KeyframePolicy):
    """Replays given keyframe ids, each inserted when a given frame arrives (itself or a later one); the first frame
    at once.
    """

    name = "timed-picks"

    def __init__(self, insert_at: dict[int, int]) -> None:
        self.insert_at = {int(k): int(v) for k, v in insert_at.items()}  # pick id -> id of the arrival inserting it
        self.reset()

    def reset(self) -> None:
        """Forget the frames seen."""
        self._seen = 0
        self._held: list[Frame] = []

    def observe(self, frame: Frame, keyframe_map: KeyframeMap) -> list[Frame]:
        """The first frame; else the held picks whose insertion frame this is."""
        self._seen += 1
        if self._seen == 1:
            return [frame]
        if int(frame.index) in self.insert_at:
            self._held.append(frame)
        due = [f for f in self._held if self.insert_at[int(f.index)] <= int(frame.index)]
        self._held = [f for f in self._held if self.insert_at[int(f.index)] > int(frame.index)]
        return due

    def params(self) -> dict[str, Any]:
        """The ids and when each is inserted."""
        return {"insert_at": {str(k): v for k, v in sorted(self.insert_at.items())}}


def map_picks(
    scene_path: Path, policy: KeyframePolicy, out_dir: Path, mapper: MapperConfig | None = None
) -> dict[str, Any]:
    """Map the scene with exactly these keyframes (bench defaults unless ``mapper`` is given); its metrics."""
    source = open_frames(scene_path)
    return run_offline(
        source, policy, mapper or MapperConfig(), out_dir, gt_mesh=source.gt_mesh_path, eval_config=EvalConfig(),
        progress=False, overwrite=True,
    )  # fmt: skip


def read_bench(path: Path) -> list[dict[str, Any]]:
    """The stream runs of a ``roigsf bench`` folder: label, seed, keyframe ids and measured mesh metrics."""
    results = read_json(path / "results.json", "not found (give a `roigsf bench --setting stream` output folder)")
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
                "fscore@5cm": m.get("fscore@5cm"),
                "psnr": m.get("psnr"),
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
        "| set | keyframes | coverage | measured R@5cm | coverage - R@5cm | F@5cm | PSNR (dB) |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    if over := report.get("mapper_overrides"):
        note = ", ".join(f"{k}={v}" for k, v in over.items())
        lines[4:4] = [f"Sets marked 'mapped' were mapped with these MapperConfig overrides: {note}", ""]

    def fmt(v: float | None, spec: str) -> str:
        return "" if v is None else format(v, spec)

    for row in report["rows"]:
        r = row.get("recall@5cm")
        gap = fmt(row["coverage"] - r if r is not None else None, ".4f")
        lines.append(
            f"| {row['name']} | {row['n']} | {row['coverage']:.4f} | {fmt(r, '.4f')} | {gap} | "
            f"{fmt(row.get('fscore@5cm'), '.4f')} | {fmt(row.get('psnr'), '.2f')} |"
        )
    lines += ["", "Causal threshold oracle: smallest new-coverage threshold (bisection) for a keyframe budget", ""]
    lines += ["| budget | threshold (fraction of GT samples) | samples | keyframes | coverage |"]
    lines += ["|---:|---:|---:|---:|---:|"]
    for t in report["threshold"]:
        lines.append(f"| {t['k_max']} | {t['tau']:.6f} | {t['min_new']} | {t['n']} | {t['coverage']:.4f} |")
    for b in report["budget"]:
        lines += [
            "",
            f"Budget-trigger oracle ({', '.join(f'{k}={v}' for k, v in b['params'].items())}): {b['n']} keyframes, "
            f"{b['banked_at_end']:.2f} banked at the end, coverage {b['coverage']:.4f}; picks (inserted at): "
            + ", ".join(f"{i}@{b['insert_at'][str(i)]}" for i in b["picks"]),
        ]
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


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments, measure, write ``coverage.json`` and ``coverage.md``, print the table; 2 on bad input."""
    ev, mc = EvalConfig(), MapperConfig()
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", type=Path, default=Path("runs/office0_240_s5"), help="scene folder")
    ap.add_argument("--out", type=Path, default=Path("runs/coverage_office0"), help="output folder")
    ap.add_argument("--bench", type=Path, action="append", default=[], help="roigsf bench --setting stream folder")
    ap.add_argument("--tau", type=float, default=0.05, help="distance threshold (m), as in R@5cm")
    ap.add_argument("--window", type=int, default=13, help="trigger window (frames) of the budget")
    ap.add_argument("--ref-window", type=int, default=9, help="a second window for reference")
    ap.add_argument(
        "--lookahead", type=int, default=None, help="frames the lookahead oracle looks past a window (default: window)"
    )
    ap.add_argument("--targets", default="0.981,0.985,0.991", help="coverages for the greedy curve")
    ap.add_argument(
        "--threshold-budgets",
        default="",
        help="keyframe budgets for the causal threshold oracle (default: those of --window, --ref-window and 160)",
    )
    ap.add_argument("--budget-trigger-every", type=int, default=4, help="budget oracle: frames between triggers")
    ap.add_argument("--budget-burst", type=float, default=3.0, help="budget oracle: keyframes banked at most")
    ap.add_argument(
        "--budget-ratios",
        default="1,0.5",
        help="budget oracle: adaptive_ratio values, one oracle each (the first is --map budget's 'budget', the others "
        "'budget_r<ratio>'; 1 is the policy's default, 0.5 was chosen afterwards on office0 itself)",
    )
    ap.add_argument("--n-samples", type=int, default=ev.mesh_samples, help="GT samples drawn (bench default)")
    ap.add_argument("--seed", type=int, default=ev.seed, help="sampling seed (bench default)")
    ap.add_argument(
        "--map",
        action="append",
        default=[],
        choices=MAPPABLE,
        help="also map this set (bench defaults, picks inserted when the policy would insert them) and report its "
        "measured recall, F@5cm and PSNR (under a minute each; repeatable)",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a MapperConfig field for the --map runs, as `roigsf bench --set` (e.g. init_max_stretch=4 to map as "
        "the stretching benches did; repeatable)",
    )
    args = ap.parse_args(argv)
    mdefaults = {f.name: getattr(mc, f.name) for f in fields(MapperConfig)}
    try:
        overrides = parse_overrides(args.set, mdefaults, "--set", skip=("seed",))
        mapper = replace(mc, **overrides)
        if args.lookahead is not None and args.lookahead < 0:
            raise InputError("--lookahead", f"must be 0 or more frames, got {args.lookahead}")
    except InputError as e:
        print(f"coverage_bound: {e}", file=sys.stderr)
        return 2

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
    oracle_delayed = delayed_oracle(obs, win)
    lookahead = args.window if args.lookahead is None else args.lookahead
    oracle_lookahead = lookahead_oracle(obs, win, lookahead)
    oracle_tail = stream_oracle(obs, win_tail)
    oracle_ref = stream_oracle(obs, ref_win)
    oracle_ref_refined = refine_windows(obs, oracle_ref, ref_win)
    pickable = list(range(win[-1][-1] + 1)) if win else [0]
    cadence = list(range(0, n_frames, args.window))
    fits = len(cadence) == k and all(c in w for c, w in zip(cadence[1:], win, strict=True))
    cadence_refined = refine_windows(obs, cadence, win) if fits else None
    wall["selection"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    budgets = [int(b) for b in args.threshold_budgets.split(",") if b.strip()] or [k, len(ref_win) + 1, 160]
    thresholds = []
    for kb in budgets:
        min_new, picks = threshold_for(obs, kb)
        thresholds.append({"k_max": kb, "min_new": min_new, "tau": min_new / obs.shape[1], "n": len(picks),
                           "coverage": coverage(obs, picks), "picks": picks})  # fmt: skip
    threshold = thresholds[budgets.index(k)]["picks"] if k in budgets else thresholds[0]["picks"]
    budgets_b = []
    for i, ratio in enumerate(float(r) for r in args.budget_ratios.split(",") if r.strip()):
        params = {"window": args.window, "trigger_every": args.budget_trigger_every, "budget_every": args.window,
                  "budget_burst": args.budget_burst, "adaptive_ratio": ratio, "adaptive_history": 8}  # fmt: skip
        picks, at, banked = budget_oracle(obs, args.window, args.budget_trigger_every, float(args.window),
                                          args.budget_burst, ratio)  # fmt: skip
        budgets_b.append({"name": "budget" if i == 0 else f"budget_r{ratio:g}", "params": params, "picks": picks,
                          "n": len(picks), "coverage": coverage(obs, picks), "banked_at_end": banked,
                          "insert_at": {str(q): at[q] for q in picks}})  # fmt: skip
    wall["threshold_budget"] = time.perf_counter() - t0

    def row(name: str, picks: list[int], **extra: Any) -> dict[str, Any]:
        return {"name": name, "n": len(picks), "coverage": coverage(obs, picks), "picks": sorted(picks), **extra}

    budget_name = f"budget-trigger oracle, GT gain (W={args.window}, trigger every {args.budget_trigger_every}"
    rows = [
        row(f"all {n_frames} frames", list(range(n_frames))),
        row(f"all frames a W={args.window} window policy can pick (0..{pickable[-1]})", pickable),
        row(f"every {args.window}th frame (0, {args.window}, ...)", cadence),
        row(f"offline greedy, {k} frames (0 forced)", greedy[:k]),
        row(f"stream oracle, windows of {args.window} (full windows only)", oracle),
        row(f"stream oracle W={args.window} deciding one window late", oracle_delayed),
        row(f"stream oracle W={args.window}, the policies' lookahead rule (L={lookahead})", oracle_lookahead),
        row(f"stream oracle W={args.window} + coordinate ascent in windows", oracle_refined),
        *([row(f"every {args.window}th + coordinate ascent in windows", cadence_refined)] if cadence_refined else []),
        row(f"stream oracle W={args.window} incl. partial last window", oracle_tail),
        row(f"stream oracle, windows of {args.ref_window}", oracle_ref),
        row(f"stream oracle W={args.ref_window} + coordinate ascent in windows", oracle_ref_refined),
        *[
            row(f"causal threshold oracle, new coverage >= {t['tau']:.5f} (budget {t['k_max']})", t["picks"])
            for t in thresholds
        ],
        *[row(f"{budget_name}, adaptive_ratio {b['params']['adaptive_ratio']:g})", b["picks"]) for b in budgets_b],
    ]
    named = {"oracle": oracle, "delayed": oracle_delayed, "lookahead": oracle_lookahead, "ascent": oracle_refined,
             "cadence": cadence, "threshold": threshold} | {b["name"]: b["picks"] for b in budgets_b}  # fmt: skip
    timed = {b["name"]: {scene.ids[q]: scene.ids[at] for q, at in zip(b["picks"], b["insert_at"].values(), strict=True)}
             for b in budgets_b}  # fmt: skip
    to_map = [m for name in args.map for m in ([b["name"] for b in budgets_b] if name == "budget" else [name])]
    for name in dict.fromkeys(to_map):
        t0 = time.perf_counter()
        ids = [scene.ids[p] for p in named[name]]
        policy: KeyframePolicy
        if name == "threshold":
            policy = TimedPicks({i: i for i in ids})
        elif name in timed:
            policy = TimedPicks(timed[name])
        else:
            delay = {"delayed": 1, "lookahead": -(-lookahead // args.window)}.get(name, 0)  # windows, rounded up
            policy = ScheduledPicks(ids, args.window, delay, len(win) - 1)
        m = map_picks(args.scene, policy, args.out / "maps" / name, mapper)
        wall[f"map_{name}"] = time.perf_counter() - t0
        if sorted(m["keyframe_ids"]) != sorted(ids):
            print(f"warning: mapping {name}: keyframes {m['keyframe_ids']} differ from the picks {ids}")
        picks = [pos[i] for i in m["keyframe_ids"] if i in pos]
        rows.append(row(f"mapped: {name} (this script)", picks, **{k_: m.get(k_) for k_ in METRICS}))

    losses: dict[str, list[dict[str, Any]]] = {}
    bench_runs: list[dict[str, Any]] = []
    for b in args.bench:
        for run in read_bench(b):
            picks = [pos[i] for i in run["keyframe_ids"] if i in pos]
            name = f"{run['label']} seed {run['seed']} ({b.name})"
            rows.append(row(name, picks, **{k_: run.get(k_) for k_ in METRICS}))
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
        "mapper_overrides": overrides,
        "rows": rows,
        "greedy_order": greedy,
        "greedy_curve": curve,
        "greedy_frames_to_reach": {f"{t:g}": frames_to_reach(curve, t) for t in targets},
        "greedy_coverage_at": {str(n): curve[min(n, len(curve)) - 1] for n in (k, len(ref_win) + 1, 160)},
        "threshold": thresholds,
        "budget": budgets_b,
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
