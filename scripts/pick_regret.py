#!/usr/bin/env python3
"""Which of a pool policy's picks lose coverage, and why: its own run replayed, every pick against the true gain (#10).

``unseen_vs_gain.py`` compares the unseen term U with the surface a candidate would add at the first pick only, where
every policy stands on the same map. This re-runs one ``roi-gsurfisher`` policy of a pool bench (``--label``; the
bench's settings and seeds) and, at each of its picks, takes the candidates' U and fused score from that pick's scoring
and their true gain given the views so far: the fraction of the GT samples (those the bench's recall counts) a
candidate's true depth observes within ``--tau`` that neither the initial views nor the policy's earlier picks observe
(``pool_bound.observed``). The replay's chosen positions are checked against the bench's own run of the label where it
has one. Reported per seed and pick: the gain of the pick, of argmax U (U alone) and the best gain, and Spearman's rho
of U and of the fused score with the gain over the candidates not flagged; summed over picks, per seed and over the
seeds. For a plain ``roi-gsurfisher`` fusion (no FisherRF term) it also screens rank fusion: the gain of the argmax of
the fused score with each term's z-score taken over the candidates' ranks instead of their values. For any label it
also screens pose diversity (:func:`pose_diversity`): the gain of the argmax of the fused score plus z(D), and of D
alone, D being how far a candidate stands and looks from every view taken so far.

With ``--pixels`` (a carved-space policy) it also asks whether U's pixels are the new ones: for each candidate, U* is
the fraction of the pixels U counts (at the scorer's resolution, rays meeting the unseen term's box) whose true-depth
point lies farther than ``--tau`` from every point the views so far observe by their true depth, with U's own unseen
pixels against those as a confusion (true / false unseen, missed new) and by the length of the unknown stretch they look
through, summed over each pick's candidates; U is recomputed from the scorer's carved grid and checked against the
scorer's value. It also splits each pick's gain, and the best candidate's, by where the gained GT samples lie in the
carved grid that pick was scored on (:func:`sample_classes`): on surface the grid holds, in unknown space, in carved
free space, outside the box; and screens U_sf, the unseen pixels whose unknown stretch begins next to an occupied cell
(where observed surface ends), and U_ray, U with each unseen pixel weighed by its unknown stretch's length in cells
(the volumetric information gain's unknown voxels per ray), each by the gain of the argmax of the fused score with it
in place of U at each pick. Writes ``pick_regret.json`` and ``.md`` under ``--out`` (atomically) and prints the table.

    .venv/bin/python scripts/pick_regret.py runs/bench_pool_room5_240_base36 --out runs/s42/px_room5 --pixels
"""

from __future__ import annotations

import argparse
import itertools
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import binary_dilation
from scipy.spatial import cKDTree
from scipy.stats import rankdata

import roigsf_ros.nbv.scorer as scorer_module
import roigsf_ros.nbv.unseen as unseen_module
from roigsf_ros.core.errors import InputError
from roigsf_ros.experiments.bench import parse_policies, read_results
from roigsf_ros.experiments.pool import make_pool_policy, run_pool
from roigsf_ros.mapping.observed_space import FREE, OCCUPIED, UNKNOWN

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/ is no package
import pool_bound as pb
import unseen_vs_gain as uvg

VARIANT = "roi-gsurfisher:unseen_weight=1:unseen_source=carved"
"""The label replayed by default: the variant the README recommends for the pool setting."""


STRETCH_BINS = (0.0, 1.0, 2.0, 4.0, 8.0, np.inf)
"""Bins (in cells of the carved grid, along the camera's z) of the unknown stretch U's unseen pixels look through."""


SAMPLE_CLASSES = ("held", "unknown", "free", "outside")
"""Where a GT sample lies in a carved grid: within one cell of an OCCUPIED cell (surface the keyframes saw), else in
an UNKNOWN cell (space none saw), else in a FREE cell (a hole they saw through), or outside the grid's box."""


