"""The ``roigsf`` command line: the front door for everything offline.

Each subcommand group lives in its own module with a ``register(subparsers)`` function. This module imports only the
light ``core`` modules at its top: everything heavier (numpy, rosbags, open3d) comes in :func:`main`, where a Ctrl-C
during those first seconds is one line, not a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import re
import shlex
import signal
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import check_replaceable, check_writable, deferred_interrupts

if TYPE_CHECKING:
    from collections.abc import Sequence

    from roigsf_ros.data.bags import CameraTopics

# Subcommand modules, in the order `roigsf --help` lists them.
_COMMAND_MODULES = ("demo", "scene", "bag", "map", "bench", "targets", "perf", "ros")


def image_size(args: argparse.Namespace) -> tuple[int | None, int | None] | None:
    """(width, height) from ``--width``/``--height``; None if neither is given.

    One alone is returned with None for the other, which then follows the source's aspect ratio
    (:meth:`roigsf_ros.core.camera.Intrinsics.resized`), the same for every command with these options.
    """
    for name, value in (("--width", args.width), ("--height", args.height)):
        if value is not None and value <= 0:
            raise InputError(name, f"image size must be positive, got {value}")
    return None if args.width is None and args.height is None else (args.width, args.height)


def show_progress(args: argparse.Namespace) -> bool:
    """Whether a command draws progress bars: not ``--no-progress``, and stderr a terminal (bars written into a log
    file or a pipe came out as carriage-return lines; ``roigsf scene`` already drew them on a terminal only).
    """
    return not args.no_progress and sys.stderr.isatty()


_CAMERA_OPTIONS = {
    "color": "--color-topic",
    "depth": "--depth-topic",
    "camera_info": "--camera-info-topic",
    "pose": "--pose-topic",
    "pose_source": "--pose-source",
    "tf_parent_frame": "--tf-parent-frame",
    "tf_child_frame": "--tf-child-frame",
    "tf_topic": "--tf-topic",
    "tf_static_topic": "--tf-static-topic",
    "tf_tolerance_s": "--tf-tolerance",
    "color_transport": "--color-transport",
    "depth_transport": "--depth-transport",
}
"""CameraTopics field -> the command-line option that sets it."""


REALSENSE_HELP = (
    "RealSense names under NS (default /camera): NS/color/image_raw, NS/aligned_depth_to_color/image_raw, "
    "NS/color/camera_info, pose from TF; the options below override single names"
)
"""``--realsense``'s help in :func:`add_camera_options` (a command may say more, as the demo does)."""


def add_camera_options(
    parser: argparse.ArgumentParser, realsense_help: str = REALSENSE_HELP, transport_default: str = "auto: from the bag"
) -> None:
    """Options that say how a bag's camera is read: topics, transports, pose from a topic or TF, RealSense names.

    ``transport_default``: what a transport not typed is, in the help (the demo's nodes have their own default).
    """
    from roigsf_ros.data.bags import AUTO, COLOR_TRANSPORTS, DEPTH_TRANSPORTS, POSE_SOURCES, CameraTopics

    d = CameraTopics()
    g = parser.add_argument_group("camera topics (bags)")
    g.add_argument("--realsense", nargs="?", const="/camera", metavar="NS", help=realsense_help)
    g.add_argument("--color-topic", metavar="TOPIC", help=f"colour image topic (default {d.color})")
    g.add_argument("--depth-topic", metavar="TOPIC", help=f"depth image topic (default {d.depth})")
    g.add_argument("--camera-info-topic", metavar="TOPIC", help=f"camera info topic (default {d.camera_info})")
    g.add_argument("--pose-topic", metavar="TOPIC", help=f"PoseStamped topic of the camera pose (default {d.pose})")
    g.add_argument(
        "--color-transport",
        choices=(AUTO, *COLOR_TRANSPORTS),
        help=f"raw (Image) or compressed (CompressedImage JPEG/PNG, on TOPIC/compressed); default {transport_default}",
    )
    g.add_argument(
        "--depth-transport",
        choices=(AUTO, *DEPTH_TRANSPORTS),
        help=f"raw, compressed (16-bit PNG) or compressedDepth (on TOPIC/compressedDepth); default {transport_default}",
    )
    g.add_argument(
        "--pose-source",
        choices=POSE_SOURCES,
        help="camera pose from the pose topic or from TF (/tf + /tf_static); default topic (tf with --realsense)",
    )
    g.add_argument("--tf-parent-frame", metavar="FRAME", help=f"TF: the world frame (default {d.tf_parent_frame})")
    g.add_argument(
        "--tf-child-frame", metavar="FRAME", help=f"TF: the camera optical frame (default {d.tf_child_frame})"
    )
    g.add_argument("--tf-topic", metavar="TOPIC", help=f"TF topic (default {d.tf_topic})")
    g.add_argument("--tf-static-topic", metavar="TOPIC", help=f"static TF topic (default {d.tf_static_topic})")
    g.add_argument(
        "--tf-tolerance",
        type=float,
        metavar="S",
        help=f"TF: interpolate only between samples within S seconds of the image stamp (default {d.tf_tolerance_s:g})",
    )


