#!/usr/bin/env bash
# The main job: set up (idempotent), then the active-mapping demo on the shipped bag: the bag player and
# active_mapping (mapper + NBV planner + keyframe selector, policy roi-gsurfisher) in one process, a progress
# line, then a table and runs/demo/ (metrics.json, mesh.ply, map.ply, plot.png, strip.png, replay.json).
# Extra args go to `roigsf demo`, e.g. --policy gaus-slam, --rate 0.5, --set mapper.iters_per_keyframe=20.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
cd "$REPO"
exec roigsf demo --bag bags/synth_room --out runs/demo "$@"
