#!/usr/bin/env bash
# Issue 12's long-sequence figure: Replica office0 re-rendered at 240x136 along EVERY pose of its trajectory
# (2000 frames), mapped in trajectory order by `roi-gsurfisher` (the paper's score, one keyframe per window of
# WINDOW = 9 frames), image metrics on every 10th non-keyframe, mesh metrics against the GT mesh. The wall time
# that counts is metrics.json's mapping wall time (target: the whole sequence in <= 10 min on 2 cores).
# Needs the Replica sample in ../shared/data (not redistributable).
# Writes runs/office0_240_s1/ (the scene, reused when present) and runs/office0_full_roi/.
# Each run writes over its earlier map (--overwrite; the rendered scene is reused when its mesh.ply is there).
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/script_args.sh
source "$REPO/scripts/script_args.sh"
script_args "${BASH_SOURCE[0]}" "$@"
require_replica "$REPO"
WINDOW="${WINDOW:-9}"
require_int WINDOW 1
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
cd "$REPO"
if [ ! -f runs/office0_240_s1/mesh.ply ]; then
    roigsf scene render --mesh "$DATA/office0_mesh.ply" --traj "$DATA/office0/traj.txt" --cam "$DATA/cam_params.json" \
        --out runs/office0_240_s1 --width 240 --height 136 --stride 1 --overwrite
fi
roigsf map runs/office0_240_s1 --policy roi-gsurfisher --window "$WINDOW" --eval-every 10 \
    --out runs/office0_full_roi --overwrite --no-progress
