#!/usr/bin/env bash
# Issue 10's headline verdicts from one command (twenty-sixth session): the pool rows of the three scenes the issue
# names, at 240 wide (office0 at 240x136, the first synthetic room and the cluttered objects at 240x180: the variant
# roi-gsurfisher:unseen_weight=1:unseen_backfaces=unconfirmed, the same with unseen_measure=area (twenty-eighth
# session, TAG=area), roi-gsurfisher:unseen_weight=1:unseen_source=carved with 5 cm cells (twenty-ninth session,
# TAG=carved) and with 2.5 cm cells (thirtieth session, TAG=cell025: unseen_voxel_m=0.025, the default since), then
# fisherrf and random beside them, 3 seeds each), the
# office0 stream rows of issue 10's 20 % budget, 3 seeds (gaus-slam on the default mapper and with init_max_stretch=4;
# N with lookahead, area and pixels measure, with it; the fused ROI-GSurFisher score with the unseen term and N weighted
# 4, thirty-second session), then scripts/figure_targets.sh on whatever benches are there.
# The same commands as the tables of docs/measured-figures.md (scripts/figure_nbv_pool.sh with TAG=unconfirmed /
# TAG=base25, scripts/figure_nbv_stream_office0.sh with SEEDS=3); each figure script runs the set-up, renders its scene
# once into runs/ and overwrites its bench. Needs the Replica sample in ../shared/data (or $ROIGSF_SHARED_DATA). Writes
# runs/bench_pool_{office0,synth,clutter}_240_{unconfirmed,area,carved,cell025,base25}/,
# runs/bench_stream_office0_w13/<row>/, runs/targets/ (targets.md: every verdict), then scripts/figure_pool_bound.sh
# on the three pool scenes' benches (what a greedy coverage oracle's 20 views and all pool views reach;
# runs/pool_bound/), and prints each step's wall time.
# Measured 2026-11-28 on a fresh 2-core machine in a fresh clone: 55 min (30 min for the pool rows, the set-up from
# nothing included, 25 min for the stream rows), before the pool-bound step (twenty-seventh session: about 8 min a
# scene, measured on its own), the area benches (twenty-eighth session: 3-5 min a scene) and the carved benches
# (twenty-ninth session: 3-7 min a scene; the 2.5 cm ones of the thirtieth session as long) were added.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/script_args.sh
source "$REPO/scripts/script_args.sh"
script_args "${BASH_SOURCE[0]}" "$@"
cd "$REPO"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
V="roi-gsurfisher:unseen_weight=1:unseen_backfaces=unconfirmed"
step() {  # step NAME CMD...: run a figure script, print its wall time
    local name=$1 t0
    shift
    t0=$(date +%s)
    "$@"
    echo "[issue10] $name: $(($(date +%s) - t0)) s"
}
for scene in office0 synth clutter; do
    step "pool $scene 240, the variant" env TAG=unconfirmed POLICIES="$V" SCALE=2 SCENES="$scene" \
        bash scripts/figure_nbv_pool.sh
    step "pool $scene 240, the variant counting unseen area" env TAG=area POLICIES="$V:unseen_measure=area" SCALE=2 \
        SCENES="$scene" bash scripts/figure_nbv_pool.sh
    step "pool $scene 240, the unseen term from carved space" env TAG=carved \
        POLICIES="roi-gsurfisher:unseen_weight=1:unseen_source=carved:unseen_voxel_m=0.05" SCALE=2 SCENES="$scene" \
        bash scripts/figure_nbv_pool.sh
    step "pool $scene 240, the unseen term from carved space, 2.5 cm cells" env TAG=cell025 \
        POLICIES="roi-gsurfisher:unseen_weight=1:unseen_source=carved:unseen_voxel_m=0.025" SCALE=2 SCENES="$scene" \
        bash scripts/figure_nbv_pool.sh
    step "pool $scene 240, fisherrf and random" env TAG=base25 POLICIES=fisherrf,random SCALE=2 SCENES="$scene" \
        bash scripts/figure_nbv_pool.sh
done
step "stream office0, 3 seeds" env SEEDS=3 \
    ROWS="gaus-slam gaus-slam-stretch4 novelty-lookahead-stretch4 novelty-lookahead-pixels-stretch4 \
unseen-novelty4-lookahead-stretch4" \
    bash scripts/figure_nbv_stream_office0.sh
step "verdicts" bash scripts/figure_targets.sh
step "pool bound: office0, synth, clutter" env SCENES="office0 synth clutter" bash scripts/figure_pool_bound.sh
