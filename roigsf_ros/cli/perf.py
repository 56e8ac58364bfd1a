"""``roigsf perf``: speed benchmarks that write JSON and print a table."""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable
from pathlib import Path

from roigsf_ros.cli import add_camera_options, camera_topics, with_bag_hint
from roigsf_ros.core.errors import InputError

# Benchmark modules under roigsf_ros.perf; each exposes add_arguments(parser) and run(args).
_BENCHMARKS = ("io", "render", "nbv", "novelty")


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``perf <benchmark>`` subcommands."""
    parser = sub.add_parser("perf", help="speed benchmarks (JSON + table)", description=__doc__)
    perf_sub = parser.add_subparsers(dest="benchmark", metavar="BENCHMARK", required=True)
    for name in _BENCHMARKS:
        module = importlib.import_module(f"roigsf_ros.perf.{name}")
        doc = (module.__doc__ or name).strip().splitlines()[0]
        p = perf_sub.add_parser(name, help=doc, description=module.__doc__)
        module.add_arguments(p)
        if getattr(module, "READS_CAMERA_BAG", False):  # a robot's bag too: roigsf map's camera options
            add_camera_options(p)
            p.set_defaults(func=_with_camera_topics(module.run))
        else:
            p.set_defaults(func=module.run)


def _with_camera_topics(run: Callable[..., int]) -> Callable[[argparse.Namespace], int]:
    """``run(args, topics=...)`` with the topics the camera options give, and the RealSense hint on a bag it cannot
    read (as ``roigsf map`` gives it).
    """

    def with_topics(args: argparse.Namespace) -> int:
        try:
            return run(args, topics=camera_topics(args))
        except InputError as exc:  # the bag named, or the shipped sample (--realsense on it: "leave it out")
            bag = args.bag if args.bag is not None else Path(str(exc.where))
            if str(exc.where) == str(bag) and bag.exists():
                raise with_bag_hint(exc, args, bag) from None
            raise

    return with_topics