def camera_options(args: argparse.Namespace) -> dict[str, Any]:
    """The :class:`CameraTopics` fields typed among :func:`add_camera_options`' options (``--realsense`` aside)."""
    given = {field: getattr(args, opt[2:].replace("-", "_")) for field, opt in _CAMERA_OPTIONS.items()}
    return {k: v for k, v in given.items() if v is not None}


def camera_topics(args: argparse.Namespace) -> CameraTopics:
    """The :class:`CameraTopics` of :func:`add_camera_options`' options; errors name the option typed."""
    from roigsf_ros.data.bags import AUTO, CameraTopics, realsense_topics

    given = camera_options(args)
    given.setdefault("color_transport", AUTO)
    given.setdefault("depth_transport", AUTO)
    try:
        if args.realsense is not None:
            return realsense_topics(args.realsense, **given)
        return CameraTopics(**given)
    except InputError as exc:
        raise InputError(_CAMERA_OPTIONS.get(exc.where, exc.where), exc.problem) from None


def realsense_hint(
    bag: Path, present: dict[str, str], given: str | None, named: tuple[str, ...] = (), command: str = ""
) -> str:
    """``; the bag has a RealSense camera's topics under NS: try --realsense NS`` when the bag (its ``{topic: type}``
    ``present``) holds a RealSense camera's topics not under ``given`` (the ``--realsense`` typed), else "": the hint of
    ``roigsf demo`` and ``roigsf map`` when they read no frame. ``named``: options typed that would override the
    RealSense names or transports (``--color-transport``), which the hint says to leave out. ``command``: the command
    that takes the option, for a command that has none (``roigsf bag to-robot``): ``map it with `COMMAND --realsense```.
    The namespace is written out where ``--realsense`` was typed with another (``--realsense /camera``).
    """
    from roigsf_ros.data.bags import AUTO, realsense_topics

    suffix = "/color/camera_info"
    for topic in sorted(present):
        if topic.endswith(suffix):
            ns = topic[: -len(suffix)] or "/"
            if given is not None and ns.strip("/") == given.strip("/"):
                continue
            try:
                realsense_topics(ns, color_transport=AUTO, depth_transport=AUTO).in_bag(present, bag)
            except InputError:
                continue
            option = "--realsense" if ns == "/camera" and given is None else f"--realsense {ns}"
            drop = f" without {', '.join(named)}" if named else ""
            advice = f"map it with `{command} {option}`" if command else f"try {option}{drop}"
            return f"; the bag has a RealSense camera's topics under {ns}: {advice}"
    return ""


OVERRIDING_OPTIONS = ("color_topic", "depth_topic", "camera_info_topic", "color_transport", "depth_transport")
"""The camera options that would override the names or transports ``--realsense`` sets."""


