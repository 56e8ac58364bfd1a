#!/usr/bin/env bash
# Issue 10's stream setting on the scene the beyond-paper options are checked on (never office0): the synthetic room
# (`roigsf scene synth --seed 7`), one loop of 400 frames at 160x120, mapped in trajectory order by GauS-SLAM's
# keyframe rule and by the policies at 20 % of its keyframes (gaus-slam takes 177 here, so one keyframe per
# window of WINDOW = 12 frames: 1 + 399 // 12 = 34, 19.2 %). One bench per group, in runs/bench_stream_synth/:
#   gaus-slam/  the reference
#   variants/   roi-gsurfisher:window=12:unseen_weight=1, the same with window=24 (trigger every 12), the budget
#               trigger (trigger_every=4, window 12 and 24), random:window=12
#   baselines/  every-n:n=12, roi-gsurfisher:window=12 (the paper)
#   novelty/    roi-gsurfisher:window=12:unseen_weight=1:novelty_weight=1, novelty:window=12 (observed novelty,
#               eighteenth session)
#   lookahead/  novelty:window=12:lookahead=12 and the unseen variant with novelty_weight=1:lookahead=12 (each window
#               decided once the next one is in; nineteenth session)
#   pixels/     novelty:window=12:lookahead=12:novelty_measure=pixels (the novelty counted in the held frames'
#               pixels a frame brings within reach; twenty-first session, tuned on the suite)
#   stretch/    novelty:window=12:lookahead=12 and gaus-slam, both with the mapper's init_max_stretch=4 (new surfels
#               stretched along the surface's tilt; twentieth session's option, twenty-second session's rows)
#   pixels-stretch/  the pixels row with init_max_stretch=4 (twenty-fifth session: the two options together)
#   fused-stretch/   the fused score with both beyond-paper terms and lookahead,
#                    roi-gsurfisher:window=12:unseen_weight=1:novelty_weight=K:lookahead=12 for K = 1, 2, 4, with
#                    init_max_stretch=4 (thirty-second session: the novelty weight chosen here, then run on office0)
#   fused-pixels-stretch/  the same with K = 4 and novelty_measure=pixels (thirty-second session, after K was chosen;
#                    less recall than the area count here, so not run on office0)
#   fused4-stretch/  the fused-stretch group's K = 4 alone (the weight chosen above; for other layouts; only when
#                    BENCHES names it)
#   f3unseen-stretch/  the same with the pool's recommended unseen term (F3's: unseen_weight=2, carved grid, ray count)
#                    in place of its own (fifty-first session; only when BENCHES names it)
# Measured 2026-11-25 on 2 cores beside one other job (load 1.5-3): 179 s, 652 s, about 300 s; novelty/ (2026-11-27)
# about 100 s. BENCHES="a b ..." runs only those folders (default: all); SEEDS=N maps each policy with N seeds.
#
# KIND=suite: the same on `roigsf scene synth --kind suite --seed 7` (two rooms joined by a doorway: a loop in one,
# a walk through the doorway, a loop in the other; nineteenth session, made after the lookahead was fixed), 400
# frames at 160x120, into runs/bench_stream_suite/; gaus-slam takes 182 keyframes there, so WINDOW stays 12 (34
# keyframes, 18.7 %).
# LAYOUT=N (default 7): the scene's layout seed instead of 7, into runs/synth_sN_400/ or runs/suite_sN_400/ and
# runs/bench_stream_{synth,suite}_sN/ (thirty-second session: a suite nothing was chosen on, LAYOUT=10).
# Each run writes over the output of every bench it runs (--overwrite; BENCHES= runs some; the scene is reused).
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/script_args.sh
source "$REPO/scripts/script_args.sh"
script_args "${BASH_SOURCE[0]}" "$@"
WINDOW="${WINDOW:-12}"
SEEDS="${SEEDS:-1}"
require_int WINDOW 1
require_int SEEDS 1
require_words BENCHES gaus-slam variants baselines novelty lookahead pixels stretch pixels-stretch fused-stretch \
    fused4-stretch f3unseen-stretch fused-pixels-stretch
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
KIND="${KIND:-room}"
LAYOUT="${LAYOUT:-7}"
[[ "$LAYOUT" =~ ^[0-9]+$ ]] || { echo "LAYOUT must be a layout seed (a whole number), got $LAYOUT" >&2; exit 2; }
LS=""; [ "$LAYOUT" = 7 ] || LS="_s$LAYOUT"
case "$KIND" in
    room) SCENE=runs/synth_s${LAYOUT}_400 OUT=runs/bench_stream_synth$LS ;;
    suite) SCENE=runs/suite_s${LAYOUT}_400 OUT=runs/bench_stream_suite$LS ;;
    *) echo "KIND must be room or suite, got $KIND" >&2; exit 2 ;;
