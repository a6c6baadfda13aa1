#!/usr/bin/python3
"""Goodness-of-fit false alarms: how often does `raymatch fit` say "model mismatch" on images
its own model made?

Each realisation's "experiment" is traced by `raymatch simulate` with its own seed (ray counting
is photon counting: the model is right), then fitted with its own ray streams (fit seed) from a
start off the truth. Under that null each goodness statistic (deviance, residual blocks,
neighbour correlation) should be about N(0, 1), and `mismatch` (any of the three above 3,
one-sided) should fire in at most 0.4 % of fits (0.135 % per statistic). Printed: per statistic
its mean and standard deviation over the fits, the share above 2 and above 3 with the normal
distribution's share beside it, and the share of fits flagged, with a 95 % interval.
Cases:
  small   the CI honesty test's drop (tests/fit/fit_honesty_test.cpp): radius 9 um, n 1.36,
          27 deg cone, 1 um pixels, 32 x 28, 400 photons per pixel, 6 um before focus; x, y,
          radius fitted at ray factor 4
  sample  a sample-like drop: radius 23 um, n 1.3388, 27 deg cone, 1 um pixels, 64 x 64,
          2500 photons per pixel, 5 um before focus; x, y, z, radius, index fitted at the
          default ray factor 1
  quarter the sample case with fractions [1/16, 1/4], as the sample's own sphere fit: the
          template's counting noise 4x the experiment's
Usage: bench/gof_false_alarms.py OUT [--case small|sample|quarter] [--k 200] [--seed-base 1000]
Writes OUT/<case>/summary.json (and each fit's fit.json under OUT/<case>/k<i>/).
Environment: RAYMATCH (the executable; default build/release/apps/raymatch).
"""
import argparse
import json
import math
import os
import subprocess
import sys
import time

from fit_accuracy import KEYS, RAYMATCH, scene  # the accuracy benchmark's sphere scene

CASES = {
    "small": dict(truth=[0.3, -0.2, 0.0, 9.0, 1.36], start=[0.0, 0.0, 0.0, 8.6, 1.36],
                  cone=27, pitch=20, pixels=[32, 28], ppp=400, plane=-6.0, ray_factor=4,
                  free=[(0, -2, 2, 0.1), (1, -2, 2, 0.1), (3, 8, 10, 0.1)]),
    "sample": dict(truth=[0.4, -0.3, 0.2, 23.0, 1.3388], start=[0.0, 0.0, 1.0, 22.6, 1.342],
                   cone=27, pitch=20, pixels=[64, 64], ppp=2500, plane=-5.0, ray_factor=1,
                   free=[(0, -2, 2, 0.1), (1, -2, 2, 0.1), (2, -3, 3, 0.3), (3, 21, 25, 0.2),
                         (4, 1.32, 1.36, 0.002)]),
}
# The sample's own sphere fit ends at a quarter of the photon-matched rays: the template's
# counting noise is 4x the experiment's there.
CASES["quarter"] = dict(CASES["sample"], fractions="[0.0625, 0.25]")
STATS = [("deviance", "deviance_z"), ("blocks", "block_z"), ("neighbours", "neighbour_z")]


def upper_tail(z):
    """P(N(0, 1) > z)."""
    return 0.5 * math.erfc(z / math.sqrt(2))


