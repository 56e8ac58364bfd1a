"""The ``roigsf`` command line: the front door for everything offline.

Each subcommand group lives in its own module with a ``register(subparsers)`` function.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from roigsf_ros.core.errors import InputError

# Subcommand modules, in the order `roigsf --help` lists them.
_COMMAND_MODULES = ("demo", "scene", "bag", "map", "bench", "perf")


def image_size(args: argparse.Namespace) -> tuple[int, int] | None:
    """(width, height) from ``--width``/``--height``, which come together or not at all."""
    if (args.width is None) != (args.height is None):
        raise InputError("--width/--height", "give both or neither")
    return (args.width, args.height) if args.width is not None else None


def check_out(out: Path, overwrite: bool) -> None:
    """Fail early, before any work, if the output folder ``out`` exists and may not be replaced."""
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: already exists (pass --overwrite to replace it)")
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")


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
