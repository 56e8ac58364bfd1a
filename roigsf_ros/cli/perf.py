"""``roigsf perf``: speed benchmarks that write JSON and print a table."""

from __future__ import annotations

import argparse
import importlib

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
        p.set_defaults(func=module.run)