def near_occupied(space: Any) -> np.ndarray:
    """[X, Y, Z] bool: the cells of the carved grid ``space`` within one cell (26 neighbours) of an occupied one."""
    return binary_dilation(space.state == OCCUPIED, structure=np.ones((3, 3, 3), dtype=bool))


def sample_classes(space: Any, held: np.ndarray, points_w: np.ndarray) -> np.ndarray:
    """[N] int8 index into :data:`SAMPLE_CLASSES` of each world point [N, 3] in the carved grid ``space``, whose
    :func:`near_occupied` cells are ``held``.
    """
    ijk = np.floor((points_w - space.lo_m) / space.voxel_m).astype(np.int64)
    inside = np.all((ijk >= 0) & (ijk < np.array(space.state.shape)), axis=1)
    out = np.full(len(points_w), SAMPLE_CLASSES.index("outside"), dtype=np.int8)
    i, j, k = ijk[inside].T
    state = space.state[i, j, k]
    cls = np.where(held[i, j, k], 0, np.where(state == UNKNOWN, 1, np.where(state == FREE, 2, 0)))
    out[inside] = cls
    return out


def rank_fused(s: dict[str, Any], ok: np.ndarray) -> np.ndarray:
    """The variant's fused score [M] with each term's z-score taken over its ranks (average ranks for ties) instead of
    its values: ``epsilon r(F) + delta r(C) + w r(U)`` over the candidates ``ok``, -inf elsewhere (the rank screen).
    Checks first that ``s``'s fused score is ``epsilon z(F) + delta z(C) + w z(U)`` (Eq. 15 plus the unseen term), so
    that the screen changes the normalisation alone.
    """
    z = scorer_module.zscore
    rebuilt = s["epsilon"] * z(s["fisher"][ok]) + s["delta"] * z(s["close_front"][ok], s["cf_min_std"])
    rebuilt = rebuilt + s["w"] * z(s["u"][ok], s["min_std"])
    if not np.allclose(rebuilt, s["fused"][ok], rtol=0, atol=1e-9):
        raise RuntimeError("the fused score is not epsilon z(F) + delta z(C) + w z(U)")
    out = np.full(len(s["fused"]), -np.inf)
    out[ok] = sum(c * z(rankdata(s[key][ok])) for c, key in
                  ((s["epsilon"], "fisher"), (s["delta"], "close_front"), (s["w"], "u")))  # fmt: skip
    return out


def pool_scale(centres_m: np.ndarray) -> float:
    """L (m): the median over ``centres_m`` [M, 3] (the pool's camera centres) of the distance to the nearest other."""
    d, _ = cKDTree(centres_m).query(centres_m, k=2)
    return float(np.median(d[:, 1]))


def pose_diversity(T_wc: np.ndarray, seen_T_wc: np.ndarray, scale_m: float) -> np.ndarray:
    """D [M] of candidate poses ``T_wc`` [M, 4, 4] against the views so far ``seen_T_wc`` [K, 4, 4]: the minimum over
    the views of ``|t_c - t_v| / scale_m + (1 - a_c . a_v)``, t the camera centre, a the optical axis (the diversity
    screen: how far a candidate stands and looks from every view taken).
    """
    dist = np.linalg.norm(T_wc[:, None, :3, 3] - seen_T_wc[None, :, :3, 3], axis=2) / scale_m
    turn = 1.0 - np.einsum("mi,ki->mk", T_wc[:, :3, 2], seen_T_wc[:, :3, 2])
    return (dist + turn).min(axis=1)


def true_points(setup: Any, position: int, lo_m: float, hi_m: float) -> tuple[np.ndarray, np.ndarray]:
    """World points [N, 3] of a scene frame's valid true depth and their pixel mask [H, W]."""
    return pb.cb.depth_points(setup.scene.depths[position], setup.scene.poses[position], setup.scene.intr, lo_m, hi_m)


