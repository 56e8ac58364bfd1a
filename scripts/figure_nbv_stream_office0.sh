#!/usr/bin/env bash
# The stream NBV figures of docs/measured-figures.md on office0 re-rendered at 240x136 along every 5th pose (400
# frames), mapped in trajectory order with GauS-SLAM's keyframe rule and with the NBV policies choosing one keyframe per
# window of frames. Needs the Replica sample in ../shared/data or $ROIGSF_SHARED_DATA (not
# redistributable). Writes runs/office0_240_s5/ (the scene, reused when present).
#
# Issue 10 (default, ISSUE10=1): the 20 % keyframe budget. WINDOW10 = 13 (1 + 399 / 13 = 31 keyframes,
# 19.4 % of gaus-slam's 160); one bench per policy, each in its own folder of runs/bench_stream_office0_w13/
# (so a finished run is kept if a later one fails), in this order:
#   unseen/      roi-gsurfisher:window=13:unseen_weight=1  (unseen_weight chosen on the synthetic room, not here)
#   gaus-slam/   gaus-slam (the reference)
#   random/      random:window=13 (seeded pick per window, the control)
#   paper/       roi-gsurfisher:window=13 (the paper's fused score as published)
#   roi-fisher/  roi-fisher:window=13 (the Fisher term alone)
#   every-n/     every-n:n=13 (every 13th frame: the same count at a fixed cadence, no scoring)
#   budget/      roi-gsurfisher:window=13:trigger_every=4:trigger=budget:unseen_weight=1 (the same budget, keyframes
#                placed where the unseen fraction is high; its settings fixed before any run, checked on the synthetic
#                room by scripts/figure_nbv_stream_synth.sh)
#   novelty/           novelty:window=13 (beyond the paper: per window the frame whose captured depth shows the most
#                      surface no keyframe's depth showed; eighteenth session, its constants fixed before any run)
#   unseen-novelty/    roi-gsurfisher:window=13:unseen_weight=1:novelty_weight=1 (the unseen variant plus z(novelty))
#   paper-novelty/     roi-gsurfisher:window=13:novelty_weight=1 (the paper's score plus z(novelty))
#   budget-novelty/    the budget row with novelty_weight=1 (its gain is then the novelty)
#   unseen-novelty-it52/  unseen-novelty with 52 steps per keyframe (31 x 52 ~ gaus-slam's 160 x 10 steps)
#   novelty-lookahead/         novelty:window=13:lookahead=13 (beyond the paper: each window decided once the next
#                              13 frames are in, by the pair a frame makes with the best of them; nineteenth session)
#   unseen-novelty-lookahead/  unseen-novelty with lookahead=13
#   novelty-lookahead-it52/    novelty-lookahead with 52 steps per keyframe
#   gaus-slam-it40/, novelty-lookahead-it40/      both at 40 steps per keyframe (GauS-SLAM's own mapping budget on a
#                              GPU; the bench's 10 is scaled for the CPU; twentieth session)
#   novelty-lookahead-w14-it40/  the same with window = lookahead = 14 (29 keyframes: gaus-slam takes 154 at 40 steps,
#                              and 31 would be 20.1 % of them)
#   gaus-slam-stretch4/, novelty-lookahead-stretch4/  both with the mapper's new surfels stretched along the surface's
#                              tilt (init_max_stretch=4; twentieth session; with SEEDS=3 in the twenty-second)
#   unseen-novelty-lookahead-stretch4/  unseen-novelty-lookahead on that mapper (thirty-first session: the fused
#                              ROI-GSurFisher score with both beyond-paper terms, SEEDS=3)
#   unseen-novelty2-lookahead-stretch4/, unseen-novelty4-lookahead-stretch4/  the same with novelty_weight=2 and 4
#                              (thirty-second session: only 4, the weight chosen on the suite by
#                              scripts/figure_nbv_stream_synth.sh, was run here)
#   unseen-novelty4-lookahead-stretch4-nofisher/, -nocf/, novelty4-lookahead-stretch4/  that row without one term
#                              each: epsilon=0 (no Fisher), delta=0 (no close-front), unseen_weight=0 (no unseen term)
#                              (thirty-fifth session, SEEDS=3: what each term of the stream variant's score buys)
#   novelty-lookahead-pixels/  novelty-lookahead with novelty_measure=pixels (a candidate's novelty counted in the
#                              held frames' pixels it brings within reach, not its own new area; twenty-first session)
#   novelty-lookahead-pixels-stretch4/  the two together (twenty-fifth session: the suite's best, checked here)
#   novelty-lookahead-w10/     novelty-lookahead with window = lookahead = 10 (40 keyframes, 25 % of gaus-slam's 160:
#                              the ratio of the paper's own Replica claim, 200+ keyframes against GauS-SLAM's 800+)
#   novelty-lookahead-w11/, novelty-lookahead-w12/  the same with 11 and 12 (37 and 34 keyframes, 23 % and 21 %)
# Every row is also evaluated on runs/office0_240_s5_between/ (the poses 2, 7, 12, ... of traj.txt, between the
# mapped ones, which no policy sees: `roigsf bench --test-scene`, columns "PSNR test scene" and "Depth L1 (cm) test
# scene"; the bench's own PSNR is over each run's non-keyframes, a different set for each policy).
# ROWS="a b ..." runs only those folders (default: all). SENSOR=kinect renders the frames through the simulated
# Kinect v1 (`roigsf scene render --sensor kinect`) into runs/office0_240_s5_kinect/ and writes
# runs/bench_stream_office0_w13_kinect/ instead (recall and precision still against the true mesh).
# Each folder: results.json, results.md, quality_vs_views.png, chosen_views.png, runs/.
# Measured wall time (2026-11-25, commit 3d0251f code, 2 cores shared with two other jobs, every bench under
# nice -n 10, so these are inflated): unseen 248 s (load avg 3-4.5; 129 s in a rerun at load ~1),
# gaus-slam 313 s (load 3-4.5; 210 s in a rerun at load ~1.5), random 87 s, paper 133 s, roi-fisher 105 s
# (load 2-3.5); 886 s for the five. Reruns gave identical metrics.
#
# Issue 4 (ISSUE4=1; off by default): the older table, WINDOW = 9 (1 + 399 / 9 = 45 keyframes, 28 % of
# gaus-slam's 160), gaus-slam + roi-gsurfisher + random in runs/bench_stream_office0/ and, unless ABLATION=0,
# roi-fisher + close-front in runs/bench_stream_office0_ablation/. Measured (2026-11-21, older code, 2 cores
# shared): 1832 s, and 841 s for the ablations.
# Each run writes over the output of every row it runs (--overwrite; ROWS= runs some; the rendered scenes are reused).
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/script_args.sh
source "$REPO/scripts/script_args.sh"
script_args "${BASH_SOURCE[0]}" "$@"
WINDOW="${WINDOW:-9}"
WINDOW10="${WINDOW10:-13}"
SEEDS="${SEEDS:-1}"
require_int WINDOW 1
require_int WINDOW10 1
require_int SEEDS 1
mapfile -t ROW_NAMES < <(sed -n 's/^ *row \([a-z0-9-]*\) .*/\1/p' "${BASH_SOURCE[0]}")
require_words ROWS "${ROW_NAMES[@]}"
require_replica "$REPO"
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
NICE="${NICE:-10}"
cd "$REPO"
SCENE=runs/office0_240_s5${SENSOR:+_$SENSOR}
if [ ! -f "$SCENE/mesh.ply" ]; then
    roigsf scene render --mesh "$DATA/office0_mesh.ply" --traj "$DATA/office0/traj.txt" --cam "$DATA/cam_params.json" \
        --out "$SCENE" --width 240 --height 136 --stride 5 ${SENSOR:+--sensor "$SENSOR"} --overwrite