def wilson(k, n):
    """95 % Wilson score interval of a binomial share k / n."""
    if n == 0:
        return (0.0, 1.0)
    z = 1.96
    p = k / n
    c = (p + z * z / (2 * n)) / (1 + z * z / n)
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (max(0.0, c - h), min(1.0, c + h))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--case", default="small", choices=sorted(CASES))
    ap.add_argument("--k", type=int, default=200)
    ap.add_argument("--seed-base", type=int, default=1000)
    a = ap.parse_args()
    case = CASES[a.case]
    base = os.path.join(a.out, a.case)
    values = {s: [] for s, _ in STATS}
    flagged, walls = 0, []
    for k in range(a.k):
        d = os.path.join(base, f"k{k}")
        os.makedirs(d, exist_ok=True)
        open(os.path.join(d, "truth.toml"), "w").write(scene(case, case["truth"], a.seed_base + k))
        open(os.path.join(d, "model.toml"), "w").write(scene(case, case["start"], 1))
        sub = os.path.join(d, "exp")
        subprocess.run([RAYMATCH, "simulate", os.path.join(d, "truth.toml"), "--defocus-um",
                        f"{case['plane']}", "-o", sub, "-q", "--no-png"], check=True)
        tif = [f for f in os.listdir(sub) if f.endswith(".tif")][0]
        lines = ["scene = \"model.toml\"", f"seed = {7 + k}", "[[image]]",
                 f"file = \"exp/{tif}\"", f"defocus_um = {case['plane']}"]
        for i, lo, hi, st in case["free"]:
            lines += ["[[parameter]]", f"key = \"{KEYS[i]}\"", f"lower = {lo}", f"upper = {hi}",
                      f"step = {st}"]
        lines += ["[rays]", f"ray_factor = {case['ray_factor']}"]
        if "fractions" in case:
            lines += [f"fractions = {case['fractions']}"]
        lines += [
                  "[uncertainty]", "repeat_seeds = 0", "slice_points = 0"]
        open(os.path.join(d, "fit.toml"), "w").write("\n".join(lines) + "\n")
        t0 = time.time()
        subprocess.run([RAYMATCH, "fit", os.path.join(d, "fit.toml"), "-o", os.path.join(d, "fit"),
                        "--quiet"], stdout=subprocess.DEVNULL)
        walls.append(time.time() - t0)
        g = json.load(open(os.path.join(d, "fit", "fit.json")))["goodness_of_fit"]
        for s, field in STATS:
            values[s].append(g[field])
        flagged += 1 if g["model_mismatch"] else 0
        print(f"{a.case} k{k}: {walls[-1]:.1f} s; z deviance {g['deviance_z']:+.2f}, blocks "
              f"{g['block_z']:+.2f}, neighbours {g['neighbour_z']:+.2f}"
              f"{'  MISMATCH' if g['model_mismatch'] else ''}", file=sys.stderr, flush=True)
    n = len(walls)
    summary = dict(case=a.case, fits=n, seconds_per_fit=sum(walls) / n, statistics=[],
                   flagged=flagged, flagged_share=flagged / n, flagged_95=wilson(flagged, n),
                   nominal_flag_share_at_most=1 - (1 - upper_tail(3)) ** 3)
    print(f"\n{a.case}: {n} fits, {sum(walls) / n:.1f} s per fit\n")
    print("| statistic | mean | sd | share > 2 (normal 2.3 %) | share > 3 (normal 0.13 %) |")
    print("|---|---|---|---|---|")
    for s, _ in STATS:
        v = values[s]
        mean = sum(v) / n
        sd = math.sqrt(sum((x - mean) ** 2 for x in v) / max(1, n - 1))
        over2 = sum(x > 2 for x in v) / n
        over3 = sum(x > 3 for x in v) / n
        summary["statistics"].append(dict(name=s, mean=mean, sd=sd, share_over_2=over2,
                                          share_over_3=over3))
        print(f"| {s} | {mean:+.2f} | {sd:.2f} | {100 * over2:.1f} % | {100 * over3:.1f} % |")
    lo, hi = summary["flagged_95"]
    print(f"\nflagged as a model mismatch: {flagged} of {n} ({100 * flagged / n:.1f} %, 95 % "
          f"interval {100 * lo:.1f}-{100 * hi:.1f} %; at most "
          f"{100 * summary['nominal_flag_share_at_most']:.2f} % if every statistic were N(0, 1))")
    json.dump(summary, open(os.path.join(base, "summary.json"), "w"), indent=1)


if __name__ == "__main__":
    main()
