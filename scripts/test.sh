#!/usr/bin/env bash
# Sets up (installs missing packages, builds) and runs the fast test set.
# Usage: scripts/test.sh          fast tests (the default CI set)
#        scripts/test.sh --all    also the slow statistical tests (label "slow")
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
if [ "${1:-}" = "--all" ]; then
  ctest --preset release-all -j 2
else
  ctest --preset release -j 2
fi
