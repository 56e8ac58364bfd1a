#!/usr/bin/env bash
# The CUDA path of the renderer and the mapper, on a machine with an NVIDIA GPU (issue 12; no test depends on one):
#   1. the CUDA tests (-k cuda) of test_render.py and test_fisher.py (the torch backend on CUDA tensors against the
#      dense reference and brute-force Fisher run on the CPU, to 1e-10 in values and gradients; the benchmark room,
#      20k surfels at 160x120, on CUDA against the CPU) and test_mapping_cuda.py (five keyframes mapped with
#      device cuda and on the CPU: the same map size and held-out quality);
#   2. `python -m roigsf_ros.perf.render --device cuda` (forward, forward+backward, exact geometric Fisher);
#   3. the same benchmark with the torch backend on that machine's CPU cores, for a same-machine ratio;
#   4. where that python has numba: the same benchmark with the default numba backend at 1, 2, 4, 8 and 16 threads
#      (capped at the machine's cores), how the CPU kernels scale with cores (the machine's own numba, version recorded).
# Needs python3 with a CUDA build of torch, numpy, opencv, pytest and pytest-timeout (numba optional: the CPU side
# of the mapper test uses it when present); not ROS, rosbags or open3d. The NBV scorer needs open3d (its TSDF),
# which does not fit the 64 MiB a lent machine is sent, so the scorer is not run there.
# Writes $OUT (default runs/device_check/): system.txt, cuda_tests.log, perf_render_cuda.{json,txt},
# perf_render_cpu_torch.{json,txt}, perf_render_numba_threads.{json,txt} (one list of the runs: the device tool sends
# back 8 files at most). Exit status: that of the tests.
# Measured (sessions 12, 16, 24, 43 and 44: an H100, then an H200 four times, via the device tool): the "CUDA" section of
# docs/measured-figures.md.
set -uo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO"
OUT="${OUT:-runs/device_check}"
mkdir -p "$OUT"
PY="${PYTHON:-python3}"
export PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST  # the test set-up's default; nothing here talks ROS

{
    date -u
    nvidia-smi -L 2>&1 || echo "nvidia-smi: not found"
    "$PY" -c 'import torch; print("torch", torch.__version__, "cuda", torch.version.cuda, "available",
        torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")'
    nproc
    lscpu 2>/dev/null | grep -m1 "Model name" || echo "lscpu: no model name"
    "$PY" -c 'import numba; print("numba", numba.__version__)' 2>&1 || true
} 2>&1 | tee "$OUT/system.txt"
if ! "$PY" -c 'import sys, torch; sys.exit(not torch.cuda.is_available())'; then
    echo "device_check: this python's torch sees no CUDA device; nothing to check" >&2
    exit 3
fi

"$PY" -m pytest -q -rs --durations=5 -p no:cacheprovider test/test_render.py test/test_fisher.py test/test_mapping_cuda.py \
    -k cuda 2>&1 |
    tee "$OUT/cuda_tests.log"
tests=${PIPESTATUS[0]}

"$PY" -m roigsf_ros.perf.render --device cuda --repeats 20 --out "$OUT/perf_render_cuda.json" 2>&1 |
    tee "$OUT/perf_render_cuda.txt"
"$PY" -m roigsf_ros.perf.render --device cpu --backend torch --threads "$(nproc)" --repeats 7 \
    --out "$OUT/perf_render_cpu_torch.json" 2>&1 | tee "$OUT/perf_render_cpu_torch.txt"

if "$PY" -c 'import numba' 2>/dev/null; then
    tmp="$(mktemp -d)"
    {
        for t in 1 2 4 8 16; do
            [ "$t" -le "$(nproc)" ] || continue
            echo "== numba, $t threads"
            "$PY" -m roigsf_ros.perf.render --threads "$t" --repeats 7 --out "$tmp/t$t.json"
        done
    } 2>&1 | tee "$OUT/perf_render_numba_threads.txt"
    "$PY" -c 'import json, sys; json.dump([json.load(open(f)) for f in sys.argv[2:]], open(sys.argv[1], "w"), indent=1)' \
        "$OUT/perf_render_numba_threads.json" $(ls "$tmp"/t*.json | sort -V)
    rm -rf "$tmp"
fi
exit "$tests"
