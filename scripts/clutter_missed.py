#!/usr/bin/env python3
"""Where each policy's 20-view mesh of the clutter scene misses the ground truth by more than 5 cm (issue 10).

The 5 cm recall of ``roigsf bench`` on ``roigsf scene synth --kind clutter-dome`` says how much surface a policy
missed, not where. This splits the missed ground-truth samples by the parts of
:func:`roigsf_ros.data.scene.synth_clutter` (seed 0's layout): the insides of the four cabinets (seen only from in
front of them), their outsides, the 3x3 block of boxes, and the rest (the disc, whose underside no view sees).
The ground-truth samples are drawn and culled as the bench's recall does (``mesh_samples`` points, the run's seed, kept
where some frame of the scene sees them), so a run's misses over all parts are its 1 - R@5cm. For each
bench folder given, every ``runs/<policy>/seed<k>/mesh.ply`` is compared with them; prints a table and, with
``--out``, writes it as JSON.

``miss_split.py`` splits any pool bench the same way by the ground truth's connected parts (no layout needed, and it
checks the recomputed recall against the bench's); this one knows the clutter layout's regions, which are not
connected parts, and can render the maps at the cabinets' insides (``--render-check``).

    .venv/bin/python scripts/clutter_missed.py --scene runs/clutter_dome_240 runs/bench_pool_clutter_240
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import open3d as o3d

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import write_json
from roigsf_ros.data.sources import open_frames
from roigsf_ros.evaluation.metrics import gt_visible_mask, sample_surface
from roigsf_ros.render.rasterize import render_map
from roigsf_ros.render.surfels import SurfelMap, depth_to_points

REGIONS = ("cabinet inside", "cabinet outside", "box block", "other")


def regions(p: np.ndarray) -> np.ndarray:
    """The part of :func:`synth_clutter` each point [N, 3] lies on (one of :data:`REGIONS`), by its layout: boxes
    within 0.37 m of the centre, cabinets from 0.40 to 0.75 m out along +-x and +-y, their insides 24 cm wide and
    27 cm high from 0.48 m out.
    """
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    out = np.full(len(p), "other", dtype=object)
    out[(np.abs(x) < 0.37) & (np.abs(y) < 0.37) & (z > 0.005)] = "box block"
    for turn in range(4):  # the cabinet facing +x, turned by turn * 90 deg: rotate the points back
        a = -turn * np.pi / 2
        xr = x * np.cos(a) - y * np.sin(a)
        yr = x * np.sin(a) + y * np.cos(a)
        inside = (xr > 0.47) & (xr < 0.76) & (np.abs(yr) < 0.125) & (z < 0.275)
        shell = (xr > 0.39) & (xr < 0.76) & (np.abs(yr) < 0.21) & (z < 0.36) & ~inside
        out[inside] = "cabinet inside"
        out[shell & (out == "other")] = "cabinet outside"
    return out


def missed(gt_points: np.ndarray, mesh_path: Path, threshold_m: float) -> np.ndarray:
    """Bool [N]: the ground-truth points farther than ``threshold_m`` from the mesh at ``mesh_path``."""
    mesh = o3d.io.read_triangle_mesh(str(mesh_path))
    if len(mesh.triangles) == 0:
        raise SystemExit(f"{mesh_path}: no triangles")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    d = scene.compute_distance(o3d.core.Tensor(gt_points.astype(np.float32))).numpy()
    return d > threshold_m


def inside_pixels_seen_through(
    map_path: Path, frames: list, intr: Intrinsics, every: int = 3, behind_m: float = 0.05
) -> tuple[int, float, float]:
    """How the map at ``map_path`` renders the pixels of every ``every``-th frame whose true surface is a cabinet's
    inside: their number, the fraction with alpha < 0.5 (what the unseen term U counts) and the fraction that renders
    opaque more than ``behind_m`` behind the true surface (seen through the missing inside, onto a farther surface).
    """
    import torch  # here, after roigsf_ros: it sets torch's OpenMP wait policy before torch loads

    m = SurfelMap.load_ply(map_path)
    total, holes, through = 0, 0, 0
    for f in frames[::every]:
        v, u = np.nonzero(f.depth_m > 0)
        z = f.depth_m[v, u]
        p_cam = depth_to_points(torch.from_numpy(np.asarray(f.depth_m, np.float64)), intr).numpy()[v, u]
        inside = regions(p_cam @ f.T_wc[:3, :3].T + f.T_wc[:3, 3]) == "cabinet inside"
        if not inside.any():
            continue
        out = render_map(m, f.T_wc, intr)  # a loaded map's tensors need no gradient: no graph is kept
        alpha = out.alpha.detach().numpy()[v, u][inside]
        depth = out.median_depth.detach().numpy()[v, u][inside]
        total += int(inside.sum())
        holes += int((alpha < 0.5).sum())
        through += int(((alpha >= 0.5) & (depth > z[inside] + behind_m)).sum())
    return total, holes / max(total, 1), through / max(total, 1)


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments, print the table of missed fractions per part, optionally write it as JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("benches", nargs="+", type=Path, help="roigsf bench output folders (with runs/<policy>/seed<k>/)")
    ap.add_argument("--scene", type=Path, required=True, help="the clutter scene's folder (mesh.ply, traj.txt, ...)")
    ap.add_argument("--samples", type=int, default=50_000, help="ground-truth samples (default 50000, the bench's)")
    ap.add_argument("--threshold", type=float, default=0.05, help="miss distance in metres (default 0.05)")
    ap.add_argument("--out", type=Path, help="also write the table as JSON here")
    ap.add_argument(
        "--render-check",
        action="store_true",
        help="also render each run's map.ply at every 3rd frame: of the pixels on a cabinet's inside, the fraction "
        "with alpha < 0.5 (what the unseen term counts) and the fraction seen through onto a farther surface",
    )
    args = ap.parse_args(argv)
    for bench in args.benches:
        if not (bench / "runs").is_dir():
            raise SystemExit(f"clutter_missed: error: {bench / 'runs'}: no such folder (is {bench} a roigsf bench?)")
    gt_path = args.scene / "mesh.ply"
    if not gt_path.is_file():
        raise SystemExit(f"clutter_missed: error: {gt_path}: no such file (--scene is a `roigsf scene synth` folder)")
    gt = o3d.io.read_triangle_mesh(str(gt_path))
    if len(gt.triangles) == 0:
        raise SystemExit(f"{gt_path}: no triangles")
    source = open_frames(args.scene)
    frames = list(source)
    poses = np.stack([f.T_wc for f in frames])
    samples: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def gt_samples(seed: int) -> tuple[np.ndarray, np.ndarray]:
        """The run of seed ``seed``'s recall samples [N, 3] (its seed, culled to the observed) and their parts."""
        if seed not in samples:
            pts = sample_surface(gt, args.samples, seed)
            pts = pts[gt_visible_mask(pts, gt, poses, source.intrinsics)]
            samples[seed] = pts, regions(pts)
        return samples[seed]

    pts, reg = gt_samples(0)
    counts = {r: int((reg == r).sum()) for r in REGIONS}
    print(f"ground-truth samples per part (seed 0): {counts}")
    print(f"{'policy':<64} {'all':>6} " + " ".join(f"{r:>15}" for r in REGIONS) + "   per seed (all)")
    table: dict[str, dict] = {}
    for bench in args.benches:
        for pol in sorted(p for p in (bench / "runs").iterdir() if p.is_dir()):
            per_seed = []
            for sd in sorted(p for p in pol.iterdir() if (p / "mesh.ply").is_file()):
                pts, reg = gt_samples(int(sd.name.removeprefix("seed")))
                m = missed(pts, sd / "mesh.ply", args.threshold)
                per_seed.append([float(m.mean())] + [float(m[reg == r].mean()) for r in REGIONS])
                if args.render_check:
                    if not (sd / "map.ply").is_file():
                        raise SystemExit(f"clutter_missed: error: {sd / 'map.ply'}: no such file (--render-check)")
                    n, holes, through = inside_pixels_seen_through(sd / "map.ply", frames, source.intrinsics)
                    per_seed[-1] += [holes, through]
                    print(f"  {pol.name}/{sd.name}: {n} pixels on cabinet insides, alpha < 0.5 {holes:.3f}, "
                          f"seen through {through:.3f}")  # fmt: skip
            if not per_seed:
                continue
            mean = np.mean(per_seed, axis=0)
            table[pol.name] = {"bench": str(bench), "all": mean[0], **dict(zip(REGIONS, mean[1:5], strict=True)),
                               "per_seed_all": [s[0] for s in per_seed]}  # fmt: skip
            if args.render_check:
                table[pol.name] |= {"inside_alpha_below_half": mean[5], "inside_seen_through": mean[6]}
            print(f"{pol.name:<64} {mean[0]:6.3f} " + " ".join(f"{v:15.3f}" for v in mean[1:5])
                  + "   " + ", ".join(f"{s[0]:.3f}" for s in per_seed))  # fmt: skip
    if args.out:
        write_json(args.out, {"samples": counts, "threshold_m": args.threshold, "policies": table})
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except InputError as e:  # a missing scene folder or a bad frame: one line naming it, not a traceback
        sys.exit(f"clutter_missed: error: {e}")
