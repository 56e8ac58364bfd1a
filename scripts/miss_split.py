#!/usr/bin/env python3
"""Where a pool bench's final meshes miss the true surface: recall's misses split by part of the scene (issue 10).

R@5cm is one number over the whole scene; two policies can differ by it for reasons that have nothing to do with the
parts a view-selection rule is meant to find (the inside of a shelf, the crate under a table). For each run of each
bench folder given (``runs/<policy>/seed<k>/mesh.ply``) this draws the ground-truth samples exactly as the bench did
(the same seed, count and culling to what the scene's poses observe), finds those farther than ``--tau`` from the
run's mesh, and splits them by the connected component of the ground-truth mesh they lie on (a synthetic scene's
parts: the floor disc, each board, each box). For each component it also gives the misses' median horizontal
distance from the scene's centre against the component's own reach, which says whether a floor is missed at its edge,
and the misses off the largest part (mean and std over the seeds: the objects, where the largest part is a floor).
Prints a table (means over the seeds) and, with ``--out``, writes JSON. The recomputed recall of each run must equal
the one in its ``results.json`` (it is checked), so the split adds up to the bench's figure.

``clutter_missed.py`` is the hand-made twin for one scene: it splits the clutter scene by regions that are not
connected parts (a cabinet's inside and outside are faces of the same boards) and renders the maps at the insides;
this one needs no layout, so it works on any scene whose parts are separate meshes.

    .venv/bin/python scripts/miss_split.py runs/bench_pool_shelf_unconfirmed runs/bench_pool_shelf
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
import open3d.core as o3c

from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import read_json, write_json
from roigsf_ros.data.sources import open_frames
from roigsf_ros.evaluation import as_legacy_mesh, gt_visible_mask, raycasting_scene, sample_surface
from roigsf_ros.experiments.bench import read_results

MIN_SHARE = 0.01
"""Components with less than this share of every policy's misses are pooled as ``other``."""


