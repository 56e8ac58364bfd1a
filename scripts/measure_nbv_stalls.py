"""Re-measure the three stalls the "NBV scoring speed" section of docs/measured-figures.md names (issue 12), as medians.

1. The TSDF's block-map growth: open3d rehashes the map when an ``integrate`` needs more blocks than it holds (or
   at ``reserve``); the time of the integrate that grew it against the median integrate, and how long another
   Python thread was stalled meanwhile (open3d holds the GIL throughout), with colour (the mesh TSDF) and without
   (the scoring TSDF), synthetic room, 160x120, 2 cm.
2. Eq. 10's sum per candidate: the per-candidate torch formula against ``gain_with`` with the denominators made
   once (the 20k-surfel room of ``roigsf perf nbv``).
3. Importing torch before ``roigsf_ros`` (OpenMP threads spin) against after, beside one busy process: a float32
   -> float64 conversion of 180k values, in two fresh interpreters.

    .venv/bin/python scripts/measure_nbv_stalls.py

Measure on a quiet machine: a job beside it inflates every figure (they are wall times and stalls).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from functools import partial

# roigsf_ros first (it sets OMP_WAIT_POLICY, read when torch loads): torch is imported only through it.
from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.data.scene import MeshRenderer, synth_room, synth_trajectory
from roigsf_ros.mapping.tsdf import TSDFVolume
from roigsf_ros.nbv.scorer import NBVScorer, gain_with, inverse_denominators
from roigsf_ros.perf.nbv import build_state
from roigsf_ros.render.fisher import fisher_diag

CONVERT = "import time, torch; x = torch.rand(60000, 3); t = time.perf_counter()\n" + (
    "for _ in range(200): x.to(torch.float64)\nprint((time.perf_counter() - t) / 200 * 1e3)"
)


def block_map_growth() -> None:
    """1: every 10th frame of the seed-7 room loop fused at 160x120, with colour (the mesh TSDF) and without (the
    scoring TSDF), both from 1000 blocks; the integrates that grew the map apart, then one more doubling.
    """
    intr = Intrinsics(width=160, height=120, fx=128.0, fy=128.0, cx=79.5, cy=59.5)
    renderer, poses = MeshRenderer(synth_room(7)), synth_trajectory(7, 400)[::10]
    frames = [renderer.render(T, intr) for T in poses]
    ticks: list[float] = []
    done = threading.Event()

    def tick() -> None:  # another Python thread: its longest gap is how long the call held the GIL
        while not done.is_set():
            ticks.append(time.perf_counter())
            time.sleep(0.001)

    def timed(fn: Callable[[], object]) -> tuple[float, float]:
        """Wall seconds of fn() and the other thread's longest stall meanwhile."""
        n0, t0 = len(ticks), time.perf_counter()
        fn()
        dt = time.perf_counter() - t0
        return dt, max((b - a for a, b in zip(ticks[n0 - 1 :], ticks[n0:], strict=False)), default=dt)

    ticker = threading.Thread(target=tick)
    ticker.start()
    try:
        for with_color in (True, False):
            tsdf = TSDFVolume(0.02, 0.08, block_count=1000, with_color=with_color)
            hm, times, grown = tsdf.vbg.hashmap(), [], []
            for T, (rgb, depth) in zip(poses, frames, strict=True):
                cap = hm.capacity()
                dt, gap = timed(partial(tsdf.integrate, depth, T, intr, rgb if with_color else None))
                (grown if hm.capacity() != cap else times).append((dt, cap, hm.capacity(), gap))
            cap = hm.capacity()
            dt, gap = timed(partial(hm.reserve, 2 * cap))
            grown.append((dt, cap, hm.capacity(), gap))
            print(f"1. TSDF {'with' if with_color else 'without'} colour ({hm.size()} blocks): integrate median "
                  f"{statistics.median(t[0] for t in times) * 1e3:.1f} ms, all {len(poses)} "
                  f"{sum(t[0] for t in times + grown[:-1]):.2f} s; block map growths: "
                  + ", ".join(f"{dt * 1e3:.0f} ms ({a} -> {b} blocks; another thread stalled {gap * 1e3:.0f} ms)"
                              for dt, a, b, gap in grown))  # fmt: skip
    finally:
        done.set()
        ticker.join()


def gain_per_candidate() -> None:
    """2: Eq. 10 over one candidate's Fisher, 50 calls, median of 5 repeats per formula (alternated)."""
    scorer = NBVScorer()
    st = build_state(20000, 160, 120, 50, 0.02, scorer)
    h, params = st.h_train["roi-gsurfisher"], list(scorer.config.fisher_params)
    f = fisher_diag(st.surfel_map, st.view, st.intr, outputs=scorer.config.fisher_outputs, params=params)
    inv = inverse_denominators(h, {k: tuple(v.shape) for k, v in f.items()}, 0.1)
    rows: dict[str, list[float]] = {"torch formula": [], "gain_with": []}
    for _ in range(5):
        for name, fn in (
            ("torch formula", lambda: sum(float((f[k].double() / (h[k].double() + 0.1)).sum()) for k in f)),
            ("gain_with", lambda: gain_with(f, inv)),
        ):
            t0 = time.perf_counter()
            for _ in range(50):
                fn()
            rows[name].append((time.perf_counter() - t0) / 50 * 1e3)
    print("2. Eq. 10 per candidate: " + ", ".join(f"{k} {statistics.median(v):.3f} ms" for k, v in rows.items()))


def torch_first() -> None:
    """3: the same conversion in two fresh interpreters without OMP_WAIT_POLICY, beside a busy process."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        out = {}
        for name, first in (("torch first", "pass"), ("roigsf_ros first", "import roigsf_ros")):
            code = f"import warnings; warnings.simplefilter('ignore'); {first}\n" + CONVERT
            out[name] = float(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                             check=True).stdout)  # fmt: skip
    finally:
        busy.kill()
        busy.wait()
    print("3. one conversion beside a busy process: " + ", ".join(f"{k} {v:.3f} ms" for k, v in out.items()))


def main(argv: list[str] | None = None) -> int:
    """Run the three measurements in order and print them (no options: ``--help`` says what they are)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.parse_args(argv)  # --help, and any argument refused: the script used to ignore them and measure
    print(f"(1-min load {os.getloadavg()[0]:.1f}; torch and numba at their defaults)")
    block_map_growth()
    gain_per_candidate()
    torch_first()
    return 0


if __name__ == "__main__":
    sys.exit(main())
