#!/usr/bin/env bash
# The pool NBV figures of docs/measured-figures.md (issues 4 and 10): FisherRF's "v20seq1" active reconstruction, 20
# views (4 initial: first + farthest camera centres, then one greedy pick per training phase), 3 seeds,
# policies roi-gsurfisher (the paper), roi-gsurfisher with the unseen-space term (unseen_weight=1, issue 10),
# fisherrf, random (POLICIES=... adds e.g. roi-fisher, close-front), on
#   1. office0 re-rendered at 120x68 along every 20th pose (100 frames; 13 held-out test views,
#      pool = every 2nd of the other 87 -> 44 candidates; SCALE=2 renders 240x136 instead),
#   2. the synthetic room (`roigsf scene synth`, 96 frames at 120x90; 12 test views, 42 candidates), the
#      only scene the unseen term's weight was checked on, and
#   3. an object-centric scene (`roigsf scene synth --kind object`: primitives on a disc, 96 orbit views at
#      120x90, empty background), and
#   4. (SCENES=dome; not in the default list) the same objects seen from a hemisphere (`--kind object-dome`,
#      120 views at 120x90; 15 test views, 53 candidates), where 20 views no longer see everything the pool sees;
#   5. (SCENES=clutter; not in the default list) a 3x3 block of tall boxes 8 cm apart and four open cabinets
#      facing outward, seen from the same hemisphere (`--kind clutter-dome`, 120 views at 120x90), whose insides
#      only a few views see into (2026-11-26: 284 s for the four policies x 3 seeds on a quiet machine).
#   6. (SCENES=shelf; not in the default list) an open shelf, a table with a crate under it and an L of two walls
#      (`--kind shelf-dome`), from the same hemisphere: the scene the options' constants are chosen on.
#   7. (SCENES=bins; not in the default list) two open-top bins, a tunnel and a screen with a crate behind it
#      (`--kind bins-dome`), from the same hemisphere, made after the options were fixed (issue 10, fourteenth session).
#   8. (SCENES=room1, room2, ... room99; not in the default list) more synthetic rooms, `roigsf scene synth --seed N`
#      (another layout, furniture, texture and loop; 96 frames), made after the options were fixed: the check on
#      rooms nothing was chosen on (issue 10, fourteenth session; room10-room12 made in the fiftieth).
#   9. (SCENES=dining; not in the default list) a table with two chairs pushed under it, a cabinet with its door half
#      open, a plank leaning on it and a stool (`--kind dining-dome`), from the same hemisphere, made in the fiftieth
#      session after every option was fixed.
# Schedule (both): 60 steps after the initial views, 20 steps after each added view, no final refinement;
# mapper densify_stride 2 (about 10k surfels), so every policy scores and trains the same way.
# Needs the Replica sample in ../shared/data (not redistributable) for part 1; SCENES=synth skips it.
# Writes runs/office0_<W>_s20/, runs/synth_room_<W>/, ... (scenes, reused when present; W = 120 SCALE) and
# runs/bench_pool_office0_<W>/, runs/bench_pool_{synth,object,dome,clutter,shelf,bins,roomN}/ (_<W> when SCALE > 1;
# results.json, results.md, plots, runs/).
# Measured wall time (2026-11-21, 2 cores shared with other jobs): 1112 s (office0) + 1264 s (synth).
# TAG=name writes runs/bench_pool_<scene>[_<W>]_<name> instead, e.g. one more policy beside a finished bench (issue 10,
# thirteenth session: TAG=surfels POLICIES="roi-gsurfisher:unseen_weight=1:unseen_backfaces=surfels" with
# SCENES="shelf clutter synth", SCALE=2 SCENES="clutter office0", 2-6 min a scene and resolution;
# docs/measured-figures.md lists the others); twenty-third session: TAG=unconfirmed
# POLICIES=roi-gsurfisher:unseen_weight=1:unseen_backfaces=unconfirmed with SCALE=2 and SCENES=clutter, room1, synth,
# room2, bins, office0 (and SENSOR=kinect), then without SCALE with SCENES=shelf, clutter, synth, room1, office0 (2.5-8
# min each); TAG=base23 SCALE=2 SCENES="room1 clutter" POLICIES=fisherrf,random re-ran two scenes' baselines.
# Twenty-fourth session, without TAG: SCALE=2 SCENES=room3 and SCENES=room4 with
# POLICIES=roi-gsurfisher:unseen_weight=1:unseen_backfaces=unconfirmed,roi-gsurfisher:unseen_weight=1,fisherrf,random
# (one comma-separated list; room3 also ,roi-gsurfisher): 23 and 16 min. Twenty-fifth session: TAG=base25
# POLICIES=fisherrf,random beside every unconfirmed bench (SCALE=2 with SCENES=office0, synth, room1, room2, clutter,
# bins and SENSOR=kinect SCENES=office0; without SCALE office0, synth, room1, clutter, shelf; 58 min), for
# scripts/figure_targets.sh. Twenty-eighth session: TAG=area
# POLICIES=roi-gsurfisher:unseen_weight=1:unseen_backfaces=unconfirmed:unseen_measure=area (SCENES=shelf first, the
# tuning scene; then SCALE=2 with SCENES=clutter, room4, bins, office0, synth, room3; 3-5 min each); SCALE=2
# SCENES=room5 (a sixth room, made to choose the unseen term's weight on a room) with TAG=base25, TAG=unconfirmed and
# TAG=k2 / TAG=k4 (POLICIES=roi-gsurfisher:unseen_weight=2 / =4:unseen_backfaces=unconfirmed), then TAG=k2 with SCENES=
# clutter, synth, room3, office0, room4, bins.
# Twenty-ninth session: TAG=carved POLICIES=roi-gsurfisher:unseen_weight=1:unseen_source=carved:unseen_voxel_m=0.05
# (the default cell then) and TAG=carveda (the same with :unseen_measure=area), SCENES=shelf, then SCALE=2
# SCENES=room5 (the two tuning scenes), then SCALE=2 with SCENES=office0, synth, clutter, room4, bins, room3 (3-7 min
# each). Thirtieth session: TAG=floor003 / TAG=floor01 POLICIES=roi-gsurfisher:unseen_weight=1:unseen_source=carved:
# unseen_voxel_m=0.05:unseen_min_std=0.003 / =0.01 and TAG=cell025 POLICIES=roi-gsurfisher:unseen_weight=1:
# unseen_source=carved:unseen_voxel_m=0.025 with SCENES=shelf, then SCALE=2 SCENES=room5 (the tuning scenes; 1-4 min
# each); then TAG=cell025 with SCALE=2 and SCENES=clutter, office0, synth, room4, bins, room3 (3-5 min each); then
# TAG=cell025k2 (the same with unseen_weight=2) with SCENES=shelf and SCALE=2 SCENES=room5; then TAG=cell025 and
# TAG=base25 (POLICIES=fisherrf,random) with SCALE=2 and SCENES=room1, SCENES=room2 and SENSOR=kinect SCENES=office0.
# Thirty-first session (scenes nothing was chosen on, each run once): TAG=held31 SCALE=2 POLICIES=roi-gsurfisher:
# unseen_weight=1:unseen_source=carved,roi-gsurfisher,fisherrf,random with SCENES=room6, room7, room8 and SCENES=office0
# OFFSET=10 (8-10 min each, 40 min in all with the clone's set-up from nothing).
# Thirty-second session: TAG=cell025a POLICIES=roi-gsurfisher:unseen_weight=1:unseen_source=carved:unseen_measure=area
# with SCENES=shelf and SCALE=2 SCENES=room5 (the tuning scenes; 1.4 and 3.6 min).
# Then TAG=held32 with the held31 policies on two more scenes nothing was chosen on: SCALE=2 SCENES=room9 and
# SCENES=office0 OFFSET=5.
# Thirty-fourth session, the variant's score without one term (C=roi-gsurfisher:unseen_weight=1:unseen_source=carved):
# TAG=abl34 POLICIES="$C,$C:epsilon=0,$C:delta=0,$C:epsilon=0:delta=0" SCENES=shelf, then without "$C," SCALE=2 with
# SCENES=room5, office0, synth, clutter, room7, SCENES=office0 OFFSET=5, room6, room8, room9, SCENES=office0 OFFSET=10
# (6-10 min each), then POLICIES="$C:epsilon=0,$C:epsilon=0:delta=0" with SCENES=room1, room2, room3, room4, bins and
# SENSOR=kinect SCENES=office0.
# Thirty-fifth session, the unseen term counted in frontier cells: TAG=cells35
# POLICIES=roi-gsurfisher:unseen_weight=1:unseen_source=carved:unseen_measure=cells SCENES=shelf, then SCALE=2 with
# SCENES=room5, synth, room7, SCENES=office0 OFFSET=5, bins, office0, clutter, room6, room8, room4, room3, room9,
# SCENES=office0 OFFSET=10, room1, room2 and SENSOR=kinect SCENES=office0 (3-4 min each, 55 min in all).
# Thirty-sixth session, on a fresh machine with another CPU: TAG=base36 POLICIES="$C,fisherrf,random" (C as above)
# with SCENES=shelf, then SCALE=2 with SCENES=room5, synth, room8, SCENES=office0 OFFSET=5 and room7 (the variant and
# both baselines again in one bench per scene; 12-45 min each beside another bench); and TAG=plan36
# POLICIES="$C:unseen_plan_views=2,$C:unseen_plan_views=4" with SCENES=shelf, then SCALE=2 SCENES=room5 (the tuning
# scenes; it lost there, so nothing else).
# Fortieth session: TAG=fine40 POLICIES="$C" POOL_SET="mesh_checkpoints=4,8,12,13,14,15,16,17,18,19,20" SCALE=2 with
# SCENES=synth, SCENES=office0 OFFSET=5 and SCENES=room8: the variant's mesh measured after every view from 12 on, for
# the views it needs to reach the baselines (`roigsf targets`; 10-16 min a scene).
# Forty-first session: TAG=rf41 POLICIES="$C:fisherrf_weight=1" with SCENES=shelf, then SCALE=2 SCENES=room5 (the
# tuning scenes; it lost there, so nothing else); and TAG=held41 with the held31 policies, SCALE=2 SCENES=office0
# OFFSET=15 (one more pool nothing was chosen on; 19 min).
# Forty-sixth session, on a fresh machine: TAG=base46 POLICIES="$C" with SCENES=shelf, then SCALE=2 SCENES=room5 (the
# variant again, for scripts/pick_regret.py; 2.6 and 6 min), then TAG=rays46
# POLICIES="roi-gsurfisher:epsilon=0:delta=0:unseen_weight=1:unseen_source=carved:unseen_measure=rays" with the same two
# (the unseen term alone, counted in unknown cells per ray; 1.5 and 3.7 min; it lost there), TAG=rays46b
# POLICIES="$C:unseen_measure=rays" with the same two (it went on), then TAG=rep46
# POLICIES="$C,$C:unseen_measure=rays,fisherrf,random" SCALE=2 with SCENES=synth, SCENES=office0 OFFSET=5, room8,
# office0 and room7 (11-18 min each).
# Forty-seventh session, the same machine: TAG=rep47 POLICIES="$C:unseen_measure=rays,fisherrf,random" SCALE=2 with
# SCENES=bins, SENSOR=kinect SCENES=office0, SCENES=clutter, room1, room2, room3, room4, room6, room9, SCENES=office0
# OFFSET=10 and OFFSET=15 (8.4-15.7 min each, 128 min in all with the scenes rendered from nothing).
# Forty-eighth session, the same machine: TAG=rar48 POLICIES="$F2:unseen_rarity=1,$F2:unseen_rarity=1:
# unseen_rarity_block_m=0.25,$F2:unseen_rarity=0.5" (F2=$C:unseen_measure=rays) with SCENES=shelf, then SCALE=2
# SCENES=room5 (the tuning scenes; 6 and 16 min; none went on, so nothing else); and SEEDS=5 TAG=s5_48
# POLICIES="$F2,fisherrf,random" SCALE=2 with SCENES=synth, SCENES=office0 OFFSET=5 and SCENES=room6 (seeds 0-4: how
# much a three-seed verdict hangs on one seed; 13-17 min each).
# Forty-ninth session, the same machine: TAG=once49 POLICIES="$F2:unseen_carve_rerender=false" with SCENES=shelf, then
# SCALE=2 SCENES=room5 (the carved grid kept between scoring calls; 101 and 247 s; it went no further); TAG=w49
# POLICIES="$F2:unseen_weight=2,$F2:unseen_weight=0.5" with the same two (213 and 549 s; weight 2 went on, F3), then
# TAG=rep49 POLICIES="$F2:unseen_weight=2" SCALE=2 with the forty-seventh session's list and SCENES=synth, SCENES=office0
# OFFSET=5, room7, SCENES=office0, room8 (3.7-6.5 min each, 73 min in all; runs/s49/rep49.sh's order).
# Sixty-second session, the Intel machine: TAG=rep62 POLICIES="$F2:unseen_weight=2,fisherrf,random" (F3 and both
# baselines in one bench) SCALE=2 with SCENES=office0 OFFSET=5 and SCENES=room7 (F3's two narrowest hits; 10-13 min).
# POOL_SET="NAME=VALUE ...": more `--pool-set` items for every bench (PoolConfig fields, e.g. mesh_checkpoints).
# SENSOR=kinect (office0 only): render the frames through the simulated Kinect v1 (`roigsf scene render --sensor kinect`:
# depth noise, holes, disparity steps, noisy colour, poses off by 1e-4..4e-4) into runs/office0_<W>_s20_kinect and
# bench into runs/bench_pool_office0_<W>_kinect[_<TAG>]; recall and precision are still against the true mesh.
# OFFSET=K (office0 only, 1-19): render every 20th pose from pose K instead of 0, a pool of other poses of the same
# trajectory, into runs/office0_<W>_s20[_kinect]_o<K> and bench into runs/bench_pool_office0_<W>[_kinect]_o<K>[_<TAG>]
# (thirty-first session: OFFSET=10, a pool no option was chosen on).
# Issue 10's 240x136 office0 run: SCALE=2 SCENES=office0 SPLIT=1 NICE=19
#   POLICIES="roi-gsurfisher:unseen_weight=1,fisherrf,random,roi-gsurfisher" bash scripts/figure_nbv_pool.sh
# (2026-11-25: 36 min for the four policies x 3 seeds under nice 19 beside other jobs, load 2.6-4).
# Each run writes over its benches' earlier output (--overwrite; a rendered scene is reused when its mesh.ply is there).
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/script_args.sh
source "$REPO/scripts/script_args.sh"
script_args "${BASH_SOURCE[0]}" "$@"
SEEDS="${SEEDS:-3}"
SCENES="${SCENES:-office0 synth object}"
SCALE="${SCALE:-1}"  # office0 at (120 SCALE) x (68 SCALE), the synthetic scenes at (120 SCALE) x (90 SCALE)
require_int SEEDS 1
require_int SCALE 1
for scene in $SCENES; do  # every name checked before any work (an unknown one used to stop the run after the others)
    case "$scene" in
        office0) require_replica "$REPO" ;;
        synth | object | dome | clutter | shelf | bins | dining | room[1-9] | room[1-9][0-9]) ;;
        *) echo "SCENES: unknown scene $scene (office0, synth, object, dome, clutter, shelf, bins, dining, room1 ... room99)" >&2
           exit 2 ;;
    esac
