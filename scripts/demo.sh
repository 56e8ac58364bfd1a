#!/usr/bin/env bash
# The main job: set up (idempotent), then run the demo on the shipped bag. Extra args go to `roigsf demo`.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
cd "$REPO"
exec roigsf demo --bag bags/synth_room --out runs/demo "$@"
