#!/usr/bin/env python3
"""ctest report_browser: makes every kind of report from small, fast inputs and opens each in
headless Chromium (browser_check.py): a script error, a console/log error or an image that does
not load fails the test; full-page screenshots go to <build>/tests/report/screenshots/.

  1. the committed sample (datasets-sample/) through `raymatch run` with 2 % of the rays
     (about 50 photons per pixel) and one small fit (a 3 x 3 grid at 1 % of the rays, 3 s):
     index.html (light field, corrector, montage, heatmaps, fit summary), compare/report.html
     (heatmaps, montage, residual maps and radial profiles per plane),
     mesh_object/compare/report.html and fit/small_grid/report.html;
  2. `raymatch bench accuracy` on a 48 x 48 scene: accuracy.png (accuracy against time).
Skipped (exit 77) when chromium is not installed.
Usage: report_browser_test.py RAYMATCH SOURCE_DIR WORK_DIR
"""
import os
import shutil
import subprocess
import sys
import time

import browser_check

PIPELINE = """# report_browser test: the sample at 2 % of the rays, one small fit
output = "out"
[calibration]
lightfield = "{s}/lightfield"
corrector = "{s}/flatfield"
zones = 9
[experiment]
scan = "{s}/drop46"
mesh_object = "{s}/merging"
[simulation]
ray_fraction = 0.02
seed = 1
[fit]
files = ["small_grid.toml"]
"""

# Radius and axial position of the 46 um drop on a 3 x 3 grid at 1 % of the rays, one image.
FIT = """scene = "{s}/fit/sphere_scene.toml"
method = "grid"
error = "poisson"
seed = 5
[[image]]
file = "{s}/drop46/drop_z-10um.tif"
defocus_um = -10
dark = "{s}/drop46/dark.tif"
gain_e_per_dn = 1.0989011
[[parameter]]
key = "object.drop.radius_um"
lower = 22
upper = 24
points = 3
[[parameter]]
key = "object.drop.center_um[2]"
lower = -2
upper = 2
points = 3
[rays]
ray_factor = 1
fractions = [0.01]
[uncertainty]
repeat_seeds = 0
slice_points = 3
"""

SCENE = """[source]
type = "cone"
half_angle_deg = 20
[[object]]
type = "sphere"
radius_um = 8
index = 1.33
[objective]
focal_length_mm = 10
na = 0.42
[tube_lens]
focal_length_mm = 200
[camera]
pixels = [48, 48]
pixel_pitch_um = 10
[trace]
photons_per_pixel = 100
"""


def sh(cmd, log):
    t0 = time.monotonic()
    with open(log, "w") as f:
        rc = subprocess.call(cmd, stdout=f, stderr=subprocess.STDOUT)
    print(f"{' '.join(cmd)}: exit {rc}, {time.monotonic() - t0:.1f} s")
    if rc not in (0, 1, 2):  # run / compare verdicts (pass, warning, fail) still write reports
        print(open(log).read()[-3000:])
        sys.exit(1)


def main():
    raymatch, source, work = sys.argv[1:4]
    if not browser_check.find_chromium():
        print("SKIPPED: chromium not found (Debian: apt-get install chromium; scripts/setup.sh "
              "installs it)")
        return browser_check.SKIP
    shutil.rmtree(work, ignore_errors=True)
    os.makedirs(work)
    sample = os.path.join(os.path.abspath(source), "datasets-sample")
    with open(os.path.join(work, "pipeline.toml"), "w") as f:
        f.write(PIPELINE.format(s=sample))
    with open(os.path.join(work, "small_grid.toml"), "w") as f:
        f.write(FIT.format(s=sample))
    run = os.path.join(work, "run")
    sh([raymatch, "run", os.path.join(work, "pipeline.toml"), "-o", run], os.path.join(work, "run.log"))
    with open(os.path.join(work, "s.toml"), "w") as f:
        f.write(SCENE)
    acc = os.path.join(work, "acc")
    sh([raymatch, "bench", "accuracy", os.path.join(work, "s.toml"), "--max-divisor", "4", "-o", acc],
       os.path.join(work, "accuracy.log"))
    pages = [os.path.join(run, "index.html"), os.path.join(run, "compare", "report.html"),
             os.path.join(run, "mesh_object", "compare", "report.html"),
             os.path.join(run, "fit", "small_grid", "report.html"), os.path.join(acc, "accuracy.png")]
    for p in pages:
        if not os.path.exists(p):
            print(f"FAIL: {p} was not written")
            return 1
    return browser_check.run(pages, os.path.join(os.path.dirname(work), "screenshots"), 1)


if __name__ == "__main__":
    sys.exit(main())