esac
NICE="${NICE:-5}"
cd "$REPO"
[ -f "$SCENE/mesh.ply" ] || roigsf scene synth --kind "$KIND" --out "$SCENE" --seed "$LAYOUT" --frames 400 --width 160 \
    --height 120 --overwrite
stream_bench() {  # stream_bench OUT POLICIES [bench options]
    local out=$1 policies=$2
    shift 2
    nice -n "$NICE" roigsf bench --scene "$SCENE" --setting stream --policies "$policies" --seeds "$SEEDS" \
        --uncertainty-views 0 --out "$out" --overwrite "$@"
}
bench_group() {  # bench_group NAME POLICIES [bench options]: one folder, unless BENCHES leaves it out
    local name=$1
    shift
    case " ${BENCHES:-$name} " in *" $name "*) stream_bench "$OUT/$name" "$@" ;; esac
}
bench_group gaus-slam "gaus-slam"
R=roi-gsurfisher
W2=$((2 * WINDOW))
bench_group variants "$R:window=$WINDOW:unseen_weight=1,$R:window=$W2:trigger_every=$WINDOW:unseen_weight=1,\
$R:window=$WINDOW:trigger_every=4:trigger=budget:unseen_weight=1,\
$R:window=$W2:trigger_every=4:trigger=budget:budget_every=$WINDOW:unseen_weight=1,random:window=$WINDOW"
bench_group baselines "every-n:n=$WINDOW,roi-gsurfisher:window=$WINDOW"
bench_group novelty "$R:window=$WINDOW:unseen_weight=1:novelty_weight=1,novelty:window=$WINDOW"
bench_group lookahead "novelty:window=$WINDOW:lookahead=$WINDOW,\
$R:window=$WINDOW:unseen_weight=1:novelty_weight=1:lookahead=$WINDOW"
bench_group pixels "novelty:window=$WINDOW:lookahead=$WINDOW:novelty_measure=pixels"
bench_group stretch "novelty:window=$WINDOW:lookahead=$WINDOW,gaus-slam" --set init_max_stretch=4
bench_group pixels-stretch "novelty:window=$WINDOW:lookahead=$WINDOW:novelty_measure=pixels" --set init_max_stretch=4
FUSED="$R:window=$WINDOW:unseen_weight=1:lookahead=$WINDOW"
bench_group fused-stretch "$FUSED:novelty_weight=1,$FUSED:novelty_weight=2,$FUSED:novelty_weight=4" \
    --set init_max_stretch=4
case " ${BENCHES:-} " in  # only when BENCHES names it: the default run has K = 4 in fused-stretch already
    *" fused4-stretch "*) stream_bench "$OUT/fused4-stretch" "$FUSED:novelty_weight=4" --set init_max_stretch=4 ;;
esac
F3U="$R:window=$WINDOW:unseen_weight=2:unseen_source=carved:unseen_measure=rays:novelty_weight=4:lookahead=$WINDOW"
case " ${BENCHES:-} " in  # only when BENCHES names it
    *" f3unseen-stretch "*) stream_bench "$OUT/f3unseen-stretch" "$F3U" --set init_max_stretch=4 ;;
esac
bench_group fused-pixels-stretch "$FUSED:novelty_weight=4:novelty_measure=pixels" --set init_max_stretch=4
