#!/usr/bin/env bash
# The exact wave image of a sphere (optics = "mie", docs/wave-optics.md): time per plane of the
# sample's 46 um water drop (datasets-sample/drop46/scene.toml at planes -10, 0, +10 um, 27 deg
# cone, 2500 photons per pixel) and, at 1000 photons per pixel, where rays are enough
# (--compare-optics: the chi-square per pixel of the ray image against the wave image).
# Usage: bench/wave_image.sh [OUT=build/bench-wave]
# Prints the per-plane times and the comparison table; the files stay in OUT.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-build/bench-wave}
raymatch=${RAYMATCH:-build/release/apps/raymatch}
mkdir -p "$out"
sed -e 's/^photons_per_pixel = 2500/photons_per_pixel = 2500\noptics = "mie"/' \
    -e 's/^defocus_um = .*/defocus_um = [-10, 0, 10]/' \
    datasets-sample/drop46/scene.toml > "$out/drop46_mie.toml"
echo "== wave image, $(nproc) cores, $(lscpu | sed -n 's/^Model name: *//p'), $(git rev-parse --short HEAD)"
"$raymatch" simulate "$out/drop46_mie.toml" -o "$out/mie" --no-png
echo "== --compare-optics at 1000 photons per pixel"
"$raymatch" simulate "$out/drop46_mie.toml" -o "$out/compare" --compare-optics \
  --photons-per-pixel 1000
