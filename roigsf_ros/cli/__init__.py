"""The ``roigsf`` command line: the front door for everything offline.

Each subcommand group lives in its own module with a ``register(subparsers)`` function.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import tempfile
from pathlib import Path

from roigsf_ros.core.errors import InputError

# Subcommand modules, in the order `roigsf --help` lists them.
_COMMAND_MODULES = ("demo", "scene", "bag", "map", "bench", "perf")


def image_size(args: argparse.Namespace) -> tuple[int | None, int | None] | None:
    """(width, height) from ``--width``/``--height``; None if neither is given.

    One alone is returned with None for the other, which then follows the source's aspect ratio
    (:meth:`roigsf_ros.core.camera.Intrinsics.resized`), the same for every command with these options.
    """
    for name, value in (("--width", args.width), ("--height", args.height)):
        if value is not None and value <= 0:
            raise InputError(name, f"image size must be positive, got {value}")
    return None if args.width is None and args.height is None else (args.width, args.height)


def check_out(out: Path, overwrite: bool) -> None:
    """Fail early, before any work, if the output folder ``out`` exists and may not be replaced or cannot be written."""
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: already exists (pass --overwrite to replace it)")
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    check_writable(out)


def check_writable(out: Path) -> None:
    """Fail before any work if ``out`` cannot be created: its parent is read-only, not writable or not a folder.

    Outputs are written beside their final name and renamed (:mod:`roigsf_ros.core.fileio`), so the test
    is to create and remove a temporary file in the parent (or the nearest existing ancestor, as
    missing parents are created); a run would otherwise fail only at its end, with a traceback.
    """
    folder = Path(os.path.abspath(out)).parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise InputError(folder, f"is not a folder, so the output {out} cannot be created there")
    try:
        fd, probe = tempfile.mkstemp(prefix=".roigsf-write-test-", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise InputError(folder, f"output folder is not writable ({exc.strerror or exc}); choose another one") from None


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser with every subcommand registered."""
    parser = argparse.ArgumentParser(
        prog="roigsf",
        description="Active mapping with 2D Gaussian surfels: scenes, bags, mapping and NBV benchmarks.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in _COMMAND_MODULES:
        importlib.import_module(f"roigsf_ros.cli.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point: parse, run, and turn bad input into a one-line error and exit code 2."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (InputError, FileExistsError, FileNotFoundError) as exc:
        print(f"roigsf {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"roigsf {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
