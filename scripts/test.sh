#!/usr/bin/env bash
# Run the whole test suite (lint included) after an idempotent set-up. Extra args go to pytest.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/setup.sh
source "$REPO/scripts/setup.sh"
cd "$REPO"
exec python -m pytest "$@"
