#!/usr/bin/python3
"""Fit accuracy benchmark: are the fits right, not just precise?

Each case is a sphere whose "experiment" is traced by `raymatch simulate` itself with its own
seed (ray counting is photon counting, so there is no model mismatch), then fitted for x, y, z,
radius and index from nominal starts (1.8 um off in z, 0.6 um in radius, 0.005 in index,
0.4 um in x and y, with alternating signs). Over K realisations it prints, per parameter:
  mean error / CRB   (bias; |.| <= 0.5 wanted)
  RMS error / CRB    (efficiency; <= 1.5 wanted)
  RMS(error / sigma) (honest error bars; 0.8 .. 1.25 wanted)
and the time per fit. The cases:
  A  "steep": n 1.39, radius 13 um, 6 um out of focus, 20 deg cone (inside the NA),
     0.5 um object pixels (96 x 96), 1000 photons per pixel
  B  "valley": radius 18 um, n 1.337, 27 deg cone (wider than the NA), two planes (-9, +3 um)
     fitted jointly, 1 um pixels (100 x 90), 1000 photons per pixel
  C  "bench": bench/fit_sphere.sh's sphere: radius 15.5 um, n 1.3371, 27 deg cone, -4 um,
     1 um pixels (120 x 100), 1000 photons per pixel
Usage: bench/fit_accuracy.py OUT [--cases ABC] [--k 16] [--start nominal|truth]
                             [--offsets 0.4,0.4,1.8,0.6,0.005] [--seed-base 100]
                             [--fit-lines 'key = value' ...]
       bench/fit_accuracy.py OUT --pool RUN1 RUN2 ... [--cases ABC]
(--pool: no fits; the table over the fits already in RUN1/<case>/k*/fit/fit.json, RUN2/..., with
each fit's own time from its fit.json, written to OUT/summary.json)
(--offsets: |nominal start - truth| of x, y, z, radius, index; the far starts are
0.4,0.4,2,1,0.01)
Writes OUT/<case>/k<i>/fit/fit.json and OUT/summary.json; prints a Markdown table.
Environment: RAYMATCH (the executable; default build/release/apps/raymatch).
"""
import argparse
import json
import math
import os
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RAYMATCH = os.environ.get("RAYMATCH", os.path.join(ROOT, "build/release/apps/raymatch"))

CASES = {
    "A": dict(truth=[0.3, -0.2, 0.4, 13.0, 1.39], cone=20, pixels=[96, 96], pitch=10,
              planes=[6.0], ppp=1000,
              bounds=[(-3, 3, 0.2), (-3, 3, 0.2), (-4, 4, 0.4), (11, 15, 0.2), (1.37, 1.41, 0.002)]),
    "B": dict(truth=[0.4, -0.3, 0.5, 18.0, 1.337], cone=27, pixels=[100, 90], pitch=20,
              planes=[-9.0, 3.0], ppp=1000,
              bounds=[(-3, 3, 0.2), (-3, 3, 0.2), (-4, 4, 0.4), (16, 20, 0.2), (1.32, 1.355, 0.002)]),
    "C": dict(truth=[0.6, -0.4, 0.5, 15.5, 1.3371], cone=27, pixels=[120, 100], pitch=20,
              planes=[-4.0], ppp=1000,
              bounds=[(-3, 3, 0.2), (-3, 3, 0.2), (-4, 4, 0.4), (14, 17, 0.2), (1.32, 1.35, 0.002)]),
}
NAMES = ["x (um)", "y (um)", "z (um)", "radius (um)", "index"]
KEYS = ["object.drop.center_um[0]", "object.drop.center_um[1]", "object.drop.center_um[2]",
        "object.drop.radius_um", "object.drop.index"]
OFFSETS = [0.4, 0.4, 1.8, 0.6, 0.005]  # nominal start - truth (signs alternate per realisation)


# The paper's microscope: 20x / 0.42 objective, 200 mm tube lens.
MICROSCOPE = """[objective]
focal_length_mm = 10
na = 0.42
working_distance_mm = 20
[tube_lens]
focal_length_mm = 200
"""


