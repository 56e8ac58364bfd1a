#!/usr/bin/env bash
# Issue 10's pool verdicts of F3, the recommendation (README "Which policy to use"), from one command on any machine
# (sixty-second session): F3, `fisherrf` and `random` in ONE bench per scene (so every verdict compares runs of one
# machine and one code base), on the sixteen reported scenes and the five made after F3 was chosen, 240 wide, 20
# views, 3 seeds, with scripts/figure_nbv_pool.sh's settings; then `roigsf targets` on each bench.
#
# F3's table in docs/measured-figures.md ran F3 alone (TAG=rep49) against baselines of earlier benches; a verdict
# decided by 0.00001 of F@5cm can flip between CPUs ("F3's two narrowest hits on the Intel machine"). This script is how
# to see where a machine stands. It takes about 4 h on a 2-core machine (10-13 min a scene, the scenes' renders
# included), so it keeps every bench it finishes: run again, it skips a scene whose bench is complete (FORCE=1 re-runs).
#
#   bash scripts/figure_f3.sh                      # all 21 scenes, then the verdicts
#   ONLY="office0_o5 room7" bash scripts/figure_f3.sh   # some of them (names as in SCENE_LIST below)
#   TAG=f3b ...                                    # another set of benches (default TAG=f3)
#
# Writes runs/bench_pool_<scene>_240[...]_<TAG>/ (figure_nbv_pool.sh's names), runs/f3_<TAG>/<scene>.json (one
# verdict each, `roigsf targets --out`, its report beside as .txt) and runs/f3_<TAG>/summary.md: each scene's verdict
# line as `roigsf targets` prints it (the checks missed, else the narrowest: margin for what it requires) and the count
# met. Needs the Replica sample in ../shared/data for the office0 scenes.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/script_args.sh
source "$REPO/scripts/script_args.sh"
script_args "${BASH_SOURCE[0]}" "$@"
TAG="${TAG:-f3}"
F3="roi-gsurfisher:unseen_weight=2:unseen_source=carved:unseen_measure=rays"
# name:figure_nbv_pool.sh's settings:bench folder (without runs/bench_pool_ and _TAG); reported first, then held out
SCENE_LIST=(
    "synth:SCENES=synth:synth_240" "office0_o5:SCENES=office0 OFFSET=5:office0_240_o5" "bins:SCENES=bins:bins_240"
    "office0:SCENES=office0:office0_240" "room7:SCENES=room7:room7_240" "room6:SCENES=room6:room6_240"
    "clutter:SCENES=clutter:clutter_240" "office0_kinect:SCENES=office0 SENSOR=kinect:office0_240_kinect"
    "room1:SCENES=room1:room1_240" "room2:SCENES=room2:room2_240" "room3:SCENES=room3:room3_240"
    "room4:SCENES=room4:room4_240" "room8:SCENES=room8:room8_240" "room9:SCENES=room9:room9_240"
    "office0_o10:SCENES=office0 OFFSET=10:office0_240_o10" "office0_o15:SCENES=office0 OFFSET=15:office0_240_o15"
    "room10:SCENES=room10:room10_240" "room11:SCENES=room11:room11_240" "room12:SCENES=room12:room12_240"
    "office0_o3:SCENES=office0 OFFSET=3:office0_240_o3" "dining:SCENES=dining:dining_240"
)
names=()
for entry in "${SCENE_LIST[@]}"; do names+=("${entry%%:*}"); done
require_words ONLY "${names[@]}"  # a name not in the list is an error now, not after hours of benches
[[ "$TAG" =~ ^[A-Za-z0-9_.-]+$ ]] || { echo "TAG=$TAG: letters, digits, '_', '.' and '-' only (it names folders)" >&2; exit 2; }
for name in ${ONLY:-${names[*]}}; do  # the Replica sample checked now, not at the first office0 scene (10-13 min in)
    [[ "$name" != office0* ]] || { require_replica "$REPO"; break; }
done
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
cd "$REPO"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
OUT="runs/f3_$TAG"
mkdir -p "$OUT"
for entry in "${SCENE_LIST[@]}"; do
    name="${entry%%:*}"; rest="${entry#*:}"; settings="${rest%%:*}"; bench="runs/bench_pool_${rest#*:}_$TAG"
    [ -z "${ONLY:-}" ] || [[ " $ONLY " == *" $name "* ]] || continue
    if [ "${FORCE:-0}" != 1 ] && [ -f "$bench/results.json" ]; then
        echo "[f3] $name: $bench is there (FORCE=1 runs it again)"
    else
        t0=$(date +%s)
        # shellcheck disable=SC2086  # the settings are VAR=VALUE words for env
        env $settings TAG="$TAG" POLICIES="$F3,fisherrf,random" SCALE=2 bash scripts/figure_nbv_pool.sh
        echo "[f3] $name: $(($(date +%s) - t0)) s"
    fi
    roigsf targets "$bench#$F3" --against "$bench#fisherrf" --against "$bench#random" --out "$OUT/$name.json" \
        > "$OUT/$name.txt"
done
python - "$OUT" "${names[@]}" <<'PY'
"""runs/f3_<TAG>/summary.md: each scene's verdict line as `roigsf targets` printed it, and the count met."""
import json
import os
import sys
from pathlib import Path

out, names = Path(sys.argv[1]), sys.argv[2:]
rows, met, n = [], 0, 0
for i, name in enumerate(names):
    path = out / f"{name}.json"
    if not path.is_file():
        continue
    head = (out / f"{name}.txt").read_text().splitlines()[0]  # "pool target for `...`: **met** (narrowest ...: ...)"
    held = " (held out)" if i >= 16 else ""
    rows.append(f"| {name}{held} | {head.split('`: ', 1)[1]} |")
    met, n = met + bool(json.loads(path.read_text())["met"]), n + 1
text = "| scene | F3's pool target (`roigsf targets`) |\n|---|---|\n" + "\n".join(rows)
text += f"\n\nF3 meets the target on {met} of {n} scenes.\n"
tmp = out / ".summary.md.tmp"
tmp.write_text(text)
os.replace(tmp, out / "summary.md")
print(text)
PY
