"""The recommended variant's first planner requests after a fresh set-up: the set-up's kernel step into an empty numba
cache, then, in a new process, three requests of F3 (``RECOMMENDED_UNSEEN``) timed one by one.

What a user meets first on a fresh machine: with the kernel step's warm-up covering F3, the first request costs what
the next ones do; without it, the first one compiles the carved grid's kernels. ``--checkout DIR`` measures another
checkout's code (e.g. a ``git worktree`` of an older commit) with this interpreter. Room, candidates and sizes are
``roigsf perf nbv``'s (160x120, 20k surfels, 50 candidates); ``--keyframes`` of them synced before the requests.
Prints one JSON line (the step's output line, the requests' seconds and their unseen phases); ``--out`` also writes it.

    .venv/bin/python scripts/first_request_cold.py [--checkout DIR] [--keyframes 16] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

_REQUESTS = r"""
import json, sys, time
sys.path.insert(0, sys.argv[1])
import roigsf_ros  # noqa: F401  first: it sets OMP_WAIT_POLICY before torch loads
from roigsf_ros.nbv.config import NBVConfig
from roigsf_ros.nbv.scorer import NBVScorer
from roigsf_ros.nbv.state import ScoringState
from roigsf_ros.perf import nbv as perf

try:
    from roigsf_ros.nbv.config import RECOMMENDED_UNSEEN as F3
except ImportError:  # a checkout older than the constant: F3's fields as the README then named them
    F3 = {"unseen_weight": 2.0, "unseen_source": "carved", "unseen_measure": "rays"}
st = perf.build_state(20000, 160, 120, 50, 0.04, NBVScorer())
poses = perf.keyframe_poses(st, int(sys.argv[2]))
h = st.h_train["roi-gsurfisher"]
outputs = tuple(NBVConfig().fisher_outputs)
def rgbd(T):
    return perf.map_rgbd(st.surfel_map, T, st.intr)
state = ScoringState(NBVConfig(**F3), st.tsdf.voxel_size_m, st.tsdf.sdf_trunc_m, st.tsdf.depth_max_m)
state.update(st.surfel_map, h, outputs, poses, st.intr, rgbd)
rows = []
for _ in range(3):
    t0 = time.perf_counter()
    res = state.score(st.surfel_map, h, outputs, poses, st.candidates, st.intr, rgbd)
    rows.append({"request_s": time.perf_counter() - t0, "unseen_s": res.timings_s["unseen"]})
print(json.dumps(rows))
"""


def main(argv: list[str] | None = None) -> int:
    """Kernel step into an empty cache, then three timed F3 requests in a new process; one JSON line."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkout", type=Path, default=REPO, help="the checkout whose code runs (default: this one)")
    parser.add_argument("--keyframes", type=int, default=16, help="keyframes synced before the requests (default 16)")
    parser.add_argument("--jobs", type=int, default=2, help="processes of the kernel step (default 2)")
    parser.add_argument("--out", type=Path, help="also write the JSON here")
    args = parser.parse_args(argv)
    checkout = args.checkout.resolve()
    if not (checkout / "roigsf_ros" / "nbv" / "warmup.py").is_file():
        print(f"first_request_cold.py: {checkout} is not a roigsf_ros checkout", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="roigsf-numba-cache-") as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": str(checkout)}
        step = subprocess.run([sys.executable, "-m", "roigsf_ros.nbv.warmup", "--jobs", str(args.jobs)], cwd=checkout,
                              env=env, capture_output=True, text=True, check=True)  # fmt: skip
        req = subprocess.run([sys.executable, "-c", _REQUESTS, str(checkout), str(args.keyframes)], cwd=checkout,
                             env=env, capture_output=True, text=True, check=True)  # fmt: skip
    result = {
        "checkout": str(checkout),
        "keyframes": args.keyframes,
        "kernel_step": step.stdout.strip().splitlines()[-1],
        "requests": json.loads(req.stdout.strip().splitlines()[-1]),
    }
    line = json.dumps(result)
    print(line)
    if args.out:
        sys.path.insert(0, str(REPO))  # this checkout's file helpers (no torch): the measured code is --checkout's
        from roigsf_ros.core.fileio import atomic_path

        with atomic_path(args.out) as tmp:
            tmp.write_text(line + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
