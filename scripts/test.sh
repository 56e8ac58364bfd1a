#!/usr/bin/env bash
# Run the whole test suite (lint included) after an idempotent set-up. Extra args go to pytest.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# The tests import this checkout's roigsf_ros, not the copy set-up installs (and compiles) in the venv; numba
# caches kernels per source file, so set-up compiles this copy's too (about a second when its cache is warm), at
# the same time as the installed copy's. Without this, the first test to render paid the whole compile (100 s on a
# slow 2-core machine) inside the suite.
export ROIGSF_WARM_CHECKOUT=1
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
cd "$REPO"
# Two pytest-xdist workers, whole files each (a module's fixtures are built once): most system and node tests wait
# on wall-clock time (playback rates, timeouts) with a core idle. Files in collection order, which puts the files
# with `slow` tests first (test/conftest.py; xdist's default reorder by test count left the system tests to run
# alone at the end). `-n 0` (or any -n) among the extra args wins.
WORKERS="${ROIGSF_TEST_WORKERS:-$(( $(nproc) < 2 ? 1 : 2 ))}"
exec python -m pytest -n "$WORKERS" --dist loadfile --no-loadscope-reorder "$@"
