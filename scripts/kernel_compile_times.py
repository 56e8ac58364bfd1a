"""What the numba kernels' compile costs, kernel by kernel: the warm-up set-up runs, timed by numba's compile events.

``python -m roigsf_ros.nbv.warmup`` compiles every kernel mapping and NBV scoring use in one process (one core); this
runs the same warm-up under numba's ``numba:compile`` event recorder and sums each kernel's compile time over its
signatures. By default into an empty numba cache in a temporary folder (the cold compile of a fresh machine, as in
the README's main-job figures); ``--warm`` keeps the normal cache (then mostly cache loads). Writes JSON with
``--out`` and prints a table, slowest first. ``--write-signatures`` also rewrites the package's kernel signature list
(``roigsf_ros/nbv/kernel_signatures.json``: each kernel's argument types and cold compile time, from which
``python -m roigsf_ros.nbv.warmup --jobs N`` splits the cold compile over N processes); run it after a change to a
kernel's arguments (a test says when).

    .venv/bin/python scripts/kernel_compile_times.py [--warm] [--out FILE.json] [--write-signatures]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's roigsf_ros (the one --write-signatures writes into), not the installed


def main(argv: list[str] | None = None) -> int:
    """Run the warm-up under numba's compile-event recorder; print and optionally write the per-kernel times."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--warm", action="store_true", help="use the normal numba cache instead of an empty one")
    parser.add_argument("--out", type=Path, help="write the times as JSON")
    parser.add_argument(
        "--write-signatures", action="store_true", help="rewrite roigsf_ros/nbv/kernel_signatures.json (cold only)"
    )
    args = parser.parse_args(argv)
    if args.warm and args.write_signatures:
        parser.error("--write-signatures needs the cold compile's times: drop --warm")
    with tempfile.TemporaryDirectory(prefix="roigsf-numba-cache-") as cache:
        if not args.warm:
            os.environ["NUMBA_CACHE_DIR"] = cache  # read by numba at import: before anything imports it
        from numba.core import event

        from roigsf_ros.core.fileio import write_json
        from roigsf_ros.nbv import warmup

        with event.install_recorder("numba:compile") as recorder:
            phases = warmup.warm_up_kernels()
    started: dict[int, float] = {}
    kernels: dict[str, dict[str, float]] = {}
    listed = {
        id(d): f"{key}.{name}" for key, g in warmup.kernel_groups().items() for name, d in g.dispatchers().items()
    }
    listed_s: dict[str, float] = {}
    for stamp, ev in recorder.buffer:
        dispatcher = (ev.data or {}).get("dispatcher")
        if dispatcher is None:
            continue
        key = id(ev.data)  # one dict per compile, shared by its start and end events
        if ev.is_start:
            started[key] = stamp
        elif key in started:
            row = kernels.setdefault(dispatcher.py_func.__qualname__, {"seconds": 0.0, "compiles": 0})
            seconds = stamp - started.pop(key)
            row["seconds"] += seconds
            row["compiles"] += 1
            if id(dispatcher) in listed:
                listed_s[listed[id(dispatcher)]] = listed_s.get(listed[id(dispatcher)], 0.0) + seconds
    rows = sorted(({"kernel": k, **v} for k, v in kernels.items()), key=lambda r: -r["seconds"])
    result = {"cache": "warm" if args.warm else "empty", "warm_up_s": phases, "kernels": rows}
    print(f"numba compile times ({result['cache']} cache; warm-up {phases['total_s']:.1f} s)")
    print(f"{'kernel':<40} {'s':>8} {'compiles':>9}")
    for r in rows:
        print(f"{r['kernel']:<40} {r['seconds']:>8.1f} {r['compiles']:>9d}")
    if args.out:
        write_json(args.out, result)
    if args.write_signatures:
        rows = [
            {"kernel": kernel, "compile_s": round(listed_s.get(kernel, 0.0), 2), "signatures": sigs}
            for kernel, sigs in warmup.compiled_signatures().items()
        ]
        note = (
            "written by scripts/kernel_compile_times.py --write-signatures: the warm-up's kernels, cold compile times"
        )
        write_json(warmup.SIGNATURES_PATH, {"note": note, "kernels": rows})
        print(f"wrote {len(rows)} kernels to {warmup.SIGNATURES_PATH}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
