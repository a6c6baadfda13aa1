#!/usr/bin/env python3
"""A CFD-like test drop (issue 23; docs/sensitivity.md): a 43 um water drop holding an
axisymmetric pressure wave, a spherical shell of +AMPLITUDE kg/m^3 (a smooth cos^2 profile of
compact support across the shell: outside it the density is exactly the reference, so the tracer
crosses those cells in straight steps) whose centre, and so its axis, is offset OFFSET um along x
from the drop's centre, stored
as a 3D density grid [nz][ny][nx] (numpy .npy), and scenes that image it at 405 nm under a 23 deg
cone through a 20x / 0.42 objective with the sample's photon count (2500 per flat-field pixel):

  OUT/rho.npy          density grid, kg/m^3 (998.2 outside the shell)
  OUT/scene.toml       the wave as made (perturbation_scale = 1)
  OUT/scene_ref.toml   the reference drop (perturbation_scale = 0: 998.2 kg/m^3 everywhere)
  OUT/scene_plus4.toml the wave scaled to +4 kg/m^3 (the paper's Fig. 8)

Usage: scripts/make-wave-drop.py OUT [--amplitude-kg-m3 20] [--offset-um 2.5]
       [--shell-radius-um 12] [--shell-width-um 3] [--spacing-um 1]
"""
import argparse
import os

import numpy as np

RADIUS_UM = 21.5  # a 43 um drop
REFERENCE = 998.2  # kg/m^3, water at 20 C


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--amplitude-kg-m3", type=float, default=20.0)
    ap.add_argument("--offset-um", type=float, default=2.5)
    ap.add_argument("--shell-radius-um", type=float, default=12.0)
    ap.add_argument("--shell-width-um", type=float, default=3.0, help="half-width (support)")
    ap.add_argument("--spacing-um", type=float, default=1.0)
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    half = RADIUS_UM + 1.0  # the grid covers the drop with a margin; the field holds its edges
    n = int(np.ceil(2 * half / a.spacing_um)) + 1
    c = -half + a.spacing_um * np.arange(n)
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    d = np.sqrt((x - a.offset_um) ** 2 + y * y + z * z)  # from the wave's centre
    u = np.clip((d - a.shell_radius_um) / a.shell_width_um, -1, 1)
    rho = REFERENCE + a.amplitude_kg_m3 * np.cos(0.5 * np.pi * u) ** 2
    np.save(os.path.join(a.out, "rho.npy"), rho)
    for name, scale, note in (("scene", 1.0, "the wave as made"),
                              ("scene_ref", 0.0, "the reference drop"),
                              ("scene_plus4", 4.0 / a.amplitude_kg_m3, "the wave at +4 kg/m^3")):
        with open(os.path.join(a.out, name + ".toml"), "w") as f:
            f.write(f"""# {note}: scripts/make-wave-drop.py (amplitude {a.amplitude_kg_m3} kg/m^3, axis offset
# {a.offset_um} um along x, shell radius {a.shell_radius_um} um, width {a.shell_width_um} um)
name = "{name}"
wavelength_um = 0.405
medium_index = 1.0
seed = 1
[source]
type = "cone"
half_angle_deg = 23
[[object]]
name = "drop"
type = "sphere"
radius_um = {RADIUS_UM}
[object.index_field]
type = "grid_3d"
file = "rho.npy"
spacing_um = [{a.spacing_um}, {a.spacing_um}, {a.spacing_um}]
origin_um = [{-half}, {-half}, {-half}]
quantity = "density"
temperature_K = 293.15
reference_density_kg_m3 = {REFERENCE}
perturbation_scale = {scale!r}
[objective]
focal_length_mm = 10
na = 0.42
[tube_lens]
focal_length_mm = 200
[camera]
pixels = [64, 64]
pixel_pitch_um = 20
[trace]
photons_per_pixel = 2500
[scan]
defocus_um = [10]
""")
    print(f"{a.out}: rho.npy ({n}^3, {a.spacing_um} um), scene.toml, scene_ref.toml, scene_plus4.toml")


if __name__ == "__main__":
    main()
