"""``roigsf scene``: ground-truth RGB-D sequences in the Replica layout, ray-cast from meshes.

``scene render`` re-renders a mesh (e.g. Replica office0) along a ``traj.txt`` at any resolution;
``scene synth`` builds the procedural test room and a handheld-like loop and renders it. Both write
``results/``, ``traj.txt``, ``cam_params.json``, the ground-truth ``mesh.ply`` and ``render.json``
into a new folder, all or nothing. ``--sensor kinect`` passes the frames and poses through a
simulated Kinect v1 (:mod:`roigsf_ros.data.sensor`).
"""

from __future__ import annotations

import argparse
import difflib
import math
from pathlib import Path

from roigsf_ros.cli import OVERWRITE_HELP, check_out, image_size, show_progress
from roigsf_ros.cli.map import parse_set_value
from roigsf_ros.core.camera import MAX_IMAGE_SIDE, Intrinsics, derive_size
from roigsf_ros.core.errors import InputError
from roigsf_ros.data.replica import SCENE_MARKS, load_traj
from roigsf_ros.data.sensor import CAMERAS, SENSORS, SensorConfig, SensorModel, load_camera

SYNTH_WIDTH, SYNTH_HEIGHT = 320, 240
SYNTH_FOCAL_PER_WIDTH = 0.8
"""``scene synth`` camera: fx = fy = 0.8 * width (64 deg horizontal field of view, like a Kinect/TUM
RGB-D camera's fx = 525 at 640 px), principal point at the image centre."""


def synth_intrinsics(width: int, height: int) -> Intrinsics:
    """The ``scene synth`` pinhole camera for a ``width`` x ``height`` image (see SYNTH_FOCAL_PER_WIDTH)."""
    if width <= 0 or height <= 0:
        raise InputError("--width/--height", f"image size must be positive, got {width}x{height}")
    f = SYNTH_FOCAL_PER_WIDTH * width
    return Intrinsics(width=width, height=height, fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2)


def _check_texture(strength: float) -> None:
    """``--texture-strength`` must be finite and >= 0."""
    if not math.isfinite(strength) or strength < 0:
        raise InputError("--texture-strength", f"must be a finite number >= 0, got {strength}")


def _sensor(args: argparse.Namespace) -> SensorModel | None:
    """The ``--sensor`` model with its ``--sensor-seed`` and ``--sensor-set`` overrides (None: ideal frames)."""
    if args.sensor == "none":
        if args.sensor_set:
            raise InputError("--sensor-set", "needs --sensor (e.g. --sensor kinect)")
        return None
    defaults = SensorConfig().to_dict()
    overrides: dict[str, object] = {}
    for item in args.sensor_set:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or name not in defaults:
            close = difflib.get_close_matches(name, list(defaults), n=1)
            hint = f" (did you mean {close[0]}?)" if close and sep else ""
            raise InputError(f"--sensor-set {item}", f"expected NAME=VALUE with NAME a SensorConfig field{hint}: "
                             f"{', '.join(defaults)}")  # fmt: skip
        overrides[name] = parse_set_value(name, text.strip(), defaults[name], "--sensor-set")
    return SensorModel.named(args.sensor, seed=args.sensor_seed, **overrides)


def _sensor_note(sensor: SensorModel | None) -> str:
    """The summary line's mention of the sensor and its holes."""
    if sensor is None:
        return ""
    holes = sensor.holes.fractions()
    return f", simulated {sensor.name} sensor (seed {sensor.seed}): {100 * holes['total']:.1f} % depth holes"


def _render(args: argparse.Namespace) -> int:
    """Handler of ``scene render``."""
    from roigsf_ros.data.scene import load_mesh, render_sequence  # open3d import only when used

    out = Path(args.out)
    check_out(out, args.overwrite, SCENE_MARKS, "a scene", [args.mesh, args.traj, args.cam])
    _check_texture(args.texture_strength)
    sensor = _sensor(args)
    if args.stride < 1:
        raise InputError("--stride", f"must be >= 1, got {args.stride}")
    if not 0 <= args.offset < args.stride:
        raise InputError("--offset", f"must be in 0..{args.stride - 1} (below --stride), got {args.offset}")
    if args.max_frames is not None and args.max_frames < 1:
        raise InputError("--max-frames", f"must be >= 1, got {args.max_frames}")
    size = image_size(args)
    intr = load_camera(args.cam)
    if size is not None:
        intr = intr.resized(*size)
    poses = load_traj(args.traj)[args.offset :: args.stride]
    if args.max_frames is not None:
        poses = poses[: args.max_frames]
    mesh = load_mesh(args.mesh)
    render_sequence(
        mesh,
        poses,
        intr,
        out,
        texture_strength=args.texture_strength,
        texture_seed=args.texture_seed,
        overwrite=args.overwrite,
        metadata={"source_mesh": str(args.mesh), "source_traj": str(args.traj), "source_cam": str(args.cam),
                  "stride": args.stride, "offset": args.offset},
        sensor=sensor,
        progress=show_progress(args),
    )  # fmt: skip
    print(f"wrote {len(poses)} frames of {intr.width}x{intr.height} to {out}{_sensor_note(sensor)}")
    return 0


