"""calibrate_lightfield, calibrate_corrector, calibrate_sphere and fit: the same results as the
CLI's files."""
import os

import numpy as np
import pytest
import tifffile

import raymatch
from conftest import SOURCE_DIR, TINY_SCENE, read_json, run_cli

SAMPLE = SOURCE_DIR / "datasets-sample"


@pytest.fixture(scope="module")
def lightfield(tmp_path_factory):
    """Python's light-field calibration of the sample (a small map keeps it quick)."""
    return raymatch.calibrate_lightfield(SAMPLE / "lightfield", map_size=16)


def test_lightfield_equals_cli(exe, lightfield, tmp_path):
    out = tmp_path / "cli.toml"
    run_cli(exe, "calibrate", "lightfield", SAMPLE / "lightfield", "-o", out, "--map-size", 16)
    cli = raymatch.Calibration.read(out)
    py = lightfield["calibration"]
    assert py.has_light_field and not py.has_corrector
    assert py.angular_map.shape == (16, 16)
    # The CLI's file stores the map as float32 TIFF: the same numbers.
    np.testing.assert_array_equal(py.angular_map, cli.angular_map)
    assert py.cone_half_angle_deg == pytest.approx(cli.cone_half_angle_deg, abs=1e-9)
    assert py.na == cli.na and py.wavelength_um == cli.wavelength_um
    assert lightfield["report"] and lightfield["cone"]["half_angle_deg"] > 0
    # Written from Python, read back: a round trip.
    py.write(tmp_path / "py.toml")
    back = raymatch.Calibration.read(tmp_path / "py.toml")
    np.testing.assert_array_equal(back.angular_map, py.angular_map)


def test_corrector_equals_cli(exe, lightfield, tmp_path):
    base = tmp_path / "lf.toml"
    lightfield["calibration"].write(base)
    out = tmp_path / "cli.toml"
    run_cli(exe, "calibrate", "corrector", SAMPLE / "flatfield", "--base", base, "-o", out,
            "--zones", 5)
    cli = raymatch.Calibration.read(out)
    py = raymatch.calibrate_corrector(SAMPLE / "flatfield", zones=5, base=base)
    same = raymatch.calibrate_corrector(SAMPLE / "flatfield", zones=5, base=lightfield["calibration"])
    assert len(py["transmissions"]) == 5 and py["transmissions"][0] == 1.0
    np.testing.assert_allclose(py["transmissions"], cli.transmissions, rtol=1e-9)
    assert py["transmissions"] == same["transmissions"]
    assert py["calibration"].has_light_field and py["calibration"].has_corrector
    assert py["weights"].shape[1] == 5


@pytest.mark.skipif(not hasattr(raymatch, "calibrate_sphere"), reason="built without pipeline")
@pytest.mark.skipif("libasan" in os.environ.get("LD_PRELOAD", ""),
                    reason="under AddressSanitizer (scripts/check-sanitizers.sh) the sphere "
                           "calibration takes over 10 minutes; the golden pipeline test leaves "
                           "it out there too")
def test_sphere_calibration_equals_cli(exe, tmp_path):
    """The sample drop's sphere calibration with few rays (1/256 of the photon-matched ones, so
    its values are rough): Python's and the CLI's calibration files and values are the same, on
    1 and 2 threads."""
    base = tmp_path / "base.toml"
    lf = raymatch.calibrate_lightfield(SAMPLE / "lightfield", map_size=16)["calibration"]
    lf.write(base)
    frac = 0.00390625
    run_cli(exe, "calibrate", "sphere", SAMPLE / "drop46", "--base", base, "-o",
            tmp_path / "cli.toml", "--fractions", frac, "--threads", 2)
    r = raymatch.calibrate_sphere(SAMPLE / "drop46", base, tmp_path / "py.toml",
                                  fractions=[frac], threads=1)
    cli = raymatch.Calibration.read(tmp_path / "cli.toml")
    py = r["calibration"]
    assert py.edge_half_angle_deg == cli.edge_half_angle_deg > 0
    assert py.psf_sigma_um == cli.psf_sigma_um
    # The file's 12 significant digits against the fit's doubles.
    assert r["edge_half_angle_deg"] == pytest.approx(py.edge_half_angle_deg, rel=1e-10)
    assert r["psf_sigma_um"] == pytest.approx(py.psf_sigma_um, rel=1e-10)
    keys = [v["key"] for v in r["values"]]
    assert keys[:5] == ["object.drop.center_um[0]", "object.drop.center_um[1]",
                        "object.drop.center_um[2]", "object.drop.radius_um", "object.drop.index"]
    assert "camera.psf_sigma_um" in keys and "light_field_edge.half_angle_deg" in keys
    cli_fit = read_json(tmp_path / "cli_sphere" / "fit.json")
    assert [v["value"] for v in r["values"]] == [p["best"] for p in cli_fit["parameters"]]
    assert r["status"] == "converged" and r["report"].endswith("report.html")
    assert (tmp_path / "py_sphere" / "fit.json").is_file()
    with pytest.raises(raymatch.Error, match="no plane at defocus 3.3"):
        raymatch.calibrate_sphere(SAMPLE / "drop46", base, tmp_path / "bad.toml", planes_um=[3.3])
    assert not (tmp_path / "bad.toml").exists()


