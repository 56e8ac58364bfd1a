"""``roigsf bag``: Replica folders to ROS 2 bags (rosbag2, MCAP) and bag summaries."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from roigsf_ros.cli import (
    OVERWRITE_HELP,
    add_camera_options,
    camera_topics,
    check_out,
    image_size,
    realsense_hint,
    show_progress,
)
from roigsf_ros.core.errors import InputError
from roigsf_ros.data.bags import (
    AUTO,
    BAG_MARKS,
    DEFAULT_RATE_HZ,
    DEPTH_ENCODINGS,
    bag_info,
    bag_topic_types,
    write_bag,
)
from roigsf_ros.data.replica import ReplicaSequence, scene_gt_mesh
from roigsf_ros.data.robot_bag import (
    ROBOT_COLOR_FORMATS,
    ROBOT_DEPTH_TRANSPORTS,
    check_namespace,
    robot_node_parameters,
    write_robot_bag,
)
from roigsf_ros.data.sources import is_bag


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``bag from-replica``, ``bag to-robot`` and ``bag info``."""
    parser = sub.add_parser(
        "bag",
        help="make and inspect ROS 2 bags (rosbag2 MCAP)",
        description="Convert Replica folders to ROS 2 bags (rosbag2 folder, MCAP storage) and summarise bags.",
    )
    bag_sub = parser.add_subparsers(dest="bag_command", metavar="BAG_COMMAND", required=True)

    conv = bag_sub.add_parser(
        "from-replica",
        help="convert a Replica-layout folder to a rosbag2 MCAP bag",
        description="Convert a NICE-SLAM Replica folder (results/, traj.txt, cam_params.json) into a rosbag2 "
        "MCAP bag with /camera/color/image_raw, /camera/depth/image_raw, /camera/camera_info and "
        "/camera/pose, all four messages of a frame sharing one header stamp.",
    )
    conv.add_argument("dir", type=Path, metavar="DIR", help="Replica scene folder (or its results/ folder)")
    conv.add_argument("--out", type=Path, required=True, metavar="BAG", help="bag folder to create")
    conv.add_argument(
        "--cam",
        type=Path,
        metavar="CAM_JSON",
        help="camera parameters JSON, or a named camera (kinect-v1) (default: DIR/cam_params.json, else the parent "
        "folder's)",
    )
    conv.add_argument("--width", type=int, metavar="W", help="resize images to this width (alone: keeps the aspect)")
    conv.add_argument("--height", type=int, metavar="H", help="resize images to this height (alone: keeps the aspect)")
    conv.add_argument("--stride", type=int, default=1, metavar="S", help="keep every S-th frame (default 1)")
    conv.add_argument("--max-frames", type=int, metavar="N", help="write at most N frames (default all)")
    conv.add_argument(
        "--rate",
        type=float,
        default=DEFAULT_RATE_HZ,
        metavar="HZ",
        help=f"frame rate of the stamps, frames per second (default {DEFAULT_RATE_HZ:g})",
    )
    conv.add_argument(
        "--depth-encoding",
        choices=DEPTH_ENCODINGS,
        default="32FC1",
        help="depth as float32 metres (32FC1, default) or uint16 millimetres (16UC1)",
    )
    conv.add_argument(
        "--allow-partial",
        action="store_true",
        help="accept a traj.txt with more poses than frames on disk (a partial download)",
    )
    conv.add_argument("--no-mesh", action="store_true", help=_NO_MESH_HELP.format(what="the scene's", src="DIR"))
    conv.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP.format(what="bag", out="--out"))
    conv.add_argument("--no-progress", action="store_true", help="no progress bar (shown only on a terminal)")
    conv.set_defaults(func=_from_replica)

    robot = bag_sub.add_parser(
        "to-robot",
        help="rewrite a camera bag as a robot records it: pose on TF, compressed images, RealSense names",
        description="Rewrite a camera bag (one `bag from-replica` wrote, say) as a RealSense on a mobile robot records "
        "it, to try the robot settings without a robot: the pose on /tf through map -> odom -> base_link -> "
        "camera_link -> camera_color_optical_frame (static parts on /tf_static), colour as CompressedImage on "
        "NS/color/image_raw/compressed, depth a 16-bit PNG of millimetres on "
        "NS/aligned_depth_to_color/image_raw/compressedDepth, camera info on NS/color/camera_info.",
    )
    robot.add_argument(
        "src",
        type=Path,
        metavar="SRC",
        help="camera bag in this package's layout (`bag from-replica`), folder or .mcap",
    )
    robot.add_argument("--out", type=Path, required=True, metavar="BAG", help="bag folder to create")
    robot.add_argument("--namespace", default="/camera", metavar="NS", help="the camera's namespace (default /camera)")
    robot.add_argument(
        "--color-format", choices=ROBOT_COLOR_FORMATS, default="png", help="png (lossless, default) or jpeg"
    )
    robot.add_argument(
        "--depth-transport",
        choices=ROBOT_DEPTH_TRANSPORTS,
        default="compressedDepth",
        help="compressedDepth (default) or compressed",
    )
    robot.add_argument(
        "--tf-lag-ms",
        type=float,
        default=1.0,
        metavar="MS",
        help="record each frame's /tf this long after its images, as on a robot (default 1)",
    )
    robot.add_argument("--no-mesh", action="store_true", help=_NO_MESH_HELP.format(what="the bag's", src="SRC"))
    robot.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP.format(what="bag", out="--out"))
    robot.add_argument("--no-progress", action="store_true", help="no progress bar (shown only on a terminal)")
    robot.set_defaults(func=_to_robot)

    info = bag_sub.add_parser(
        "info",
        help="summarise a bag: topics, types, counts, duration, resolution",
        description="Summarise a rosbag2 bag folder or .mcap file: topics with types and message counts, "
        "duration, image resolution, depth encoding and the frames `roigsf map` reads with the same camera "
        "options (complete, posed, and decoded: frames that do not convert are counted as refused, with why).",
    )
    info.add_argument("bag", type=Path, metavar="BAG", help="rosbag2 folder or .mcap file")
    info.add_argument("--json", action="store_true", help="print the summary as JSON")
    info.add_argument(
        "--no-decode",
        action="store_true",
        help="count complete, posed frames without decoding their images (faster on a long bag; "
        "a frame that does not convert is then counted)",
    )
    add_camera_options(info)
    info.set_defaults(func=_info)


