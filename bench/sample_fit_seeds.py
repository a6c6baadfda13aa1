#!/usr/bin/python3
"""The sample's sphere fit (datasets-sample/fit/sphere.toml) with other ray streams: its goodness
of fit and its errors against datasets-sample/truth.toml, seed by seed.

The fit file's `seed` sets the fit's ray streams (the search's, the final steps' derivative sets',
the template's); the experiment and the calibration stay. A goodness-of-fit test that holds its
false-alarm rate reads "consistent" at every seed; the errors in reported sigmas show whether the
sigmas describe the scatter from seed to seed.
Usage: bench/sample_fit_seeds.py OUT --calibration out/sample/calibration.toml [--seeds 1,2,3,4,5]
Writes OUT/seed<k>/ (each fit's outputs) and OUT/summary.json; prints a Markdown table.
Environment: RAYMATCH (the executable; default build/release/apps/raymatch).
"""
import argparse
import json
import os
import subprocess
import sys
import time
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RAYMATCH = os.environ.get("RAYMATCH", os.path.join(ROOT, "build/release/apps/raymatch"))
FIT = os.path.join(ROOT, "datasets-sample/fit/sphere.toml")


def truth_of(key, truth):
    """The generator's value of a fit key (None where truth.toml has none)."""
    drop, lf, cam = truth["drop"], truth["light_field"], truth["camera"]
    table = {
        "object.drop.center_um[0]": drop["center_um"][0],
        "object.drop.center_um[1]": drop["center_um"][1],
        "object.drop.center_um[2]": drop["center_um"][2],
        "object.drop.radius_um": drop["radius_um"],
        "object.drop.index": drop["index"],
        "light_field_edge.half_angle_deg": lf["edge_half_angle_deg"],
        "camera.psf_sigma_um": cam["psf_sigma_um"],
    }
    return table.get(key)


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--calibration", required=True)
    ap.add_argument("--seeds", default="1,2,3,4,5")
    a = ap.parse_args()
    truth = tomllib.load(open(os.path.join(ROOT, "datasets-sample/truth.toml"), "rb"))
    text = open(FIT).read()
    if "\nseed = " not in text:
        sys.exit("sample_fit_seeds: no 'seed = ' line in " + FIT)
    rows = []
    for seed in [int(s) for s in a.seeds.split(",")]:
        # The fit file beside the sample's, so its relative paths hold.
        lines = [f"seed = {seed}" if ln.startswith("seed = ") else ln for ln in text.split("\n")]
        fit_file = os.path.join(os.path.dirname(FIT), f".seed{seed}.toml")
        open(fit_file, "w").write("\n".join(lines))
        out = os.path.join(a.out, f"seed{seed}")
        t0 = time.time()
        try:
            r = subprocess.run([RAYMATCH, "fit", fit_file, "-q", "-o", out, "--calibration",
                                os.path.abspath(a.calibration)], capture_output=True, text=True)
        finally:
            os.remove(fit_file)
        wall = time.time() - t0
        if r.returncode not in (0, 4):
            sys.exit(f"sample_fit_seeds: seed {seed}: exit {r.returncode}\n{r.stderr}")
        j = json.load(open(os.path.join(out, "fit.json")))
        g = j["goodness_of_fit"]
        errs = []
        for p in j["parameters"]:
            t = truth_of(p["key"], truth)
            sigma = p.get("sigma")
            errs.append(None if t is None or not sigma else (p["best"] - t) / sigma)
        rows.append(dict(seed=seed, wall_s=wall, exit=r.returncode, deviance_z=g["deviance_z"],
                         block_z=g["block_z"], neighbour_z=g["neighbour_z"],
                         mismatch=g["model_mismatch"], step=g.get("step_to_tested_point"),
                         keys=[p["key"] for p in j["parameters"]], errors_in_sigma=errs))
        print(f"seed {seed}: {g['verdict']} ({wall:.0f} s)", file=sys.stderr, flush=True)
    json.dump(rows, open(os.path.join(a.out, "summary.json"), "w"), indent=1)
    print("| seed | deviance (sd) | blocks (sd) | neighbours (sd) | verdict | "
          "(fitted - truth) / sigma: " + ", ".join(k.split(".")[-1] for k in rows[0]["keys"]) + " |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        e = ", ".join("-" if v is None else f"{v:+.2f}" for v in r["errors_in_sigma"])
        print(f"| {r['seed']} | {r['deviance_z']:+.2f} | {r['block_z']:+.2f} | "
              f"{r['neighbour_z']:+.2f} | {'mismatch' if r['mismatch'] else 'consistent'} | {e} |")


if __name__ == "__main__":
    main()
