#!/bin/bash
# Same images, bit for bit, from two raymatch builds (a change that must not alter any image):
#   scripts/check-identical-images.sh OLD/raymatch NEW/raymatch [OUTDIR]
# Traces the scenes in scripts/identity-scenes/ (every source the packet path takes, the sphere
# stage, corrector, two lenses, polarised Fresnel, PSF, photon target; a mesh, a gradient-index
# sphere, nested objects and the interaction cap on the scalar objects stage) with both binaries, two
# of them also with --no-simd, and compares every image pixel for pixel (tifffile + numpy: the
# same shape, dtype and bits) and the sidecars' counters, fates, hits and path classes.
set -euo pipefail
old=$(realpath "$1"); new=$(realpath "$2")
out=${3:-$(mktemp -d)}
here=$(cd "$(dirname "$0")" && pwd)
run() {  # binary, folder
  for s in s1 s2 s3 s4 s5 s6; do
    "$1" simulate "$here/identity-scenes/$s.toml" -o "$2/$s" --threads 2 > /dev/null
  done
  for s in s1 s2; do
    "$1" simulate "$here/identity-scenes/$s.toml" -o "$2/${s}_nosimd" --threads 2 --no-simd > /dev/null
  done
}
run "$old" "$out/old"
run "$new" "$out/new"
/usr/bin/python3 - "$out/old" "$out/new" <<'PY'
import glob, json, os, sys
import numpy as np, tifffile
a, b = sys.argv[1], sys.argv[2]
bad = n = 0
for fa in sorted(glob.glob(a + '/*/*.tif')):
    fb = b + fa[len(a):]
    n += 1
    if not os.path.exists(fb):
        print('missing', fb); bad += 1; continue
    ia, ib = tifffile.imread(fa), tifffile.imread(fb)
    same = ia.dtype == ib.dtype and ia.shape == ib.shape and ia.tobytes() == ib.tobytes()
    ja, jb = (json.load(open(f[:-4] + '.json')) for f in (fa, fb))
    keys = ['counters', 'fates', 'hits', 'path_classes', 'rays']
    if not (same and all(ja.get(k) == jb.get(k) for k in keys)):
        bad += 1; print('DIFFERENT', fa[len(a) + 1:])
print(f'{n} images compared, {bad} differ')
sys.exit(1 if bad or n == 0 else 0)
PY
