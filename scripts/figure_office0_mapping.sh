#!/usr/bin/env bash
# The mapping figure of docs/measured-figures.md: office0 re-rendered at 240x136 along every 10th pose (200 frames),
# mapped with the gaus-slam keyframe rule. Needs the Replica sample in ../shared/data (not redistributable).
# Writes runs/office0_240/ (the scene) and runs/office0_gaus_slam/ (metrics.json, mesh.ply, map.ply, strip.png).
# Each run renders the scene again and writes over its earlier output (--overwrite).
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/script_args.sh
source "$REPO/scripts/script_args.sh"
script_args "${BASH_SOURCE[0]}" "$@"
require_replica "$REPO"
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
cd "$REPO"
roigsf scene render --mesh "$DATA/office0_mesh.ply" --traj "$DATA/office0/traj.txt" --cam "$DATA/cam_params.json" \
    --out runs/office0_240 --width 240 --height 136 --stride 10 --overwrite
roigsf map runs/office0_240 --policy gaus-slam --out runs/office0_gaus_slam --overwrite --no-progress