fi
TEST_SCENE=${SCENE}_between
if [ ! -f "$TEST_SCENE/mesh.ply" ]; then  # the true frames (no sensor model): what the map should render
    roigsf scene render --mesh "$DATA/office0_mesh.ply" --traj "$DATA/office0/traj.txt" --cam "$DATA/cam_params.json" \
        --out "$TEST_SCENE" --width 240 --height 136 --stride 5 --offset 2 --overwrite
fi
stream_bench() {  # stream_bench OUT POLICIES [bench options]
    local out=$1 policies=$2
    shift 2
    nice -n "$NICE" roigsf bench --scene "$SCENE" --setting stream --policies "$policies" --seeds "$SEEDS" \
        --uncertainty-views 0 --test-scene "$TEST_SCENE" --out "$out" --overwrite "$@"
}
row() {  # row NAME POLICIES [bench options]: one folder of the issue-10 table, unless ROWS leaves it out
    local name=$1
    shift
    case " ${ROWS:-$name} " in *" $name "*) stream_bench "$W13/$name" "$@" ;; esac
}
if [ "${ISSUE10:-1}" != 0 ]; then
    W13=runs/bench_stream_office0_w13${SENSOR:+_$SENSOR}
    R="roi-gsurfisher:window=$WINDOW10"
    BUDGET="$R:trigger_every=4:trigger=budget:unseen_weight=1"
    row unseen "$R:unseen_weight=1"
    row gaus-slam "gaus-slam"
    row random "random:window=$WINDOW10"
    row paper "$R"
    row roi-fisher "roi-fisher:window=$WINDOW10"
    row every-n "every-n:n=$WINDOW10"
    row budget "$BUDGET"
    row novelty "novelty:window=$WINDOW10"
    row unseen-novelty "$R:unseen_weight=1:novelty_weight=1"
    row paper-novelty "$R:novelty_weight=1"
    row budget-novelty "$BUDGET:novelty_weight=1"
    row unseen-novelty-it52 "$R:unseen_weight=1:novelty_weight=1" --set iters_per_keyframe=52
    row novelty-lookahead "novelty:window=$WINDOW10:lookahead=$WINDOW10"
    row unseen-novelty-lookahead "$R:unseen_weight=1:novelty_weight=1:lookahead=$WINDOW10"
    row novelty-lookahead-it52 "novelty:window=$WINDOW10:lookahead=$WINDOW10" --set iters_per_keyframe=52
    row gaus-slam-it40 "gaus-slam" --set iters_per_keyframe=40
    row novelty-lookahead-it40 "novelty:window=$WINDOW10:lookahead=$WINDOW10" --set iters_per_keyframe=40
    row novelty-lookahead-w14-it40 "novelty:window=14:lookahead=14" --set iters_per_keyframe=40
    row gaus-slam-stretch4 "gaus-slam" --set init_max_stretch=4
    row novelty-lookahead-stretch4 "novelty:window=$WINDOW10:lookahead=$WINDOW10" --set init_max_stretch=4
    row unseen-novelty-lookahead-stretch4 "$R:unseen_weight=1:novelty_weight=1:lookahead=$WINDOW10" \
        --set init_max_stretch=4
    row unseen-novelty2-lookahead-stretch4 "$R:unseen_weight=1:novelty_weight=2:lookahead=$WINDOW10" \
        --set init_max_stretch=4
    row unseen-novelty4-lookahead-stretch4 "$R:unseen_weight=1:novelty_weight=4:lookahead=$WINDOW10" \
        --set init_max_stretch=4
    S4="$R:unseen_weight=1:novelty_weight=4:lookahead=$WINDOW10"
    row unseen-novelty4-lookahead-stretch4-nofisher "$S4:epsilon=0" --set init_max_stretch=4
    row unseen-novelty4-lookahead-stretch4-nocf "$S4:delta=0" --set init_max_stretch=4
    row novelty4-lookahead-stretch4 "$R:novelty_weight=4:lookahead=$WINDOW10" --set init_max_stretch=4
    row novelty-lookahead-pixels "novelty:window=$WINDOW10:lookahead=$WINDOW10:novelty_measure=pixels"
    row novelty-lookahead-pixels-stretch4 "novelty:window=$WINDOW10:lookahead=$WINDOW10:novelty_measure=pixels" \
        --set init_max_stretch=4
    row novelty-lookahead-w10 "novelty:window=10:lookahead=10"
    row novelty-lookahead-w11 "novelty:window=11:lookahead=11"
    row novelty-lookahead-w12 "novelty:window=12:lookahead=12"
fi
if [ "${ISSUE4:-0}" != 0 ]; then
    stream_bench runs/bench_stream_office0 "gaus-slam,roi-gsurfisher:window=$WINDOW,random:window=$WINDOW"
    # The ablations of the stream table in docs/measured-figures.md (the method's two terms alone), unless ABLATION=0.
    if [ "${ABLATION:-1}" != 0 ]; then
        stream_bench runs/bench_stream_office0_ablation "roi-fisher:window=$WINDOW,close-front:window=$WINDOW"
    fi
fi
