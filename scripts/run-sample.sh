#!/usr/bin/env bash
# Sets up (installs missing packages, builds) and runs the main job on datasets-sample/:
# calibrate -> simulate the focus scan -> compare -> report, all under out/sample/.
# Open out/sample/index.html. Extra arguments go to `raymatch run` (e.g. --ray-fraction 0.25).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
exec build/release/apps/raymatch run datasets-sample/pipeline.toml -o out/sample "$@"