def scene(case, theta, seed):
    x, y, z, r, n = theta
    return f"""name = "sphere"
seed = {seed}
[source]
type = "cone"
half_angle_deg = {case['cone']}
[[object]]
name = "drop"
type = "sphere"
center_um = [{x}, {y}, {z}]
radius_um = {r}
index = {n}
{MICROSCOPE}[camera]
pixels = [{case['pixels'][0]}, {case['pixels'][1]}]
pixel_pitch_um = {case['pitch']}
[trace]
photons_per_pixel = {case['ppp']}
partial_reflection = "unpolarized"
"""


def run_case(name, case, K, out, fit_lines, from_truth=False, offsets=OFFSETS, seed_base=100):
    rows = []
    for k in range(K):
        d = os.path.join(out, name, f"k{k}")
        os.makedirs(d, exist_ok=True)
        truth = case["truth"]
        sgn = 1 if k % 2 == 0 else -1
        start = [t + (0 if from_truth else sgn * o * (1 if i % 2 == 0 else -1))
                 for i, (t, o) in enumerate(zip(truth, offsets))]
        open(os.path.join(d, "truth.toml"), "w").write(scene(case, truth, seed_base + k))
        open(os.path.join(d, "model.toml"), "w").write(scene(case, start, 1))
        images = []
        for p in case["planes"]:
            sub = os.path.join(d, f"exp{p:+g}")
            subprocess.run([RAYMATCH, "simulate", os.path.join(d, "truth.toml"), "--defocus-um", f"{p}",
                            "-o", sub, "-q", "--no-png"], check=True)
            tif = [f for f in os.listdir(sub) if f.endswith(".tif")][0]
            images.append((os.path.relpath(os.path.join(sub, tif), d), p))
        lines = ["scene = \"model.toml\"", f"seed = {7 + k}"] + list(fit_lines)
        for f, p in images:
            lines += ["[[image]]", f"file = \"{f}\"", f"defocus_um = {p}"]
        for key, (lo, hi, st) in zip(KEYS, case["bounds"]):
            lines += ["[[parameter]]", f"key = \"{key}\"", f"lower = {lo}", f"upper = {hi}", f"step = {st}"]
        lines += ["[uncertainty]", "repeat_seeds = 0", "slice_points = 0"]
        open(os.path.join(d, "fit.toml"), "w").write("\n".join(lines) + "\n")
        t0 = time.time()
        rc = subprocess.run([RAYMATCH, "fit", os.path.join(d, "fit.toml"), "-o", os.path.join(d, "fit"),
                             "--quiet"]).returncode
        wall = time.time() - t0
        fj = json.load(open(os.path.join(d, "fit", "fit.json")))
        rows.append(dict(fit=fj, wall=wall, rc=rc))
        errs = [(p["best"] - t) / p["sigma_cramer_rao"] for p, t in zip(fj["parameters"], truth)]
        print(f"{name} k{k}: {wall:.1f} s, exit {rc}, (best - truth)/CRB " +
              " ".join(f"{e:+.2f}" for e in errs), file=sys.stderr, flush=True)
    return rows


def pooled_rows(runs, name):
    """The fits of case `name` already made in each run folder, in order, as run_case's rows
    (the wall time is the fit's own total from fit.json; the exit code is not kept there)."""
    rows = []
    for run in runs:
        d = os.path.join(run, name)
        ks = sorted((int(k[1:]) for k in os.listdir(d) if k.startswith("k")) if os.path.isdir(d) else [])
        for k in ks:
            f = os.path.join(d, f"k{k}", "fit", "fit.json")
            if not os.path.exists(f):
                print(f"--pool: {f} missing (a fit not finished): left out", file=sys.stderr)
                continue
            fj = json.load(open(f))
            rows.append(dict(fit=fj, wall=fj["seconds"]["total"], rc=0 if fj["converged"] else 1))
    if not rows:
        sys.exit(f"--pool: no fits of case {name} in {', '.join(runs)}")
    return rows


