#!/usr/bin/env python3
"""Where the unseen term's back-face test fires on a map: at the true surface, or behind it (issue 10).

``unseen_backfaces=surfels`` counts a pixel as unseen when most of its alpha comes from surfels that face away from
the camera. That is right where the surface in front of them is unmapped (the map renders opaque *behind* the true
surface: a cabinet's inside, seen through onto the back of its far wall), and wrong where those surfels *are* the
true surface, seen from their other side: a shell thinner than the mapper's ``densify_depth_margin_m`` (a 1 cm
bowl) is mapped by its outside's surfels alone, and from inside the test calls it unseen however often a keyframe
saw it. For each run's map (``runs/<policy>/seed<k>/`` of each bench folder given) this renders every ``--every``-th
frame of the scene, splits the back pixels by the scene's depth into "at the surface" (within ``--margin``) and
"behind it", and reports the share of each that ``unseen_backfaces=unconfirmed`` spares (a keyframe of that run saw
the point from the same side, unoccluded). Prints a table (means over the seeds) and, with ``--out``, writes JSON.

    .venv/bin/python scripts/backface_split.py --scene runs/synth_room1_240 runs/bench_pool_room1_240_unconfirmed
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import write_json
from roigsf_ros.data.sources import open_frames
from roigsf_ros.mapping.mapper import Mapper
from roigsf_ros.nbv.unseen import KeyframeDepths, surfels_facing
from roigsf_ros.render.rasterize import render_map

COLUMNS = ("back", "at_surface", "behind", "spared_at_surface", "spared_behind")
"""Per run: back pixels per frame pixel; of them, the shares at the true surface and behind it; of each, the share
``unconfirmed`` spares."""


def split_run(run: Path, frames: list, every: int, margin_m: float, near_m: float = 0.2) -> dict[str, float]:
    """The :data:`COLUMNS` of the map saved in ``run`` (a mapper folder) over every ``every``-th of ``frames``."""
    import torch  # here, after roigsf_ros: it sets torch's OpenMP wait policy before torch loads

    mapper = Mapper.load(run)
    m = mapper.map.detach()
    intr = mapper.intr
    seen_by = KeyframeDepths.render(m, mapper.loaded_keyframe_poses, intr, margin_m, near_m, 100.0)
    n = {"px": 0, "back": 0, "at": 0, "behind": 0, "spared_at": 0, "spared_behind": 0}
    for f in frames[::every]:
        gt = np.asarray(f.depth_m, dtype=np.float64)
        if gt.shape != (intr.height, intr.width):
            raise InputError(
                run, f"map made at {intr.width}x{intr.height}, scene frames are {gt.shape[1]}x{gt.shape[0]}"
            )
        feats = surfels_facing(m, f.T_wc)[:, None].to(m.dtype)
        with torch.no_grad():
            out = render_map(m, f.T_wc, intr, features=feats, near=near_m, far=100.0, with_distortion=False)
        alpha = out.alpha.cpu().numpy()
        back = (alpha >= 0.5) & (out.features[..., 0].cpu().numpy() < 0.5 * alpha)
        depth = out.median_depth.cpu().numpy()
        spared = seen_by.confirmed(f.T_wc, depth, out.normal.cpu().numpy(), back)
        at = back & (gt > 0) & (np.abs(depth - gt) <= margin_m)
        behind = back & (gt > 0) & (depth > gt + margin_m)
        n["px"] += alpha.size
        n["back"] += int(back.sum())
        n["at"], n["behind"] = n["at"] + int(at.sum()), n["behind"] + int(behind.sum())
        n["spared_at"] += int((at & spared).sum())
        n["spared_behind"] += int((behind & spared).sum())
    return {
        "back": n["back"] / max(n["px"], 1),
        "at_surface": n["at"] / max(n["back"], 1),
        "behind": n["behind"] / max(n["back"], 1),
        "spared_at_surface": n["spared_at"] / max(n["at"], 1),
        "spared_behind": n["spared_behind"] / max(n["behind"], 1),
    }


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments, print the table, optionally write it as JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("benches", nargs="+", type=Path, help="roigsf bench output folders (with runs/<policy>/seed<k>/)")
    ap.add_argument("--scene", type=Path, required=True, help="the scene's folder (its frames' depth is the truth)")
    ap.add_argument("--every", type=int, default=3, help="render every this-many-th frame (default 3)")
    ap.add_argument("--margin", type=float, default=0.05, help="'at the surface' and the keyframe test (m, 0.05)")
    ap.add_argument("--out", type=Path, help="also write the table as JSON here")
    args = ap.parse_args(argv)
    if args.every < 1 or not args.margin > 0:
        raise SystemExit("backface_split: error: --every must be >= 1 and --margin > 0")
    for bench in args.benches:
        if not (bench / "runs").is_dir():
            raise SystemExit(f"backface_split: error: {bench / 'runs'}: no such folder (is {bench} a roigsf bench?)")
    frames = list(open_frames(args.scene))
    print(f"{'policy':<64} " + " ".join(f"{c:>17}" for c in COLUMNS))
    table: dict[str, dict] = {}
    for bench in args.benches:
        for pol in sorted(p for p in (bench / "runs").iterdir() if p.is_dir()):
            seeds = sorted(p for p in pol.iterdir() if (p / "map.ply").is_file())
            if not seeds:
                continue
            rows = [split_run(sd, frames, args.every, args.margin) for sd in seeds]
            mean = {c: float(np.mean([r[c] for r in rows])) for c in COLUMNS}
            table[pol.name] = {"bench": str(bench), **mean, "seeds": [sd.name for sd in seeds]}
            print(f"{pol.name:<64} " + " ".join(f"{mean[c]:17.4f}" for c in COLUMNS))
    if args.out:
        write_json(args.out, {"scene": str(args.scene), "every": args.every, "margin_m": args.margin,
                              "policies": table})  # fmt: skip
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except InputError as e:  # a missing scene folder, a bad frame or a map of another size: one line naming it
        sys.exit(f"backface_split: error: {e}")
