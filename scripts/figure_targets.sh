#!/usr/bin/env bash
# Issue 10's targets, checked by `roigsf targets` on the benches the figure scripts write (twenty-fifth session):
# every verdict of the issue-10 tables in docs/measured-figures.md, from a command instead of by hand.
#
# Pool: the `unconfirmed` variant (TAG=unconfirmed benches of scripts/figure_nbv_pool.sh) against `fisherrf` and
# `random` re-run beside it (TAG=base25), or, on the fourth and fifth rooms, the one bench that holds all of them:
#   TAG=unconfirmed POLICIES=roi-gsurfisher:unseen_weight=1:unseen_backfaces=unconfirmed SCALE=2 SCENES=<s> \
#       bash scripts/figure_nbv_pool.sh          (and TAG=base25 POLICIES=fisherrf,random; also without SCALE=2)
# and the same variant with unseen_measure=area (twenty-eighth session, rows pool_*_area): TAG=area
#   POLICIES=roi-gsurfisher:unseen_weight=1:unseen_backfaces=unconfirmed:unseen_measure=area, against TAG=base25 on
#   every scene, the fourth and fifth rooms included; and with unseen_weight=2 (rows pool_*_k2): TAG=k2
#   POLICIES=roi-gsurfisher:unseen_weight=2:unseen_backfaces=unconfirmed (SCENES=room5 also TAG=unconfirmed, TAG=k4);
#   and with the unseen term from carved space (twenty-ninth session, rows pool_*_carved and pool_*_carveda): TAG=carved
#   POLICIES=roi-gsurfisher:unseen_weight=1:unseen_source=carved:unseen_voxel_m=0.05, and TAG=carveda the same with
#   unseen_measure=area;
#   and (thirtieth session, rows pool_*_floor003, pool_*_floor01, pool_*_cell025) TAG=floor003 / TAG=floor01 the
#   TAG=carved policy with :unseen_min_std=0.003 / 0.01 (tuning scenes only), TAG=cell025
#   POLICIES=roi-gsurfisher:unseen_weight=1:unseen_source=carved:unseen_voxel_m=0.025, and TAG=cell025k2 the same with
#   unseen_weight=2 (tuning scenes only).
# Stream: the rows of scripts/figure_nbv_stream_office0.sh (SEEDS=3; SENSOR=kinect for the Kinect rows) and of
# KIND=suite SEEDS=3 scripts/figure_nbv_stream_synth.sh, each against the `gaus-slam` run with the same mapper and,
# where the mapper differs (init_max_stretch=4), also against the default one (--allow-config-difference).
# Writes runs/targets/<name>.json (one verdict each) and runs/targets/targets.md (every table); a bench that is not
# there is listed as skipped, and a pair `roigsf targets` refuses (other seeds, say) with its error; neither keeps an
# older verdict JSON. 2 min with the set-up's reinstall.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/script_args.sh
source "$REPO/scripts/script_args.sh"
script_args "${BASH_SOURCE[0]}" "$@"
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
cd "$REPO"
OUT=runs/targets
mkdir -p "$OUT"
MD="$OUT/.targets.md.tmp-$$"
trap 'rm -f "$MD"' EXIT
V="roi-gsurfisher:unseen_weight=1:unseen_backfaces=unconfirmed"
: > "$MD"
verdict() {  # verdict NAME CANDIDATE AGAINST... [-- roigsf targets options]
    local name=$1 spec
    shift
    local specs=() opts=()
    while [ $# -gt 0 ]; do
        if [ "$1" = -- ]; then shift; opts=("$@"); break; fi
        specs+=("$1"); shift
    done
    for spec in "${specs[@]}"; do
        if [ ! -f "${spec%%#*}/results.json" ]; then
            printf '### %s\n\nskipped: %s/results.json not found (see the commands at the top of %s)\n\n' \
                "$name" "${spec%%#*}" "scripts/figure_targets.sh" >> "$MD"
            rm -f "$OUT/$name.json"  # an older verdict must not stand for a bench that is gone
            return 0
        fi
    done
    local against=()
    for spec in "${specs[@]:1}"; do against+=(--against "$spec"); done
    printf '### %s\n\n' "$name" >> "$MD"
    if ! roigsf targets "${specs[0]}" "${against[@]}" "${opts[@]}" --out "$OUT/$name.json" >> "$MD" 2>&1; then
        rm -f "$OUT/$name.json"  # an older verdict must not stand for this one
    fi
    printf '\n' >> "$MD"
}
same_bench() {  # same_bench NAME BENCH POLICY: POLICY of the bench folder BENCH against its own fisherrf and random
    verdict "$1" "$2#$3" "$2#fisherrf" "$2#random"
}
pool() {  # pool NAME BENCH_PREFIX: the variant's TAG=unconfirmed bench against the TAG=base25 baselines
    verdict "pool_$1" "runs/bench_pool_$2_unconfirmed" "runs/bench_pool_$2_base25#fisherrf" \
        "runs/bench_pool_$2_base25#random"
}
pool office0_240 office0_240
pool office0_240_kinect office0_240_kinect
pool synth_240 synth_240
pool room1_240 room1_240
pool room2_240 room2_240
for room in room3 room4; do
    verdict "pool_${room}_240" "runs/bench_pool_${room}_240#$V" "runs/bench_pool_${room}_240#fisherrf" \
        "runs/bench_pool_${room}_240#random"
done
pool clutter_240 clutter_240
pool bins_240 bins_240
pool office0_120 office0_120
pool synth_120 synth
pool room1_120 room1
pool clutter_120 clutter
pool shelf_120 shelf
# Twenty-eighth session: the same variant with unseen_measure=area (TAG=area benches) and with unseen_weight=2
# (TAG=k2, the weight chosen on the sixth room, room5, where TAG=unconfirmed and TAG=k4 ran too), against the same
# baselines.
pool_tag() {  # pool_tag TAG NAME BENCH_PREFIX
    verdict "pool_$2_$1" "runs/bench_pool_$3_$1" "runs/bench_pool_$3_base25#fisherrf" "runs/bench_pool_$3_base25#random"
}
for s in office0_240 office0_240_kinect synth_240 room1_240 room2_240 room3_240 room4_240 clutter_240 bins_240 \
    office0_120; do
    pool_tag area "$s" "$s"
done
pool_tag area synth_120 synth
pool_tag area room1_120 room1
pool_tag area clutter_120 clutter
pool_tag area shelf_120 shelf
for tag in unconfirmed k2 k4; do
    pool_tag "$tag" room5_240 room5_240
done
for s in office0_240 synth_240 room3_240 room4_240 clutter_240 bins_240; do
    pool_tag k2 "$s" "$s"
done
# Twenty-ninth session: the unseen term from carved space (unseen_source=carved), counted as the pixel fraction
# (TAG=carved) and as area (TAG=carveda), chosen on the shelf and the sixth room (room5), run on the six scenes above.
for tag in carved carveda; do
    pool_tag "$tag" shelf_120 shelf
    for s in room5_240 office0_240 synth_240 clutter_240 room4_240 bins_240 room3_240; do
        pool_tag "$tag" "$s" "$s"
    done
done
# Thirtieth session: a floor under z(U)'s divisor (TAG=floor003, TAG=floor01: unseen_min_std 0.003, 0.01) and the
# weight 2 with 2.5 cm cells (TAG=cell025k2) on the two tuning scenes only (they lost there), and 2.5 cm carved cells
# (TAG=cell025: unseen_voxel_m=0.025, chosen there), run on the six scenes above, then on the second and third rooms and
# office0 through the Kinect model (with TAG=base25 re-run beside them).
for tag in floor003 floor01 cell025 cell025k2; do
    pool_tag "$tag" shelf_120 shelf
    pool_tag "$tag" room5_240 room5_240
done
for s in office0_240 synth_240 clutter_240 room4_240 bins_240 room3_240 room1_240 room2_240 office0_240_kinect; do
    pool_tag cell025 "$s" "$s"
done
# Thirty-second session: the carved area count with 2.5 cm cells (TAG=cell025a, POLICIES=roi-gsurfisher:unseen_weight=1:
# unseen_source=carved:unseen_measure=area) on the two tuning scenes only (it lost there to TAG=cell025).
pool_tag cell025a shelf_120 shelf
pool_tag cell025a room5_240 room5_240
# Thirty-first session: scenes nothing was chosen or looked at on, run once with every setting fixed beforehand (the
# seventh, eighth and ninth rooms, and office0's pool from pose 10 instead of 0), one bench each holding the variant
# reported first, the paper's score and the baselines:
#   TAG=held31 SCALE=2 POLICIES=roi-gsurfisher:unseen_weight=1:unseen_source=carved,roi-gsurfisher,fisherrf,random \
#       SCENES=<room6|room7|room8> bash scripts/figure_nbv_pool.sh   (and SCENES=office0 OFFSET=10)
# and, thirty-second session, two more the same way: TAG=held32 with SCENES=room9, and SCENES=office0 OFFSET=5; and,
# forty-first session, on the AMD EPYC machine, TAG=held41 with SCENES=office0 OFFSET=15 (no ablation or cells35 run).
for run in held31:room6_240 held31:room7_240 held31:room8_240 held31:office0_240_o10 held32:room9_240 \
    held32:office0_240_o5 held41:office0_240_o15; do
    b="runs/bench_pool_${run#*:}_${run%%:*}"
    for pair in "carved:roi-gsurfisher:unseen_weight=1:unseen_source=carved" "paper:roi-gsurfisher"; do
        same_bench "pool_${run#*:}_${run%%:*}_${pair%%:*}" "$b" "${pair#*:}"
    done
done

# Thirty-fourth session: the variant's fused score without one of its terms, the other weights kept (TAG=abl34;
# POLICIES="$C:epsilon=0,$C:delta=0,$C:epsilon=0:delta=0", $C the variant; SCENES=shelf also runs $C itself, the check
# that it reproduces the TAG=cell025 bench), against the same baselines as the variant's rows above; on the second to
# fifth rooms, the bins and office0 through the Kinect model only the two cheap ones (POLICIES="$C:epsilon=0,
# $C:epsilon=0:delta=0").
C="roi-gsurfisher:unseen_weight=1:unseen_source=carved"
abl() {  # abl NAME BENCH FISHERRF_RANDOM_BENCH ABLATION...: ABLATION is row:policy-options
    local name=$1 bench=$2 base=$3 pair
    shift 3
    for pair in "$@"; do
        verdict "pool_${name}_abl34_${pair%%:*}" "$bench#$C:${pair#*:}" "$base#fisherrf" "$base#random"
    done
}
ALL=("nofisher:epsilon=0" "nocf:delta=0" "uonly:epsilon=0:delta=0")
abl shelf_120 runs/bench_pool_shelf_abl34 runs/bench_pool_shelf_base25 "${ALL[@]}"
for s in room5_240 office0_240 synth_240 clutter_240; do
    abl "$s" "runs/bench_pool_${s}_abl34" "runs/bench_pool_${s}_base25" "${ALL[@]}"
done
for run in held31:room6_240 held31:room7_240 held31:room8_240 held31:office0_240_o10 held32:room9_240 \
    held32:office0_240_o5; do
    abl "${run#*:}" "runs/bench_pool_${run#*:}_abl34" "runs/bench_pool_${run#*:}_${run%%:*}" "${ALL[@]}"
done
for s in room1_240 room2_240 room3_240 room4_240 bins_240 office0_240_kinect; do
    abl "$s" "runs/bench_pool_${s}_abl34" "runs/bench_pool_${s}_base25" "${ALL[0]}" "${ALL[2]}"
done
# Thirty-fifth session: the variant counting the carved frontier cells (TAG=cells35
# POLICIES=roi-gsurfisher:unseen_weight=1:unseen_source=carved:unseen_measure=cells; SCENES=shelf, then SCALE=2), rows
# pool_*_cells35, against the same baselines as the variant's rows.
for s in shelf_120:shelf room5_240 office0_240 synth_240 clutter_240 room1_240 room2_240 room3_240 room4_240 bins_240 \
    office0_240_kinect; do
    pool_tag cells35 "${s%%:*}" "${s#*:}"
done
for run in held31:room6_240 held31:room7_240 held31:room8_240 held31:office0_240_o10 held32:room9_240 \
    held32:office0_240_o5; do
    b="runs/bench_pool_${run#*:}_${run%%:*}"
    verdict "pool_${run#*:}_cells35" "runs/bench_pool_${run#*:}_cells35" "$b#fisherrf" "$b#random"
done
# Thirty-sixth session, on a fresh machine with another CPU (AMD EPYC, AVX2): the variant and both baselines re-run in
# one bench per scene (TAG=base36 POLICIES="$C,fisherrf,random"; SCENES=shelf, then SCALE=2 with SCENES=room5, synth,
# room8, SCENES=office0 OFFSET=5 and room7), rows pool_*_base36; and the unseen term planned over 2 and 4 views on the
# tuning scenes (TAG=plan36 POLICIES="$C:unseen_plan_views=2,$C:unseen_plan_views=4"), rows pool_*_plan36_k2 / _k4,
# against the base36 baselines.
for s in shelf_120:shelf room5_240 synth_240 room7_240 room8_240 office0_240_o5; do
    b="runs/bench_pool_${s#*:}_base36"
    same_bench "pool_${s%%:*}_base36" "$b" "$C"
done
for s in shelf_120:shelf room5_240; do
    for k in 2 4; do
        verdict "pool_${s%%:*}_plan36_k$k" "runs/bench_pool_${s#*:}_plan36#$C:unseen_plan_views=$k" \
            "runs/bench_pool_${s#*:}_base36#fisherrf" "runs/bench_pool_${s#*:}_base36#random"
    done
done
# Fortieth session: the variant alone with its mesh measured after every view from 12 on (TAG=fine40 POLICIES="$C"
# POOL_SET="mesh_checkpoints=4,8,12,13,14,15,16,17,18,19,20" SCALE=2 with SCENES=synth, SCENES=office0 OFFSET=5 and
# SCENES=room8; the same picks and final figures as its base36 runs), rows pool_*_fine40 against the base36
# baselines: the views it needs to reach them, one view at a time.
for s in synth_240 office0_240_o5 room8_240; do
    verdict "pool_${s}_fine40" "runs/bench_pool_${s}_fine40#$C" "runs/bench_pool_${s}_base36#fisherrf" \
        "runs/bench_pool_${s}_base36#random"
done
# Forty-first session: the variant with FisherRF's score as one more fused term (TAG=rf41
# POLICIES="$C:fisherrf_weight=1"; SCENES=shelf and SCALE=2 SCENES=room5, the tuning scenes, on which it lost, so no
# reported scene ran), rows pool_*_rf41 against the base36 baselines.
for s in shelf_120:shelf room5_240; do
    verdict "pool_${s%%:*}_rf41" "runs/bench_pool_${s#*:}_rf41#$C:fisherrf_weight=1" \
        "runs/bench_pool_${s#*:}_base36#fisherrf" "runs/bench_pool_${s#*:}_base36#random"
done
# Forty-second session: the variant counting only unknown stretches of 0.2 m or more, or from the box's side (TAG=st42
# POLICIES="$C:unseen_min_stretch_m=0.2"; SCENES=shelf and SCALE=2 SCENES=room5, the tuning scenes, then SCALE=2 with
# SCENES=room7, SCENES=office0 OFFSET=5, SCENES=synth and SCENES=room8), rows pool_*_st42 against the base36 baselines.
for s in shelf_120:shelf room5_240 room7_240 office0_240_o5 synth_240 room8_240; do
    verdict "pool_${s%%:*}_st42" "runs/bench_pool_${s#*:}_st42#$C:unseen_min_stretch_m=0.2" \
        "runs/bench_pool_${s#*:}_base36#fisherrf" "runs/bench_pool_${s#*:}_base36#random"
done

# Forty-sixth session, on a fresh machine (AMD EPYC, AVX-512): the variant with its unseen term counted in unknown cells
# per ray ("$C:unseen_measure=rays"), chosen on the tuning scenes (TAG=rays46b, against the variant's TAG=base46
# benches; no baseline ran there), then with the variant and both baselines in one bench per reported scene
# (TAG=rep46 POLICIES="$C,$C:unseen_measure=rays,fisherrf,random", SCALE=2 with SCENES=synth, SCENES=office0
# OFFSET=5, SCENES=room8, SCENES=office0 and SCENES=room7), rows pool_*_rep46 (the variant) and pool_*_rep46_rays.
for s in synth_240 office0_240_o5 room8_240 office0_240 room7_240; do
    b="runs/bench_pool_${s}_rep46"
    same_bench "pool_${s}_rep46" "$b" "$C"
    same_bench "pool_${s}_rep46_rays" "$b" "$C:unseen_measure=rays"
done
# Forty-seventh session, the same machine: the variant with unseen_measure=rays and both baselines in one bench per
# reported scene it had not run on (TAG=rep47 POLICIES="$C:unseen_measure=rays,fisherrf,random" SCALE=2 with
# SCENES=bins, SENSOR=kinect SCENES=office0, SCENES=clutter, room1, room2, room3, room4, room6, room9, SCENES=office0
# OFFSET=10 and OFFSET=15; the variant itself not re-run), rows pool_*_rep47_rays.
for s in bins_240 office0_240_kinect clutter_240 room1_240 room2_240 room3_240 room4_240 room6_240 room9_240 \
    office0_240_o10 office0_240_o15; do
    b="runs/bench_pool_${s}_rep47"
    same_bench "pool_${s}_rep47_rays" "$b" "$C:unseen_measure=rays"
done
# Forty-eighth session, the same machine: how much a verdict hangs on one seed, a reading beside the three-seed
# verdicts of record: the same three policies with seeds 0-4 (SEEDS=5 TAG=s5_48
# POLICIES="$C:unseen_measure=rays,fisherrf,random" SCALE=2 with SCENES=synth, SCENES=office0 OFFSET=5 and
# SCENES=room6), rows pool_*_s5_48_rays.
for s in synth_240 office0_240_o5 room6_240; do
    b="runs/bench_pool_${s}_s5_48"
    same_bench "pool_${s}_s5_48_rays" "$b" "$C:unseen_measure=rays"
done
# Forty-ninth session, the same machine: F2 with unseen_weight=2 (F3), chosen on the tuning scenes by the thirtieth
# session's rule (TAG=w49), alone on the reported scenes (TAG=rep49 POLICIES="$C:unseen_measure=rays:unseen_weight=2"
# SCALE=2, runs/s49/rep49.sh's order), against the baselines of the rep46 / rep47 benches (the same machine; nothing in
# the change reaches them), rows pool_*_rep49.
F3="$C:unseen_measure=rays:unseen_weight=2"
for s in synth_240:rep46 office0_240_o5:rep46 bins_240:rep47 office0_240:rep46 room7_240:rep46 room6_240:rep47 \
    clutter_240:rep47 office0_240_kinect:rep47 room1_240:rep47 room2_240:rep47 room3_240:rep47 room4_240:rep47 \
    room8_240:rep46 room9_240:rep47 office0_240_o10:rep47 office0_240_o15:rep47; do
    b="runs/bench_pool_${s%%:*}_${s#*:}"
    verdict "pool_${s%%:*}_rep49" "runs/bench_pool_${s%%:*}_rep49#$F3" "$b#fisherrf" "$b#random"
done
# Fiftieth session, the same machine: the held-out check, scenes made after F3 was chosen and never benched before
# (three rooms, a fifth office0 pool, the dining object scene), F3, F2 and both baselines in one bench each, run once
# and deciding nothing (TAG=held50 POLICIES="$F3,$C:unseen_measure=rays,fisherrf,random" SCALE=2 with SCENES=room10,
# SCENES=office0 OFFSET=3, room11, room12, dining; runs/s50/held50.sh), rows pool_*_held50 (F3) and pool_*_held50_rays
# (F2).
for s in room10_240 office0_240_o3 room11_240 room12_240 dining_240; do
    b="runs/bench_pool_${s}_held50"
    same_bench "pool_${s}_held50" "$b" "$F3"
    same_bench "pool_${s}_held50_rays" "$b" "$C:unseen_measure=rays"
done

S=runs/bench_stream_office0_w13
K=${S}_kinect
U=runs/bench_stream_suite
both_mappers() {  # both_mappers NAME CANDIDATE SAME_MAPPER_REF DEFAULT_REF: a candidate on the stretching mapper
    verdict "$1" "$2" "$3"
    verdict "$1_vs_default" "$2" "$4" -- --allow-config-difference
}
both_mappers stream_office0_stretch4 "$S/novelty-lookahead-stretch4" "$S/gaus-slam-stretch4" "$S/gaus-slam"
# Thirty-first session: the fused ROI-GSurFisher score with the unseen and novelty terms and lookahead, on the mapper
# that stretches new surfels (SEEDS=3 ROWS="gaus-slam gaus-slam-stretch4 unseen-novelty-lookahead-stretch4", and the
# same with SENSOR=kinect for the stream_kinect_fused_* rows below).
both_mappers stream_office0_fused_stretch4 "$S/unseen-novelty-lookahead-stretch4" "$S/gaus-slam-stretch4" "$S/gaus-slam"
# Thirty-second session: the same with novelty_weight 2 and 4 (rows unseen-novelty{2,4}-lookahead-stretch4; the weight
# chosen on the suite's fused-stretch group below, only the chosen one run here).
for k in 2 4; do
    both_mappers "stream_office0_fused${k}_stretch4" "$S/unseen-novelty$k-lookahead-stretch4" "$S/gaus-slam-stretch4" \
        "$S/gaus-slam"
    both_mappers "stream_kinect_fused${k}_stretch4" "$K/unseen-novelty$k-lookahead-stretch4" "$K/gaus-slam-stretch4" \
        "$K/gaus-slam"
done
# Thirty-fifth session: the kappa_n 4 row without one term each (ROWS="unseen-novelty4-lookahead-stretch4-nofisher
# unseen-novelty4-lookahead-stretch4-nocf novelty4-lookahead-stretch4", SEEDS=3, and the same with SENSOR=kinect).
for row in nofisher:unseen-novelty4-lookahead-stretch4-nofisher nocf:unseen-novelty4-lookahead-stretch4-nocf \
    nounseen:novelty4-lookahead-stretch4; do
    both_mappers "stream_office0_fused4_${row%%:*}_stretch4" "$S/${row#*:}" "$S/gaus-slam-stretch4" "$S/gaus-slam"
    both_mappers "stream_kinect_fused4_${row%%:*}_stretch4" "$K/${row#*:}" "$K/gaus-slam-stretch4" "$K/gaus-slam"
done
verdict stream_office0_pixels "$S/novelty-lookahead-pixels" "$S/gaus-slam"
both_mappers stream_office0_pixels_stretch4 "$S/novelty-lookahead-pixels-stretch4" "$S/gaus-slam-stretch4" \
    "$S/gaus-slam"
for w in w10 w11 w12; do
    verdict "stream_office0_lookahead_$w" "$S/novelty-lookahead-$w" "$S/gaus-slam"
done
verdict stream_kinect_lookahead "$K/novelty-lookahead" "$K/gaus-slam"
both_mappers stream_kinect_stretch4 "$K/novelty-lookahead-stretch4" "$K/gaus-slam-stretch4" "$K/gaus-slam"
both_mappers stream_kinect_fused_stretch4 "$K/unseen-novelty-lookahead-stretch4" "$K/gaus-slam-stretch4" "$K/gaus-slam"
verdict stream_kinect_pixels "$K/novelty-lookahead-pixels" "$K/gaus-slam"
both_mappers stream_kinect_pixels_stretch4 "$K/novelty-lookahead-pixels-stretch4" "$K/gaus-slam-stretch4" "$K/gaus-slam"
verdict stream_suite_lookahead "$U/lookahead#novelty:window=12:lookahead=12" "$U/gaus-slam"
verdict stream_suite_stretch4 "$U/stretch#novelty:window=12:lookahead=12" "$U/stretch#gaus-slam"
verdict stream_suite_pixels "$U/pixels" "$U/gaus-slam"
both_mappers stream_suite_pixels_stretch4 "$U/pixels-stretch" "$U/stretch#gaus-slam" "$U/gaus-slam"
# Thirty-second session: KIND=suite SEEDS=3 BENCHES="gaus-slam stretch fused-stretch" scripts/figure_nbv_stream_synth.sh
F="roi-gsurfisher:window=12:unseen_weight=1:lookahead=12"
for k in 1 2 4; do
    both_mappers "stream_suite_fused${k}_stretch4" "$U/fused-stretch#$F:novelty_weight=$k" "$U/stretch#gaus-slam" \
        "$U/gaus-slam"
done
both_mappers stream_suite_fused4_pixels_stretch4 "$U/fused-pixels-stretch" "$U/stretch#gaus-slam" "$U/gaus-slam"
# Thirty-second session, a suite nothing was chosen on (layout seed 10): LAYOUT=10 KIND=suite SEEDS=3
# BENCHES="gaus-slam stretch fused4-stretch" scripts/figure_nbv_stream_synth.sh
U10=runs/bench_stream_suite_s10
both_mappers stream_suite_s10_fused4_stretch4 "$U10/fused4-stretch" "$U10/stretch#gaus-slam" "$U10/gaus-slam"
both_mappers stream_suite_s10_stretch4 "$U10/stretch#novelty:window=12:lookahead=12" "$U10/stretch#gaus-slam" \
    "$U10/gaus-slam"
# Fifty-first session, the tuning suite on the AVX-512 machine: KIND=suite SEEDS=3 BENCHES="fused4-stretch
# f3unseen-stretch gaus-slam stretch" scripts/figure_nbv_stream_synth.sh (the stream variant, the same with F3's unseen
# term, and the references, all re-run on that machine)
both_mappers stream_suite_fused4_stretch4_s51 "$U/fused4-stretch" "$U/stretch#gaus-slam" "$U/gaus-slam"
both_mappers stream_suite_f3unseen_stretch4 "$U/f3unseen-stretch" "$U/stretch#gaus-slam" "$U/gaus-slam"
mv "$MD" "$OUT/targets.md"
trap - EXIT
grep -E '^(###|skipped|roigsf targets: error|.*target for)' "$OUT/targets.md"
