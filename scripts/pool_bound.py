#!/usr/bin/env python3
"""How much of the true surface any choice of views from a pool bench's candidates can see (issue 10).

The pool setting's mesh is fused from the map's depth at the chosen views only, so a run's R@5cm follows how much
of the ground-truth surface those views observe (not a strict bound: the fused mesh reaches a little past the
observed pixels, so a recall can exceed its coverage by a little). For a ``roigsf bench --setting pool`` folder this
measures, per seed, on the GT samples the bench's recall counts (same seed, count and culling):

- the coverage of **all pool views** (every candidate, the initial views included): no choice of ``n_views`` of
  them observes more, and mapped (``--map``) the practical ceiling of a selection rule's recall;
- the coverage of a **greedy max-coverage pick** of ``n_views`` (the bench's initial views forced, then each
  time the candidate observing the most samples not yet observed): the oracle a perfect scorer would
  approach, given the true depth of every candidate;
- the coverage of that pick **refined by swaps** (:func:`swap_refine`: each chosen view after the initial ones
  re-chosen given all the others until none changes), since greedy max coverage is not the best pick of
  ``n_views``: hindsight, which no sequential scorer has;
- the coverage of each bench run's chosen views, beside its measured R@5cm.

A sample is observed by a view when it lies within ``--tau`` of a back-projected valid pixel of the view's input
depth (``coverage_bound.observed_sets``). With ``--map`` the greedy pick, its refinement and all pool views (or
those of ``--map-rows``) are also mapped by ``run_pool`` under the bench's own pool and mapper configuration and
seeds (the two picks replayed in their order, one view per training phase; all pool views as that order continued
over the remaining candidates, so their run trains ``iters_per_view`` more steps per added view), and their measured
R@5cm, F@5cm and test PSNR are reported. Writes ``bound.json`` and ``bound.md`` under ``--out`` (atomically) and
prints the table.

    .venv/bin/python scripts/pool_bound.py runs/bench_pool_synth_240_unconfirmed runs/bench_pool_synth_240_base25 \
        --out runs/s27/bound_synth_240 --map
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import atomic_path, write_json
from roigsf_ros.data.sources import FrameSequence, open_frames
from roigsf_ros.evaluation.metrics import to_json_safe
from roigsf_ros.experiments.bench import read_results
from roigsf_ros.experiments.pool import PoolConfig, PoolSplit, ReplayPicks, run_pool, split_pool
from roigsf_ros.mapping.mapper import MapperConfig


def _sibling(name: str) -> ModuleType:
    """``scripts/<name>.py`` (scripts/ is no package), imported once."""
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name(f"{name}.py"))
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


cb = _sibling("coverage_bound")

METRICS = ("recall@5cm", "fscore@5cm", "psnr")
"""Measured metrics a row carries when it was mapped (here or by a bench)."""


def greedy_pick(obs: np.ndarray, forced: list[int], k: int) -> list[int]:
    """Rows of ``obs`` [views, samples]: ``forced`` in order, then greedy max coverage (``offline_greedy``: the row
    adding the most samples not yet observed, ties to the lowest); once no row adds any, the lowest rows not taken,
    until ``k``.
    """
    picks = cb.offline_greedy(obs, k, forced)[0][:k]
    taken = set(picks)
    rest = [i for i in range(len(obs)) if i not in taken]
    return picks + rest[: max(0, k - len(picks))]


def swap_refine(obs: np.ndarray, picks: list[int], n_forced: int, max_rounds: int = 50) -> list[int]:
    """Local search from ``picks`` (rows of ``obs``): each slot after the first ``n_forced`` is replaced by the row
    not taken that adds the most given all the other picks, while that adds more than the slot's own row, until no
    slot changes (or ``max_rounds``). Hindsight: it re-chooses views a sequential scorer had to choose early.
    Coverage never drops; the order of the slots is kept (a replay adds the views in it).
    """
    picks = list(picks)
    for _ in range(max_rounds):
        changed = False
        for i in range(n_forced, len(picks)):
            others = picks[:i] + picks[i + 1 :]
            gains = np.count_nonzero(obs & ~obs[others].any(axis=0), axis=1)
            gains[others] = -1
            best = int(np.argmax(gains))  # ties to the lowest row
            if gains[best] > gains[picks[i]]:
                picks[i] = best
                changed = True
        if not changed:
            break
    return picks


def same_setup(a: dict[str, Any], b: dict[str, Any], path: Path) -> None:
    """InputError unless bench ``b`` (at ``path``) ran on ``a``'s scene with ``a``'s pool and mapper settings."""
    for key in ("scene", "size", "stride", "max_frames", "pool_config", "mapper_config"):
        ka, kb = a.get(key), b.get(key)
        if key.endswith("_config"):  # the policy and the seed differ from run to run by design
            ka, kb = ({k: v for k, v in c.items() if k not in ("policy", "policy_params", "seed")} for c in (ka, kb))
        if ka != kb:
            raise InputError(path / "results.json", f"field {key!r} differs from the first bench's")


@dataclass
class PoolSetup:
    """A pool bench's scene, split and settings, rebuilt from its results.json."""

    results: dict[str, Any]
    pcfg: PoolConfig
    mcfg: MapperConfig
    src: FrameSequence
    scene: Any  # coverage_bound.Scene (scripts/ is no package, so no import for the annotation)
    split: PoolSplit
    pool_scene: Any  # the scene's pool frames only, the rows of the observed sets
    row_of: dict[int, int]  # scene position -> row of the observed sets


