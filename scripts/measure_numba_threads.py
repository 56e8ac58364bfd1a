"""How the numba kernels use their threads, measured: the two choices :mod:`roigsf_ros.render.numba_setup` makes.

1. Workers pinned one per core or left to the scheduler
   (:func:`~roigsf_ros.render.numba_setup.pin_workers` pins them when they are as many as the process's CPUs).
   Fresh interpreters, alternately with ``ROIGSF_PIN_THREADS=0`` and ``1``, each time ``--calls`` training
   steps (forward + backward, as ``roigsf perf render``'s "fwd+bwd") and as many exact geometric Fisher passes
   (``fisher_diag``) of the 20k-surfel room at 160x120, interleaved in blocks of 5. The table gives medians,
   90th percentiles and the share of calls slower than 1.3x the pinned runs' median (the "slow mode").
2. ``prange`` loops only, or numba's default automatic parallelisation as well: the binning kernel of the same
   view (its ~4k kept surfels) compiled both ways, median of 200 calls each, and whether the outputs are equal.

``--out`` writes every call's time as JSON.

    .venv/bin/python scripts/measure_numba_threads.py [--runs 2] [--calls 60] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

BINNING = """
import json, time
import numpy as np
import roigsf_ros
from roigsf_ros.perf.render import room_camera, room_scene
from roigsf_ros.render import rasterize as rz
from roigsf_ros.render.fisher import _f64
from roigsf_ros.render.numba_setup import configure_numba
from roigsf_ros.render.rasterize import camera_tensors

numba = configure_numba()
m = room_scene(20_000)
T, intr = room_camera(160, 120)
V, K = (_f64(t) for t in camera_tensors(T, intr, dtype=m.dtype))
means, quats, log_s, logits = (_f64(t) for t in (m.means, m.quats, m.log_scales, m.opacity_logits))
n = len(means)
pk, nrm, rect, thr = np.empty((n, 14)), np.empty((n, 3)), np.empty((n, 4), np.int32), np.empty(n)
keep = np.empty(n, np.uint8)
rz._KERNELS["project"](means, quats, np.exp(log_s), 1 / (1 + np.exp(-logits)), V, K, 160, 120, 0.2, 100.0, pk, nrm,
                       rect, thr, keep)
args = (pk, nrm, rect, thr, keep, np.zeros((n, 0)), 4, 40, 30, numba.get_num_threads())
prange_only = rz._KERNELS["bin"]
default = numba.njit(parallel=True, nogil=True)(rz._k_bin)  # numba's automatic parallelisation on
out = {"kept": int(keep.sum())}
for name, fn in (("prange_only", prange_only), ("default", default)):
    fn(*args)
    ts = []
    for _ in range(200):
        t0 = time.perf_counter()
        fn(*args)
        ts.append((time.perf_counter() - t0) * 1e3)
    out[name] = ts
out["equal"] = all(np.array_equal(a, b) for a, b in zip(prange_only(*args), default(*args)))
print(json.dumps(out))
"""

CHILD = """
import json, sys, time
import roigsf_ros  # first: it sets OMP_WAIT_POLICY before torch loads
from roigsf_ros.perf.render import room_camera, room_scene
from roigsf_ros.perf.nbv import _train_step
from roigsf_ros.render.fisher import fisher_diag
from roigsf_ros.render.numba_setup import pinned_workers
from roigsf_ros.render.rasterize import render_map

calls = int(sys.argv[1])
m = room_scene(20_000)
T, intr = room_camera(160, 120)
step = _train_step(m, T, intr)
def fisher():
    fisher_diag(m, T, intr)
out = {"train": [], "fisher": []}
for fn in (step, fisher, step, fisher):  # compile / warm up
    fn()
for _ in range(calls // 5):
    for name, fn in (("train", step), ("fisher", fisher)):
        for _ in range(5):
            t0 = time.perf_counter()
            fn()
            out[name].append((time.perf_counter() - t0) * 1e3)
out["pinned"] = len(pinned_workers())
print(json.dumps(out))
"""


def main() -> int:
    """Run the children, print the table, optionally write JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=2, help="fresh interpreters per setting (default 2)")
    ap.add_argument("--calls", type=int, default=60, help="timed calls of each kind per interpreter (default 60)")
    ap.add_argument("--out", type=Path, help="also write every call's time here (JSON)")
    args = ap.parse_args()
    if args.runs < 1 or args.calls < 5:
        ap.error("--runs must be >= 1 and --calls >= 5")
    runs: list[dict] = []
    for _ in range(args.runs):
        for pin in ("0", "1"):
            env = dict(os.environ, ROIGSF_PIN_THREADS=pin)
            res = subprocess.run([sys.executable, "-c", CHILD, str(args.calls)], env=env, capture_output=True,
                                 text=True, check=True)  # fmt: skip
            runs.append({"pin": pin == "1", **json.loads(res.stdout.strip().splitlines()[-1])})
    print(f"{'setting':>10} {'run':>3} {'workers pinned':>14} {'kernel':>7} {'median':>7} {'p90':>7} {'slow':>6}")
    ref = {k: statistics.median([x for r in runs if r["pin"] for x in r[k]]) for k in ("train", "fisher")}
    for i, r in enumerate(runs):
        for k in ("train", "fisher"):
            xs = sorted(r[k])
            slow = sum(x > 1.3 * ref[k] for x in xs) / len(xs)
            print(f"{'pinned' if r['pin'] else 'scheduler':>10} {i // 2:>3} {r['pinned']:>14} {k:>7} "
                  f"{statistics.median(xs):7.1f} {xs[int(0.9 * (len(xs) - 1))]:7.1f} {slow:6.0%}")  # fmt: skip
    print(
        f"(milliseconds; 160x120, 20k surfels, numba at its default threads on {os.cpu_count()} CPUs; slow = calls "
        f"over 1.3x the pinned median; 1-min load {os.getloadavg()[0]:.1f})"
    )
    res = subprocess.run([sys.executable, "-c", BINNING], capture_output=True, text=True, check=True)
    binning = json.loads(res.stdout.strip().splitlines()[-1])
    print(f"binning kernel ({binning['kept']} kept surfels), median of 200: prange loops only "
          f"{statistics.median(binning['prange_only']):.3f} ms, numba's automatic parallelisation as well "
          f"{statistics.median(binning['default']):.3f} ms; outputs equal: {binning['equal']}")  # fmt: skip
    if args.out:
        from roigsf_ros.core.fileio import write_json

        write_json(args.out, {"cpu_count": os.cpu_count(), "calls": args.calls, "runs": runs, "binning": binning})
    return 0


if __name__ == "__main__":
    sys.exit(main())