def _synth(args: argparse.Namespace) -> int:
    """Handler of ``scene synth``."""
    from roigsf_ros.data.scene import (
        dome_trajectory,
        orbit_trajectory,
        render_sequence,
        suite_trajectory,
        synth_bins,
        synth_clutter,
        synth_dining,
        synth_object,
        synth_room,
        synth_shelf,
        synth_suite,
        synth_trajectory,
    )

    out = Path(args.out)
    check_out(out, args.overwrite, SCENE_MARKS, "a scene")
    _check_texture(args.texture_strength)
    sensor = _sensor(args)
    if args.frames < 1:
        raise InputError("--frames", f"must be >= 1, got {args.frames}")
    size = image_size(args) or (None, None)
    intr = synth_intrinsics(*derive_size(*size, (SYNTH_WIDTH, SYNTH_HEIGHT)))
    if args.kind == "object":
        mesh, poses = synth_object(args.seed), orbit_trajectory(args.frames)
    elif args.kind == "object-dome":
        mesh, poses = synth_object(args.seed), dome_trajectory(args.frames)
    elif args.kind == "clutter-dome":
        mesh, poses = synth_clutter(args.seed), dome_trajectory(args.frames)
    elif args.kind == "shelf-dome":
        mesh, poses = synth_shelf(args.seed), dome_trajectory(args.frames)
    elif args.kind == "bins-dome":
        mesh, poses = synth_bins(args.seed), dome_trajectory(args.frames)
    elif args.kind == "dining-dome":
        mesh, poses = synth_dining(args.seed), dome_trajectory(args.frames)
    elif args.kind == "suite":
        try:
            poses = suite_trajectory(args.seed, args.frames)
        except InputError as exc:  # "n_frames: ..." named no option of this command
            raise InputError("--frames" if exc.where == "n_frames" else exc.where, exc.problem) from None
        mesh = synth_suite(args.seed)
    else:
        mesh, poses = synth_room(args.seed), synth_trajectory(args.seed, args.frames)
    render_sequence(
        mesh,
        poses,
        intr,
        out,
        texture_strength=args.texture_strength,
        texture_seed=args.seed,
        overwrite=args.overwrite,
        metadata={"synth_seed": args.seed, "synth_kind": args.kind},
        sensor=sensor,
        progress=show_progress(args),
    )
    print(
        f"wrote {len(poses)} frames of {intr.width}x{intr.height} ({args.kind}, seed {args.seed}) to {out}"
        f"{_sensor_note(sensor)}"
    )
    return 0


