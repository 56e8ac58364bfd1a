"""Speed benchmarks behind ``roigsf perf <name>``: each module has ``add_arguments`` and ``run``.

Performance goals live here (JSON plus a readable table), never in timed tests.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.metadata
import math
import os
import platform
import subprocess
from pathlib import Path
from typing import Any

from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import check_replaceable_file, check_writable, write_json
from roigsf_ros.core.package_files import CHECKOUT_ROOT

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


def check_out_file(out: str | Path | None, benchmark: str) -> None:
    """Refuse ``--out FILE.json`` before any work: an existing folder, a path under a regular file or an unwritable
    folder would otherwise fail only when the results are written, after the whole benchmark; and an existing file
    that is not an earlier result of this benchmark (``--out bags/x/metadata.yaml`` wrote JSON over a bag's metadata).
    """
    if out is not None:
        check_writable(out, file=True)
        check_replaceable_file(out, {"benchmark": benchmark}, f"an earlier `roigsf perf {benchmark}` result")


def cpu_model() -> str:
    """The CPU's model name (Linux: /proc/cpuinfo), else what :mod:`platform` says (often only ``x86_64``)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and ":" in line:
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def environment(load_before: float) -> dict[str, Any]:
    """Where and when a benchmark ran, the same block in every ``roigsf perf`` JSON: the CPU model and cores, the
    1-min load average before and now (other processes inflate times), the versions that set the speed, the
    package's version and the checkout's commit (None when installed or not a git checkout), the time (UTC).
    """
    versions = {name: _version(name) for name in ("roigsf_ros", "torch", "numpy", "numba", "open3d")}
    return {
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "load_average_1min": [load_before, os.getloadavg()[0]],
        "python": platform.python_version(),
        "versions": versions,
        "commit": _commit(),
        "finished_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }


def threads_text(asked: int, numba_threads: int | None, torch_threads: int | None = None) -> str:
    """``2 threads`` for a table's footer, or each library's where they differ: numba has at most ``NUMBA_NUM_THREADS``
    (the CPUs), so ``--threads 64`` on 2 cores ran its kernels on 2 while the table said 64; torch takes them all, and
    more threads than CPUs slow it down: said too.
    """
    torch_threads = asked if torch_threads is None else torch_threads
    cpus = os.cpu_count() or 1
    over = f", more than the {cpus} CPUs: slower" if max(asked, torch_threads) > cpus else ""
    if numba_threads is None or numba_threads == asked == torch_threads:
        return f"{torch_threads} thread{'s' * (torch_threads != 1)}{over}"
    fewer = f" ({asked} asked: numba's most here)" if numba_threads < asked else ""
    return f"torch {torch_threads}, numba {numba_threads} threads{fewer}{over}"


def write_results(out: str | Path | None, result: dict[str, Any]) -> None:
    """Write a benchmark's ``result`` to ``--out`` (atomically) and say where; nothing without ``--out``."""
    if out is not None:
        write_json(out, result)
        print(f"wrote {out}")


def _version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def _commit() -> str | None:
    """The checkout's commit (with ``+changes`` when the tree differs), when the modules run from a git checkout."""
    if not (CHECKOUT_ROOT / ".git").exists():
        return None
    try:
        head = subprocess.run(["git", "-C", str(CHECKOUT_ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, timeout=10, check=True).stdout.strip()  # fmt: skip
        dirty = subprocess.run(["git", "-C", str(CHECKOUT_ROOT), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return None
    return head + ("+changes" if dirty else "")


__all__ = [
    "MAX_THREADS",
    "check_options",
    "check_out_file",
    "cpu_model",
    "environment",
    "threads_text",
    "write_results",
]