done
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
POLICIES="${POLICIES:-roi-gsurfisher,roi-gsurfisher:unseen_weight=1,fisherrf,random}"
W=$((120 * SCALE)); H=$((68 * SCALE)); HS=$((90 * SCALE))
SUF=""; [ "$SCALE" = 1 ] || SUF="_$W"  # SCALE=1 keeps the synthetic scenes' folder names of the figures
[ -z "${TAG:-}" ] || SUF="${SUF}_$TAG"  # TAG=name: runs/bench_pool_<scene>[_<W>]_<name>, beside a bench kept as it is
COMMON=(--setting pool --seeds "$SEEDS" --overwrite
        --set densify_stride=2
        --pool-set n_views=20 --pool-set pool_stride=2 --pool-set initial_iters=60 --pool-set iters_per_view=20
        --pool-set mesh_samples=50000 --uncertainty-views 6 --uncertainty-maps 3)
for item in ${POOL_SET:-}; do COMMON+=(--pool-set "$item"); done  # POOL_SET="NAME=VALUE ...": more PoolConfig fields
# A synthetic scene (--kind KIND, FRAMES frames, rendered once into runs/NAME_<W>) and its bench under nice LEVEL,
# into runs/bench_pool_OUT (_<W> when SCALE > 1).
# SEED (optional 6th argument, default 0): the scene's layout seed.
synth_bench() {
    local kind="$1" name="$2" frames="$3" out="$4" level="$5" seed="${6:-0}"
    if [ ! -f "runs/${name}_$W/mesh.ply" ]; then
        roigsf scene synth --kind "$kind" --seed "$seed" --out "runs/${name}_$W" --frames "$frames" --width "$W" \
            --height "$HS" --overwrite
    fi
    nice -n "$level" roigsf bench --scene "runs/${name}_$W" "${COMMON[@]}" --policies "$POLICIES" \
        --out "runs/bench_pool_$out$SUF"
}
cd "$REPO"
if [ -n "${SENSOR:-}" ] && [ "$SCENES" != office0 ]; then
    echo "SENSOR=$SENSOR is for SCENES=office0 only (got SCENES=\"$SCENES\")" >&2; exit 2