def pixel_truth(setup: Any, positions: list[int], seen: list[int], space: Any, box: Any, cfg: Any,
                u: np.ndarray, flagged: np.ndarray, tau_m: float,
                gt_w: np.ndarray | None = None) -> dict[str, Any]:  # fmt: skip
    """U* of each candidate at ``positions`` given the views ``seen`` (scene positions), U's pixel confusion, U_sf:
    the fraction of the counted pixels that are unseen and whose unknown stretch begins within one cell of an occupied
    cell (where observed surface ends: surface-edge exploration), and U_ray: U with each unseen pixel weighed by the
    length of its unknown stretch in cells (the volumetric gain's unknown voxels per ray); with ``gt_w`` [N, 3], the GT
    samples' :func:`sample_classes` in this grid.
    """
    lo, hi = max(setup.mcfg.min_depth_m, setup.mcfg.near_m), setup.mcfg.max_depth_m
    held_grid = near_occupied(space)
    held = held_grid.reshape(-1)
    tree = cKDTree(np.concatenate([true_points(setup, p, lo, hi)[0] for p in seen]))
    intr = setup.scene.intr
    u_star = np.zeros(len(positions))
    u_sf = np.zeros(len(positions))
    u_ray = np.zeros(len(positions))
    counts = {"true_unseen": 0, "false_unseen": 0, "missed_new": 0, "seen_seen": 0, "no_depth": 0}
    stretch = {
        "true_unseen": np.zeros(len(STRETCH_BINS) - 1, dtype=np.int64),
        "false_unseen": np.zeros(len(STRETCH_BINS) - 1, dtype=np.int64),
    }
    for i, p in enumerate(positions):
        T = setup.scene.poses[p]
        hole, enter, leave = unseen_module.carved_unseen(space, T, intr, box, cfg)
        meets = unseen_module.rays_meet_box(T, intr, *box)
        hole &= meets
        if not flagged[i] and not np.isclose(hole.sum() / max(int(meets.sum()), 1), u[i], rtol=0, atol=1e-12):
            raise RuntimeError(f"candidate {p}: U recomputed from the carved grid differs from the scorer's")
        pts, valid = true_points(setup, p, lo, hi)
        new = np.zeros_like(valid)
        if len(pts):
            dist, _ = tree.query(pts, k=1, distance_upper_bound=tau_m)
            new[valid] = dist >= tau_m
        u_star[i] = (new & meets).sum() / max(int(meets.sum()), 1)
        first = space.unseen_cells(T, intr, cfg.near_m, cfg.far_m)
        u_sf[i] = (hole & (first >= 0) & held[np.maximum(first, 0)]).sum() / max(int(meets.sum()), 1)
        known = meets & valid
        counts["true_unseen"] += int((hole & new & known).sum())
        counts["false_unseen"] += int((hole & ~new & known).sum())
        counts["missed_new"] += int((~hole & new & known).sum())
        counts["seen_seen"] += int((~hole & ~new & known).sum())
        counts["no_depth"] += int((meets & ~valid).sum())
        cells = (leave - enter) / space.voxel_m  # the unknown stretch's length along z, in cells
        u_ray[i] = cells[hole].sum() / max(int(meets.sum()), 1)
        for key, mask in (("true_unseen", hole & new & known), ("false_unseen", hole & ~new & known)):
            stretch[key] += np.histogram(cells[mask], bins=STRETCH_BINS)[0]
    return {
        **({} if gt_w is None else {"classes": sample_classes(space, held_grid, gt_w)}),
        "u_star": u_star,
        "u_sf": u_sf,
        "u_ray": u_ray,
        "counts": counts | {f"stretch_{k}": v.tolist() for k, v in stretch.items()},
    }


