"""Speed benchmarks behind ``roigsf perf <name>``: each module has ``add_arguments`` and ``run``.

Performance goals live here (JSON plus a readable table), never in timed tests.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import check_writable


def check_options(args: argparse.Namespace, least: dict[str, int], positive: tuple[str, ...] = ()) -> None:
    """Refuse bad numbers before any work, naming the option (``--repeats``): each of ``least`` below its minimum
    (None: the option's "not given" default, accepted) and each float of ``positive`` not finite and > 0.
    """
    for name, minimum in least.items():
        value = getattr(args, name)
        if value is not None and value < minimum:
            raise InputError(f"--{name.replace('_', '-')}", f"must be at least {minimum}, got {value}")
    for name in positive:
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):
            raise InputError(f"--{name.replace('_', '-')}", f"must be a finite number > 0, got {value}")


def check_out_file(out: str | Path | None) -> None:
    """Refuse ``--out FILE.json`` before any work: an existing folder, a path under a regular file or an unwritable
    folder would otherwise fail only when the results are written, after the whole benchmark.
    """
    if out is not None:
        check_writable(out, file=True)


__all__ = ["check_options", "check_out_file"]
