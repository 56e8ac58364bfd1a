"""A fresh process's first keyframes, as the mapper node inserts them: with and without the node's start-up warm-up.

Each run is a new interpreter that reads the shipped bag, optionally runs :func:`roigsf_ros.nbv.warmup.warm_up_mapping`
(the mapper node's ``warm_up``), then times ``Mapper.keyframe_schedule`` (``optimise_slice_iters`` 2, the Fisher
flushed, as the node runs it) on the bag's first frame and on its eighth. Runs alternate cold / warm, ``--runs`` of
each, one process at a time; writes ``results.json`` (every run, medians) and ``table.md`` into ``--out``.

    .venv/bin/python scripts/first_keyframe.py --runs 3 --out runs/s58/first_keyframe
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

_CHILD = r"""
import json, sys, time
sys.path.insert(0, sys.argv[1])
import roigsf_ros  # noqa: F401  first: it sets OMP_WAIT_POLICY before torch loads
from roigsf_ros.data.bags import read_bag_frames
from roigsf_ros.mapping.mapper import Mapper, MapperConfig
from roigsf_ros.nbv.warmup import warm_up_mapping
from roigsf_ros.nodes.mapper import frame_of

frames, _ = read_bag_frames(sys.argv[2])
warm_s = warm_up_mapping()[1] if sys.argv[3] == "warm" else 0.0
mapper = Mapper(frames[0].intrinsics, MapperConfig())
out = {"warm_up_s": warm_s, "width": frames[0].intrinsics.width, "height": frames[0].intrinsics.height}
for name, bf in (("first_s", frames[0]), ("second_s", frames[7])):
    t0 = time.perf_counter()
    for _ in mapper.keyframe_schedule(frame_of(bf), 2, flush_fisher=True):
        pass
    out[name] = time.perf_counter() - t0
print(json.dumps(out))
"""

KEYS = ("warm_up_s", "first_s", "second_s")


def main(argv: list[str] | None = None) -> int:
    """Time ``--runs`` cold and warm processes, alternating; write results.json and table.md."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, type=Path, help="folder for results.json and table.md")
    parser.add_argument("--runs", type=int, default=3, help="processes of each kind (default 3)")
    parser.add_argument("--bag", default=None, help="bag whose frames are mapped (default: the shipped sample)")
    args = parser.parse_args(argv)
    if args.bag is None:
        from roigsf_ros.data.bags import sample_path

        args.bag = str(sample_path())
    if args.runs < 1:
        parser.error("--runs must be >= 1")
    runs: dict[str, list[dict[str, float]]] = {"cold": [], "warm": []}
    for i in range(args.runs):
        for kind in ("cold", "warm"):
            proc = subprocess.run([sys.executable, "-c", _CHILD, str(REPO), args.bag, kind],
                                  capture_output=True, text=True, timeout=600)  # fmt: skip
            if proc.returncode != 0:
                print(proc.stderr, file=sys.stderr)
                return 1
            runs[kind].append(json.loads(proc.stdout.strip().splitlines()[-1]))
            print(f"{kind} {i + 1}: " + ", ".join(f"{k} {runs[kind][-1][k]:.2f}" for k in KEYS), flush=True)
    medians = {kind: {k: statistics.median(r[k] for r in rs) for k in KEYS} for kind, rs in runs.items()}
    args.out.mkdir(parents=True, exist_ok=True)
    tmp = args.out / "results.json.tmp"
    tmp.write_text(json.dumps({"bag": args.bag, "runs": runs, "median": medians}, indent=2) + "\n")
    tmp.replace(args.out / "results.json")
    rows = ["| process | warm-up (s) | first keyframe (s) | second keyframe (s) |", "|---|---|---|---|"]
    rows += [f"| {kind} (median of {args.runs}) | " + " | ".join(f"{m[k]:.2f}" for k in KEYS) + " |"
             for kind, m in medians.items()]  # fmt: skip
    (args.out / "table.md").write_text("\n".join(rows) + "\n")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