def error_stats(rows, truth, names):
    """Per parameter over the fits (rows of dict(fit=fit.json, wall=s, rc=exit)): mean error
    and RMS error in mean Cramer-Rao bounds, RMS(error / sigma), mean CRB and sigma."""
    K = len(rows)
    out = []
    for i, pname in enumerate(names):
        err = [r["fit"]["parameters"][i]["best"] - truth[i] for r in rows]
        crb = [r["fit"]["parameters"][i]["sigma_cramer_rao"] for r in rows]
        sig = [r["fit"]["parameters"][i]["sigma"] for r in rows]
        mean_crb = sum(crb) / K
        out.append(dict(parameter=pname,
                        mean_error_over_crb=sum(err) / K / mean_crb,
                        rms_error_over_crb=math.sqrt(sum(e * e for e in err) / K) / mean_crb,
                        rms_error_over_sigma=math.sqrt(sum((e / s) ** 2 for e, s in zip(err, sig)) / K),
                        mean_crb=mean_crb, mean_sigma=sum(sig) / K))
    return out


def timing_stats(rows):
    """Fits, mean and max wall time per fit, exit codes and mean evaluations per fit."""
    K = len(rows)
    walls = [r["wall"] for r in rows]
    return dict(fits=K, mean_seconds=sum(walls) / K, max_seconds=max(walls),
                exits=sorted(set(r["rc"] for r in rows)),
                evaluations=sum(len(r["fit"]["evaluations"]) for r in rows) / K)


def summarise(name, case, rows):
    return ([dict(case=name, **r) for r in error_stats(rows, case["truth"], NAMES)],
            dict(case=name, **timing_stats(rows)))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--cases", default="ABC")
    ap.add_argument("--k", type=int, default=16, help="noise realisations per case")
    ap.add_argument("--start", choices=["nominal", "truth"], default="nominal",
                    help="nominal: offset starts (the benchmark); truth: start at the truth (bias alone)")
    ap.add_argument("--offsets", default=",".join(str(o) for o in OFFSETS),
                    help="|nominal start - truth| of x, y, z (um), radius (um), index")
    ap.add_argument("--seed-base", type=int, default=100,
                    help="the experiments' seeds are SEED_BASE + k (default 100)")
    ap.add_argument("--fit-lines", nargs="*", default=[], help="extra top-level fit-file lines")
    ap.add_argument("--pool", nargs="+", metavar="RUN",
                    help="no fits: pool those already made in these output folders")
    a = ap.parse_args()
    table, timing = [], []
    os.makedirs(a.out, exist_ok=True)
    for c in a.cases:
        offsets = [float(v) for v in a.offsets.split(",")]
        if len(offsets) != 5:
            ap.error("--offsets needs five numbers: x, y, z, radius, index")
        rows = (pooled_rows(a.pool, c) if a.pool else
                run_case(c, CASES[c], a.k, a.out, a.fit_lines, a.start == "truth", offsets,
                         a.seed_base))
        t, s = summarise(c, CASES[c], rows)
        table += t
        timing.append(s)
    json.dump(dict(parameters=table, timing=timing, command=sys.argv, fit_lines=a.fit_lines),
              open(os.path.join(a.out, "summary.json"), "w"), indent=1)
    print("| case | parameter | mean error/CRB | RMS error/CRB | RMS(error/sigma) | mean CRB |")
    print("|---|---|---|---|---|---|")
    for r in table:
        print(f"| {r['case']} | {r['parameter']} | {r['mean_error_over_crb']:+.2f} | "
              f"{r['rms_error_over_crb']:.2f} | {r['rms_error_over_sigma']:.2f} | {r['mean_crb']:.3g} |")
    for s in timing:
        print(f"case {s['case']}: {s['fits']} fits, {s['mean_seconds']:.1f} s per fit (max "
              f"{s['max_seconds']:.1f}), {s['evaluations']:.0f} evaluations, exits {s['exits']}")


if __name__ == "__main__":
    main()
