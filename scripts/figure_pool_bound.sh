#!/usr/bin/env bash
# Issue 10's pool rows at 240 wide against what a choice of 20 views can reach (twenty-seventh session;
# docs/measured-figures.md, "What a choice of 20 views can reach"). For each scene of SCENES (default: office0 synth
# room3 room4 clutter bins, that section's table's six; any scene of scripts/figure_nbv_pool.sh): the variant's bench
# (TAG=unconfirmed POLICIES=roi-gsurfisher:unseen_weight=1:unseen_backfaces=unconfirmed SCALE=2), the same with
# unseen_measure=area (TAG=area, twenty-eighth session), the unseen term from carved space (TAG=carved
# POLICIES=roi-gsurfisher:unseen_weight=1:unseen_source=carved:unseen_voxel_m=0.05, twenty-ninth session; TAG=cell025
# the same with unseen_voxel_m=0.025, thirtieth session) and the baselines' (TAG=base25
# POLICIES=fisherrf,random SCALE=2), each run by scripts/figure_nbv_pool.sh unless its results.json is there (FORCE=1
# re-runs them), then scripts/pool_bound.py --map on the five: the coverage of all pool views, of a greedy
# max-coverage pick of 20 (the initial views forced: an oracle that knows what every candidate sees) and of each run's
# views, with the oracle's 20 views and all pool views mapped under the bench's own settings, 3 seeds (MAP= leaves
# the mapping out: coverage only, 6-10 s a scene). Writes
# runs/pool_bound/<scene>_240/ (bound.json, bound.md, maps/) and runs/pool_bound/bound.md (every table). Measured
# 2026-11-28 on the 2-core machine: pool_bound.py 7.8 min on the cluttered objects alone, 8-10 min a scene beside
# another bench; the benches 8-14 min a scene when they are not there.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/script_args.sh
source "$REPO/scripts/script_args.sh"
script_args "${BASH_SOURCE[0]}" "$@"
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
cd "$REPO"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
V="roi-gsurfisher:unseen_weight=1:unseen_backfaces=unconfirmed"
SCENES="${SCENES:-office0 synth room3 room4 clutter bins}"
mkdir -p runs/pool_bound
MD="runs/pool_bound/.bound.md.tmp-$$"
trap 'rm -f "$MD"' EXIT
: > "$MD"
for scene in $SCENES; do
    for pair in "unconfirmed:$V" "area:$V:unseen_measure=area" \
        "carved:roi-gsurfisher:unseen_weight=1:unseen_source=carved:unseen_voxel_m=0.05" \
        "cell025:roi-gsurfisher:unseen_weight=1:unseen_source=carved:unseen_voxel_m=0.025" "base25:fisherrf,random"; do
        tag=${pair%%:*}
        if [ "${FORCE:-0}" = 1 ] || [ ! -f "runs/bench_pool_${scene}_240_$tag/results.json" ]; then
            TAG=$tag POLICIES="${pair#*:}" SCALE=2 SCENES="$scene" bash scripts/figure_nbv_pool.sh
        fi
    done
    t0=$(date +%s)
    python scripts/pool_bound.py "runs/bench_pool_${scene}_240_unconfirmed" "runs/bench_pool_${scene}_240_area" \
        "runs/bench_pool_${scene}_240_carved" "runs/bench_pool_${scene}_240_cell025" \
        "runs/bench_pool_${scene}_240_base25" \
        --out "runs/pool_bound/${scene}_240" ${MAP---map --map-rows greedy,all}
    echo "[pool_bound] $scene: $(($(date +%s) - t0)) s"
    cat "runs/pool_bound/${scene}_240/bound.md" >> "$MD"
    echo >> "$MD"
done
mv "$MD" runs/pool_bound/bound.md
echo "wrote runs/pool_bound/bound.md"