def load_pool(results: dict[str, Any], bench: Path) -> PoolSetup:
    """The setup of a pool bench (``results``: its ``read_results``); InputError when it cannot be rebuilt."""
    pcfg = PoolConfig.from_dict(
        {k: v for k, v in results["pool_config"].items() if k in PoolConfig.__dataclass_fields__}
    )
    mcfg = MapperConfig.from_dict(
        {k: v for k, v in results["mapper_config"].items() if k in MapperConfig.__dataclass_fields__}
    )
    src = open_frames(results["scene"], size=tuple(results["size"]) if results.get("size") else None,
                      stride=results.get("stride", 1), max_frames=results.get("max_frames"))  # fmt: skip
    frames = list(src)
    if src.gt_mesh_path is None:
        raise InputError(results["scene"], "no mesh.ply (the ground truth) in the scene folder")
    scene = cb.Scene([int(f.index) for f in frames], np.stack([f.depth_m for f in frames]),
                     np.stack([f.T_wc for f in frames]), src.intrinsics, Path(results["gt_mesh"]))  # fmt: skip
    if not pcfg.cull_gt_to_observed:
        raise InputError(bench / "results.json", "pool_config.cull_gt_to_observed is False: not supported")
    split = split_pool(scene.poses, pcfg)
    pool = split.pool
    pool_scene = replace(scene, ids=[scene.ids[p] for p in pool], depths=scene.depths[pool], poses=scene.poses[pool])
    return PoolSetup(results, pcfg, mcfg, src, scene, split, pool_scene, {p: j for j, p in enumerate(pool)})


def observed(setup: PoolSetup, seed: int, tau_m: float) -> tuple[np.ndarray, np.ndarray, int]:
    """GT samples of ``seed`` (as the bench's recall counts them), their observed sets [pool views, samples] from the
    candidates' true depth, and the number drawn before culling.
    """
    gt, n_drawn = cb.gt_samples(setup.scene, setup.pcfg.mesh_samples, seed, setup.mcfg.max_depth_m)
    lo = max(setup.mcfg.min_depth_m, setup.mcfg.near_m)
    return gt, cb.observed_sets(setup.pool_scene, gt, tau_m, lo, setup.mcfg.max_depth_m), n_drawn


