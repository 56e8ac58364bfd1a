"""Where the recommended variant's unseen phase goes: its parts timed one by one on ``roigsf perf nbv``'s room.

F3's unseen term (``RECOMMENDED_UNSEEN``) renders the map at every keyframe, carves the grid from those depths, then
marches each candidate's rays through it and tests them against the box. This times the four parts separately
(medians of 3 after one untimed call; 160x120, 20k surfels, 50 candidates, ``--keyframes`` of the perf room's poses)
and one render alone, and prints one JSON line (``--out`` also writes it).

    .venv/bin/python scripts/unseen_phase_parts.py [--keyframes 64] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's roigsf_ros

import roigsf_ros  # noqa: E402, F401  first: it sets OMP_WAIT_POLICY before torch loads
from roigsf_ros.core.fileio import atomic_path  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    """Time the unseen phase's parts; one JSON line."""
    import torch

    from roigsf_ros.mapping.observed_space import ObservedSpace
    from roigsf_ros.nbv import unseen
    from roigsf_ros.nbv.config import RECOMMENDED_UNSEEN, NBVConfig
    from roigsf_ros.nbv.scorer import NBVScorer
    from roigsf_ros.perf import nbv as perf
    from roigsf_ros.render.rasterize import render_map

    def median_s(fn: Callable[[], Any], repeats: int = 3) -> float:  # perf nbv's: one untimed call, then the median
        return perf._median_ms(fn, repeats) / 1e3

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--keyframes", type=int, default=64, help="keyframes rendered and carved (default 64)")
    parser.add_argument("--out", type=Path, help="also write the JSON here")
    args = parser.parse_args(argv)
    cfg = NBVConfig(**RECOMMENDED_UNSEEN)
    st = perf.build_state(20000, 160, 120, 50, 0.04, NBVScorer(cfg))
    poses = perf.keyframe_poses(st, args.keyframes)
    box = unseen.unseen_box(st.tsdf.surface_voxels(), cfg)
    m, intr = st.surfel_map, st.intr
    depth = unseen.carve_depths(m, poses, intr, cfg)
    space = ObservedSpace.carve(*box, cfg.unseen_voxel_m, poses, depth, intr, cfg.far_m)
    with torch.no_grad():
        one = median_s(lambda: render_map(m.detach(), poses[0], intr, near=cfg.near_m, far=cfg.far_m,
                                           with_distortion=False), 10)  # fmt: skip
    result = {
        "keyframes": args.keyframes,
        "candidates": len(st.candidates),
        "renders_s": median_s(lambda: unseen.carve_depths(m, poses, intr, cfg)),
        "carve_s": median_s(lambda: ObservedSpace.carve(*box, cfg.unseen_voxel_m, poses, depth, intr, cfg.far_m)),
        "ray_marches_s": median_s(lambda: [space.unseen_rays(T, intr, cfg.near_m, cfg.far_m) for T in st.candidates]),
        "box_tests_s": median_s(lambda: [unseen.rays_meet_box(T, intr, *box) for T in st.candidates]),
        "one_render_s": one,
    }
    line = json.dumps(result)
    print(line)
    if args.out:
        with atomic_path(args.out) as tmp:
            tmp.write_text(line + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
