#!/usr/bin/env bash
# A gradient-index benchmark: a photon-matched image of the sample's size (120 x 100 pixels, 2500
# photons per flat-field pixel, 27 deg cone) of the 46 um water drop whose index comes from a
# 96^3 n(x, y, z) grid (a +20 kg/m^3 pressure-wave shell at r = 15 um, as bench_grin's
# Grid3DDropImage). Writes the grid with NumPy and the scene into OUT, then times
# `raymatch simulate` on all cores.
# Usage: bench/grid3d_drop.sh [OUT=build/grid3d-drop] [extra simulate options, e.g. --threads 1]
#        RAYMATCH_LAUNCH="mpirun -n 2" bench/grid3d_drop.sh ...   (MPI ranks; docs/scale-out.md)
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-build/grid3d-drop}
shift || true
mkdir -p "$out"
/usr/bin/python3 - "$out" <<'PY'
import sys, numpy as np
n = 96
h = 48.0 / (n - 1)
c = -24 + h * np.arange(n)
z, y, x = np.meshgrid(c, c, c, indexing="ij")
r = np.sqrt(x * x + y * y + z * z)
rho = 998.2 + 20 * np.exp(-((r - 15) / 1.5) ** 2)
np.save(sys.argv[1] + "/n3d.npy", 1.3378 + 3.3e-4 * (rho - 998.2))  # linearised water index
PY
cat > "$out/scene.toml" <<'TOML'
name = "grid3d_drop"
wavelength_um = 0.462
medium_index = 1.0
seed = 1
[source]
type = "cone"
half_angle_deg = 27
[[object]]
name = "drop"
type = "sphere"
radius_um = 23
[object.index_field]
type = "grid_3d"
file = "n3d.npy"
spacing_um = [0.5052631578947369, 0.5052631578947369, 0.5052631578947369]
origin_um = [-24, -24, -24]
[objective]
focal_length_mm = 10
na = 0.42
[tube_lens]
focal_length_mm = 200
[camera]
pixels = [120, 100]
pixel_pitch_um = 20
[trace]
photons_per_pixel = 2500
partial_reflection = "unpolarized"
[scan]
defocus_um = [0]
TOML
# shellcheck disable=SC2086
/usr/bin/time -f "wall %e s, max RSS %M kB" ${RAYMATCH_LAUNCH:-} build/release/apps/raymatch simulate "$out/scene.toml" -o "$out/images" "$@"