fi
if [ "${OFFSET:-0}" != 0 ] && { [ "$SCENES" != office0 ] || ! [[ "$OFFSET" =~ ^[0-9]+$ ]] || [ "$OFFSET" -ge 20 ]; }; then
    echo "OFFSET=$OFFSET is for SCENES=office0 only, a pose number 1-19 (got SCENES=\"$SCENES\")" >&2; exit 2
fi
for scene in $SCENES; do
    case "$scene" in
    office0)
        KS=""; SENS=()
        [ -z "${SENSOR:-}" ] || { KS="_$SENSOR"; SENS=(--sensor "$SENSOR"); }
        [ "${OFFSET:-0}" = 0 ] || { KS="${KS}_o$OFFSET"; SENS+=(--offset "$OFFSET"); }
        if [ ! -f "runs/office0_${W}_s20$KS/mesh.ply" ]; then
            roigsf scene render --mesh "$DATA/office0_mesh.ply" --traj "$DATA/office0/traj.txt" \
                --cam "$DATA/cam_params.json" --out "runs/office0_${W}_s20$KS" --width "$W" --height "$H" --stride 20 \
                "${SENS[@]}" --overwrite
        fi
        if [ "${SPLIT:-0}" = 1 ]; then  # one bench per policy (a finished policy is kept if a later one stops)
            IFS=, read -ra PS <<< "$POLICIES"
            for p in "${PS[@]}"; do
                nice -n "${NICE:-0}" roigsf bench --scene "runs/office0_${W}_s20$KS" "${COMMON[@]}" --policies "$p" \
                    --out "runs/bench_pool_office0_${W}$KS${TAG:+_$TAG}/$(echo "$p" | tr ':=' '__')"
            done
        else
            roigsf bench --scene "runs/office0_${W}_s20$KS" "${COMMON[@]}" --policies "$POLICIES" \
                --out "runs/bench_pool_office0_${W}$KS${TAG:+_$TAG}"
        fi
        ;;
    synth) synth_bench room synth_room 96 synth 0 ;;
    object) synth_bench object object 96 object 0 ;;
    dome) synth_bench object-dome object_dome 120 dome "${NICE:-0}" ;;
    clutter) synth_bench clutter-dome clutter_dome 120 clutter "${NICE:-0}" ;;
    # the scene the options' constants are chosen on (clutter is reported, tuned on nothing)
    shelf) synth_bench shelf-dome shelf_dome 120 shelf "${NICE:-0}" ;;
    bins) synth_bench bins-dome bins_dome 120 bins "${NICE:-0}" ;;
    dining) synth_bench dining-dome dining_dome 120 dining "${NICE:-0}" ;;
    room[1-9] | room[1-9][0-9]) synth_bench room "synth_$scene" 96 "$scene" "${NICE:-0}" "${scene#room}" ;;
    esac
done
