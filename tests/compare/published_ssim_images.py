#!/usr/bin/env python3
"""Writes the image pair of a published SSIM value (tests/compare/measures_test.cpp).

scikit-image's camera image and a noisy copy made exactly as in scikit-image's own test
(skimage/metrics/tests/test_structural_similarity.py: legacy NumPy RandomState seed 5, Gaussian
noise sigma 20, clipped to [0, 255], uint8). For this pair the IPOL reference implementation
(J.-M. Morel et al., "Image comparison...", IPOL 2011, https://www.ipol.im/pub/art/2011/g_lmii/,
`imdiff -m mssim`, Gaussian window sigma 1.5, K = 0.01/0.03, L = 255, mean over the valid
interior) gives 0.357959091663361 (scikit-image PR 4913).

Usage: published_ssim_images.py OUTDIR
"""
import sys

import numpy as np
import tifffile
from skimage import data

np.random.seed(5)
cam = data.camera()
noisy = np.clip(cam + 20.0 * np.random.randn(*cam.shape), 0, 255).astype(cam.dtype)
tifffile.imwrite(sys.argv[1] + "/camera.tif", cam)
tifffile.imwrite(sys.argv[1] + "/camera_noisy.tif", noisy)
