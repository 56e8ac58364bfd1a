"""How small the spread of the close-front gain I_vis gets in real scoring calls (``NBVConfig.close_front_min_std``).

Records std(I_vis) over the scored candidates of every Eq. 15 fusion while ``roigsf bench`` runs the paper's method
and the F3 variant, pool and stream, one seed, on a scene (default: the shipped bag). A floor under z(I_vis)'s
divisor changes a score only where a spread falls below it; this says how far the real spreads lie above it.

    PYTHONPATH=. .venv/bin/python scripts/close_front_spread.py --out /tmp/cf_spread
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

import roigsf_ros.nbv.scorer as scorer_module
from roigsf_ros.cli import main as cli_main
from roigsf_ros.core.fileio import write_json
from roigsf_ros.data.bags import SAMPLE_BAG, sample_path
from roigsf_ros.nbv.config import NBVConfig

POLICIES = "roi-gsurfisher,roi-gsurfisher:unseen_weight=2:unseen_source=carved:unseen_measure=rays"
"""The paper's method and F3 (``config/recommended/planner.yaml``)."""


def main(argv: list[str] | None = None) -> int:
    """Run the two benches with the recording fusion; write and print the spreads (nothing when a bench fails)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path, default=None, help="bag or scene folder (default: the shipped bag)")
    parser.add_argument("--out", type=Path, required=True, help="folder for the two benches and spread.json")
    args = parser.parse_args(argv)
    scene = str(args.scene if args.scene is not None else sample_path(SAMPLE_BAG))
    stds: list[float] = []
    fuse = scorer_module.fuse_scores

    def recording(fisher: Any, close_front: Any, *rest: Any, **kw: Any) -> np.ndarray:
        stds.append(float(np.asarray(close_front, dtype=np.float64).std()))
        return fuse(fisher, close_front, *rest, **kw)

    common = ["--scene", scene, "--policies", POLICIES, "--seeds", "1", "--uncertainty-views", "0", "--overwrite",
              "--no-progress"]  # fmt: skip
    scorer_module.fuse_scores = recording  # type: ignore[assignment]
    try:
        rc = cli_main(["bench", *common, "--setting", "pool", "--pool-set", "n_views=12", "--pool-set",
                       "pool_stride=2", "--out", str(args.out / "pool")])  # fmt: skip
        n_pool = len(stds)
        if rc == 0:
            rc = cli_main(["bench", *common, "--setting", "stream", "--stride", "2", "--out", str(args.out / "stream")])
    finally:
        scorer_module.fuse_scores = fuse
    if rc != 0:  # the bench said why; no spread.json that reads like a result of runs that did not happen
        print(f"close_front_spread.py: error: a bench failed (exit {rc}); no {args.out / 'spread.json'} written",
              file=sys.stderr)  # fmt: skip
        return int(rc)
    s = np.asarray(stds)
    floor = NBVConfig().close_front_min_std
    result = {
        "scene": scene,
        "policies": POLICIES,
        "fusions": int(s.size),
        "pool_fusions": n_pool,
        "close_front_min_std": floor,
        "spread_zero": int((s == 0).sum()),
        "spread_below_floor_nonzero": int(((s > 0) & (s < floor)).sum()),
        "smallest_nonzero_spread": float(s[s > 0].min()) if (s > 0).any() else None,
        "median_spread": float(np.median(s)) if s.size else None,
        "spreads": stds,
    }
    write_json(args.out / "spread.json", result)
    print(json.dumps({k: v for k, v in result.items() if k != "spreads"}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