MAP_ROWS = ("greedy", "swaps", "all")
"""The oracle rows ``--map`` can map: the greedy pick, the same refined by swaps, all pool views."""


def bound(
    benches: list[Path], tau_m: float, do_map: bool, map_dir: Path | None, map_rows: tuple[str, ...] = MAP_ROWS
) -> dict[str, Any]:
    """Coverage rows (with ``do_map`` also measured, for ``map_rows``) per seed of the benches' shared pool."""
    results = [read_results(b, "pool", ("scene", "gt_mesh", "runs", "pool_config", "mapper_config"),
                            ("label", "seed", "chosen_positions", "metrics")) for b in benches]  # fmt: skip
    for b, r in zip(benches[1:], results[1:], strict=True):
        same_setup(results[0], r, b)
    first = results[0]
    setup = load_pool(first, benches[0])
    pcfg, mcfg, src, scene, split, row_of = setup.pcfg, setup.mcfg, setup.src, setup.scene, setup.split, setup.row_of
    pool = split.pool
    k = pcfg.n_views
    seeds = sorted({int(r["seed"]) for res in results for r in res["runs"]})
    out: dict[str, Any] = {"benches": [str(b) for b in benches], "scene": first["scene"], "tau_m": tau_m, "n_views": k,
                           "n_pool": len(pool), "initial_positions": split.initial, "seeds": []}  # fmt: skip
    for seed in seeds:
        t0 = time.perf_counter()
        gt, obs, n_drawn = observed(setup, seed, tau_m)
        greedy_rows = greedy_pick(obs, [row_of[p] for p in split.initial], k)
        greedy = [pool[j] for j in greedy_rows]
        swapped = [pool[j] for j in swap_refine(obs, greedy_rows, len(split.initial))]
        order = [pool[j] for j in greedy_pick(obs, [row_of[p] for p in greedy], len(pool))]

        def cov(positions: list[int]) -> float:
            return cb.coverage(obs, [row_of[p] for p in positions])  # noqa: B023 (used within the iteration)

        rows: list[dict[str, Any]] = [
            {"name": f"all {len(pool)} pool views", "n": len(pool), "coverage": cov(pool), "positions": sorted(pool)},
            {"name": f"greedy max-coverage, {k} views (initial views forced)", "n": k, "coverage": cov(greedy),
             "positions": greedy},
            {"name": "the greedy pick refined by swaps (hindsight)", "n": k, "coverage": cov(swapped),
             "positions": swapped},
        ]  # fmt: skip
        for bench, res in zip(benches, results, strict=True):
            for run in res["runs"]:
                if int(run["seed"]) != seed:
                    continue
                m = run["metrics"]
                if m.get("n_gt_samples") is not None and int(m["n_gt_samples"]) != len(gt):
                    raise InputError(bench / "results.json", f"{run['label']} seed {seed}: {m['n_gt_samples']} GT "
                                     f"samples, but {len(gt)} drawn here (another scene or culling?)")  # fmt: skip
                rows.append({"name": str(run["label"]), "bench": str(bench), "n": len(run["chosen_positions"]),
                             "coverage": cov([int(p) for p in run["chosen_positions"]]),
                             "positions": [int(p) for p in run["chosen_positions"]],
                             **{key: m.get(key) for key in METRICS}})  # fmt: skip
        if do_map:
            for row, picks, tag in ((rows[1], greedy, "greedy"), (rows[2], swapped, "swaps"), (rows[0], order, "all")):
                if tag not in map_rows:
                    continue
                run_dir = None if map_dir is None else map_dir / f"{tag}_seed{seed}"
                mapped = run_pool(src, replace(pcfg, n_views=len(picks), seed=seed), mcfg, run_dir,
                                  gt_mesh=first["gt_mesh"], overwrite=True,
                                  policy=ReplayPicks([scene.ids[p] for p in picks])).metrics  # fmt: skip
                if mapped["chosen_positions"] != picks:
                    raise RuntimeError(f"seed {seed}: the replay added {mapped['chosen_positions']}, not {picks}")
                row |= {key: mapped.get(key) for key in METRICS}
        out["seeds"].append({"seed": seed, "n_gt": len(gt), "n_gt_drawn": n_drawn, "rows": rows,
                             "wall_s": time.perf_counter() - t0})  # fmt: skip
    out["summary"] = summarise(out["seeds"])
    return out


