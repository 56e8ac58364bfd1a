#!/usr/bin/env python3
r"""A pool bench whose NBV policy hands over to FisherRF's pick once the map holds H views (issue 10, forty-first
session; a diagnostic, not an option of the library).

In the thirty-sixth session's benches the variant V (``roi-gsurfisher:unseen_weight=1:unseen_source=carved``) leads
``fisherrf`` early and gains less from view 16 to 20; adding FisherRF's score to V's fused score
(``fisherrf_weight=1``) lost the early lead. This asks whether FisherRF's picks help late only: it runs ``roigsf bench``
with the arguments given after ``--`` and, for the run's duration, makes every NBV policy whose map already holds
``--after`` keyframes choose as mode ``fisherrf`` does (its own H_train from the keyframe poses, FisherRF's score),
so views ``after + 1`` onwards are FisherRF's picks given the policy's first ``after``. Run V alone in its bench, under
its own ``--out``: the results keep V's policy name. Writes ``--log`` (JSON: how many picks each mode made).

    .venv/bin/python scripts/late_handover.py --after 16 --log runs/s41/handover_shelf.json -- \
        --scene runs/shelf_dome_120 --setting pool --seeds 3 --overwrite --set densify_stride=2 \
        --pool-set n_views=20 --pool-set pool_stride=2 --pool-set initial_iters=60 --pool-set iters_per_view=20 \
        --pool-set mesh_samples=50000 --uncertainty-views 6 --uncertainty-maps 3 \
        --policies roi-gsurfisher:unseen_weight=1:unseen_source=carved --out runs/s41/bench_pool_shelf_handover16

The sixth room's run is the same with ``--scene runs/synth_room5_240`` (as ``SCALE=2 SCENES=room5 bash
scripts/figure_nbv_pool.sh`` renders it), ``--log runs/s41/handover_room5.json`` and ``--out
runs/s41/bench_pool_room5_240_handover16``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from roigsf_ros.cli import main as roigsf_main
from roigsf_ros.cli import wrapped_command_args
from roigsf_ros.core.fileio import write_json
from roigsf_ros.policies.stream import StreamNBVPolicy


def main(argv: list[str] | None = None) -> int:
    """Run the bench with the hand-over in place, then restore the policy's ``choose`` and write the pick log."""
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     usage="%(prog)s --after H --log JSON -- <roigsf bench arguments>")  # fmt: skip
    parser.add_argument("--after", required=True, type=int, help="keyframes in the map from which FisherRF picks")
    parser.add_argument("--log", required=True, type=Path, help="JSON file of the pick counts")
    args, bench_args = wrapped_command_args(parser, argv)
    if args.after < 1:
        parser.error(f"--after must be >= 1, got {args.after}")
    log: dict[str, Any] = {"after": args.after, "picks": {}}
    original = StreamNBVPolicy.choose

    def choose(self: StreamNBVPolicy, candidates: list, keyframe_map: Any, ahead: list | None = None) -> int:
        own = self.mode
        late = own is not None and len(keyframe_map.keyframe_poses) >= args.after
        if late:
            self.mode = "fisherrf"
        try:
            pick = original(self, candidates, keyframe_map, ahead)
        finally:
            self.mode = own
        key = "fisherrf" if late else str(own)
        log["picks"][key] = log["picks"].get(key, 0) + 1
        return pick

    StreamNBVPolicy.choose = choose  # type: ignore[method-assign]
    try:
        rc = roigsf_main(["bench", *bench_args])
    finally:
        StreamNBVPolicy.choose = original  # type: ignore[method-assign]
    if rc:
        return int(rc)  # the bench failed (it said why): no log that looks complete
    write_json(args.log, {"bench_args": bench_args, **log})
    print(f"late hand-over after {args.after} views: picks {log['picks']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