def with_bag_hint(exc: InputError, args: argparse.Namespace, path: str | Path) -> InputError:
    """``exc``, raised opening ``path`` with :func:`add_camera_options`' options, with ``roigsf demo``'s and ``roigsf
    bag info``'s hint when ``path`` is a bag that holds a RealSense camera's topics: ``try --realsense`` (without the
    options that would override it), or, ``--realsense`` given, this package's own: leave it out; ``exc`` itself for a
    folder or a bag without either.
    """
    from roigsf_ros.data.bags import AUTO, CameraTopics, bag_topic_types

    try:
        present = bag_topic_types(path)
    except (InputError, OSError):  # no bag (a scene folder, a path that does not exist): no hint
        return exc
    named = tuple(f"--{o.replace('_', '-')}" for o in OVERRIDING_OPTIONS if getattr(args, o) not in (None, AUTO))
    hint = realsense_hint(Path(path), present, args.realsense, named)
    if not hint and args.realsense is not None:  # --realsense on a bag of this package's own names
        try:
            CameraTopics(color_transport=AUTO, depth_transport=AUTO).in_bag(present, path)
        except InputError:
            pass
        else:
            hint = "; the bag has this package's camera topics (`roigsf bag from-replica`'s): leave out --realsense"
    return InputError(exc.where, exc.problem + hint) if hint else exc


def typed_camera_options(args: argparse.Namespace) -> list[str]:
    """The :func:`add_camera_options` options typed, as typed (``--realsense`` first), for errors that name them."""
    typed = [f"--{o.replace('_', '-')}" for o in camera_options(args)]
    return (["--realsense"] if args.realsense is not None else []) + typed


def check_camera_options_for(args: argparse.Namespace, source: str | Path | None) -> None:
    """InputError naming the camera options typed (:func:`add_camera_options`) when ``source`` is a Replica folder:
    they say how a bag's topics are read, and a folder has none (its poses are traj.txt's), so they were ignored
    without a word, as ``--cam`` given to a bag is refused.
    """
    from roigsf_ros.data.sources import is_bag

    typed = typed_camera_options(args)
    if typed and source is not None and Path(source).exists() and not is_bag(source):
        raise InputError(" ".join(typed), f"{source} is a Replica folder, not a bag: camera options say how a bag's "
                         "topics are read (a folder's images and poses are its files)")  # fmt: skip


NO_OWN_MESH = "no --gt-mesh, and no mesh.ply in the source's folder nor NAME_mesh.ply beside it"
"""Why a run without ``--gt-mesh`` has no mesh metrics (:func:`roigsf_ros.data.replica.scene_gt_mesh` found none)."""


def chosen_gt_mesh(option: str | None, own: Path | None) -> tuple[Path | None, str]:
    """The mesh ``roigsf map`` and ``roigsf demo`` take their mesh metrics against, and why there is none: ``--gt-mesh``
    (``option``; ``''``: none) when given, else the source's own (``own``, as
    :func:`~roigsf_ros.data.replica.scene_gt_mesh` finds it). Returns (the mesh or None, the reason when None, else "").
    """
    if option is not None:
        return (Path(option), "") if option.strip() else (None, "--gt-mesh ''")
    return (own, "") if own is not None else (None, NO_OWN_MESH)


OVERWRITE_HELP = "replace an earlier {what} at {out} (once the new one is complete; never another folder)"
"""``--overwrite``'s help: what it replaces (:func:`check_out`)."""


def check_out(
    out: Path,
    overwrite: bool,
    marks: Sequence[str],
    what: str,
    inputs: Sequence[str | Path | None] = (),
    own: Sequence[str] = (),
) -> None:
    """Fail early, before any work, if the output folder ``out`` exists and may not be replaced or cannot be written.

    ``--overwrite`` replaces an empty folder or ``what``, an earlier output of the command (a folder holding one of
    ``marks``), and never a folder holding one of the command's ``inputs`` or another output (other than its ``own``
    nested ones: :func:`~roigsf_ros.core.fileio.check_replaceable`).
    """
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: already exists (pass --overwrite to replace it)")
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    check_replaceable(out, marks, what, inputs, own)
    check_writable(out)


_UNINTERRUPTIBLE_IMPORTS = ("open3d",)
"""Modules imported with Ctrl-C held back (:func:`build_parser`, :func:`~roigsf_ros.core.fileio.deferred_interrupts`):
open3d's pybind11 module init turns a Ctrl-C into "ImportError: initialization failed" and leaves a half-made library
whose exit then fails (status 1 after the one line, and a memory-leak report on stdout).
"""


