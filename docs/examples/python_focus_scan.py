#!/usr/bin/python3
"""Simulate the sample drop's focus scan, compare it with the sample's experiment, plot it.

Notebook-style walk through the Python module (docs/python.md). Run from the repository root
after building (scripts/setup.sh):

    PYTHONPATH=build/release/python /usr/bin/python3 docs/examples/python_focus_scan.py [OUT]

It takes about 2 minutes on 2 busy cores (the simulation at 1/4 of the experiment's photons).
Writes OUT (default out/python-focus-scan/): focus_scan.png (the MS-SSIM matrix with the best
match per experimental plane, and the in-focus pair) when matplotlib is installed (Debian
python3-matplotlib), otherwise focus_scan.npz with the arrays; and the CLI's focus-scan report.
The nominal scene has no calibration (an ideal 27 deg cone) and no PSF, so the images differ
visibly (SSIM ~0.6 in focus) even where every best match is right; `raymatch run
datasets-sample/pipeline.toml` calibrates first.
"""
import os
import pathlib
import sys
import tomllib

import numpy as np

import raymatch

root = pathlib.Path(__file__).resolve().parents[2]
sample = root / "datasets-sample"
out = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else "out/python-focus-scan")
out.mkdir(parents=True, exist_ok=True)

# %% The experiment: a focus scan of a 46 um water drop (16-bit TIFFs with a dark frame).
experiment = raymatch.read_stack(sample / "drop46" / "scan.csv")
meta = tomllib.loads((sample / "drop46" / "metadata.toml").read_text())
rows, cols = experiment.images[0].shape
print(f"experiment: {len(experiment.images)} planes {experiment.defocus_um} um, {cols}x{rows} px")

# %% The scene: the sample's nominal drop scene as a dict, adapted to the experiment's camera.
scene = tomllib.loads((sample / "drop46" / "scene.toml").read_text())
scene["camera"] = {"pixels": [cols, rows], "pixel_pitch_um": meta["camera"]["pixel_pitch_um"]}
# The experiment has ~2500 photons per pixel; fewer rays are quicker (the tests use 10).
scene["trace"]["photons_per_pixel"] = float(os.environ.get("RAYMATCH_EXAMPLE_PHOTONS", 600))
scene = raymatch.Scene.from_dict(scene, base_dir=sample / "drop46")

# %% Simulate the same planes (the GIL is released while tracing; same seed, same images).
sim = raymatch.simulate(scene, defocus_um=experiment.defocus_um, seed=1)
print(f"simulated {len(sim.images)} planes, {sim.rays_per_image} rays per image; "
      f"plane 0 mean {sim.sidecars[0]['image']['mean_counts']:.1f} photons")

# %% The focus-scan test, as `raymatch compare-scan` (dark subtraction and gain from metadata).
result = raymatch.focus_scan(experiment, sim, dark=sample / "drop46" / meta["dark"],
                             gain=meta["camera"]["gain_e_per_dn"], report_dir=out / "report")
print(result.message)
for name, m in result.measures.items():
    print(f"  {name:13s} {'pass' if m['passes'] else 'FAIL'}  best simulated plane per "
          f"experimental plane: {m['best']}")

# %% One pair of images with every measure (data range L in photons).
mid = len(experiment.defocus_um) // 2
e, s = result.exp_images[mid], result.sim_images[mid]
print("in focus:", {k: v for k, v in raymatch.compare(e, s, result.data_range).items()
                    if k in ("mse", "ssim")})

# %% Plot: MS-SSIM matrix with defocus axes, and the in-focus pair.
try:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
except ImportError:
    np.savez(out / "focus_scan.npz", exp_defocus_um=result.exp_defocus_um,
             sim_defocus_um=result.sim_defocus_um,
             **{f"{k}_matrix": m["matrix"] for k, m in result.measures.items()},
             experiment=np.stack(result.exp_images), simulation=np.stack(result.sim_images))
    print(f"matplotlib not installed: arrays in {out / 'focus_scan.npz'}")
    sys.exit(0)

fig, ax = plt.subplots(1, 3, figsize=(13, 4))
z_e, z_s = result.exp_defocus_um, result.sim_defocus_um
m = result.measures["ms_ssim"]
im = ax[0].imshow(m["matrix"], origin="lower", cmap="viridis",
                  extent=[z_s[0] - 2.5, z_s[-1] + 2.5, z_e[0] - 2.5, z_e[-1] + 2.5])
ax[0].plot([z_s[b] for b in m["best"]], z_e, "r+", ms=10, label="best match")
ax[0].set(xlabel="simulated defocus (um)", ylabel="experimental defocus (um)",
          title=f"MS-SSIM ({'pass' if m['passes'] else 'fail'})")
ax[0].legend(loc="upper left")
fig.colorbar(im, ax=ax[0], label="MS-SSIM (1 = identical)")
vmax = max(e.max(), s.max())
for a, img, title in ((ax[1], e, "experiment"), (ax[2], s, "simulation")):
    im = a.imshow(img, cmap="gray", vmin=0, vmax=vmax)
    a.set(title=f"{title}, z = {z_e[mid]:+g} um", xlabel="x (px)", ylabel="y (px)")
    fig.colorbar(im, ax=a, label="photons per pixel")
fig.tight_layout()
fig.savefig(out / "focus_scan.png", dpi=100)
print(f"wrote {out / 'focus_scan.png'} and {out / 'report' / 'report.html'}")