def replay(
    setup: Any, seed: int, label: str, pixels: bool = False, tau_m: float = 0.05, gt_w: np.ndarray | None = None
) -> tuple[list[int], list[dict[str, Any]]]:
    """Run ``label``'s policy on ``setup`` with ``seed``; its chosen positions and, per pick, the candidates'
    positions, U, fused score, flags and the index chosen (with ``pixels``, U* and U's pixel confusion, and the
    :func:`sample_classes` of the GT samples ``gt_w`` [N, 3] in the pick's carved grid).
    """
    spec = parse_policies(label, "pool")[0]
    cfg = replace(setup.pcfg, policy=spec.name, policy_params=dict(spec.params), seed=seed)
    policy = make_pool_policy(cfg)
    scored: list[dict[str, Any]] = []
    choose = policy.choose
    carved: dict[str, Any] = {}
    carve = unseen_module.carved_space

    def capturing_carve(surfel_map: Any, poses: Any, intr: Any, lo_m: Any, hi_m: Any, ncfg: Any, *rest: Any) -> Any:
        carved.update(space=carve(surfel_map, poses, intr, lo_m, hi_m, ncfg, *rest), box=(lo_m, hi_m), cfg=ncfg)
        return carved["space"]

    def recording_choose(poses: Any, mapper: Any) -> int:
        carved.clear()
        pick = choose(poses, mapper)
        res = policy.last_result
        if res is None or res.unseen is None:
            raise RuntimeError(f"seed {seed}: pick {len(scored) + 1} was not scored with the unseen term")
        cfg = policy.config
        scored[-1] |= {"u": res.unseen.copy(), "fused": res.fused.copy(), "flagged": res.flagged.copy(), "pick": pick,
                       "fisher": res.fisher.copy(), "close_front": res.close_front.copy(), "w": cfg.unseen_weight,
                       "min_std": cfg.unseen_min_std, "cf_min_std": cfg.close_front_min_std, "epsilon": cfg.epsilon,
                       "delta": cfg.delta,
                       "plain_fusion": res.mode == "roi-gsurfisher" and cfg.fisherrf_weight == 0}  # fmt: skip
        if pixels:
            if "space" not in carved:
                raise RuntimeError(
                    f"seed {seed}: pick {len(scored)}: no carved space (--pixels needs unseen_source=carved)"
                )
            seen = list(setup.split.initial) + [s["positions"][s["pick"]] for s in scored[:-1]]
            scored[-1] |= pixel_truth(setup, scored[-1]["positions"], seen, carved["space"], carved["box"],
                                      carved["cfg"], res.unseen, res.flagged, tau_m, gt_w)  # fmt: skip
        return pick

    policy.choose = recording_choose  # type: ignore[method-assign]
    unseen_module.carved_space = capturing_carve

    def record_candidates(_mapper: Any, _policy: Any, positions: list[int], _poses: Any) -> None:
        scored.append({"positions": list(positions)})

    try:
        result = run_pool(setup.src, cfg, setup.mcfg, None, policy=policy, on_select=record_candidates)
    finally:
        unseen_module.carved_space = carve
    chosen = [int(p) for p in result.metrics["chosen_positions"]]
    return chosen, scored