def test_calibration_errors_carry_the_cli_message(exe, tmp_path):
    cli = run_cli(exe, "calibrate", "lightfield", tmp_path, check=False)
    with pytest.raises(raymatch.Error) as e:
        raymatch.calibrate_lightfield(tmp_path)
    assert cli.stderr.strip() == "raymatch: " + str(e.value)


def test_fit_recovers_a_radius_like_the_cli(exe, tmp_path):
    """A one-parameter grid fit of a tiny drop's radius from an image traced with another seed."""
    truth = raymatch.simulate(raymatch.Scene.from_toml(TINY_SCENE), defocus_um=[-6], seed=9)
    tifffile.imwrite(tmp_path / "exp.tif", truth.images[0])
    (tmp_path / "model.toml").write_text(TINY_SCENE.replace("radius_um = 10", "radius_um = 9"))
    (tmp_path / "fit.toml").write_text(
        'scene = "model.toml"\nmethod = "grid"\nseed = 2\n'
        '[[image]]\nfile = "exp.tif"\ndefocus_um = -6\n'
        '[[parameter]]\nkey = "object.drop.radius_um"\nlower = 8\nupper = 12\npoints = 5\n'
        '[rays]\nfractions = [1]\nphotons_per_pixel = 60\n'
        '[uncertainty]\nrepeat_seeds = 0\nslice_points = 0\ncramer_rao = false\nprofile = "always"\n')
    run_cli(exe, "fit", tmp_path / "fit.toml", "-o", tmp_path / "cli", "-q", check=False)
    cli = read_json(tmp_path / "cli" / "fit.json")
    r = raymatch.fit(tmp_path / "fit.toml", output=tmp_path / "py")
    p = r["parameters"][0]
    assert p["key"] == "object.drop.radius_um" and p["unit"] == "um"
    assert p["best"] == pytest.approx(10, abs=1.01)  # grid step 1 um around the truth
    assert r["report"].endswith("report.html")
    assert r["best_images"][0].shape == (32, 40)
    assert len(r["evaluations"]) >= 5
    cli_best = [q["best"] for q in cli["parameters"]]
    assert [q["best"] for q in r["parameters"]] == cli_best
    prof, cli_prof = p["profile_likelihood"], cli["parameters"][0]["profile_likelihood"]
    assert prof["reason"] == cli_prof["reason"] == 'requested (profile = "always")'
    assert [prof["lower"], prof["upper"]] == [cli_prof["lower"], cli_prof["upper"]]
    assert prof["lower"] < prof["upper"] and len(prof["t_sigma"]) == len(prof["delta_deviance"])
    with pytest.raises(raymatch.Error, match=r"model\.toml:1:1: error: missing required key 'scene'"):
        raymatch.fit(tmp_path / "model.toml")  # a scene, not a fit file


def test_sensitivity_equals_cli(exe, tmp_path):
    """The Cramer-Rao bounds of a tiny drop's x and radius: the module and the CLI agree to the
    last digit (the same ray streams), with the design's choice among two planes."""
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY_SCENE.replace("rays = 30000", "photons_per_pixel = 60"))
    keys = ["object.drop.center_um[0]", "object.drop.radius_um"]
    run_cli(exe, "sensitivity", scene, "--keys", ",".join(keys), "--defocus-um=-6,6",
            "--ray-factor", 1, "--design", "planes=1", "-o", tmp_path / "cli", "-q", "-t", 2)
    cli = read_json(tmp_path / "cli" / "sensitivity.json")
    r = raymatch.sensitivity(scene, keys, defocus_um=[-6, 6], ray_factor=1, design_planes=1,
                             threads=2, output=tmp_path / "py")
    assert [k["key"] for k in r["keys"]] == keys and r["keys"][1]["unit"] == "um"
    assert [k["crb"] for k in r["keys"]] == [k["crb"] for k in cli["keys"]]
    assert all(k["crb"] > 0 and k["crb_mc_error"] < 0.2 * k["crb"] for k in r["keys"])
    assert r["dmu"][0][1].shape == (32, 40) and len(r["mu"]) == 2
    assert r["design"]["best_per_count"][0]["defocus_um"] == \
        cli["design"]["best_per_count"][0]["defocus_um"]
    assert r["report"].endswith("report.html")
    with pytest.raises(raymatch.Error, match="no 'colour'"):
        raymatch.sensitivity(scene, ["object.drop.colour"])
