#!/usr/bin/env python3
"""Independent CW-SSIM reference for tests/compare (NumPy/SciPy only).

Usage: reference_cwssim.py A.tif B.tif L LEVEL ORIENTATIONS K [GUARD]
Prints the CW-SSIM value, then the value of every orientation, one line.

Written from the published algorithm of Sampat et al., IEEE TIP 18, 2385 (2009), as their
MATLAB cwssim_index.m computes it on Portilla & Simoncelli's complex steerable pyramid
(matlabPyrTools buildSCFpyr / buildSCFpyrLevs / rcosFn / pointOp), and deliberately organised
like that code rather than like raymatch's C++: 1-based MATLAB index arithmetic for the
frequency grid, masks read from the same lookup tables with the same linear interpolation
(256 samples per octave for the radial raised cosine, 1024 per pi for the angular lobe),
fftshift/ifftshift, a pyramid built level by level, filter2(ones(7)/49, ., 'valid') and an
fspecial-style Gaussian weight. raymatch evaluates the masks in closed form; the tables'
interpolation error (~1e-5 on a mask) moves CW-SSIM by far less than 1e-6.

Convention shared with raymatch (docs/compare.md): images are first scaled by 255 / L, so
that K means what it means for cwssim_index on 8-bit data (K = 0 needs no scaling).
"""
import math
import sys

import numpy as np
import tifffile
from scipy.signal import correlate2d


def rcos_table(width, position):
    """rcosFn(width, position, [0 1]): X positions and cos^2 values, ends repeated."""
    sz = 256
    x = np.pi * np.arange(-sz - 1, 2) / (2 * sz)
    y = np.cos(x) ** 2
    y[0] = y[1]
    y[sz + 2] = y[sz + 1]
    return position + (2 * width / np.pi) * (x + np.pi / 4), y


def point_op(values, lut, origin, increment):
    """pointOp: linear interpolation in `lut`, index truncated toward zero as the C cast does,
    and held inside the table (the end segments extrapolate)."""
    pos = (values - origin) / increment
    index = np.clip(np.trunc(pos).astype(np.int64), 0, len(lut) - 2)
    return lut[index] + (lut[index + 1] - lut[index]) * (pos - index)


def steerable_band(img, level, nbands):
    """The complex oriented bands of pyramid level `level` (1 = finest), shape (nbands, r, c)."""
    rows, cols = img.shape
    ctr = [math.ceil((rows + 0.5) / 2), math.ceil((cols + 0.5) / 2)]  # 1-based
    xramp, yramp = np.meshgrid((np.arange(1, cols + 1) - ctr[1]) / (cols / 2),
                               (np.arange(1, rows + 1) - ctr[0]) / (rows / 2))
    angle = np.arctan2(yramp, xramp)
    rad = np.sqrt(xramp ** 2 + yramp ** 2)
    rad[ctr[0] - 1, ctr[1] - 1] = rad[ctr[0] - 1, ctr[1] - 2]
    log_rad = np.log2(rad)

    xr, yr = rcos_table(1.0, -0.5)
    yr = np.sqrt(yr)
    yir = np.sqrt(1.0 - yr ** 2)
    dft = np.fft.fftshift(np.fft.fft2(img))
    dft = dft * point_op(log_rad, yir, xr[0], xr[1] - xr[0])

    order = nbands - 1
    const = (2.0 ** (2 * order)) * math.factorial(order) ** 2 / (nbands * math.factorial(2 * order))
    lutsize = 1024
    xc = np.pi * np.arange(-(2 * lutsize + 1), lutsize + 2) / lutsize  # [-2 pi, pi]
    alfa = np.mod(np.pi + xc, 2 * np.pi) - np.pi
    yc = 2 * np.sqrt(const) * np.cos(xc) ** order * (np.abs(alfa) < np.pi / 2)

    for lev in range(1, level + 1):
        xr = xr - 1.0  # one octave down
        if lev == level:
            himask = point_op(log_rad, yr, xr[0], xr[1] - xr[0])
            bands = []
            for b in range(nbands):
                anglemask = point_op(angle, yc, xc[0] + np.pi * b / nbands, xc[1] - xc[0])
                banddft = (-1j) ** order * dft * anglemask * himask
                bands.append(np.fft.ifft2(np.fft.ifftshift(banddft)))
            return np.array(bands)
        dims = np.array(dft.shape)
        c = np.ceil((dims + 0.5) / 2).astype(int)
        lodims = np.ceil((dims - 0.5) / 2).astype(int)
        loctr = np.ceil((lodims + 0.5) / 2).astype(int)
        start = c - loctr  # 0-based (MATLAB: c - loctr + 1)
        sl = (slice(start[0], start[0] + lodims[0]), slice(start[1], start[1] + lodims[1]))
        log_rad, angle, dft = log_rad[sl], angle[sl], dft[sl]
        dft = dft * point_op(log_rad, yir, xr[0], xr[1] - xr[0])
    raise ValueError("level must be >= 1")


def gaussian_weights(shape, sigma):
    """fspecial('gaussian', shape, sigma)."""
    half = (np.array(shape) - 1) / 2
    x, y = np.meshgrid(np.arange(-half[1], half[1] + 1), np.arange(-half[0], half[0] + 1))
    h = np.exp(-(x * x + y * y) / (2 * sigma * sigma))
    h[h < np.finfo(float).eps * h.max()] = 0
    return h / h.sum()


def cwssim(a, b, level, nbands, k, guard=0):
    b1 = steerable_band(a, level, nbands)
    b2 = steerable_band(b, level, nbands)
    rows = b1.shape[1]
    g = guard // 2 ** (level - 1)
    window = np.ones((7, 7)) / 49
    values = []
    for o in range(nbands):
        x = b1[o][g:b1.shape[1] - g, g:b1.shape[2] - g]
        y = b2[o][g:b2.shape[1] - g, g:b2.shape[2] - g]
        corr = x * np.conj(y)
        varr = np.abs(x) ** 2 + np.abs(y) ** 2
        corr_band = correlate2d(corr, window, mode='valid')
        varr_band = correlate2d(varr, window, mode='valid')
        cmap = (2 * np.abs(corr_band) + k) / (varr_band + k)
        values.append(float(np.sum(cmap * gaussian_weights(cmap.shape, rows / 4))))
    return float(np.mean(values)), values


def main():
    a = tifffile.imread(sys.argv[1]).astype(np.float64)
    b = tifffile.imread(sys.argv[2]).astype(np.float64)
    scale = 255.0 / float(sys.argv[3])
    level, nbands, k = int(sys.argv[4]), int(sys.argv[5]), float(sys.argv[6])
    guard = int(sys.argv[7]) if len(sys.argv) > 7 else 0
    value, per = cwssim(a * scale, b * scale, level, nbands, k, guard)
    print(" ".join(f"{v:.12f}" for v in [value] + per))


if __name__ == "__main__":
    main()
