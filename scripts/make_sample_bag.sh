#!/usr/bin/env bash
# Regenerate the shipped sample bag bags/synth_room (+ its ground-truth mesh) from `roigsf scene synth`.
# Deterministic for the seed: re-running reproduces the same frames and mesh, and the poses up to the last bits of
# their quaternions on another CPU.
#
#   bash scripts/make_sample_bag.sh           # rewrites bags/synth_room and bags/synth_room_mesh.ply (tracked files)
#   bash scripts/make_sample_bag.sh --check   # regenerates into a temporary folder and compares with them instead
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/script_args.sh
source "$REPO/scripts/script_args.sh"
# Only --check, or nothing: anything else (--help, a typo such as --chek) used to rewrite the shipped bag.
[ "$*" = --check ] || script_args "${BASH_SOURCE[0]}" "$@"
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
# --check: regenerate into a temporary folder and compare with the shipped files instead of replacing them.
WORK="$(mktemp -d)"
trap 'rm -rf "$WORK"' EXIT
roigsf scene synth --out "$WORK/synth_room" --seed 7 --frames 150 --width 160 --height 120
if [[ "${1:-}" == "--check" ]]; then
    roigsf bag from-replica "$WORK/synth_room" --out "$WORK/bag" --depth-encoding 16UC1 --rate 10 --no-mesh
    rc=0  # non-zero when the mesh or a message differs (the poses by more than their last bits)
    if cmp -s "$WORK/synth_room/mesh.ply" "$REPO/bags/synth_room_mesh.ply"; then echo "mesh: the same"
    else echo "mesh: differs"; rc=1; fi
    python "$REPO/scripts/compare_bags.py" "$REPO/bags/synth_room" "$WORK/bag" || rc=1
    exit "$rc"
fi
roigsf bag from-replica "$WORK/synth_room" --out "$REPO/bags/synth_room" --depth-encoding 16UC1 --rate 10 --no-mesh --overwrite
cp "$WORK/synth_room/mesh.ply" "$REPO/bags/synth_room_mesh.ply"
roigsf bag info "$REPO/bags/synth_room"