def measure(bench: Path, label: str, seeds: list[int] | None, tau_m: float, pixels: bool = False) -> dict[str, Any]:
    """Per seed and pick: gains of the pick, of argmax U and the best; rho of U and of the fused score with the gain."""
    results = read_results(bench, "pool", ("scene", "gt_mesh", "runs", "pool_config", "mapper_config"),
                           ("label", "seed", "chosen_positions", "metrics"))  # fmt: skip
    setup = pb.load_pool(results, bench)
    bench_runs = {
        int(r["seed"]): [int(p) for p in r["chosen_positions"]] for r in results["runs"] if r["label"] == label
    }
    if not bench_runs and seeds is None:
        raise InputError(bench / "results.json", f"no run labelled {label!r} (give --seeds to replay it anyway)")
    run_seeds = sorted(bench_runs) if seeds is None else seeds
    poses = np.asarray(setup.scene.poses, dtype=np.float64)
    scale_m = pool_scale(poses[setup.split.pool, :3, 3])
    out: dict[str, Any] = {
        "bench": str(bench),
        "label": label,
        "scene": results["scene"],
        "tau_m": tau_m,
        "scale_m": scale_m,
        "seeds": [],
    }
    for seed in run_seeds:
        gt, obs, _n = pb.observed(setup, seed, tau_m)
        chosen, scored = replay(setup, seed, label, pixels, tau_m, gt)
        if seed in bench_runs and chosen != bench_runs[seed]:
            raise RuntimeError(f"seed {seed}: the replay chose {chosen}, the bench's run {bench_runs[seed]}")
        seen = obs[[setup.row_of[p] for p in setup.split.initial]].any(axis=0)
        views = list(setup.split.initial)
        picks: list[dict[str, Any]] = []
        for k, s in enumerate(scored, start=1):
            rows = [setup.row_of[p] for p in s["positions"]]
            gain = np.count_nonzero(obs[rows] & ~seen, axis=1) / obs.shape[1]
            ok = ~s["flagged"]
            max_u = int(np.argmax(np.where(ok, s["u"], -np.inf)))
            extra: dict[str, Any] = {}
            if s["plain_fusion"]:
                extra["gain_of_rank"] = float(gain[int(np.argmax(rank_fused(s, ok)))])
            div = pose_diversity(poses[s["positions"]], poses[views], scale_m)
            with_div = np.full(len(rows), -np.inf)  # the diversity screen: fused + 1 z(D)
            with_div[ok] = s["fused"][ok] + scorer_module.zscore(div[ok], s["min_std"])
            extra |= {"gain_of_div": float(gain[int(np.argmax(with_div))]),
                      "gain_of_max_div": float(gain[int(np.argmax(np.where(ok, div, -np.inf)))]),
                      "rho_div": uvg.rho(div[ok], gain[ok])}  # fmt: skip
            if pixels:
                u_star = s["u_star"]
                new = obs[rows] & ~seen
                split = {c: np.count_nonzero(new & (s["classes"] == i), axis=1) / obs.shape[1]
                         for i, c in enumerate(SAMPLE_CLASSES)}  # fmt: skip
                best = int(np.argmax(gain))
                if int(np.argmax(np.where(ok, s["fused"], -np.inf))) != s["pick"]:
                    raise RuntimeError(f"seed {seed}: pick {k} is not the argmax of the fused score")
                z = scorer_module.zscore
                edges = s["fused"].copy()  # U_sf in place of U in the variant's score (the offline screen)
                edges[ok] += s["w"] * (z(s["u_sf"][ok], s["min_std"]) - z(s["u"][ok], s["min_std"]))
                rays = s["fused"].copy()  # U_ray in place of U (the volumetric-gain screen)
                rays[ok] += s["w"] * (z(s["u_ray"][ok], s["min_std"]) - z(s["u"][ok], s["min_std"]))
                extra |= {"rho_u_star": uvg.rho(u_star[ok], gain[ok]), "rho_u_u_star": uvg.rho(s["u"][ok], u_star[ok]),
                          "gain_of_max_u_star": float(gain[int(np.argmax(np.where(ok, u_star, -np.inf)))]),
                          "gain_of_edges": float(gain[int(np.argmax(np.where(ok, edges, -np.inf)))]),
                          "rho_u_sf": uvg.rho(s["u_sf"][ok], gain[ok]),
                          "gain_of_rays": float(gain[int(np.argmax(np.where(ok, rays, -np.inf)))]),
                          "gain_of_max_u_ray": float(gain[int(np.argmax(np.where(ok, s["u_ray"], -np.inf)))]),
                          "rho_u_ray": uvg.rho(s["u_ray"][ok], gain[ok]),
                          "pixels": s["counts"],
                          "gain_split_pick": {c: float(v[s["pick"]]) for c, v in split.items()},
                          "gain_split_best": {c: float(v[best]) for c, v in split.items()}}  # fmt: skip
            picks.append(extra | {
                "pick": k,
                "candidates": len(rows),
                "gain_of_pick": float(gain[s["pick"]]),
                "gain_of_max_u": float(gain[max_u]),
                "best_gain": float(gain.max()),
                "rho_u": uvg.rho(s["u"][ok], gain[ok]),
                "rho_fused": uvg.rho(s["fused"][ok], gain[ok]),
            })  # fmt: skip
            seen = seen | obs[rows[s["pick"]]]
            views.append(s["positions"][s["pick"]])
        out["seeds"].append({"seed": seed, "chosen": chosen, "coverage": float(seen.mean()), "picks": picks})
    return out


