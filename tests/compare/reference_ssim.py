#!/usr/bin/env python3
"""Independent SSIM / MS-SSIM references for tests/compare (Debian python3-skimage, scipy).

Usage: reference_ssim.py A.tif B.tif L SCALES
Prints three numbers:
  1. scikit-image structural_similarity (gaussian_weights, sigma 1.5, population covariance),
     which crops 5 pixels at each border: comparable with raymatch's SSIM map averaged over the
     same interior (where padding does not matter);
  2. SSIM as MATLAB ssim computes it (replicate padding, full map mean), written here with
     scipy.ndimage.correlate1d(mode='nearest');
  3. MS-SSIM with SCALES scales as MATLAB multissim computes it (its algmultissim): default
     Gaussian weights fspecial('gaussian',[1 SCALES],1) normalised; per scale the
     contrast-structure map (the full SSIM map at the last scale) with variances clamped at 0
     and values at 1, its mean (0 if negative) to the power of the weight; between scales
     imfilter(x, ones(2)/4, 'replicate') and x(1:2:end, 1:2:end).
"""
import sys

import numpy as np
import tifffile
from scipy.ndimage import correlate1d
from skimage.metrics import structural_similarity

a = tifffile.imread(sys.argv[1]).astype(np.float64)
b = tifffile.imread(sys.argv[2]).astype(np.float64)
L = float(sys.argv[3])
M = int(sys.argv[4])

sk = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                           data_range=L)

r = int(np.ceil(3 * 1.5))
g = np.exp(-np.arange(-r, r + 1) ** 2 / (2 * 1.5 ** 2))
g /= g.sum()


def filt(x):
    return correlate1d(correlate1d(x, g, axis=0, mode='nearest'), g, axis=1, mode='nearest')


def maps(x, y, clamp=False):
    c1, c2 = (0.01 * L) ** 2, (0.03 * L) ** 2
    mx, my = filt(x), filt(y)
    vx, vy, cxy = filt(x * x) - mx * mx, filt(y * y) - my * my, filt(x * y) - mx * my
    if clamp:
        vx, vy = np.maximum(vx, 0), np.maximum(vy, 0)
    lum = (2 * mx * my + c1) / (mx * mx + my * my + c1)
    cs = (2 * cxy + c2) / (vx + vy + c2)
    return lum, cs


lum, cs = maps(a, b)
matlab_ssim = (lum * cs).mean()


def down(x):
    p = np.pad(x, ((0, 1), (0, 1)), mode='edge')  # imfilter 'replicate' for a 2x2 kernel
    box = 0.25 * (p[:-1, :-1] + p[1:, :-1] + p[:-1, 1:] + p[1:, 1:])
    return box[0::2, 0::2]


w = np.exp(-(np.arange(M) - (M - 1) / 2) ** 2 / 2)
w /= w.sum()
x, y, score = a, b, 1.0
for j in range(M):
    lum, cs = maps(x, y, clamp=True)
    term = np.minimum(cs, 1).mean() if j < M - 1 else np.minimum(lum * cs, 1).mean()
    score *= max(term, 0.0) ** w[j]
    x, y = down(x), down(y)
print(f"{sk:.12f} {matlab_ssim:.12f} {score:.12f}")