def command_line(command: str) -> str | None:
    """The ``roigsf COMMAND ...`` line this process runs (shell-quoted), for an output to say how it was made; None
    when the process is not that command (the library called from Python, a test).
    """
    if sys.argv[1:2] != [command]:
        return None
    return "roigsf " + " ".join(shlex.quote(a) for a in sys.argv[1:])


def wrapped_command_args(parser: argparse.ArgumentParser, argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
    """For a script that wraps a ``roigsf`` command (``scripts/unseen_spread.py --out J -- <bench arguments>``): its own
    options, before ``--``, parsed by ``parser`` (so ``--help`` works alone), and the command's arguments after it.

    A parser error (exit 2, with the usage) when ``--`` or anything after it is missing: those scripts answered
    ``--help`` with a one-line usage and exit 2.
    """
    split = argv.index("--") if "--" in argv else len(argv)
    args = parser.parse_args(argv[:split])
    if split >= len(argv) - 1:
        parser.error("give the wrapped command's arguments after --")
    return args, argv[split + 1 :]


def metric_notes(metrics: dict[str, Any]) -> list[str]:
    """Lines under a run's table that say what its figures count: a TF frame that changed parent (its poses may be
    wrong), poses of another frame than the images', recall and completion against the GT in view of the run's poses
    (a 4-frame run's recall 0.998 read as a whole room's), most of the depth out of range (a wrong depth scale), and
    why PSNR/SSIM are missing.
    """
    from roigsf_ros.mapping.mapper import depth_scale_note  # here: the command line starts without torch

    notes = []
    if metrics.get("tf_reparented"):
        notes.append(f"TF: {metrics.get('tf_reparent_note')} ({metrics['tf_reparented']} change(s) of parent): the "
                     "poses, and every figure, may be wrong")  # fmt: skip
    if metrics.get("tf_child_frame_note"):
        notes.append(f"TF: {metrics['tf_child_frame_note']}; every figure is wrong")
    seen = metrics.get("gt_observed_fraction")
    if seen is not None and not str(metrics.get("gt_culling", "none")).startswith("none"):
        notes.append(f"recall and completion count the GT in view of the run's poses: {seen:.0%} of the GT mesh "
                     "(gt_culling in metrics.json)")  # fmt: skip
    if depth_note := depth_scale_note(metrics):
        notes.append(depth_note)
    if metrics.get("n_eval_frames") == 0:
        notes.append("no PSNR/SSIM: every frame was a keyframe, and they are measured on the frames that were not")
    return notes


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser with every subcommand registered."""
    for name in _UNINTERRUPTIBLE_IMPORTS:  # a Ctrl-C meanwhile comes just after: one line, exit 130 (main)
        with deferred_interrupts(), contextlib.suppress(ImportError):  # missing: the command that needs it says so
            importlib.import_module(name)
    parser = argparse.ArgumentParser(
        prog="roigsf",
        description="Active mapping with 2D Gaussian surfels: scenes, bags, mapping and NBV benchmarks.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in _COMMAND_MODULES:
        importlib.import_module(f"roigsf_ros.cli.{name}").register(sub)
    _no_abbreviations(parser)
    return parser


def _no_abbreviations(parser: argparse.ArgumentParser) -> None:
    """Options only as spelt, in every subcommand: argparse's default takes a unique prefix, and ``roigsf map --cam``
    (an option of other commands) was read as ``--camera-info-topic`` and ignored for a scene folder.
    """
    parser.allow_abbrev = False
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                _no_abbreviations(child)


class _Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived: the command stops as on Ctrl-C, cleaning up (``signum`` sets the exit status)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _interrupt(signum: int, frame: object) -> None:
    """First SIGINT/SIGTERM: stop the command with its clean-up; a second one exits at once."""
    signal.signal(signal.SIGINT, _exit_now)
    signal.signal(signal.SIGTERM, _exit_now)
    raise _Interrupted(signum)


def _exit_now(signum: int, frame: object) -> None:
    print(f"interrupted again (signal {signum}): exiting without clean-up", file=sys.stderr)
    os._exit(128 + signum)


def _interrupt_behind(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C / SIGTERM behind ``exc``: itself, or one in its ``__cause__`` / ``__context__`` chain (numba wraps
    an interrupt raised inside a dispatch in a SystemError); None when it was no interrupt.
    """
    seen: set[int] = set()
    todo: list[BaseException] = [exc]
    while todo:
        e = todo.pop()
        if id(e) in seen:
            continue
        seen.add(id(e))
        if isinstance(e, KeyboardInterrupt):
            return e
        todo += [c for c in (e.__cause__, e.__context__) if c is not None]
    return None


def _interrupted(command: str, exc: KeyboardInterrupt) -> int:
    """The one line and exit status of a stopped command: 128 + the signal (130 for Ctrl-C)."""
    print(f"roigsf{' ' + command if command else ''}: interrupted", file=sys.stderr)
    return 128 + exc.signum if isinstance(exc, _Interrupted) else 130


def _command_named(argv: list[str]) -> str:
    """The subcommand ``argv`` names (its first word, when that is one), for a line before the parser could say."""
    first = next((a for a in argv if not a.startswith("-")), "")
    return first if first in _COMMAND_MODULES else ""


def main(argv: list[str] | None = None) -> int:
    """Entry point: parse, run, and turn bad input into a one-line error and exit code 2.

    SIGTERM stops a command as Ctrl-C does (the demo stops its nodes and leaves no ROS shared-memory file; nothing
    half-written is left under a final name), also when the shell started it with SIGINT ignored (``&``), and also
    when a library wrapped the interrupt in another exception. Running out of memory is one line too, exit code 1.
    A Ctrl-C from the first import on (:func:`build_parser`) to the command's end is ``roigsf ...: interrupted``.
    """
    handlers = {}
    if threading.current_thread() is threading.main_thread():  # before the imports: no gap for a traceback
        handlers = {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        try:
            parser = build_parser()  # imports every command's module: the first seconds of a run
            args = parser.parse_args(argv)
        except (KeyboardInterrupt, Exception) as exc:  # Ctrl-C then printed a traceback of the import under way
            interrupt = _interrupt_behind(exc)  # also one a library wrapped ("ImportError: initialization failed")
            if interrupt is None:
                raise
            return _interrupted(_command_named(sys.argv[1:] if argv is None else argv), interrupt)
        return _run_command(args)
    finally:
        for sig, handler in handlers.items():
            if handler is not None:  # None: not set from Python, nothing to put back
                signal.signal(sig, handler)


API_OPTIONS = {
    "overwrite=True": "--overwrite",
    "allow_partial=True": "--allow-partial",
    "cam=PATH": "--cam PATH",
    "cam=kinect-v1": "--cam kinect-v1",
}
"""The library's words for an argument in its errors -> the command line's option, for a command that has it."""


def cli_words(message: str, args: argparse.Namespace) -> str:
    """A library error in the command line's words: ``allow_partial=True`` as ``--allow-partial`` where the command
    has that option (:data:`API_OPTIONS`); the library's own words elsewhere, so that a Python caller reads Python.
    """
    for api, option in API_OPTIONS.items():
        if hasattr(args, api.split("=", 1)[0]):
            message = re.sub(rf"(?<![\w-]){re.escape(api)}", option, message)
    return message


def _run_command(args: argparse.Namespace) -> int:
    """Run the parsed command: bad input one line and 2, an interrupt one line and 128 + signal, memory one line, a
    closed output pipe nothing and 141 (128 + SIGPIPE, as a shell tool).
    """
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:  # `roigsf bag info ... | head -1`: the reader left; quiet, as a shell tool is
        with contextlib.suppress(OSError, ValueError):  # no flush at exit into the closed pipe either
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except (InputError, FileExistsError, FileNotFoundError) as exc:
        print(f"roigsf {args.command}: error: {cli_words(str(exc), args)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        return _interrupted(args.command, exc)
    except Exception as exc:
        interrupt = _interrupt_behind(exc)
        if interrupt is not None:
            return _interrupted(args.command, interrupt)
        if isinstance(exc, MemoryError):  # numpy's says how much: "Unable to allocate 168. GiB for an array ..."
            hint = "; try a smaller --width/--height" if hasattr(args, "width") else ""
            why = str(exc) or "MemoryError"
            print(f"roigsf {args.command}: error: not enough memory for this command ({why}){hint}", file=sys.stderr)
            return 1
        raise


if __name__ == "__main__":
    sys.exit(main())