_NO_MESH_HELP = (
    "leave {what} ground-truth mesh out (default: its mesh.ply, or NAME_mesh.ply beside {src} NAME, is checked and "
    "copied into the bag folder as mesh.ply, where roigsf map, bench and demo find it; the bag's readers ignore it)"
)


def _source_mesh(folder: Path, no_mesh: bool) -> Path | None:
    """The ground-truth mesh to copy into a bag made from ``folder`` (:func:`scene_gt_mesh`), read and checked now, so
    that a broken one is refused naming it, not found broken later as the bag's ``mesh.ply``; None with ``--no-mesh``.
    """
    from roigsf_ros.data.scene import load_mesh  # open3d: only where a mesh is read

    mesh = None if no_mesh else scene_gt_mesh(folder)
    if mesh is not None:
        try:
            load_mesh(mesh)
        except InputError as exc:
            raise InputError(exc.where, f"{exc.problem} (the ground-truth mesh to copy into the bag; --no-mesh: "
                             "without it)") from None  # fmt: skip
    return mesh


def _print_mesh(mesh: Path | None, folder: Path, out: Path, no_mesh: bool) -> None:
    """Say which mesh went into the bag, or why none did: ``--no-mesh``, or none there to copy."""
    if mesh is not None:
        print(f"  with the ground-truth mesh {mesh} as {out / 'mesh.ply'} (--no-mesh: without)")
    elif no_mesh:
        print("  no ground-truth mesh: --no-mesh")
    else:
        print(f"  no ground-truth mesh: none in {folder} nor {folder.name}_mesh.ply beside it")


def _depth_scale_warning(seq: ReplicaSequence) -> str:
    """A warning when most of the first frame's depth lies outside the mapper's default depth range (a wrong depth
    scale: millimetres read as metres, a 'scale' of 1000 for Replica's 6553.5); "" otherwise.

    Why here: the bag is written as the camera file says, and every reader of it (map, demo, bench, the nodes) then
    masks those values and warns, but only after the conversion and a mapping run; this says it before the minutes
    of writing.
    """
    from roigsf_ros.mapping.mapper import MapperConfig  # torch: imported only when a conversion runs

    cfg = MapperConfig()
    if not len(seq):
        return ""
    first = seq.frame(0)
    depth_m = first.depth_m
    shown = depth_m[np.isfinite(depth_m) & (depth_m > 0)]  # holes (0, NaN) are a sensor's, not a scale's
    out = int(np.count_nonzero((shown < cfg.min_depth_m) | (shown > cfg.max_depth_m)))
    if out <= 0.5 * depth_m.size:
        return ""
    return (f"warning: {out / depth_m.size:.0%} of frame {first.index}'s depth values are outside "
            f"{cfg.min_depth_m:g}-{cfg.max_depth_m:g} m (the mapper's default min_depth_m..max_depth_m), read at depth "
            f"scale {seq.native.depth_scale:g} (cam_params.json's 'scale', or --cam's): a wrong depth scale? The bag "
            "is written as the camera file says, and every reader of it masks those values")  # fmt: skip