def summarise(per_seed: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per row name (in first-seen order): mean and population std over the seeds of coverage and each metric."""
    names: dict[str, list[dict[str, Any]]] = {}
    for s in per_seed:
        for row in s["rows"]:
            names.setdefault(row["name"], []).append(row)
    out = []
    for name, rows in names.items():
        entry: dict[str, Any] = {"name": name, "n": rows[0]["n"], "seeds": len(rows)}
        for key in ("coverage", *METRICS):
            vals = [float(r[key]) for r in rows if r.get(key) is not None]
            if vals:
                entry[key] = {"mean": float(np.mean(vals)), "std": float(np.std(vals))}
        out.append(entry)
    return out


def markdown(report: dict[str, Any]) -> str:
    """The summary as a markdown table (means ± population std over the seeds)."""

    def cell(entry: dict[str, Any], key: str, spec: str) -> str:
        v = entry.get(key)
        return "-" if v is None else f"{v['mean']:{spec}} ± {v['std']:{spec}}"

    lines = [
        f"# Pool coverage at {report['tau_m'] * 100:g} cm: {report['scene']}",
        "",
        f"{report['n_pool']} pool views, {report['n_views']} chosen; seeds {[s['seed'] for s in report['seeds']]}; "
        f"GT samples (culled to observed) {[s['n_gt'] for s in report['seeds']]}",
        "",
        "| views | n | coverage | R@5cm | F@5cm | PSNR (dB) |",
        "|---|---|---|---|---|---|",
    ]
    for e in report["summary"]:
        lines.append(f"| {e['name']} | {e['n']} | {cell(e, 'coverage', '.4f')} | {cell(e, 'recall@5cm', '.4f')} | "
                     f"{cell(e, 'fscore@5cm', '.4f')} | {cell(e, 'psnr', '.2f')} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def write_report(out: Path, stem: str, report: dict[str, Any], text: str) -> None:
    """``out/<stem>.json`` and ``out/<stem>.md`` (each written to a temporary name, then renamed); print ``text``."""
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / f"{stem}.json", to_json_safe(report))
    with atomic_path(out / f"{stem}.md") as tmp:
        tmp.write_text(text)
    print(text, end="")


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments, measure, write ``bound.json`` and ``bound.md``, print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("benches", type=Path, nargs="+", help="roigsf bench --setting pool folders of one scene and pool")
    ap.add_argument("--out", type=Path, required=True, help="output folder (bound.json, bound.md, maps/ with --map)")
    ap.add_argument("--tau", type=float, default=0.05, help="distance threshold (m), as in R@5cm")
    ap.add_argument("--map", action="store_true", help="also map the oracle rows (each seed; see --map-rows)")
    ap.add_argument(
        "--map-rows",
        default=",".join(MAP_ROWS),
        help=f"which oracle rows --map maps, comma-separated among {', '.join(MAP_ROWS)} (default: all three)",
    )
    args = ap.parse_args(argv)
    map_rows = tuple(r.strip() for r in args.map_rows.split(",") if r.strip())
    if not map_rows or any(r not in MAP_ROWS for r in map_rows):
        print(f"pool_bound: --map-rows {args.map_rows!r}: expected names among {', '.join(MAP_ROWS)}", file=sys.stderr)
        return 2
    try:
        report = bound(args.benches, args.tau, args.map, args.out / "maps", map_rows)
    except InputError as e:
        print(f"pool_bound: {e}", file=sys.stderr)
        return 2
    write_report(args.out, "bound", report, markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
