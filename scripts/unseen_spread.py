#!/usr/bin/env python3
r"""How much the candidates' unseen term U differs at each scoring call of a bench run (issue 10, thirtieth session).

Eq. 15's terms and the unseen term are z-scored over the candidates, so a spread of U of a few pixels late in a run
weighs as much as one of a third of the image at the first pick. This runs ``roigsf bench`` with the arguments
given after ``--`` and records, at every scoring call that has an unseen term, the number of scored candidates, the
mean, std, min and max of their U, U of the fused score's pick, and whether the pick has the largest U. The bench
has no per-call hook, so the script wraps :meth:`NBVScorer.score` for the run's duration (results are unchanged).
With several seeds or policies the records follow the bench's run order, one per pick after the initial views of
each pool run; policies without an unseen term (``fisherrf``, ``random``) add none.

    .venv/bin/python scripts/unseen_spread.py --out runs/spread_room5.json -- --scene runs/synth_room5_240 \
        --setting pool --seeds 1 --overwrite --set densify_stride=2 --pool-set n_views=20 --pool-set pool_stride=2 \
        --pool-set initial_iters=60 --pool-set iters_per_view=20 --pool-set mesh_samples=50000 \
        --policies roi-gsurfisher:unseen_weight=1:unseen_source=carved --out runs/spread_room5_bench
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from roigsf_ros.cli import main as roigsf_main
from roigsf_ros.cli import wrapped_command_args
from roigsf_ros.core.fileio import write_json
from roigsf_ros.nbv import scorer as scorer_module


def record_calls(log: list[dict[str, Any]]) -> Any:
    """Wrap ``NBVScorer.score`` so that each result with an unseen term appends its U statistics to ``log``."""
    original = scorer_module.NBVScorer.score

    def score(self: scorer_module.NBVScorer, *args: Any, **kwargs: Any) -> scorer_module.NBVResult:
        result = original(self, *args, **kwargs)
        if result.unseen is not None and len(result.unseen):
            # the candidates the scorer z-scores: the unflagged ones, or all of them when every one is flagged
            ok = ~result.flagged if (~result.flagged).any() else np.ones(len(result.unseen), dtype=bool)
            u = result.unseen[ok]
            u_pick = float(result.unseen[result.best_index])
            log.append(
                {
                    "candidates": int(ok.sum()),
                    "u_mean": float(u.mean()),
                    "u_std": float(u.std()),
                    "u_min": float(u.min()),
                    "u_max": float(u.max()),
                    "u_of_pick": u_pick,
                    "pick_has_max_u": bool(u_pick == float(u.max())),
                }
            )
        return result

    scorer_module.NBVScorer.score = score  # type: ignore[method-assign]
    return original


def main(argv: list[str] | None = None) -> int:
    """Run the bench with the scorer wrapped, write the per-call records as JSON and print them as a table."""
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     usage="%(prog)s --out JSON -- <roigsf bench arguments>")  # fmt: skip
    parser.add_argument("--out", required=True, type=Path, help="JSON file of the per-call records")
    args, bench_args = wrapped_command_args(parser, argv)
    log: list[dict[str, Any]] = []
    original = record_calls(log)
    try:
        rc = roigsf_main(["bench", *bench_args])
    finally:
        scorer_module.NBVScorer.score = original  # type: ignore[method-assign]
    if rc:
        return int(rc)  # the bench failed (it said why): no records that look complete
    write_json(args.out, {"bench_args": bench_args, "calls": log})
    print("| call | candidates | U mean | U std | U min | U max | U of the pick | the pick has the largest U |")
    print("|---|---|---|---|---|---|---|---|")
    for i, c in enumerate(log):
        print(
            f"| {i} | {c['candidates']} | {c['u_mean']:.4f} | {c['u_std']:.4f} | {c['u_min']:.4f} | {c['u_max']:.4f} "
            f"| {c['u_of_pick']:.4f} | {'yes' if c['pick_has_max_u'] else 'no'} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
