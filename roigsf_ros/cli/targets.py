"""``roigsf targets``: is a policy measurably ahead? Issue 10's pool and stream targets from bench results.

Pool: ``roigsf targets runs/A#CANDIDATE --against runs/A#fisherrf --against runs/B#random`` (each ``FOLDER`` written by
``roigsf bench --out``, or its results.json; ``#LABEL`` picks a policy where the folder holds several). Stream: one
``--against``, the reference (``gaus-slam``); never the candidate itself. Prints a table of every check with its
margin, what was required and the slack (pool: then with how many views the candidate first reaches each baseline's
final mean, from the runs' curves), and with ``--out`` writes the verdict as JSON. The setting is the candidate bench's.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from roigsf_ros.cli import check_writable
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import check_replaceable_file, write_json
from roigsf_ros.experiments.targets import (
    POOL_PSNR_MARGIN_DB,
    STREAM_MAX_KEYFRAME_RATIO,
    STREAM_PSNR_MARGIN_DB,
    STREAM_RECALL_MARGIN,
    VERDICT_MARK,
    PolicyResults,
    check_margin,
    load_policy,
    pool_target,
    stream_target,
)


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``targets`` subcommand."""
    p = sub.add_parser("targets", help="check issue 10's pool / stream targets from bench results", description=__doc__)
    p.add_argument(
        "candidate",
        metavar="FOLDER[#LABEL]",
        help="the candidate policy's bench folder or its results.json (and label)",
    )
    p.add_argument(
        "--against",
        action="append",
        required=True,
        metavar="FOLDER[#LABEL]",
        help="a baseline (pool: repeat for each) or the reference (stream: exactly one)",
    )
    p.add_argument(
        "--psnr-margin-db",
        type=float,
        help=f"PSNR (dB) it may trail by, >= 0 (default pool {POOL_PSNR_MARGIN_DB}, stream {STREAM_PSNR_MARGIN_DB})",
    )
    p.add_argument(
        "--recall-margin",
        type=float,
        default=STREAM_RECALL_MARGIN,
        help=f"stream: R@5cm it may trail by, >= 0 (default {STREAM_RECALL_MARGIN})",
    )
    p.add_argument(
        "--max-keyframe-ratio",
        type=float,
        default=STREAM_MAX_KEYFRAME_RATIO,
        help=f"stream: its keyframes / the reference's at most, > 0 (default {STREAM_MAX_KEYFRAME_RATIO})",
    )
    p.add_argument(
        "--allow-config-difference",
        action="store_true",
        help="compare benches whose mapper or pool settings differ (they are listed in the verdict)",
    )
    p.add_argument("--out", type=Path, help="write the verdict here as JSON")
    p.add_argument("--fail-if-not-met", action="store_true", help="exit 1 when the target is not met")
    p.set_defaults(func=run)


def _same_policy(a: PolicyResults, b: PolicyResults) -> bool:
    """Whether two loaded specs are one policy of one bench (the folder however written, or its results.json)."""
    return a.label == b.label and a.source.resolve() == b.source.resolve()


def _check_margins(args: argparse.Namespace) -> None:
    """Refuse a nan, infinite or negative margin (a ratio also 0) before anything is read, naming the option: nan
    printed "at most nan%" and inf made every check "met".
    """
    options = (("--psnr-margin-db", args.psnr_margin_db, False), ("--recall-margin", args.recall_margin, False),
               ("--max-keyframe-ratio", args.max_keyframe_ratio, True))  # fmt: skip
    for option, value, positive in options:
        if value is not None:
            check_margin(value, option, positive)


def run(args: argparse.Namespace) -> int:
    """Load, compare, print; write JSON atomically."""
    _check_margins(args)
    if args.out is not None:
        check_writable(args.out, file=True)
        check_replaceable_file(args.out, VERDICT_MARK, "an earlier `roigsf targets` verdict")
    candidate = load_policy(args.candidate)
    others = [load_policy(spec) for spec in args.against]
    for i, (spec, other) in enumerate(zip(args.against, others, strict=True)):
        if _same_policy(candidate, other):
            raise InputError(
                f"--against {spec}",
                f"is the candidate itself ({candidate.label!r} of {candidate.source}): compare it with another policy",
            )
        if other.summary == candidate.summary:  # a copied bench: another folder, the same runs
            why = f"holds the results of the candidate ({candidate.label!r} of {candidate.source}) to the last digit"
            raise InputError(f"--against {spec}", f"{why}: a copy of the same runs? Compare it with another policy")
        twice = [s for s, o in zip(args.against[:i], others[:i], strict=True) if _same_policy(o, other)]
        if twice:
            raise InputError(f"--against {spec}", f"given twice (also as --against {twice[0]}): each baseline once")
    setting = candidate.bench["setting"]
    if setting == "pool":
        margin = POOL_PSNR_MARGIN_DB if args.psnr_margin_db is None else args.psnr_margin_db
        verdict = pool_target(
            candidate, others, psnr_margin_db=margin, allow_config_difference=args.allow_config_difference
        )
    else:
        if len(others) != 1:
            raise InputError("--against", f"the stream target compares with one reference, got {len(others)}")
        margin = STREAM_PSNR_MARGIN_DB if args.psnr_margin_db is None else args.psnr_margin_db
        verdict = stream_target(
            candidate,
            others[0],
            max_keyframe_ratio=args.max_keyframe_ratio,
            recall_margin=args.recall_margin,
            psnr_margin_db=margin,
            allow_config_difference=args.allow_config_difference,
        )
    sys.stdout.write(verdict.markdown())
    if args.out is not None:
        write_json(args.out, verdict.as_dict())
    return 1 if args.fail_if_not_met and not verdict.met else 0
