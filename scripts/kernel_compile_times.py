"""What the numba kernels' compile costs, kernel by kernel: the warm-up set-up runs, timed by numba's compile events.

``python -m roigsf_ros.nbv.warmup`` compiles every kernel mapping and NBV scoring use in one process (one core); this
runs the same warm-up under numba's ``numba:compile`` event recorder and sums each kernel's compile time over its
signatures. By default into an empty numba cache in a temporary folder (the cold compile of a fresh machine, as in
the README's main-job figures); ``--warm`` keeps the normal cache (then mostly cache loads). Writes JSON with
``--out`` and prints a table, slowest first.

    .venv/bin/python scripts/kernel_compile_times.py [--warm] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    """Run the warm-up under numba's compile-event recorder; print and optionally write the per-kernel times."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--warm", action="store_true", help="use the normal numba cache instead of an empty one")
    parser.add_argument("--out", type=Path, help="write the times as JSON")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="roigsf-numba-cache-") as cache:
        if not args.warm:
            os.environ["NUMBA_CACHE_DIR"] = cache  # read by numba at import: before anything imports it
        from numba.core import event

        from roigsf_ros.core.fileio import write_json
        from roigsf_ros.nbv.warmup import warm_up_kernels

        with event.install_recorder("numba:compile") as recorder:
            phases = warm_up_kernels()
    started: dict[int, float] = {}
    kernels: dict[str, dict[str, float]] = {}
    for stamp, ev in recorder.buffer:
        dispatcher = (ev.data or {}).get("dispatcher")
        if dispatcher is None:
            continue
        key = id(ev.data)  # one dict per compile, shared by its start and end events
        if ev.is_start:
            started[key] = stamp
        elif key in started:
            row = kernels.setdefault(dispatcher.py_func.__qualname__, {"seconds": 0.0, "compiles": 0})
            row["seconds"] += stamp - started.pop(key)
            row["compiles"] += 1
    rows = sorted(({"kernel": k, **v} for k, v in kernels.items()), key=lambda r: -r["seconds"])
    result = {"cache": "warm" if args.warm else "empty", "warm_up_s": phases, "kernels": rows}
    print(f"numba compile times ({result['cache']} cache; warm-up {phases['total_s']:.1f} s)")
    print(f"{'kernel':<40} {'s':>8} {'compiles':>9}")
    for r in rows:
        print(f"{r['kernel']:<40} {r['seconds']:>8.1f} {r['compiles']:>9d}")
    if args.out:
        write_json(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
