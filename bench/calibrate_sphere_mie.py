#!/usr/bin/python3
"""`raymatch calibrate sphere --optics mie` on wave images of a monochromatic drop in air
(docs/calibration.md, "With the wave model"), over noise seeds.

The experiment: the sample's light field measured by `calibrate lightfield` (cut at the NA),
continued by a soft edge 0.6 deg beyond the NA, 1 deg wide, its axis tilted [0.3, -0.2] deg; an
8 um water drop (index 1.33935) in air at (0.3, -0.2, 0.4) um, 0.462 um light, a camera blur of
0.1 um beyond diffraction; 44 x 44 pixels of 0.5 um, planes -4 and +4 um at 1000 photons per
pixel (--large: 64 x 64 pixels, planes -6, 0, +6 um fitted jointly, 2500 photons). The
metadata gives the nominal diameter 0.02 um large and 293.15 K (water's index 0.0005 below the
truth); the calibration starts the edge 1 deg beyond the NA, untilted, the PSF at 0.05 lambda/NA.
With --from truth the calibration's fit file is also run from the truth (the deviance the fit
from the user's start can be compared with); --from drop and --from nuisances start only the
drop's five parameters, or only the edge, PSF and tilt, at the truth (the others at the
calibration's starts).

Usage: bench/calibrate_sphere_mie.py OUT [--seeds 1 2 3] [--large] [--from truth drop nuisances]
       [--rays]
Prints per seed the errors in reported sigmas (x, y, z, radius, index, edge half-angle, PSF,
tilt x, tilt y), the deviance against its expectation and the time.
Environment: RAYMATCH (the executable; default build/release/apps/raymatch).
"""
import argparse
import json
import os
import re
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RAYMATCH = os.environ.get("RAYMATCH", os.path.join(ROOT, "build/release/apps/raymatch"))
NA_DEG = 24.8346  # the sample's objective, NA 0.42 in air (its light field's cut)
TRUTH = {"object.drop.center_um[0]": 0.3, "object.drop.center_um[1]": -0.2,
         "object.drop.center_um[2]": 0.4, "object.drop.radius_um": 8.0,
         "object.drop.index": 1.33935, "light_field_edge.half_angle_deg": NA_DEG + 0.6,
         "camera.psf_sigma_um": 0.1, "light_field_edge.tilt_deg[0]": 0.3,
         "light_field_edge.tilt_deg[1]": -0.2}


def truth_scene(lf, seed, large):
    pixels, photons, planes = ((64, 2500, [-6, 0, 6]) if large else (44, 1000, [-4, 4]))
    return planes, f"""name = "wave"
seed = {seed}
calibration = "{lf}"
[[object]]
name = "drop"
type = "sphere"
center_um = [0.3, -0.2, 0.4]
radius_um = 8
index = 1.33935
[light_field_edge]
half_angle_deg = {NA_DEG + 0.6!r}
width_deg = 1
tilt_deg = [0.3, -0.2]
[camera]
pixels = [{pixels}, {pixels}]
psf_sigma_um = 0.1
[trace]
optics = "mie"
photons_per_pixel = {photons}
[scan]
defocus_um = {planes}
"""


METADATA = """scan = "scan.csv"
object = "water drop"
nominal_diameter_um = 16.02
temperature_K = 293.15
[camera]
pixel_pitch_um = 10
bit_depth = 16
gain_e_per_dn = 1
well_capacity_e = 65535
read_noise_e = 0
[optics]
objective_focal_mm = 10
na = 0.42
working_distance_mm = 20
tube_focal_mm = 200
wavelength_um = 0.462
"""