def _from_replica(args: argparse.Namespace) -> int:
    # Checked here, before any work, so that errors name the options typed (write_bag's are rate_hz, ...).
    if not (math.isfinite(args.rate) and args.rate > 0):
        raise InputError("--rate", f"must be a positive number of frames per second, got {args.rate:g}")
    if args.stride < 1:
        raise InputError("--stride", f"must be >= 1, got {args.stride}")
    if args.max_frames is not None and args.max_frames < 1:
        raise InputError("--max-frames", f"must be >= 1, got {args.max_frames}")
    size = image_size(args)
    check_out(args.out, args.overwrite, BAG_MARKS, "a bag", [args.dir])
    seq = ReplicaSequence(args.dir, cam=args.cam, size=size, allow_partial=args.allow_partial)
    mesh = _source_mesh(seq.root, args.no_mesh)
    warning = _depth_scale_warning(seq)
    if warning:
        print(warning, file=sys.stderr)
    n = write_bag(
        seq,
        args.out,
        rate_hz=args.rate,
        depth_encoding=args.depth_encoding,
        stride=args.stride,
        max_frames=args.max_frames,
        overwrite=args.overwrite,
        progress=show_progress(args),
        gt_mesh=mesh,
    )
    intr = seq.intrinsics
    print(f"wrote {n} frames ({intr.width}x{intr.height}, depth {args.depth_encoding}, {args.rate:g} Hz) to {args.out}")
    _print_mesh(mesh, seq.root, args.out, args.no_mesh)
    return 0


def _to_robot(args: argparse.Namespace) -> int:
    src = args.src
    if src.is_dir() and not is_bag(src) and ((src / "results").is_dir() or (src / "traj.txt").is_file()):
        raise InputError(src, "is a Replica scene folder, not a bag: make a camera bag of it with `roigsf bag "
                         "from-replica`, then rewrite that bag (to-robot reads a camera bag)")  # fmt: skip
    if not (math.isfinite(args.tf_lag_ms) and args.tf_lag_ms >= 0):
        raise InputError("--tf-lag-ms", f"must be a number of milliseconds >= 0, got {args.tf_lag_ms:g}")
    if args.out.resolve() == args.src.resolve():  # before check_out: --overwrite would let it replace the source
        raise InputError("--out", f"{args.out} is the bag being rewritten: write the robot's bag elsewhere")
    try:
        check_namespace(args.namespace)
    except InputError as exc:
        raise InputError("--namespace", exc.problem) from None
    check_out(args.out, args.overwrite, BAG_MARKS, "a bag", [args.src])
    src_folder = args.src if args.src.is_dir() else args.src.parent
    mesh = _source_mesh(src_folder, args.no_mesh)
    try:
        n = write_robot_bag(
            args.src,
            args.out,
            namespace=args.namespace,
            color_format=args.color_format,
            depth_transport=args.depth_transport,
            tf_lag_s=args.tf_lag_ms * 1e-3,
            overwrite=args.overwrite,
            progress=show_progress(args),
            gt_mesh=mesh,
        )
    except InputError as exc:  # a robot's bag given: it needs no rewriting, only --realsense to be read
        try:
            present = bag_topic_types(args.src)
        except (InputError, OSError):
            raise exc from None
        hint = realsense_hint(args.src, present, None, command=f"roigsf map {args.src}")
        if not hint:
            raise
        why = "to-robot rewrites a bag of this package's layout (`roigsf bag from-replica`), and this one is already"
        raise InputError(exc.where, f"{exc.problem}; {why} a robot's, to be read as it is{hint}") from None
    ns = "/" + args.namespace.strip("/") if args.namespace.strip("/") else "/"
    params = " ".join(f"-p {k}:={v}" for k, v in robot_node_parameters(args.namespace, args.depth_transport).items())
    print(f"wrote {n} frames to {args.out}; read it with `roigsf map {args.out} --realsense {ns}`, or give the "
          f"nodes: {params}")  # fmt: skip
    _print_mesh(mesh, src_folder, args.out, args.no_mesh)
    return 0


