#!/usr/bin/env bash
# The stream NBV figure of the README (issue 4): office0 re-rendered at 240x136 along every 5th pose
# (400 frames), mapped in trajectory order with GauS-SLAM's keyframe rule and with ROI-GSurFisher
# choosing one keyframe per window of WINDOW = 9 frames (1 + 399 / 9 = 45 keyframes, 28 % of gaus-slam's 160),
# and a seeded random pick per window of the same size as the control. Needs the Replica sample in
# ../shared/data (not redistributable).
# Writes runs/office0_240_s5/ (the scene, reused when present) and runs/bench_stream_office0/
# (results.json, results.md, quality_vs_views.png, chosen_views.png, uncertainty_*.png, runs/).
# Measured wall time (2026-11-21, 2 cores shared with other jobs): 1832 s, and 841 s for the ablations
# (runs/bench_stream_office0_ablation/).
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
DATA="${ROIGSF_SHARED_DATA:-$REPO/../shared/data}/replica_office0"
WINDOW="${WINDOW:-9}"
SEEDS="${SEEDS:-1}"
[ -f "$DATA/office0_mesh.ply" ] || { echo "Replica office0 sample not found at $DATA" >&2; exit 2; }
cd "$REPO"
if [ ! -f runs/office0_240_s5/mesh.ply ]; then
    roigsf scene render --mesh "$DATA/office0_mesh.ply" --traj "$DATA/office0/traj.txt" --cam "$DATA/cam_params.json" \
        --out runs/office0_240_s5 --width 240 --height 136 --stride 5 --overwrite
fi
roigsf bench --scene runs/office0_240_s5 --setting stream \
    --policies "gaus-slam,roi-gsurfisher:window=$WINDOW,random:window=$WINDOW" --seeds "$SEEDS" \
    --uncertainty-views 0 \
    --out runs/bench_stream_office0 --overwrite
# The ablations of the README's stream table (the method's two terms alone), unless ABLATION=0.
if [ "${ABLATION:-1}" != 0 ]; then
    roigsf bench --scene runs/office0_240_s5 --setting stream \
        --policies "roi-fisher:window=$WINDOW,close-front:window=$WINDOW" --seeds "$SEEDS" \
        --uncertainty-views 0 --out runs/bench_stream_office0_ablation --overwrite
fi
