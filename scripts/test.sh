#!/usr/bin/env bash
# Run the whole test suite (lint included) after an idempotent set-up. Extra args go to pytest.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
cd "$REPO"
# The tests import this checkout's roigsf_ros, not the copy set-up installed (and compiled) in the venv; numba
# caches kernels per source file, so compile this copy's too (about a second when its cache is warm). Without
# this, the first test to render paid the whole compile (100 s on a slow 2-core machine) inside the suite.
python -m roigsf_ros.nbv.warmup | sed 's/^/[test] /' >&2
exec python -m pytest "$@"
