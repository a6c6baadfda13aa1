#!/usr/bin/python3
"""Pressure-wave fit benchmark (docs/sensitivity.md): the amplitude of a pressure wave
inside a drop and the misalignment of its axis, fitted from one photon-matched image.

The drop is scripts/make-wave-drop.py's CFD-like 43 um water drop (a +20 kg/m^3 cos^2 shell,
radius 12 um, axis 2.5 um off the drop's centre along x, 46^3 density grid at 1 um) at 405 nm
under a 23 deg cone through 20x / 0.42, 2500 photons per flat-field pixel, imaged 10 um behind
the focus (the design's best plane). Each of K "experiments" is traced by `raymatch simulate`
with its own seed (no model mismatch); the model starts at amplitude scale 0.8 and the field
0.5 um off in x and y (signs alternating) and fits
  object.drop.index_field.perturbation_scale  (1 = +20 kg/m^3; step 0.2)
  object.drop.index_field.origin_um[0], [1]   (the field's misalignment, um; step 0.8)
at the fit's default settings but the ray factor (default 0.5: half the photon-matched rays per
template, which keeps a fit within 5 minutes on 2 cores; the templates' noise then puts the
floor of the RMS error at about 1.4 Cramer-Rao bounds) and without slices or repeated fits
(diagnostics that do not change the estimate). Prints per key the mean error and RMS error in
Cramer-Rao bounds, RMS(error / reported sigma), and the time per fit with its split (fit.json
"seconds").

Usage: bench/fit_wave.py OUT [--k 6] [--plane 10] [--ray-factor 0.5] [--fit-lines 'key = value' ...]
Writes OUT/k<i>/fit/fit.json and OUT/summary.json; prints a Markdown table.
Environment: RAYMATCH (the executable; default build/release/apps/raymatch).
"""
import argparse
import json
import os
import re
import subprocess
import sys
import time

from fit_accuracy import error_stats, timing_stats  # the same statistics (bench/)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RAYMATCH = os.environ.get("RAYMATCH", os.path.join(ROOT, "build/release/apps/raymatch"))

FIELD = "object.drop.index_field."
# key, truth (from make-wave-drop.py's defaults: origin -22.5 um), start offset, bounds, step
KEYS = [("perturbation_scale", 1.0, -0.2, (0.0, 2.0), 0.2),
        ("origin_um[0]", -22.5, 0.5, (-24.5, -20.5), 0.8),
        ("origin_um[1]", -22.5, 0.5, (-24.5, -20.5), 0.8)]
NAMES = ["amplitude (scale)", "offset x (um)", "offset y (um)"]


def scene_with(text, scale, ox, oy, seed):
    text = re.sub(r"^seed = .*$", f"seed = {seed}", text, flags=re.M)
    text = re.sub(r"^perturbation_scale = .*$", f"perturbation_scale = {scale!r}", text, flags=re.M)
    return re.sub(r"^origin_um = \[[^\]]*,", f"origin_um = [{ox!r}, {oy!r},", text, flags=re.M)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--k", type=int, default=6, help="noise realisations")
    ap.add_argument("--ray-factor", type=float, default=0.5, help="simulated rays per photon")
    ap.add_argument("--plane", type=float, default=10.0, help="defocus of the image (um)")
    ap.add_argument("--fit-lines", nargs="*", default=[], help="extra top-level fit-file lines")
    a = ap.parse_args()
    wave = os.path.join(a.out, "wave")
    if not os.path.exists(os.path.join(wave, "scene.toml")):
        subprocess.run([sys.executable, os.path.join(ROOT, "scripts/make-wave-drop.py"), wave],
                       check=True)
    base = open(os.path.join(wave, "scene.toml")).read()
    truth = [t for _, t, _, _, _ in KEYS]
    rows = []
    for k in range(a.k):
        d = os.path.join(a.out, f"k{k}")
        os.makedirs(d, exist_ok=True)
        sgn = 1 if k % 2 == 0 else -1
        start = [t + (o if i == 0 else sgn * o * (1 if i == 1 else -1))
                 for i, (_, t, o, _, _) in enumerate(KEYS)]
        rho = os.path.relpath(os.path.join(wave, "rho.npy"), d)
        for name, vals, seed in (("truth", truth, 100 + k), ("model", start, 1)):
            text = scene_with(base, *vals, seed).replace('file = "rho.npy"', f'file = "{rho}"')
            open(os.path.join(d, name + ".toml"), "w").write(text)
        sub = os.path.join(d, "exp")
        subprocess.run([RAYMATCH, "simulate", os.path.join(d, "truth.toml"), "--defocus-um",
                        f"{a.plane}", "-o", sub, "-q", "--no-png"], check=True)
        tif = [f for f in os.listdir(sub) if f.endswith(".tif")][0]
        lines = ['scene = "model.toml"', f"seed = {7 + k}"] + list(a.fit_lines)
        lines += ["[rays]", f"ray_factor = {a.ray_factor}"]
        lines += ["[[image]]", f'file = "exp/{tif}"', f"defocus_um = {a.plane}"]
        for key, _, _, (lo, hi), st in KEYS:
            lines += ["[[parameter]]", f'key = "{FIELD}{key}"', f"lower = {lo}", f"upper = {hi}",
                      f"step = {st}"]
        lines += ["[uncertainty]", "repeat_seeds = 0", "slice_points = 0"]
        open(os.path.join(d, "fit.toml"), "w").write("\n".join(lines) + "\n")
        t0 = time.time()
        rc = subprocess.run([RAYMATCH, "fit", os.path.join(d, "fit.toml"), "-o",
                             os.path.join(d, "fit"), "--quiet"]).returncode
        wall = time.time() - t0
        fj = json.load(open(os.path.join(d, "fit", "fit.json")))
        rows.append(dict(fit=fj, wall=wall, rc=rc))
        errs = [(p["best"] - t) / p["sigma_cramer_rao"] for p, t in zip(fj["parameters"], truth)]
        print(f"k{k}: {wall:.1f} s, exit {rc}, {len(fj['evaluations'])} evaluations, "
              f"(best - truth)/CRB " + " ".join(f"{e:+.2f}" for e in errs), file=sys.stderr,
              flush=True)
    K = len(rows)
    table = error_stats(rows, truth, NAMES)
    split = {}
    for r in rows:
        for key, v in r["fit"].get("seconds", {}).items():
            split[key] = split.get(key, 0) + v / K
    timing = dict(timing_stats(rows), split=split)
    json.dump(dict(parameters=table, timing=timing, command=sys.argv, fit_lines=a.fit_lines,
                   ray_factor=a.ray_factor),
              open(os.path.join(a.out, "summary.json"), "w"), indent=1)
    print("| parameter | mean error/CRB | RMS error/CRB | RMS(error/sigma) | mean CRB | mean sigma |")
    print("|---|---|---|---|---|---|")
    for r in table:
        print(f"| {r['parameter']} | {r['mean_error_over_crb']:+.2f} | {r['rms_error_over_crb']:.2f} | "
              f"{r['rms_error_over_sigma']:.2f} | {r['mean_crb']:.3g} | {r['mean_sigma']:.3g} |")
    print(f"{K} fits, {timing['mean_seconds']:.1f} s per fit (max {timing['max_seconds']:.1f}), "
          f"{timing['evaluations']:.0f} evaluations, exits {timing['exits']}; split (s): " +
          ", ".join(f"{k} {v:.1f}" for k, v in split.items()))


if __name__ == "__main__":
    main()
