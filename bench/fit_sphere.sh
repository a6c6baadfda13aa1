#!/usr/bin/env bash
# A five-parameter sphere fit benchmark (x, y, z, radius, index) on this machine,
# timed, over K independent noise realisations, with the achieved precision (the scatter of the
# fitted values about the truth) set beside the Cramer-Rao bound the fit reports.
# Problem: a 31 um sphere (index 1.3371) imaged 4 um out of focus under a
# 27 deg cone, 1000 photons per flat-field pixel, 120 x 100 pixels of 1 um at the object,
# unpolarised partial reflection. Each realisation's "experiment" is the truth traced with its
# own seed (ray counting is photon counting); the fit starts at nominal values (centre 0, radius
# 15.5 um, index 1.335).
# Usage: bench/fit_sphere.sh [OUT=build/bench-fit-sphere] [K=5] [extra fit-file lines ...]
#   e.g. bench/fit_sphere.sh build/fs 5 'method = "pattern"'
# Writes OUT/k<i>/fit.json per realisation and OUT/summary.json, and prints a table.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-build/bench-fit-sphere}
K=${2:-5}
shift 2 || shift $# || true
extra=$(printf '%s\n' "$@")
raymatch=${RAYMATCH:-build/release/apps/raymatch}
mkdir -p "$out"

scene() {  # x y z radius index seed
  cat <<TOML
name = "sphere"
seed = $6
[source]
type = "cone"
half_angle_deg = 27
[[object]]
name = "drop"
type = "sphere"
center_um = [$1, $2, $3]
radius_um = $4
index = $5
[objective]
focal_length_mm = 10
na = 0.42
working_distance_mm = 20
[tube_lens]
focal_length_mm = 200
[camera]
pixels = [120, 100]
pixel_pitch_um = 20
[trace]
photons_per_pixel = 1000
partial_reflection = "unpolarized"
TOML
}

for ((k = 0; k < K; ++k)); do
  d="$out/k$k"
  mkdir -p "$d"
  scene 0.6 -0.4 0.5 15.5 1.3371 $((100 + k)) > "$d/truth.toml"
  scene 0 0 0 15.3 1.335 1 > "$d/model.toml"
  "$raymatch" simulate "$d/truth.toml" --defocus-um -4 -o "$d/exp" -q --no-png
  cat > "$d/fit.toml" <<TOML
scene = "model.toml"
seed = $((7 + k))
$extra
[[image]]
file = "exp/sphere_z-004.00um.tif"
defocus_um = -4
[[parameter]]
key = "object.drop.center_um[0]"
lower = -3
upper = 3
step = 0.2
[[parameter]]
key = "object.drop.center_um[1]"
lower = -3
upper = 3
step = 0.2
[[parameter]]
key = "object.drop.center_um[2]"
lower = -4
upper = 4
step = 0.4
[[parameter]]
key = "object.drop.radius_um"
lower = 14
upper = 17
step = 0.2
[[parameter]]
key = "object.drop.index"
lower = 1.32
upper = 1.35
step = 0.002
[uncertainty]
repeat_seeds = 0
slice_points = 0
TOML
  start=$(date +%s.%N)
  "$raymatch" fit "$d/fit.toml" -o "$d/fit" --quiet || echo "realisation $k: fit exit $?" >&2
  echo "realisation $k: $(echo "$(date +%s.%N) - $start" | bc) s" >&2
done

/usr/bin/python3 - "$out" "$K" <<'PY'
import json, math, sys
out, K = sys.argv[1], int(sys.argv[2])
truth = [0.6, -0.4, 0.5, 15.5, 1.3371]
names = ["x (um)", "y (um)", "z (um)", "radius (um)", "index"]
fits = [json.load(open(f"{out}/k{k}/fit/fit.json")) for k in range(K)]
rows = []
for i, name in enumerate(names):
    best = [f["parameters"][i]["best"] for f in fits]
    sig = [f["parameters"][i]["sigma"] for f in fits]
    crb = [f["parameters"][i]["sigma_cramer_rao"] for f in fits]
    scatter = math.sqrt(sum((b - truth[i]) ** 2 for b in best) / K)  # RMS about the truth
    msig, mcrb = sum(sig) / K, sum(crb) / K
    rows.append(dict(parameter=name, truth=truth[i], mean=sum(best) / K, rms_error=scatter,
                     mean_sigma=msig, mean_crb=mcrb, rms_over_crb=scatter / mcrb,
                     rms_over_sigma=scatter / msig))
secs = [f["seconds"]["total"] for f in fits]
evals = [len(f["evaluations"]) for f in fits]
summary = dict(realisations=K, seconds=secs, evaluations=evals, parameters=rows,
               time_split=[f["seconds"] for f in fits],
               retraced_ray_fraction=fits[0]["rays"]["retraced_ray_fraction"],
               status=[f["status"] for f in fits])
json.dump(summary, open(f"{out}/summary.json", "w"), indent=1)
print(f"fits: {K}, time per fit {min(secs):.1f} .. {max(secs):.1f} s (mean {sum(secs)/K:.1f}), "
      f"evaluations {min(evals)} .. {max(evals)}, status {sorted(set(summary['status']))}")
print("| parameter | truth | mean | RMS error | mean sigma | mean CRB | RMS/CRB | RMS/sigma |")
print("|---|---|---|---|---|---|---|---|")
for r in rows:
    print(f"| {r['parameter']} | {r['truth']} | {r['mean']:.5g} | {r['rms_error']:.3g} | "
          f"{r['mean_sigma']:.3g} | {r['mean_crb']:.3g} | {r['rms_over_crb']:.2f} | {r['rms_over_sigma']:.2f} |")
PY
