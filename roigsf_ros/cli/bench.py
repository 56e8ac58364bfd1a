"""``roigsf bench``: run NBV / keyframe policies on identical inputs and seeds; tables and plots.

Stream setting: each policy maps the sequence in trajectory order (``roigsf map``'s loop). Pool
setting: FisherRF's "v20seq1" active reconstruction (:mod:`roigsf_ros.experiments.pool`). Writes
``runs/<policy>/seed<k>/``, ``results.json``, ``results.md``, ``quality_vs_views.png``,
``chosen_views.png`` and ``uncertainty_<policy>.png`` into ``--out``, all built in a hidden temporary folder
beside it (``.OUT.tmp-*``) that becomes ``--out`` once complete: an interrupted bench leaves no ``--out``, or with
``--overwrite`` the old one as it was. With ``--rescore-ause``, recompute the AUSE study of an existing ``--out`` from
its saved runs (no training) and rewrite its results, swapped in the same way (``--scene`` overrides the scene path
stored in results.json).
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import fields, replace
from pathlib import Path

from roigsf_ros.cli import (
    add_camera_options,
    camera_topics,
    check_camera_options_for,
    check_out,
    command_line,
    image_size,
    typed_camera_options,
    with_bag_hint,
)
from roigsf_ros.cli.map import parse_overrides
from roigsf_ros.core.errors import InputError
from roigsf_ros.experiments.bench import BENCH_OUTPUT, BenchConfig, parse_policies, rescore_ause, run_bench
from roigsf_ros.experiments.pool import PoolConfig
from roigsf_ros.mapping.mapper import MapperConfig


def _mesh_path(text: str) -> Path:
    """``--gt-mesh``'s path; ``''`` (no mesh, as ``roigsf map`` takes it) is refused: policies are compared on it."""
    if not text.strip():
        raise argparse.ArgumentTypeError("'' (no mesh) is not taken here: the benchmark compares the policies' meshes")
    return Path(text)


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``bench`` subcommand."""
    p = sub.add_parser("bench", help="benchmark keyframe / NBV policies (stream or pool setting)", description=__doc__)
    p.add_argument("--scene", type=Path, metavar="DIR_OR_BAG", help="scene folder or rosbag2 bag (required)")
    p.add_argument("--setting", choices=("stream", "pool"), help="stream (SLAM order) or pool (required)")
    p.add_argument(
        "--policies",
        help="comma-separated policies, each name[:key=value...] (a list value joined by +), e.g. "
        "gaus-slam,roi-gsurfisher:window=12 (required)",
    )
    p.add_argument(
        "--rescore-ause",
        action="store_true",
        help="recompute the AUSE study of the finished bench in --out from its saved maps (no training); "
        "rewrites results.json, results.md and the plots",
    )
    p.add_argument("--seeds", type=int, default=1, help="run seeds 0..N-1 (default 1)")
    p.add_argument("--gt-mesh", type=_mesh_path, help="ground-truth mesh (default: the source's own, as in roigsf map)")
    p.add_argument("--width", type=int, help="resize frames to this width (alone: the height keeps the aspect ratio)")
    p.add_argument("--height", type=int, help="resize frames to this height (alone: the width keeps the aspect ratio)")
    p.add_argument("--stride", type=int, default=1, help="use every S-th frame of the scene")
    p.add_argument("--max-frames", type=int, help="stop after N frames (after the stride)")
    p.add_argument("--allow-partial", action="store_true", help="accept a traj.txt with more poses than frames")
    p.add_argument("--cam", type=Path, metavar="CAM_JSON", help="a Replica folder's camera parameters JSON, or a named "
                   "camera (kinect-v1) (default: its cam_params.json, else the parent folder's), for a folder given to "
                   "--test-scene too")  # fmt: skip
    p.add_argument("--eval-every", type=int, default=1, help="stream: evaluate every K-th non-keyframe")
    p.add_argument("--test-scene", type=Path, metavar="DIR_OR_BAG",
                   help="stream: also evaluate every run on these frames, which no policy sees (the same camera; e.g. "
                   "`roigsf scene render --offset` poses between the scene's)")  # fmt: skip
    p.add_argument("--uncertainty-views", type=int, help="held-out views per run for AUSE (0: none; default 6, "
                   "with --rescore-ause: the bench's)")  # fmt: skip
    p.add_argument("--uncertainty-maps", type=int, help="of those, views drawn per policy (default 3)")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an earlier bench at --out (a folder with results.json; never another folder, nor one holding "
        "the scene): all of it, and only once the new bench is complete (until then, and if interrupted, the old one "
        "stays as it was)",
    )
    p.add_argument("--no-progress", action="store_true", help="no per-run progress lines")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override a MapperConfig field for every run, e.g. --set iters_per_keyframe=20 (repeatable; a list "
        "value comma-separated)",
    )
    p.add_argument(
        "--pool-set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override a PoolConfig field, e.g. --pool-set n_views=20 --pool-set pool_stride=2 (repeatable; a list "
        "value comma-separated, e.g. --pool-set mesh_checkpoints=4,8)",
    )
    add_camera_options(p)
    p.set_defaults(func=run)


def config_from_args(args: argparse.Namespace) -> BenchConfig:
    """The :class:`BenchConfig` of the command line (validated)."""
    policies = parse_policies(args.policies, args.setting)
    if args.setting == "stream" and args.pool_set:  # was ignored without a word
        raise InputError("--pool-set", "sets the pool setting: not used with --setting stream")
    mdefaults = {f.name: getattr(MapperConfig(), f.name) for f in fields(MapperConfig)}
    mapper = replace(MapperConfig(), **parse_overrides(args.set, mdefaults, "--set", skip=("seed",)))
    pdefaults = {f.name: getattr(PoolConfig(), f.name) for f in fields(PoolConfig)}
    overrides = parse_overrides(args.pool_set, pdefaults, "--pool-set", skip=("seed", "policy", "policy_params"))
    try:
        pool = replace(PoolConfig(), **overrides)
    except InputError as exc:  # said as the option that set it ("n_views: must be ..." named no option)
        raise InputError(f"--pool-set {exc.where}" if str(exc.where) in pdefaults else exc.where, exc.problem) from None
    return BenchConfig(
        scene=args.scene,
        setting=args.setting,
        policies=policies,
        seeds=args.seeds,
        gt_mesh=args.gt_mesh,
        size=image_size(args),
        stride=args.stride,
        max_frames=args.max_frames,
        mapper=mapper,
        pool=pool,
        eval_every=args.eval_every,
        test_scene=args.test_scene,
        uncertainty_views=6 if args.uncertainty_views is None else args.uncertainty_views,
        uncertainty_maps=3 if args.uncertainty_maps is None else args.uncertainty_maps,
        topics=camera_topics(args),
        cam=args.cam,
        allow_partial=args.allow_partial,
    ).validate()


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and print the results table."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.rescore_ause:
        given = [f for f, v in (("--setting", args.setting), ("--policies", args.policies)) if v is not None]
        given += typed_camera_options(args)
        given += [f for f, v in (("--cam", args.cam), ("--allow-partial", args.allow_partial)) if v]
        if given:
            raise InputError(" ".join(given), "not used with --rescore-ause (the bench's own are rescored)")
        rescore_ause(args.out, scene=args.scene, uncertainty_views=args.uncertainty_views,
                     uncertainty_maps=args.uncertainty_maps, progress=not args.no_progress)  # fmt: skip
        print((args.out / "results.md").read_text())
        return 0
    missing = [f for f, v in (("--scene", args.scene), ("--setting", args.setting), ("--policies", args.policies))
               if v is None]  # fmt: skip
    if missing:
        raise InputError(" ".join(missing), "required (unless --rescore-ause)")
    cfg = config_from_args(args)  # first: a missing scene is said as such, not as an --out already there
    check_camera_options_for(args, args.scene)
    out = BENCH_OUTPUT
    check_out(
        args.out, args.overwrite, out["marks"], out["what"], [args.scene, args.gt_mesh, args.test_scene], out["own"]
    )
    try:
        run_bench(cfg, args.out, overwrite=args.overwrite, progress=not args.no_progress, command=command_line("bench"))
    except InputError as exc:  # a bag read with the wrong camera options: the RealSense hint, as roigsf map gives
        scene = next((p for p in (args.scene, args.test_scene) if p is not None and str(exc.where) == str(p)), None)
        raise (with_bag_hint(exc, args, scene) if scene is not None else exc) from None
    print((args.out / "results.md").read_text())
    return 0
