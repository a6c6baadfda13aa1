#!/usr/bin/env bash
# Sets up (installs missing packages, builds) and runs the main job on datasets-sample/,
# writing everything under out/sample/. Open out/sample/index.html (or the PNGs) to look.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
mkdir -p out/sample
exec build/release/apps/raymatch simulate datasets-sample/drop46/scene.toml -o out/sample "$@"
