"""Speed benchmarks behind ``roigsf perf <name>``: each module has ``add_arguments`` and ``run``.

Performance goals live here (JSON plus a readable table), never in timed tests.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import check_writable

MAX_THREADS = 1024
"""The most threads a benchmark may be asked for (more than any machine here has; a typo's 99999999999 overflowed
inside torch with a traceback)."""


def check_options(
    args: argparse.Namespace,
    least: dict[str, int],
    positive: tuple[str, ...] = (),
    most: dict[str, float] | None = None,
) -> None:
    """Refuse bad numbers before any work, naming the option (``--repeats``): each of ``least`` below its minimum
    (None: the option's "not given" default, accepted), each float of ``positive`` not finite and > 0, and each of
    ``most`` above its maximum.
    """
    for name, minimum in least.items():
        value = getattr(args, name)
        if value is not None and value < minimum:
            raise InputError(f"--{name.replace('_', '-')}", f"must be at least {minimum}, got {value}")
    for name, maximum in (most or {}).items():
        value = getattr(args, name)
        if value is not None and value > maximum:
            raise InputError(f"--{name.replace('_', '-')}", f"must be at most {maximum:g}, got {value}")
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


__all__ = ["MAX_THREADS", "check_options", "check_out_file"]
