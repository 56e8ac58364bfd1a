"""``roigsf map``: map a bag or Replica-layout folder offline with a keyframe policy; metrics, mesh, map."""

from __future__ import annotations

import argparse
import difflib
import logging
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

from roigsf_ros.cli import (
    OVERWRITE_HELP,
    add_camera_options,
    camera_topics,
    check_camera_options_for,
    check_out,
    chosen_gt_mesh,
    command_line,
    image_size,
    metric_notes,
    show_progress,
    with_bag_hint,
)
from roigsf_ros.core.errors import InputError
from roigsf_ros.data.bags import CameraTopics
from roigsf_ros.data.sources import FrameSource, is_bag, open_frames
from roigsf_ros.experiments.offline import EvalConfig, run_offline
from roigsf_ros.mapping.mapper import MapperConfig
from roigsf_ros.policies.base import KeyframePolicy, make_policy, parse_params, policy_names, policy_parameters

_SUMMARY_KEYS = (
    ("frames", "n_frames", "{:d}"),
    ("keyframes", "n_keyframes", "{:d}"),
    ("surfels", "map_size", "{:d}"),
    ("evaluated frames", "n_eval_frames", "{:d}"),
    ("PSNR (dB)", "psnr", "{:.2f}"),
    ("SSIM", "ssim", "{:.3f}"),
    ("depth L1 (cm)", "depth_l1_cm", "{:.2f}"),
    ("test-scene frames", "test_scene_frames", "{:d}"),
    ("test-scene PSNR (dB)", "test_scene_psnr", "{:.2f}"),
    ("test-scene depth L1 (cm)", "test_scene_depth_l1_cm", "{:.2f}"),
    ("test-scene hole error", "test_scene_uncovered_error_share", "{:.3f}"),
    ("precision @1cm", "precision@1cm", "{:.3f}"),
    ("recall @1cm", "recall@1cm", "{:.3f}"),
    ("precision @5cm", "precision@5cm", "{:.3f}"),
    ("recall @5cm", "recall@5cm", "{:.3f}"),
    ("F-score @5cm", "fscore@5cm", "{:.3f}"),
    ("accuracy (cm)", "accuracy_cm", "{:.2f}"),
    ("completion (cm)", "completion_cm", "{:.2f}"),
    ("completion ratio <5cm", "completion_ratio_5cm", "{:.3f}"),
    ("wall time (s)", "wall_s", "{:.1f}"),
)


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``map`` subcommand."""
    p = sub.add_parser(
        "map",
        help="map a bag or scene folder offline: metrics.json, mesh.ply, map.ply, strip.png",
        description=__doc__,
    )
    p.add_argument("source", metavar="BAG_OR_DIR", help="rosbag2 bag (folder or .mcap) or Replica-layout folder")
    p.add_argument(
        "--policy",
        default="gaus-slam",
        metavar="NAME[:KEY=VALUE...]",
        help=f"keyframe policy: {', '.join(policy_names())}; its parameters as in roigsf bench --policies, e.g. "
        "every-n:every_n=4 or roi-gsurfisher:window=13:unseen_weight=1",
    )
    p.add_argument("--out", required=True, type=Path, help="run folder to write (atomically)")
    p.add_argument(
        "--gt-mesh",
        metavar="PLY",
        help="ground-truth mesh (default: the source's own: mesh.ply in the scene or bag folder, else NAME_mesh.ply "
        "beside the folder NAME, as Replica's office0_mesh.ply beside office0/; '' for none: no mesh metrics)",
    )
    p.add_argument("--width", type=int, help="resize frames to this width (alone: the height keeps the aspect ratio)")
    p.add_argument("--height", type=int, help="resize frames to this height (alone: the width keeps the aspect ratio)")
    p.add_argument("--stride", type=int, default=1, help="use every S-th frame")
    p.add_argument("--max-frames", type=int, help="stop after N frames (after the stride)")
    p.add_argument("--allow-partial", action="store_true", help="accept a traj.txt with more poses than frames")
    p.add_argument(
        "--cam",
        type=Path,
        metavar="CAM_JSON",
        help="a Replica folder's camera parameters JSON, or a named camera (kinect-v1) (default: its cam_params.json, "
        "else the parent folder's), for a folder given to --eval-against and --test-scene too; a bag's camera is its "
        "camera_info",
    )
    p.add_argument("--iters-per-keyframe", type=int, help="optimiser steps per keyframe")
    p.add_argument("--final-iters", type=int, help="global refinement steps at the end")
    p.add_argument("--every-n", type=int, help="N of the every-n policy")
    p.add_argument("--tau-k", type=float, help="unmapped-pixel fraction of the gaus-slam policy")
    p.add_argument("--window", type=int, help="candidate window (frames) of the stream NBV policies (default 8)")
    p.add_argument("--eval-every", type=int, default=1, help="evaluate every K-th non-keyframe")
    p.add_argument(
        "--eval-against",
        metavar="BAG_OR_DIR",
        help="image metrics against these frames (same sequence, read with the same size and stride) instead of "
        "the mapped ones: e.g. the noise-free render of a 'scene render --sensor' sequence",
    )
    p.add_argument(
        "--test-scene",
        metavar="BAG_OR_DIR",
        help="also evaluate the final map on these frames, which the policy never sees (same camera, read at the same "
        "size; e.g. `roigsf scene render --offset`: poses between the mapped ones)",
    )
    p.add_argument("--no-h-train", action="store_true", help="do not track the training Fisher (faster)")
    p.add_argument("--seed", type=int, default=0, help="seed of the mapper")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP.format(what="map run", out="--out"))
    p.add_argument("--no-progress", action="store_true", help="no progress bar (shown only on a terminal)")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override any MapperConfig field, e.g. --set lr_means=1e-4 (repeatable; a list value comma-separated, "
        "e.g. --set fisher_params=means,quats)",
    )
    add_camera_options(p)
    p.set_defaults(func=run)


LIST_SEPARATOR = ","
"""What separates the items of a list value in ``--set``/``--pool-set``/``--sensor-set`` (``+`` does so only inside a
``roigsf bench --policies`` spec, where ``,`` already separates the policies)."""


def parse_set_value(name: str, text: str, default: object, flag: str = "--set") -> object:
    """A config value of ``default``'s type from the command line option ``flag``; a list's items comma-separated."""
    if isinstance(default, tuple):
        items = [v.strip() for v in text.split(LIST_SEPARATOR) if v.strip()]
        if default and isinstance(default[0], int | float) and not isinstance(default[0], bool):
            kind = type(default[0])
            bad = [v for v in items if not _parses(kind, v)]
            if bad and "+" not in text:  # commas already: an item is no number (the hint would repeat the input)
                raise InputError(f"{flag} {name}", f"cannot parse {bad[0]!r} of {text!r} as {kind.__name__}")
            if bad:
                raise InputError(f"{flag} {name}", _list_problem(text, "numbers"))
            return tuple(kind(v) for v in items)
        if "+" in text and LIST_SEPARATOR not in text:  # a policy spec's list syntax: one name that matches nothing
            raise InputError(f"{flag} {name}", _list_problem(text, "a list"))
        return tuple(items)
    try:
        if isinstance(default, bool):
            if text.lower() not in ("1", "0", "true", "false", "yes", "no"):
                raise ValueError(text)
            return text.lower() in ("1", "true", "yes")
        return type(default)(text)
    except ValueError:
        raise InputError(f"{flag} {name}", f"cannot parse {text!r} as {type(default).__name__}") from None


def _parses(kind: type, text: str) -> bool:
    """Whether ``kind(text)`` is a value (int or float from a command line item)."""
    try:
        kind(text)
    except ValueError:
        return False
    return True


def _list_problem(text: str, what: str) -> str:
    """Why ``text`` is no list value of ``what``, naming the separator to use (with ``text`` rewritten in it)."""
    example = LIST_SEPARATOR.join(
        v.strip() for v in text.replace("+", LIST_SEPARATOR).split(LIST_SEPARATOR) if v.strip()
    )
    return f"cannot parse {text!r} as {what}: separate the items with commas, e.g. {example}"


def parse_overrides(
    items: list[str], defaults: dict[str, Any], flag: str, skip: tuple[str, ...] = ()
) -> dict[str, Any]:
    """{name: value} from NAME=VALUE items of option ``flag``, typed like ``defaults`` (:func:`parse_set_value`).

    A name not in ``defaults``, or in ``skip`` (set by an option of its own), is an InputError listing the names it
    takes (after the closest ones, if any): the one check of ``roigsf map --set`` and ``roigsf bench --set``/
    ``--pool-set``.
    """
    names = sorted(n for n in defaults if n not in skip)
    out: dict[str, Any] = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep:
            raise InputError(f"{flag} {item}", f"expected NAME=VALUE; NAME is one of {', '.join(names)}")
        if name not in names:  # the form was right: the name is what is wrong
            close = difflib.get_close_matches(name, names, n=3)
            hint = f" (did you mean {' or '.join(close)}?)" if close else ""
            raise InputError(f"{flag} {item}", f"unknown name '{name}'{hint}; NAME is one of {', '.join(names)}")
        out[name] = parse_set_value(name, text.strip(), defaults[name], flag)
    return out


_POLICY_OPTIONS = {"n": "--every-n", "tau_k": "--tau-k", "window": "--window"}
"""The ``roigsf map`` option of each policy parameter it passes."""


def config_from_args(args: argparse.Namespace) -> MapperConfig:
    """The MapperConfig of the command line (defaults, then named options, then ``--set``)."""
    cfg = MapperConfig(seed=args.seed, track_h_train=not args.no_h_train)
    if args.iters_per_keyframe is not None:
        cfg = replace(cfg, iters_per_keyframe=args.iters_per_keyframe)
    if args.final_iters is not None:
        cfg = replace(cfg, final_iters=args.final_iters)
    defaults = {f.name: getattr(cfg, f.name) for f in fields(MapperConfig)}
    for item in args.set:  # a policy parameter is no MapperConfig field: name its own option
        name = item.partition("=")[0].strip()
        if name in _POLICY_OPTIONS:
            raise InputError(
                f"--set {item}", f"{name} is a policy parameter, not a MapperConfig field: use {_POLICY_OPTIONS[name]}"
            )
    return replace(cfg, **parse_overrides(args.set, defaults, "--set")).validate()


def policy_from_args(args: argparse.Namespace) -> KeyframePolicy:
    """The keyframe policy of the command line: ``--policy NAME[:KEY=VALUE...]`` (the spec of ``roigsf bench
    --policies``) and the options ``--every-n``, ``--tau-k``, ``--window``; an error names the option typed.
    """
    name, *pairs = [p.strip() for p in args.policy.split(":")]
    spec = parse_params(pairs, f"--policy {args.policy}", "expected NAME:KEY=VALUE...")
    typed = {"n": args.every_n, "tau_k": args.tau_k, "window": args.window}
    options = {k: v for k, v in typed.items() if v is not None}
    if name in policy_names():  # an option the policy does not take: name the option, not the constructor's name
        takes = policy_parameters(name)
        for key in options:
            if key not in takes:
                its = f" (it takes {', '.join(takes) or 'none'})" if len(takes) <= 6 else ""
                raise InputError(_POLICY_OPTIONS[key], f"policy {name} takes no {key}{its}")
            if key in spec:
                raise InputError(_POLICY_OPTIONS[key], f"{key} is given in --policy {args.policy} too")
    try:
        return make_policy(name, **spec, **options)
    except InputError as exc:
        where = exc.where
        if where == f"policy {name!r}":
            where = f"--policy {args.policy}"
        elif where in options:  # the option typed, not the --policy spec's key of the same name
            where = _POLICY_OPTIONS[where]
        elif where in spec:
            where = f"--policy {args.policy}: {where}"
        raise InputError(where, exc.problem) from None


def run(args: argparse.Namespace) -> int:
    """Run the offline mapping loop and print a summary table."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    size = image_size(args)
    topics = camera_topics(args)
    policy = policy_from_args(args)
    cfg = config_from_args(args)
    if args.gt_mesh and not Path(args.gt_mesh).is_file():  # now, before the sources are read
        raise InputError(args.gt_mesh, "ground-truth mesh not found (--gt-mesh)")
    for path, option in (
        (args.source, ""),
        (args.eval_against, " (--eval-against)"),
        (args.test_scene, " (--test-scene)"),
    ):
        if path is not None and not Path(path).exists():  # said as such, not as an --out already there
            raise InputError(path, f"no such bag or scene folder{option}")
    check_camera_options_for(args, args.source)
    check_out(args.out, args.overwrite, ("metrics.json",), "a map's output",
              [args.source, args.gt_mesh, args.test_scene])  # fmt: skip
    source = _open(args, args.source, topics, size=size, stride=args.stride, max_frames=args.max_frames,
                   allow_partial=args.allow_partial)  # fmt: skip
    eval_source = None
    if args.eval_against is not None:
        eval_source = _open(args, args.eval_against, topics, size=size, stride=args.stride, max_frames=args.max_frames,
                            allow_partial=args.allow_partial, option="--eval-against")  # fmt: skip
    test_source = None
    if args.test_scene is not None:
        test_source = _open(args, args.test_scene, topics, size=size, allow_partial=args.allow_partial,
                            option="--test-scene")  # fmt: skip
    gt_mesh, no_mesh = chosen_gt_mesh(args.gt_mesh, source.gt_mesh_path)
    metrics = run_offline(
        source,
        policy,
        cfg,
        args.out,
        gt_mesh=gt_mesh,
        eval_config=EvalConfig(eval_every=args.eval_every),
        progress=show_progress(args),
        overwrite=args.overwrite,
        eval_source=eval_source,
        test_source=test_source,
        no_gt_mesh_reason=no_mesh,
        command=command_line("map"),
    )
    print(f"\nroigsf map: policy {args.policy} on {args.source} -> {args.out}")
    if eval_source is not None:
        print(f"  (PSNR, SSIM, depth L1 against {args.eval_against})")
    print_summary(metrics)
    print(f"  mesh metrics against {gt_mesh}" if gt_mesh is not None else f"  no mesh metrics ({no_mesh})")
    return 0