def components(gt: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """Triangle -> component index [T], and per component: its name (``c<i>``, largest area first), area (m^2),
    bounding box (metres) and horizontal reach from the scene's centre (the GT bounding box's, metres).
    """
    tri_cluster, _, areas = gt.cluster_connected_triangles()
    tri_cluster = np.asarray(tri_cluster)
    order = np.argsort(-np.asarray(areas), kind="stable")
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    tri_comp = rank[tri_cluster]
    verts, tris = np.asarray(gt.vertices), np.asarray(gt.triangles)
    centre = 0.5 * (verts.min(0) + verts.max(0))
    info = []
    for c, k in enumerate(order):
        v = verts[np.unique(tris[tri_cluster == k])]
        info.append({
            "name": f"c{c}",
            "area_m2": float(areas[k]),
            "bbox_min_m": v.min(0).round(3).tolist(),
            "bbox_max_m": v.max(0).round(3).tolist(),
            "reach_m": float(np.hypot(*(v[:, :2] - centre[:2]).T).max()),
        })  # fmt: skip
    return tri_comp, info


def split_bench(bench: Path, tau_m: float) -> dict[str, Any]:
    """Per policy and seed: recall, misses per component, the misses' median horizontal radius per component."""
    res = read_results(bench, "pool", ("scene", "gt_mesh", "runs"), ("label", "seed", "dir", "metrics"))
    src = open_frames(res["scene"], size=tuple(res["size"]) if res.get("size") else None, stride=res.get("stride", 1),
                      max_frames=res.get("max_frames"))  # fmt: skip
    poses = np.stack([f.T_wc for f in src])
    gt = as_legacy_mesh(res["gt_mesh"], "gt_mesh")
    tri_comp, info = components(gt)
    verts = np.asarray(gt.vertices)
    centre = 0.5 * (verts.min(0) + verts.max(0))
    gt_scene = raycasting_scene(gt)
    max_depth = float(res.get("mapper_config", {}).get("max_depth_m", 10.0))
    out: dict[str, Any] = {"bench": str(bench), "components": info, "runs": []}
    for run in res["runs"]:
        cfg = run["metrics"].get("pool_config", res.get("pool_config", {}))
        seed = int(run["seed"])
        pts = sample_surface(gt, int(cfg.get("mesh_samples", 200_000)), seed)
        if cfg.get("cull_gt_to_observed", True):
            pts = pts[gt_visible_mask(pts, gt_scene, poses, src.intrinsics, max_depth)]
        mesh_path = bench / run["dir"] / "mesh.ply"
        pred = as_legacy_mesh(str(mesh_path), str(mesh_path))
        d = raycasting_scene(pred).compute_distance(o3c.Tensor(pts.astype(np.float32))).numpy()
        miss = d >= tau_m
        recall = float(1.0 - miss.mean())
        want = run["metrics"].get(f"recall@{round(tau_m * 100, 6):g}cm")
        if want is not None and abs(recall - want) > 1e-6:
            raise InputError(mesh_path, f"recomputed recall {recall:.6f} differs from results.json's {want:.6f}")
        prim = gt_scene.compute_closest_points(o3c.Tensor(pts[miss].astype(np.float32)))["primitive_ids"].numpy()
        comp = tri_comp[prim]
        radius = np.hypot(*(pts[miss][:, :2] - centre[:2]).T)
        out["runs"].append({
            "policy": run["label"],
            "seed": seed,
            "recall": recall,
            "n_gt": len(pts),
            "missed": {info[c]["name"]: int(n) for c, n in zip(*np.unique(comp, return_counts=True), strict=True)},
            "missed_median_radius_m": {info[c]["name"]: float(np.median(radius[comp == c])) for c in np.unique(comp)},
        })  # fmt: skip
    return out


def table(benches: list[dict[str, Any]]) -> tuple[list[str], dict[str, dict[str, float]], list[dict[str, Any]]]:
    """Columns (components holding at least :data:`MIN_SHARE` of some policy's misses, then ``other``), and per
    policy the mean over its seeds of recall and of each column's misses as a share of the GT samples.
    """
    info = benches[0]["components"]
    runs = [r for b in benches for r in b["runs"]]
    names = [c["name"] for c in info]
    by_policy: dict[str, list[dict[str, Any]]] = {}
    for r in runs:
        by_policy.setdefault(r["policy"], []).append(r)
    keep = [n for n in names if any(
        np.mean([r["missed"].get(n, 0) / max(sum(r["missed"].values()), 1) for r in rs]) >= MIN_SHARE
        for rs in by_policy.values())]  # fmt: skip
    rows: dict[str, dict[str, float]] = {}
    for pol, rs in by_policy.items():
        row = {"recall": float(np.mean([r["recall"] for r in rs]))}
        for n in keep:
            row[n] = float(np.mean([r["missed"].get(n, 0) / r["n_gt"] for r in rs]))
            radii = [r["missed_median_radius_m"][n] for r in rs if n in r["missed_median_radius_m"]]
            row[f"{n}_radius_m"] = float(np.median(radii)) if radii else float("nan")
        row["other"] = float(np.mean([sum(v for k, v in r["missed"].items() if k not in keep) / r["n_gt"] for r in rs]))
        off = [sum(v for k, v in r["missed"].items() if k != "c0") / r["n_gt"] for r in rs]  # all but the largest part
        row["off_c0"], row["off_c0_std"] = float(np.mean(off)), float(np.std(off))
        rows[pol] = row
    return keep, rows, [c for c in info if c["name"] in keep]


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments, print the table, optionally write it as JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("benches", nargs="+", type=Path, help="roigsf bench pool output folders of one scene")
    ap.add_argument("--tau", type=float, default=0.05, help="recall's threshold in metres (default 0.05)")
    ap.add_argument("--out", type=Path, help="write the table and every run's split here as JSON")
    args = ap.parse_args(argv)
    try:
        benches = [split_bench(b, args.tau) for b in args.benches]
        scenes = {read_json(b / "results.json")["gt_mesh"] for b in args.benches}
        if len(scenes) > 1:
            raise InputError("benches", f"they are of different scenes: {sorted(scenes)}")
    except InputError as e:
        sys.exit(f"miss_split: {e}")
    keep, rows, info = table(benches)
    print(f"misses at {args.tau * 100:g} cm as a share of the GT samples (mean over seeds); component: bbox, reach")
    for c in info:
        box = f"{c['bbox_min_m']} .. {c['bbox_max_m']}"
        print(f"  {c['name']}: {box}, {c['area_m2']:.3f} m^2, reach {c['reach_m']:.2f} m")
    head = ["policy", "recall"] + [f"{n} (r median)" for n in keep] + ["other", "all but c0 (std)"]
    print(" | ".join(head))
    for pol, row in rows.items():
        cells = [pol, f"{row['recall']:.4f}"]
        cells += [f"{row[n]:.4f} ({row[n + '_radius_m']:.2f} m)" for n in keep] + [f"{row['other']:.4f}"]
        cells.append(f"{row['off_c0']:.4f} ({row['off_c0_std']:.4f})")
        print(" | ".join(cells))
    if args.out:
        write_json(args.out, {"tau_m": args.tau, "columns": keep, "policies": rows, "benches": benches})
    return 0


if __name__ == "__main__":
    sys.exit(main())