def sums(picks: list[dict[str, Any]], lo: int, hi: int) -> dict[str, float]:
    """Summed gains of picks ``lo``..``hi`` (1-based, inclusive)."""
    sel = [p for p in picks if lo <= p["pick"] <= hi]
    return {key: float(sum(p[key] for p in sel)) for key in ("gain_of_pick", "gain_of_max_u", "best_gain")}


def screen_rows(seeds: list[dict[str, Any]], n: int, keys: tuple[str, ...], rho_key: str) -> list[str]:
    """Table rows of a screen over picks 1..n/2, the rest and all: the mean of ``rho_key`` over the picks and seeds,
    then the gains ``keys`` summed over them.
    """
    rows = []
    for lo, hi in ((1, n // 2), (n // 2 + 1, n), (1, n)):
        sel = [p for s in seeds for p in s["picks"] if lo <= p["pick"] <= hi]
        rho = float(np.nanmean([p[rho_key] for p in sel]))
        rows.append(f"| {lo}-{hi} | {rho:+.2f} | {' / '.join(f'{sum(p[k] for p in sel):.4f}' for k in keys)} |")
    return rows


def markdown(report: dict[str, Any]) -> str:
    """Per pick: gains and rhos as means over the seeds; then sums over pick ranges."""
    seeds = report["seeds"]
    n = min(len(s["picks"]) for s in seeds)
    lines = [
        f"# Each pick against the true gain: {report['label']} on {report['bench']}",
        "",
        f"gain = fraction of the GT samples a candidate observes within {report['tau_m'] * 100:g} cm that the initial "
        f"views and the earlier picks do not; means over seeds {', '.join(str(s['seed']) for s in seeds)}; coverage of "
        f"the run's views (sum of the picks' gains plus the initial views'): "
        + ", ".join(f"{s['coverage']:.4f}" for s in seeds),
        "",
        "| pick | gain of the pick | gain of argmax U | best gain | rho(U, gain) | rho(fused, gain) |",
        "|---|---|---|---|---|---|",
    ]
    for k in range(n):
        rows = [s["picks"][k] for s in seeds]
        m = {
            key: float(np.nanmean([r[key] for r in rows]))
            for key in rows[0]
            if key not in ("pick", "candidates", "pixels", "gain_split_pick", "gain_split_best")
        }
        lines.append(f"| {k + 1} | {m['gain_of_pick']:.4f} | {m['gain_of_max_u']:.4f} | {m['best_gain']:.4f} | "
                     f"{m['rho_u']:+.2f} | {m['rho_fused']:+.2f} |")  # fmt: skip
    lines += ["", "| picks | seed | summed gain of the picks | of argmax U | of the best |", "|---|---|---|---|---|"]
    half = n // 2
    for lo, hi in ((1, half), (half + 1, n), (1, n)):
        for s in seeds:
            t = sums(s["picks"], lo, hi)
            lines.append(f"| {lo}-{hi} | {s['seed']} | {t['gain_of_pick']:.4f} | {t['gain_of_max_u']:.4f} | "
                         f"{t['best_gain']:.4f} |")  # fmt: skip
    if "gain_of_rank" in seeds[0]["picks"][0]:
        lines += ["", "Rank fusion: the fused score with each term's z-score taken over the candidates' ranks instead "
                  "of their values (epsilon r(F) + delta r(C) + w r(U)); the gain of its argmax at each pick (one step "
                  "on this run's own views), summed over the picks and the seeds:", "",
                  "| picks | gain of the pick / of argmax of the rank fusion / best |", "|---|---|"]  # fmt: skip
        for lo, hi in ((1, half), (half + 1, n), (1, n)):
            sel = [p for s in seeds for p in s["picks"] if lo <= p["pick"] <= hi]
            g = [sum(p[key] for p in sel) for key in ("gain_of_pick", "gain_of_rank", "best_gain")]
            lines.append(f"| {lo}-{hi} | {' / '.join(f'{x:.4f}' for x in g)} |")
    lines += ["", "Pose diversity D: each candidate's minimum over the views so far of |t_c - t_v| / L + "
              f"(1 - a_c . a_v) (camera centres t, optical axes a; L = {report['scale_m']:.3f} m, the median "
              "distance from a pool position to its nearest other); the gain of the argmax of the fused score plus "
              "z(D) and of D alone (one step on this run's own views), summed over the picks and the seeds:", "",
              "| picks | rho(D, gain) | gain of the pick / of argmax fused + z(D) / of argmax D / best |",
              "|---|---|---|"]  # fmt: skip
    lines += screen_rows(seeds, n, ("gain_of_pick", "gain_of_div", "gain_of_max_div", "best_gain"), "rho_div")
    if "rho_u_star" in seeds[0]["picks"][0]:
        lines += ["", "U* = the fraction of the pixels U counts whose true-depth point is new (farther than the "
                  "threshold from every point the views so far observe); U's unseen pixels against those, summed over "
                  "the candidates of the picks and the seeds:", "",
                  "| picks | rho(U, gain) | rho(U*, gain) | rho(U, U*) | gain of the pick / argmax U / argmax U* / "
                  "best (summed) | U's unseen pixels that are new (precision) | new pixels U counts unseen (recall) |",
                  "|---|---|---|---|---|---|---|"]  # fmt: skip
        for lo, hi in ((1, half), (half + 1, n), (1, n)):
            sel = [p for s in seeds for p in s["picks"] if lo <= p["pick"] <= hi]
            r = {key: float(np.nanmean([p[key] for p in sel])) for key in ("rho_u", "rho_u_star", "rho_u_u_star")}
            g = [
                sum(p[key] for p in sel) for key in ("gain_of_pick", "gain_of_max_u", "gain_of_max_u_star", "best_gain")
            ]
            c = {key: sum(p["pixels"][key] for p in sel) for key in sel[0]["pixels"] if not key.startswith("stretch")}
            prec = c["true_unseen"] / max(c["true_unseen"] + c["false_unseen"], 1)
            rec = c["true_unseen"] / max(c["true_unseen"] + c["missed_new"], 1)
            lines.append(f"| {lo}-{hi} | {r['rho_u']:+.2f} | {r['rho_u_star']:+.2f} | {r['rho_u_u_star']:+.2f} | "
                         f"{' / '.join(f'{x:.4f}' for x in g)} | {prec:.3f} ({c['true_unseen']} of "
                         f"{c['true_unseen'] + c['false_unseen']}) | {rec:.3f} ({c['true_unseen']} of "
                         f"{c['true_unseen'] + c['missed_new']}) |")  # fmt: skip
        edges = [f"{a:g}-{b:g}" for a, b in itertools.pairwise(STRETCH_BINS)]
        lines += ["", "Length of the unknown stretch U's unseen pixels look through, in carved cells (along z), new "
                  "pixels / not new, summed over the candidates of the picks and the seeds:", "",
                  f"| picks | {' | '.join(edges)} |", "|---|" + "---|" * len(edges)]  # fmt: skip
        for lo, hi in ((1, half), (half + 1, n)):
            sel = [p for s in seeds for p in s["picks"] if lo <= p["pick"] <= hi]
            t = np.sum([p["pixels"]["stretch_true_unseen"] for p in sel], axis=0)
            f = np.sum([p["pixels"]["stretch_false_unseen"] for p in sel], axis=0)
            lines.append(f"| {lo}-{hi} | " + " | ".join(f"{a} / {b}" for a, b in zip(t, f, strict=True)) + " |")
        lines += ["", "U_sf = the fraction of the counted pixels that are unseen and whose unknown stretch begins "
                  "within one cell of an occupied cell (where observed surface ends); the gain of the argmax of the "
                  "fused score with U_sf in place of U (one step on this run's own views), summed over the picks and "
                  "the seeds:", "", "| picks | rho(U_sf, gain) | gain of the pick / with U_sf in place of U / best |",
                  "|---|---|---|"]  # fmt: skip
        lines += screen_rows(seeds, n, ("gain_of_pick", "gain_of_edges", "best_gain"), "rho_u_sf")
        lines += ["", "U_ray = U with each unseen pixel weighed by the length of its unknown stretch in carved cells "
                  "(along z), over the counted pixels: the unknown voxels each ray crosses, as the volumetric "
                  "information gain counts them; the gain of the argmax of the fused score with U_ray in place of U "
                  "and of U_ray alone (one step on this run's own views), summed over the picks and the seeds:", "",
                  "| picks | rho(U_ray, gain) | gain of the pick / with U_ray in place of U / of argmax U_ray / best |",
                  "|---|---|---|"]  # fmt: skip
        lines += screen_rows(seeds, n, ("gain_of_pick", "gain_of_rays", "gain_of_max_u_ray", "best_gain"), "rho_u_ray")
        lines += ["", "Where the gained GT samples lie in the carved grid each pick was scored on (held: within one "
                  "cell of an occupied cell; unknown; free; outside the box), gain of the pick / of the best "
                  "candidate, summed over the picks and the seeds:", "",
                  f"| picks | {' | '.join(SAMPLE_CLASSES)} | all |",
                  "|---|" + "---|" * (len(SAMPLE_CLASSES) + 1)]  # fmt: skip
        for lo, hi in ((1, half), (half + 1, n), (1, n)):
            sel = [p for s in seeds for p in s["picks"] if lo <= p["pick"] <= hi]
            pk = [sum(p["gain_split_pick"][c] for p in sel) for c in SAMPLE_CLASSES]
            bs = [sum(p["gain_split_best"][c] for p in sel) for c in SAMPLE_CLASSES]
            cells = [f"{a:.4f} / {b:.4f}" for a, b in zip([*pk, sum(pk)], [*bs, sum(bs)], strict=True)]
            lines.append(f"| {lo}-{hi} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments, measure, write ``pick_regret.json`` and ``.md``, print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bench", type=Path, help="a roigsf bench --setting pool folder")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--label", default=VARIANT, help=f"the bench's policy label to replay (default: {VARIANT})")
    ap.add_argument("--seeds", type=int, nargs="*", help="seeds (default: the label's runs in the bench)")
    ap.add_argument("--tau", type=float, default=0.05, help="distance threshold (m), as in R@5cm")
    ap.add_argument(
        "--pixels",
        action="store_true",
        help="also U*, U's pixel confusion, the gain by where it lies in "
        "the carved grid and the U_sf and U_ray screens (carved-space policies)",
    )
    args = ap.parse_args(argv)
    try:
        report = measure(args.bench, args.label, args.seeds, args.tau, args.pixels)
    except InputError as e:
        print(f"pick_regret: {e}", file=sys.stderr)
        return 2
    pb.write_report(args.out, "pick_regret", report, markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