def line(fit, wall):
    g = fit["goodness_of_fit"]
    errs = " ".join(f"{(p['best'] - TRUTH[p['key']]) / p['sigma']:+.1f}" if p["sigma"] else "n/a"
                    for p in fit["parameters"])
    return (f"{errs} | deviance {g['deviance']:.0f} for {g['expected_deviance']:.0f} +- "
            f"{g['expected_deviance_sd']:.0f}{' MISMATCH' if g['model_mismatch'] else ''} | "
            f"{wall:.0f} s")


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 7])
    ap.add_argument("--large", action="store_true", help="64 x 64 pixels, 3 planes, 2500 photons")
    ap.add_argument("--from", dest="starts", nargs="+", default=[],
                    choices=["truth", "drop", "nuisances"],
                    help="also fit from these starts at the truth")
    ap.add_argument("--rays", action="store_true", help="calibrate with rays instead")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    lf = os.path.abspath(os.path.join(a.out, "lf.toml"))
    if not os.path.exists(lf):
        subprocess.run([RAYMATCH, "calibrate", "lightfield",
                        os.path.join(ROOT, "datasets-sample/lightfield"), "-o", lf],
                       check=True, stdout=subprocess.DEVNULL)
    print("seed | errors / sigma: x y z radius index edge PSF tilt-x tilt-y | goodness | time")
    for seed in a.seeds:
        d = os.path.join(a.out, f"seed{seed}")
        drop = os.path.join(d, "drop")
        os.makedirs(drop, exist_ok=True)
        planes, text = truth_scene(lf, seed, a.large)
        with open(os.path.join(drop, "truth.toml"), "w") as f:
            f.write(text)
        subprocess.run([RAYMATCH, "simulate", "truth.toml", "-o", ".", "--no-png", "-q"],
                       cwd=drop, check=True)
        scan = json.load(open(os.path.join(drop, "wave_scan.json")))
        with open(os.path.join(drop, "scan.csv"), "w") as f:
            f.write("defocus_um,file\n" + "".join(f"{p['defocus_um']},{p['image']}\n"
                                                  for p in scan["planes"]))
        with open(os.path.join(drop, "metadata.toml"), "w") as f:
            f.write(METADATA)
        cmd = [RAYMATCH, "calibrate", "sphere", drop, "--base", lf, "-o",
               os.path.join(d, "sphere.toml"), "--optics", "rays" if a.rays else "mie",
               "--planes-um", *[str(p) for p in planes]]
        t0 = time.time()
        subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wall = time.time() - t0
        work = os.path.join(d, "sphere_sphere")
        print(f"{seed} | {line(json.load(open(os.path.join(work, 'fit.json'))), wall)}", flush=True)
        for start in a.starts:  # the same fit file from (part of) the truth
            scene = open(os.path.join(work, "scene.toml")).read()
            for key, value in TRUTH.items():
                if start == "truth" or (start == "drop") == key.startswith("object."):
                    scene = set_key(scene, key, value)
            t = os.path.join(d, "from_" + start)
            os.makedirs(t, exist_ok=True)
            with open(os.path.join(t, "scene.toml"), "w") as f:
                f.write(scene)
            with open(os.path.join(t, "fit.toml"), "w") as f:
                f.write(open(os.path.join(work, "fit.toml")).read())
            t0 = time.time()
            subprocess.run([RAYMATCH, "fit", "fit.toml", "-o", ".", "-q"], cwd=t,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            wall = time.time() - t0
            print(f"{seed} from the truth ({start}) | "
                  f"{line(json.load(open(os.path.join(t, 'fit.json'))), wall)}", flush=True)
    return 0


def set_key(scene, key, value):
    """The calibration's scene.toml with one fit key set (its own simple layout)."""
    m = re.fullmatch(r"(?:object\.drop\.|light_field_edge\.|camera\.)(\w+)(?:\[(\d)\])?", key)
    name, index = m.group(1), m.group(2)
    pat = re.compile(rf"^{name} = (.*)$", re.M)
    old = pat.search(scene)
    if index is None:
        return scene[:old.start(1)] + repr(value) + scene[old.end(1):]
    items = [v.strip() for v in old.group(1).strip("[] ").split(",")]
    items[int(index)] = repr(value)
    return scene[:old.start(1)] + "[" + ", ".join(items) + "]" + scene[old.end(1):]


if __name__ == "__main__":
    sys.exit(main())