def _add_sensor_options(p: argparse.ArgumentParser) -> None:
    """``--sensor``, ``--sensor-seed``, ``--sensor-set`` (shared by ``scene render`` and ``scene synth``)."""
    p.add_argument(
        "--sensor",
        choices=("none", *sorted(SENSORS)),
        default="none",
        help="pass every frame through a simulated sensor: kinect = Kinect v1 structured light (axial and lateral "
        "depth noise, 1/8 px disparity steps, holes out of 0.4-4 m, at grazing incidence, in projector shadows and "
        "1 %% dropouts; noisy JPEG colour; traj.txt off orthonormal by 1e-4..4e-4, the true poses in traj_gt.txt). "
        "Simulated, not real sensor data; default none (ideal frames)",
    )
    p.add_argument("--sensor-seed", type=int, default=0, metavar="S", help="seed of the sensor's noise (default 0)")
    p.add_argument(
        "--sensor-set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override a SensorConfig field (roigsf_ros.data.sensor), e.g. drift_trans_m_per_sqrt_m=0.01 (repeatable)",
    )


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``scene render`` and ``scene synth``."""
    parser = sub.add_parser("scene", help="ray-cast ground-truth RGB-D sequences (Replica layout)", description=__doc__)
    scene_sub = parser.add_subparsers(dest="scene_command", metavar="ACTION", required=True)

    p = scene_sub.add_parser(
        "render",
        help="render a mesh along a traj.txt into a Replica-layout folder",
        description="Ray-cast MESH at the camera-to-world poses of TRAJ with CAM_JSON's intrinsics (optionally "
        "resized) and write colour, z-depth, poses, intrinsics and the mesh into OUT.",
    )
    p.add_argument(
        "--mesh",
        required=True,
        metavar="MESH",
        help="triangle mesh with vertex colours (PLY/OBJ), e.g. office0_mesh.ply",
    )
    p.add_argument(
        "--traj", required=True, metavar="TRAJ", help="traj.txt: one row-major 4x4 camera-to-world pose per line"
    )
    p.add_argument(
        "--cam",
        required=True,
        metavar="CAM_JSON",
        help="cam_params.json ({'camera': {w, h, fx, fy, cx, cy, scale}}), or a named camera: "
        + ", ".join(f"{name} ({c.width}x{c.height}, fx = fy = {c.fx:g})" for name, c in CAMERAS.items()),
    )
    p.add_argument("--out", required=True, metavar="OUT", help="output folder (must not exist unless --overwrite)")
    p.add_argument(
        "--width",
        type=int,
        metavar="W",
        help=f"output width in px, at most {MAX_IMAGE_SIDE}; intrinsics are scaled (alone: the height keeps CAM_JSON's "
        "aspect ratio)",
    )
    p.add_argument(
        "--height",
        type=int,
        metavar="H",
        help=f"output height in px, at most {MAX_IMAGE_SIDE}; intrinsics are scaled (alone: the width keeps CAM_JSON's "
        "aspect ratio)",
    )
    p.add_argument("--stride", type=int, default=1, metavar="S", help="render every S-th pose of TRAJ (default 1)")
    p.add_argument(
        "--offset",
        type=int,
        default=0,
        metavar="K",
        help="start at pose K (below S): with --stride S, --offset K gives the poses between another render's, "
        "a test set no policy sees (roigsf bench --test-scene; default 0)",
    )
    p.add_argument("--max-frames", type=int, metavar="N", help="render at most N frames (after --stride; default all)")
    p.add_argument(
        "--texture-strength",
        type=float,
        default=1.0,
        metavar="X",
        help="procedural surface texture multiplied onto vertex colours: 0 off, 1 full (default 1)",
    )
    p.add_argument(
        "--texture-seed",
        type=int,
        default=0,
        metavar="SEED",
        help="seed of the procedural texture pattern (default 0; `scene synth` used its --seed: give the same to "
        "re-render a synth scene's mesh in its colours)",
    )
    _add_sensor_options(p)
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP.format(what="scene", out="OUT"))
    p.add_argument("--no-progress", action="store_true", help="no progress bar (shown only on a terminal)")
    p.set_defaults(func=_render)

    p = scene_sub.add_parser(
        "synth",
        help="procedural textured room + handheld loop, rendered to a Replica-layout folder",
        description="Build the seeded procedural room and camera loop and render it into OUT. Camera: "
        f"fx = fy = {SYNTH_FOCAL_PER_WIDTH} * width (64 deg horizontal FOV), principal point at the image centre.",
    )
    p.add_argument("--out", required=True, metavar="OUT", help="output folder (must not exist unless --overwrite)")
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        metavar="SEED",
        help="seed of the room layout, trajectory and texture (default 0)",
    )
    p.add_argument(
        "--kind",
        choices=("room", "object", "object-dome", "clutter-dome", "shelf-dome", "bins-dome", "dining-dome", "suite"),
        default="room",
        help="room: the procedural room and a handheld loop inside it (default); object: an object-centric scene "
        "(five primitives on a disc) and one orbit around it, the background empty (no depth); object-dome: the "
        "same objects seen from a hemisphere of viewpoints (10-75 deg elevation, 1.0-1.3 m); clutter-dome: tall boxes "
        "8 cm apart and four open cabinets facing outward, seen from the same hemisphere (insides only a few views "
        "see); shelf-dome: an open shelf, a table with a crate under it and an L of two walls, from the same "
        "hemisphere (the scene the NBV options are tuned on; clutter-dome is reported); bins-dome: two open-top bins, "
        "a tunnel and a screen with a crate behind it, from the same hemisphere (made after the options were fixed); "
        "dining-dome: a table with two chairs pushed under it, a cabinet with its door half open, a plank leaning on "
        "it and a stool, from the same hemisphere (made after every option was fixed, a held-out scene); "
        "suite: two rooms (seeds SEED and SEED + 1) joined by a doorway, a loop in the first, a walk through the "
        "doorway and a loop in the second (a stream that meets a new room; made for the stream NBV check)",
    )
    p.add_argument("--frames", type=int, default=100, metavar="N", help="number of frames along one loop (default 100)")
    p.add_argument(
        "--width",
        type=int,
        metavar="W",
        help=f"image width in px, at most {MAX_IMAGE_SIDE} (default {SYNTH_WIDTH}; alone, the height keeps the "
        "default's 4:3 aspect)",
    )
    p.add_argument(
        "--height",
        type=int,
        metavar="H",
        help=f"image height in px, at most {MAX_IMAGE_SIDE} (default {SYNTH_HEIGHT}; alone, the width keeps the "
        "default's 4:3 aspect)",
    )
    p.add_argument(
        "--texture-strength",
        type=float,
        default=1.0,
        metavar="X",
        help="procedural surface texture multiplied onto vertex colours: 0 off, 1 full (default 1)",
    )
    _add_sensor_options(p)
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP.format(what="scene", out="OUT"))
    p.add_argument("--no-progress", action="store_true", help="no progress bar (shown only on a terminal)")
    p.set_defaults(func=_synth)
