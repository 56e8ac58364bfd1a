"""One NBV candidate's cost over a training step, in two checkouts compared fairly: fresh interpreters, alternately.

The machine's speed drifts between runs by more than a small change buys (the training step measured 11.5 to
13.6 ms on one morning), so a change is judged by the ratio, in interpreters of the two checkouts run
alternately (base, new, base, new, ...). Each child imports ``roigsf_ros`` from its own tree and runs
:func:`roigsf_ros.perf.nbv.bench_candidate` (``roigsf perf nbv``'s per-candidate rows: the candidate's ROI and
Fisher phases and a training forward+backward, interleaved, medians) for ``roi-gsurfisher`` and ``fisherrf``.
The table gives each child's ratios and each checkout's median; ``--out`` writes them as JSON.

    git worktree add /tmp/base <rev>
    .venv/bin/python scripts/compare_candidate_cost.py /tmp/base . [--rounds 3] [--repeats 41] [--out FILE.json]

A checkout's first child compiles its numba kernels (outside the timed calls) where its cache is cold.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

CHILD = """
import json, sys
repo, surfels, width, height, repeats = sys.argv[1], *map(int, sys.argv[2:6])
sys.path.insert(0, repo)
import roigsf_ros  # first: it sets OMP_WAIT_POLICY before torch loads
from pathlib import Path
assert Path(roigsf_ros.__file__).resolve().is_relative_to(Path(repo).resolve()), roigsf_ros.__file__
import torch
from roigsf_ros.nbv.scorer import NBVScorer
from roigsf_ros.perf import nbv
from roigsf_ros.render.numba_setup import pin_workers, set_numba_threads
torch.set_num_threads(2)
set_numba_threads(2)
pin_workers()
scorer = NBVScorer()
st = nbv.build_state(surfels, width, height, 1, 0.02, scorer)
out = {}
for mode in nbv.MODES:
    r = nbv.bench_candidate(st, scorer, mode, repeats)
    out[mode] = {k: r[k] for k in ("ratio_candidate_over_train", "ratio_fisher_over_train", "train_fwd_bwd_ms",
                                   "candidate_ms", "roi_ms", "fisher_ms")}
print(json.dumps(out))
"""

MODES = ("roi-gsurfisher", "fisherrf")


def run_child(repo: Path, args: argparse.Namespace) -> dict:
    """One fresh interpreter measuring the checkout at ``repo``; its per-mode medians."""
    cmd = [sys.executable, "-c", CHILD, str(repo), str(args.surfels), str(args.width), str(args.height),
           str(args.repeats)]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise SystemExit(f"compare_candidate_cost: the child for {repo} failed:\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> int:
    """Alternate the two checkouts' children, print the table, optionally write JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("base", type=Path, help="the checkout to compare against (a git worktree of the old revision)")
    ap.add_argument("new", type=Path, help="the checkout with the change")
    ap.add_argument("--rounds", type=int, default=3, help="children per checkout, alternating (default 3)")
    ap.add_argument("--repeats", type=int, default=41, help="timed repeats per child and mode; medians (default 41)")
    ap.add_argument("--surfels", type=int, default=20_000, help="surfels in the room (default 20000)")
    ap.add_argument("--width", type=int, default=160, help="image width (default 160)")
    ap.add_argument("--height", type=int, default=120, help="image height (default 120)")
    ap.add_argument("--out", type=Path, help="also write every child's medians here (JSON)")
    args = ap.parse_args()
    for name in ("rounds", "repeats", "surfels", "width", "height"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be >= 1")
    for name in ("base", "new"):
        if not (getattr(args, name) / "roigsf_ros" / "__init__.py").is_file():
            ap.error(f"{name}: {getattr(args, name)} is not a checkout of this package (no roigsf_ros/__init__.py)")
    runs: list[dict] = []
    for i in range(args.rounds):
        for label in ("base", "new"):
            runs.append({"checkout": label, "round": i, **run_child(getattr(args, label), args)})
    head = ("checkout", "round", "mode", "fwd+bwd", "ROI", "Fisher", "F ratio", "ratio")
    widths = (8, 5, 15, 8, 6, 7, 7, 6)
    print(" ".join(f"{h:>{w}}" for h, w in zip(head, widths, strict=True)))
    for r in runs:
        for mode in MODES:
            m = r[mode]
            cells = (r["checkout"], r["round"], mode, f"{m['train_fwd_bwd_ms']:.2f}", f"{m['roi_ms']:.2f}",
                     f"{m['fisher_ms']:.2f}", f"{m['ratio_fisher_over_train']:.3f}",
                     f"{m['ratio_candidate_over_train']:.3f}")  # fmt: skip
            print(" ".join(f"{c:>{w}}" for c, w in zip(cells, widths, strict=True)))
    summary = {
        label: {mode: statistics.median(r[mode]["ratio_candidate_over_train"] for r in runs if r["checkout"] == label)
                for mode in MODES}
        for label in ("base", "new")
    }  # fmt: skip
    for mode in MODES:
        b, n = summary["base"][mode], summary["new"][mode]
        print(f"{mode}: candidate / training step, median of {args.rounds}: base {b:.3f}, new {n:.3f} "
              f"({n / b - 1:+.1%})")  # fmt: skip
    print(f"({args.width}x{args.height}, {args.surfels} surfels, 2 threads, workers pinned; milliseconds, medians "
          f"of {args.repeats}; ratio = (ROI + Fisher) / training fwd+bwd per repeat; 1-min load "
          f"{os.getloadavg()[0]:.1f})")  # fmt: skip
    if args.out:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
        from roigsf_ros.core.fileio import write_json

        write_json(args.out, {"base": str(args.base), "new": str(args.new), "runs": runs, "median_ratio": summary,
                              "surfels": args.surfels, "width": args.width, "height": args.height})  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