def format_info(info: dict[str, Any]) -> str:
    """A readable multi-line summary of :func:`roigsf_ros.data.bags.bag_info`'s dictionary."""
    lines = [f"bag:          {info['path']}"]
    if info["start_ns"] is not None:
        lines.append(
            f"duration:     {info['duration_s']:.3f} s "
            f"(logged {info['start_ns'] / 1e9:.3f} .. {info['end_ns'] / 1e9:.3f} s)"
        )
    else:
        lines.append("duration:     empty bag")
    if info["width"] is not None:
        lines.append(
            f"images:       {info['width']}x{info['height']}, colour {info['color_encoding'] or 'no message'}, "
            f"depth {info['depth_encoding'] or 'no message'}, pose from {info['pose_source']}"
        )
    no_tf, refused = info.get("frames_without_tf"), info.get("frames_refused")
    read = "complete" if no_tf is None else "complete and posed by TF"
    line = f"frames:       {info['frame_count']} {read}"
    line += "" if no_tf is None else f", {no_tf} complete without a TF pose"
    line += " (not decoded)" if refused is None else f", {refused} refused"
    lines.append(f"{line}, {info['incomplete_stamps']} incomplete stamps")
    if no_tf:
        lines.append(f"no TF pose:   {info['no_tf_reason']}")
    if info.get("tf_reparented"):
        lines.append(f"TF warning:   {info['tf_reparent_note']} ({info['tf_reparented']} change(s) of parent)")
    if info.get("tf_child_frame_note"):
        lines.append(f"TF warning:   {info['tf_child_frame_note']}")
    if refused:
        lines.append(f"refused:      {info['refused_reason']}")
    if info.get("frames_repeating_stamp"):
        lines.append(
            f"repeated:     {info['frames_repeating_stamp']} more frame(s) with an earlier frame's header stamp, not "
            "counted above (roigsf map and the nodes read one frame a stamp)"
        )
    if info.get("frames_other_size"):
        lines.append(
            f"other size:   {info['frames_other_size']} more frame(s) not at the first frame's image size (first: "
            f"{info['first_other_size']}), not counted above (roigsf map and the nodes refuse them)"
        )
    if info.get("frames_stamped_back"):
        lines.append(
            f"stamps back:  {info['frames_stamped_back']} frame(s) stamped before the frame before them (first: "
            f"{info['first_stamped_back']}): roigsf map maps them in the bag's order with ids in stamp order; the "
            "nodes drop a frame stamped before one they delivered, unless the next frame stays back too (read as "
            "a restarted stream)"
        )
    mesh = info["gt_mesh"] or "none (no mesh.ply in the bag folder nor NAME_mesh.ply beside it: no mesh metrics)"
    lines.append(f"ground truth: {mesh}")
    for problem in info.get("missing_topics") or []:
        lines.append(f"missing:      {problem}")
    if info.get("hint"):
        lines.append(f"hint:         {info['hint']}")
    lines.append(f"messages:     {info['message_count']}")
    width = max([len(t) for t in info["topics"]] + [5])
    lines.append("topics:")
    for topic, entry in sorted(info["topics"].items()):
        lines.append(f"  {topic:<{width}}  {entry['type']:<32}  {entry['count']:>7}")
    return "\n".join(lines)


def _info(args: argparse.Namespace) -> int:
    info = bag_info(args.bag, camera_topics(args), decode=not args.no_decode)
    hint = _hint(args, info)
    if hint is not None:  # in --json too: a field only when there is a hint
        info["hint"] = hint
    print(json.dumps(info, indent=2) if args.json else format_info(info))
    return 0


def _hint(args: argparse.Namespace, info: dict[str, Any]) -> str | None:
    """The options that read a bag whose camera topics are not the ones asked for, when it holds a RealSense's."""
    ns = info.get("realsense_namespace")
    if ns is None:
        return None
    typed_other = args.realsense is not None and args.realsense.strip("/") != ns.strip("/")  # another namespace typed
    option = "--realsense" if ns == "/camera" and not typed_other else f"--realsense {ns}"
    named = [o for o in ("color_transport", "depth_transport") if getattr(args, o) not in (None, AUTO)]
    named += [o for o in ("color_topic", "depth_topic", "camera_info_topic") if getattr(args, o) is not None]
    drop = f" without {', '.join('--' + o.replace('_', '-') for o in named)}" if named else ""
    return f"the bag holds a RealSense camera under {ns}: try {option}{drop}"
