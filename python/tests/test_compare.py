"""raymatch.compare and the measures: the CLI's numbers, scikit-image's SSIM, the focus scan."""
import json

import numpy as np
import pytest
import tifffile
from scipy.ndimage import gaussian_filter
from skimage.metrics import structural_similarity

import raymatch
from conftest import TINY_SCENE, read_json, run_cli


def smooth_pair(seed=4, shape=(64, 72), L=1000.0):
    """Two related images with structure at several scales, in [0, L]."""
    rng = np.random.default_rng(seed)
    base = gaussian_filter(rng.random(shape), 3) * 0.8 + 0.1
    a = L * base
    b = L * np.clip(base + gaussian_filter(rng.normal(0, 0.05, shape), 1), 0, 1)
    return a.astype(np.float32), b.astype(np.float32), L


def test_compare_equals_cli_json(exe, tmp_path):
    a, b, L = smooth_pair()
    tifffile.imwrite(tmp_path / "a.tif", a)
    tifffile.imwrite(tmp_path / "b.tif", b)
    cli = json.loads(run_cli(exe, "compare", tmp_path / "a.tif", tmp_path / "b.tif", "-L", L,
                             "--cw-ssim-orientations", 8).stdout)
    py = raymatch.compare(a, b, L, cw_ssim_orientations=8)
    for key in ("a", "b"):
        del cli[key]
    # Same library calls on the same float32 pixels: equal to the last bit (JSON round-trips).
    assert py == cli
    # And each measure on its own.
    assert raymatch.mse(a, b) == cli["mse"]
    assert raymatch.psnr(a, b, L) == cli["psnr_db"]
    assert raymatch.ssim(a, b, L) == cli["ssim"]
    assert raymatch.ms_ssim(a, b, L)["value"] == cli["ms_ssim"]["value"]
    assert raymatch.cw_ssim(a, b, L, orientations=8)["value"] == cli["cw_ssim"]["value"]
    assert raymatch.poisson(a, b) == cli["poisson"]


def test_ssim_agrees_with_scikit_image_on_the_interior():
    """docs/compare.md: raymatch's SSIM is MATLAB's ssim (replicate padding, whole-map mean).
    scikit-image's structural_similarity with gaussian_weights=True, sigma=1.5 and
    use_sample_covariance=False computes the same map but averages only the interior it can
    compute without padding (5 pixels in from each border for the 11-tap window), so they must
    agree there, map value by map value."""
    for seed in (1, 2):
        a, b, L = smooth_pair(seed)
        full = raymatch.ssim(a.astype(np.float64), b.astype(np.float64), L, full=True)
        sk_mean, sk_map = structural_similarity(
            a.astype(np.float64), b.astype(np.float64), gaussian_weights=True, sigma=1.5,
            use_sample_covariance=False, data_range=L, full=True)
        m = full["map"]
        assert m.shape == a.shape and m.dtype == np.float32
        pad = 5
        np.testing.assert_allclose(m[pad:-pad, pad:-pad], sk_map[pad:-pad, pad:-pad], atol=1e-6)
        assert m[pad:-pad, pad:-pad].mean(dtype=np.float64) == pytest.approx(sk_mean, abs=1e-6)
        # The whole-map means differ (padding at the border): the test can tell them apart.
        assert full["ssim"] != pytest.approx(sk_mean, abs=1e-6)
        assert full["ssim"] == pytest.approx(m.mean(dtype=np.float64), abs=1e-6)


def test_measure_options_and_errors():
    a, b, L = smooth_pair()
    assert raymatch.ssim(a, a, L) == pytest.approx(1.0)
    assert raymatch.ssim(a, b, L, sigma=0.5) != raymatch.ssim(a, b, L)
    ms = raymatch.ms_ssim(a, b, L, scales=3, weights="wang2003")
    assert ms["scales_used"] == 3 and ms["weights"] == "wang2003" and len(ms["per_scale"]) == 3
    custom = raymatch.ms_ssim(a, b, L, scales=2, weights=[1, 1])
    assert custom["weights"] == "custom"
    uint16 = raymatch.mse(a.astype(np.uint16), b.astype(np.uint16))  # any numeric dtype
    assert uint16 > 0
    with pytest.raises(raymatch.CompareError) as e:
        raymatch.ssim(a, b[:10], L)
    assert e.value.kind == "size_mismatch" and isinstance(e.value, raymatch.Error)
    nan = a.copy()
    nan[3, 4] = np.nan
    with pytest.raises(raymatch.CompareError) as e:
        raymatch.mse(nan, b)
    assert e.value.kind == "invalid_input"
    with pytest.raises(raymatch.CompareError, match="weights"):
        raymatch.ms_ssim(a, b, L, weights="nope")
    with pytest.raises(raymatch.CompareError):
        raymatch.ssim(a, b, 0)  # L must be > 0
    with pytest.raises(ValueError, match="2-D"):
        raymatch.mse(a[0], b[0])


def test_focus_scan_equals_cli_and_accepts_arrays(exe, tiny_scene_file, tmp_path):
    z = "-6,-3,0,3,6"
    for name, seed in (("exp", 21), ("sim", 22)):
        run_cli(exe, "simulate", tiny_scene_file, "-o", tmp_path / name, "-q", "--no-png",
                "--seed", seed, "--defocus-um", z, "--rays", 300000)
    exp_index, sim_index = tmp_path / "exp" / "tiny_scan.json", tmp_path / "sim" / "tiny_scan.json"
    cli = run_cli(exe, "compare-scan", exp_index, sim_index, "-o", tmp_path / "cmp", check=False)
    assert cli.returncode in (0, 1, 2), cli.stderr
    cli_json = read_json(tmp_path / "cmp" / "compare_scan.json")

    r = raymatch.focus_scan(exp_index, sim_index)
    assert r.exit_code == cli.returncode
    py_json = r.to_dict()
    assert py_json["measures"] == cli_json["measures"]
    # The report's scale from simulate's sidecars, as the CLI reads it.
    assert cli_json["object_pixel_um"] > 0
    assert raymatch.read_stack(sim_index).object_pixel_um == cli_json["object_pixel_um"]
    assert py_json["object_pixel_um"] == cli_json["object_pixel_um"]
    assert r.exp_defocus_um == [-6, -3, 0, 3, 6]
    mse = r.measures["mse"]
    assert mse["matrix"].shape == (5, 5) and not mse["higher_is_better"]
    # Two noisy images of the same plane (~30 photons per pixel) match best within one 3 um step
    # (the test's criterion; near focus the drop looks alike at 0 and +3 um).
    assert mse["expected"] == [0, 1, 2, 3, 4]
    assert all(abs(b - x) <= 1 for b, x in zip(mse["best"], mse["expected"])), mse["best"]
    assert mse["passes"] and r.verdict == "pass"
    assert len(r.exp_images) == 5 and not r.exp_images[0].flags.writeable

    # The same stacks traced in Python (same seeds) give the same result.
    scene = raymatch.Scene.from_file(tiny_scene_file)
    zs = [-6, -3, 0, 3, 6]
    e = raymatch.simulate(scene, defocus_um=zs, seed=21, rays=300000)
    s = raymatch.simulate(scene, defocus_um=zs, seed=22, rays=300000)
    r2 = raymatch.focus_scan(e, (s.defocus_um, np.stack(s.images)), report_dir=tmp_path / "py")
    assert r2.to_dict()["measures"] == py_json["measures"]
    assert (tmp_path / "py" / "report.html").exists()
    with pytest.raises(raymatch.CompareError, match="images but"):
        raymatch.focus_scan(([0, 1], s.images[:1]), s)
