#!/usr/bin/env bash
# What views chosen with hindsight reach where issue 10's targets are missed (thirty-third session).
#
# Pool (PARTS containing "pool"): on the first synthetic room, the eighth room and office0's pool from pose 5, the
# greedy max-coverage pick of 20 views and the same refined by swaps (scripts/pool_bound.py, mapped with each bench's
# own settings and seeds: --map --map-rows greedy,swaps), beside the policies of the bench the verdicts use:
#   runs/bench_pool_synth_240_carved         TAG=carved, the variant alone (scripts/figure_nbv_pool.sh)
#   runs/bench_pool_room7_240_held31         TAG=held31, the variant, the paper's score, fisherrf, random
#   runs/bench_pool_office0_240_o5_held32    TAG=held32 OFFSET=5, the same four
# each made only where missing. Writes runs/hindsight/pool_<scene>/bound.{md,json}.
#
# Stream (PARTS containing "suite"): on the two-room suites (layout 7, the stream tuning scene, and 10, the one
# nothing was chosen on), the benches the verdicts use (KIND=suite SEEDS=3 scripts/figure_nbv_stream_synth.sh with
# BENCHES="gaus-slam stretch fused4-stretch": gaus-slam on both mappers, N alone and the fused score with
# novelty_weight 4 on the stretching one), made only where missing; then scripts/coverage_bound.py at their budget
# (windows of 12, 34 keyframes) with the window oracles (the true coverage in place of the frames' own depth) mapped
# on the stretching mapper (init_max_stretch=4) as the policies' benches were: `oracle` (each window's frame adding
# the most true coverage when it closes), `delayed` (the same one window late), `lookahead` (the policies' own
# lookahead rule, one window, with the true coverage), `ascent` (each window's pick re-chosen with hindsight). Writes
# runs/hindsight/suite_sN/coverage.{md,json}.
#
# PARTS (default "pool suite"), NICE (default 19). Measured 2026-11-28 with the benches present: the pool part about
# 3 min a scene, the stream part 2 min a layout; 25 min in all in a fresh clone that made two of the benches.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/script_args.sh
source "$REPO/scripts/script_args.sh"
script_args "${BASH_SOURCE[0]}" "$@"
PARTS="${PARTS:-pool suite}"
require_words PARTS pool suite
[[ " $PARTS " != *" pool "* ]] || require_replica "$REPO"  # office0 from pose 5 is a pool part
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
cd "$REPO"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
NICE="${NICE:-19}"
PARTS="${PARTS:-pool suite}"
V="roi-gsurfisher:unseen_weight=1:unseen_source=carved"
FOUR="$V,roi-gsurfisher,fisherrf,random"
pool_part() {  # pool_part NAME BENCH [figure_nbv_pool.sh variables...]
    local name=$1 bench=$2
    shift 2
    [ -f "$bench/results.json" ] || env SCALE=2 NICE="$NICE" "$@" bash scripts/figure_nbv_pool.sh
    nice -n "$NICE" python scripts/pool_bound.py "$bench" --out "runs/hindsight/pool_$name" --map \
        --map-rows greedy,swaps
}
if [[ " $PARTS " == *" pool "* ]]; then
    pool_part synth runs/bench_pool_synth_240_carved TAG=carved SCENES=synth "POLICIES=$V:unseen_voxel_m=0.05"
    pool_part room7 runs/bench_pool_room7_240_held31 TAG=held31 SCENES=room7 "POLICIES=$FOUR"
    pool_part office0_o5 runs/bench_pool_office0_240_o5_held32 TAG=held32 SCENES=office0 OFFSET=5 "POLICIES=$FOUR"
fi
if [[ " $PARTS " == *" suite "* ]]; then
    for layout in 7 10; do
        suffix=""; [ "$layout" = 7 ] || suffix="_s$layout"
        benches=runs/bench_stream_suite$suffix
        missing=""
        for group in gaus-slam stretch fused4-stretch; do
            [ -f "$benches/$group/results.json" ] || missing="$missing $group"
        done
        if [ -n "$missing" ]; then
            KIND=suite SEEDS=3 LAYOUT=$layout NICE=$NICE BENCHES="${missing# }" bash scripts/figure_nbv_stream_synth.sh
        fi
        # the scene as figure_nbv_stream_synth.sh renders it (its benches may have been made elsewhere)
        scene="runs/suite_s${layout}_400"
        [ -f "$scene/mesh.ply" ] || roigsf scene synth --kind suite --out "$scene" --seed "$layout" --frames 400 \
            --width 160 --height 120 --overwrite
        nice -n "$NICE" python scripts/coverage_bound.py --scene "$scene" \
            --out "runs/hindsight/suite_s$layout" --window 12 --ref-window 9 --bench "$benches/gaus-slam" \
            --bench "$benches/stretch" --bench "$benches/fused4-stretch" --map oracle --map delayed --map lookahead \
            --map ascent --set init_max_stretch=4
    done
fi