def _open(
    args: argparse.Namespace, path: str | Path, topics: CameraTopics, option: str = "", **kwargs: Any
) -> FrameSource:
    """:func:`open_frames` of ``path``; a bag it reads no frame of gets the RealSense hint (:func:`with_bag_hint`).

    ``option``: the option that named ``path`` when it is not the source (``--test-scene``): a bag's error there says
    that the source's camera options apply to it too, so a camera bag beside a robot's is read with the robot's.
    """
    # --cam: every folder's camera. A bag carries its camera_info: open_frames refuses --cam for the source bag, and
    # a bag beside a folder source (--test-scene, --eval-against) reads its own, as the bench does.
    cam = None if option and is_bag(path) else args.cam
    try:
        return open_frames(path, topics=topics, cam=cam, **kwargs)
    except InputError as exc:
        if option and is_bag(path):  # not the source's hint: dropping or adding --realsense would break the source
            raise InputError(exc.where, f"{exc.problem} ({option} is read with the source's camera options, so both "
                             "bags must be of one layout: `roigsf bag to-robot` rewrites a camera bag as a robot's)"
                             ) from None  # fmt: skip
        raise (exc if args.cam is not None else with_bag_hint(exc, args, path)) from None  # --cam on a bag: no hint


_SKIPPED_KEYS = (
    ("skipped: no TF pose", "frames_skipped_no_tf", "frames_skipped_no_tf_reason"),
    ("skipped: incomplete", "frames_skipped_incomplete", None),
    ("skipped: refused", "frames_skipped_refused", "frames_skipped_refused_reason"),
    ("skipped: bad pose", "frames_skipped_bad_pose", None),
    ("skipped: repeated stamp", "frames_skipped_repeated_stamp", None),
    ("stamps gone back", "frames_stamped_back", None),
)
"""Summary lines printed only when frames were skipped: (label, count key, reason key)."""


def print_summary(metrics: dict) -> None:
    """The short table of a run's metrics (frames, keyframes, PSNR, mesh precision/recall, wall time).

    Frames skipped (no pose on TF, incomplete, refused, bad pose, a repeated stamp) get a line each, with the reason, so
    a run that mapped fewer frames than the source holds says why; so do frames whose stamps went back.
    """
    for label, key, fmt in _SUMMARY_KEYS:
        value = metrics.get(key)
        if value is not None:
            print(f"  {label:<24} {fmt.format(value)}")
        if key == "n_frames":
            for skip_label, skip_key, reason_key in _SKIPPED_KEYS:
                if metrics.get(skip_key):
                    reason = metrics.get(reason_key) if reason_key is not None else None
                    print(f"  {skip_label:<24} {metrics[skip_key]:d}" + (f" ({reason})" if reason else ""))
    for note in metric_notes(metrics):
        print(f"  {note}")
