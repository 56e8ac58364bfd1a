#!/usr/bin/env python3
"""Does the unseen term follow the surface a candidate would add? Measured at a pool bench's first pick (issue 10).

At the first pick every policy of a pool bench stands on the same map (the same initial views and training, same seed).
This maps a bench's scene up to that pick seven times with the `unconfirmed` variant
(``roi-gsurfisher:unseen_weight=1:unseen_backfaces=unconfirmed``), counting U as the pixel fraction, as the area
(``unseen_measure=area``), as the area of the alpha holes alone (``unseen_backfaces=none``, so the difference is the
back faces' area), and, in place of the map's render, from the space the keyframes carved (``unseen_source=carved``,
which has no back-face test) as the pixel fraction and as the area (5 cm cells), and as the pixel fraction and the
frontier cells (``unseen_measure=cells``) at 2.5 cm, and compares each candidate's U with its true gain: the fraction of
the GT samples (those the bench's recall counts) its true depth observes within ``--tau`` that no initial view observes
(``pool_bound.observed``). Reported per seed: Spearman's rho of U and of the fused score with the gain over the
candidates that are not flagged, the true gain of each count's pick (its argmax of U and of the fused score) against the
best gain, and the share of the area count that comes from back faces, over all candidates and at the argmax of U.
Writes ``unseen_vs_gain.json`` and ``.md`` under ``--out`` (atomically) and prints the table.

    .venv/bin/python scripts/unseen_vs_gain.py runs/bench_pool_clutter_240_area --out runs/s28/gain_clutter --seeds 0
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import spearmanr

from roigsf_ros.core.errors import InputError
from roigsf_ros.experiments.bench import read_results
from roigsf_ros.experiments.pool import make_pool_policy, run_pool

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/ is no package
import pool_bound as pb

VARIANT = {"unseen_weight": 1.0, "unseen_backfaces": "unconfirmed"}
COUNTS = {
    "pixels": VARIANT | {"unseen_measure": "pixels"},
    "area": VARIANT | {"unseen_measure": "area"},
    "area_holes": VARIANT | {"unseen_measure": "area", "unseen_backfaces": "none"},
    "carved": VARIANT | {"unseen_measure": "pixels", "unseen_source": "carved", "unseen_voxel_m": 0.05},
    "carved_area": VARIANT | {"unseen_measure": "area", "unseen_source": "carved", "unseen_voxel_m": 0.05},
    "carved25": VARIANT | {"unseen_measure": "pixels", "unseen_source": "carved", "unseen_voxel_m": 0.025},
    "carved25_cells": VARIANT | {"unseen_measure": "cells", "unseen_source": "carved", "unseen_voxel_m": 0.025},
}
"""The ways U is counted here: policy parameters of ``roi-gsurfisher``. ``carved`` and ``carved_area`` keep the 5 cm
cells the twenty-ninth session chose the carved rule with (a table of docs/measured-figures.md); ``carved25`` and
``carved25_cells`` (the pixel fraction and the frontier cells, thirty-fifth session) the 2.5 cm default chosen after
it."""
RHO_COUNTS = ("pixels", "area", "carved", "carved_area", "carved25", "carved25_cells")
"""The counts whose rho with the gain is reported (``area_holes`` only gives the back faces' share)."""


def rho(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rho of two arrays; nan when either is constant."""
    return float(spearmanr(a, b).statistic) if np.ptp(a) > 0 and np.ptp(b) > 0 else float("nan")


def first_pick(setup: Any, seed: int, params: dict[str, Any]) -> tuple[list[int], np.ndarray, np.ndarray, np.ndarray]:
    """Map up to the first pick under ``roi-gsurfisher`` with ``params``: the candidates' scene positions, U, the
    fused score and the flags of that pick's scoring.
    """
    cfg = replace(setup.pcfg, policy="roi-gsurfisher", policy_params=params, seed=seed,
                  n_views=len(setup.split.initial) + 1)  # fmt: skip
    policy = make_pool_policy(cfg)
    seen: list[list[int]] = []
    run_pool(setup.src, cfg, setup.mcfg, None, policy=policy,
             on_select=lambda _m, _p, positions, _poses: seen.append([int(p) for p in positions]))  # fmt: skip
    res = policy.last_result
    if res is None or res.unseen is None or len(seen) != 1:
        raise RuntimeError(f"seed {seed}: expected one scored pick with the unseen term, got {len(seen)}")
    return seen[0], res.unseen, res.fused, res.flagged


def measure(bench: Path, seeds: list[int] | None, tau_m: float) -> dict[str, Any]:
    """Per seed: rho of each count (and its fused score) with the true gain, the gains of the picks, back shares."""
    results = read_results(bench, "pool", ("scene", "gt_mesh", "runs", "pool_config", "mapper_config"),
                           ("label", "seed", "chosen_positions", "metrics"))  # fmt: skip
    setup = pb.load_pool(results, bench)
    run_seeds = sorted({int(r["seed"]) for r in results["runs"]}) if seeds is None else seeds
    out: dict[str, Any] = {"bench": str(bench), "scene": results["scene"], "tau_m": tau_m, "seeds": []}
    for seed in run_seeds:
        _gt, obs, _n = pb.observed(setup, seed, tau_m)
        initial = obs[[setup.row_of[p] for p in setup.split.initial]].any(axis=0)
        scored = {name: first_pick(setup, seed, params) for name, params in COUNTS.items()}
        positions = scored["pixels"][0]
        if any(s[0] != positions for s in scored.values()):
            raise RuntimeError(f"seed {seed}: the runs scored different candidates")
        gain = np.array([np.count_nonzero(obs[setup.row_of[p]] & ~initial) for p in positions]) / obs.shape[1]
        row: dict[str, Any] = {"seed": seed, "candidates": len(positions), "best_gain": float(gain.max())}
        for name in RHO_COUNTS:
            _pos, u, fused, flagged = scored[name]
            ok = ~flagged
            row[name] = {
                "rho_u": rho(u[ok], gain[ok]),
                "rho_fused": rho(fused[ok], gain[ok]),
                "gain_of_max_u": float(gain[int(np.argmax(np.where(ok, u, -np.inf)))]),
                "gain_of_pick": float(gain[int(np.argmax(np.where(ok, fused, -np.inf)))]),
            }
        area, holes = scored["area"][1], scored["area_holes"][1]
        back = np.clip(area - holes, 0.0, None)
        top = int(np.argmax(np.where(~scored["area"][3], area, -np.inf)))
        row["back_share_all"] = float(back.sum() / max(area.sum(), 1e-12))
        row["back_share_at_max_area"] = float(back[top] / max(area[top], 1e-12))
        out["seeds"].append(row)
    return out


def markdown(report: dict[str, Any]) -> str:
    """One row per seed and count."""
    lines = [
        f"# Unseen term against the true gain at the first pick: {report['bench']}",
        "",
        f"gain = fraction of the GT samples a candidate observes within {report['tau_m'] * 100:g} cm that no initial "
        "view observes",
        "",
        "| seed | count | rho(U, gain) | rho(fused, gain) | gain of argmax U | gain of the pick | best gain | "
        "back-face share of the area (all / at argmax) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in report["seeds"]:
        for name in RHO_COUNTS:
            r = s[name]
            share = f"{s['back_share_all']:.2f} / {s['back_share_at_max_area']:.2f}" if name == "area" else "-"
            gains = f"{r['gain_of_max_u']:.4f} | {r['gain_of_pick']:.4f} | {s['best_gain']:.4f}"
            lines.append(f"| {s['seed']} | {name} | {r['rho_u']:+.2f} | {r['rho_fused']:+.2f} | {gains} | {share} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments, measure, write ``unseen_vs_gain.json`` and ``.md``, print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bench", type=Path, help="a roigsf bench --setting pool folder")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--seeds", type=int, nargs="*", help="seeds (default: the bench's)")
    ap.add_argument("--tau", type=float, default=0.05, help="distance threshold (m), as in R@5cm")
    args = ap.parse_args(argv)
    try:
        report = measure(args.bench, args.seeds, args.tau)
    except InputError as e:
        print(f"unseen_vs_gain: {e}", file=sys.stderr)
        return 2
    pb.write_report(args.out, "unseen_vs_gain", report, markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
