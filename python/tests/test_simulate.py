"""raymatch.simulate and scenes: bit-identical to `raymatch simulate`, errors as the CLI's."""
import threading
import time
import tomllib

import numpy as np
import pytest
import tifffile

import raymatch
from conftest import TINY_SCENE, read_json, run_cli


def cli_scan(exe, scene_file, out, *extra):
    run_cli(exe, "simulate", scene_file, "-o", out, "-q", "--no-png", *extra)
    index = read_json(out / "tiny_scan.json")
    images = [tifffile.imread(out / p["image"]) for p in index["planes"]]
    sidecars = [read_json(out / p["sidecar"]) for p in index["planes"]]
    return index, images, sidecars


def test_images_bit_identical_to_cli(exe, tiny_scene_file, tmp_path):
    index, cli_images, cli_sidecars = cli_scan(exe, tiny_scene_file, tmp_path / "cli", "--seed", 11,
                                               "--rays", 20000, "--defocus-um", "-4,3")
    r = raymatch.simulate(raymatch.Scene.from_file(tiny_scene_file), rays=20000, defocus_um=[-4, 3],
                          seed=11)
    assert r.defocus_um == [-4.0, 3.0]
    assert r.rays_per_image == index["rays_per_image"] == 20000
    assert len(r.images) == len(cli_images) == 2
    for py_img, cli_img, py_meta, cli_meta in zip(r.images, cli_images, r.sidecars, cli_sidecars):
        assert py_img.dtype == np.float32 and py_img.shape == (32, 40)
        assert cli_img.dtype == np.float32
        assert py_img.sum() > 1000  # light reached the sensor
        np.testing.assert_array_equal(py_img, cli_img)
        for key in ("seed", "rays", "hits", "fates", "path_classes", "defocus_um", "plane_index",
                    "effects", "scene_checksum_fnv1a64"):
            assert py_meta[key] == cli_meta[key], key
        assert py_meta["image"]["mean_counts"] == cli_meta["image"]["mean_counts"]
    # The same scene as text and as a dict gives the same images (same seed, same rays).
    text = raymatch.simulate(raymatch.Scene.from_toml(TINY_SCENE), rays=20000, defocus_um=[-4, 3],
                             seed=11)
    as_dict = raymatch.simulate(tomllib.loads(TINY_SCENE), rays=20000, defocus_um=[-4, 3], seed=11)
    for a, b, c in zip(r.images, text.images, as_dict.images):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)
    assert text.sidecars[0]["scene_file"] == "<string>"
    assert text.sidecars[0]["scene_checksum_fnv1a64"] == ""


def test_camera_code_values_bit_identical_to_cli(exe, tmp_path):
    # [camera.readout]: the code values (<stem>_dn.tif) come back as arrays, equal to the CLI's.
    text = TINY_SCENE.replace("[trace]", "[camera.readout]\ngain_e_per_dn = 2\ndark_dn = 50\n"
                              "read_noise_e = 5\nbit_depth = 10\n\n[trace]")
    scene_file = tmp_path / "tiny.toml"
    scene_file.write_text(text)
    index, _, cli_sidecars = cli_scan(exe, scene_file, tmp_path / "cli", "--defocus-um", "0")
    r = raymatch.simulate(raymatch.Scene.from_file(scene_file), defocus_um=[0])
    assert len(r.code_values) == 1
    cli_dn = tifffile.imread(tmp_path / "cli" / index["planes"][0]["code_values"])
    assert cli_dn.dtype == np.uint16 and cli_dn.max() <= 1023
    np.testing.assert_array_equal(r.code_values[0], cli_dn.astype(np.float32))
    assert r.sidecars[0]["code_values"]["read_noise_e"] == cli_sidecars[0]["code_values"]["read_noise_e"] == 5
    assert raymatch.simulate(raymatch.Scene.from_toml(TINY_SCENE), defocus_um=[0]).code_values == []


def test_scene_defaults_match_cli(exe, tiny_scene_file, tmp_path):
    """No overrides: the scene's own seed, rays and planes, as the CLI without options."""
    _, cli_images, _ = cli_scan(exe, tiny_scene_file, tmp_path / "cli")
    r = raymatch.simulate(tiny_scene_file)
    assert r.defocus_um == [-6.0, 0.0, 6.0]
    for a, b in zip(r.images, cli_images):
        np.testing.assert_array_equal(a, b)


def test_seed_changes_the_noise_and_threads_do_not():
    scene = raymatch.Scene.from_toml(TINY_SCENE)
    a = raymatch.simulate(scene, rays=5000, defocus_um=[0], seed=1, threads=1).images[0]
    b = raymatch.simulate(scene, rays=5000, defocus_um=[0], seed=1, threads=2).images[0]
    c = raymatch.simulate(scene, rays=5000, defocus_um=[0], seed=2).images[0]
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert a.sum() == pytest.approx(c.sum(), rel=0.1)  # same light, different draws


def test_images_are_not_copied():
    r = raymatch.simulate(raymatch.Scene.from_toml(TINY_SCENE), rays=2000, defocus_um=[0])
    img = r.images[0]
    assert not img.flags.owndata and img.base is not None  # a view of the library's buffer
    assert img.flags.c_contiguous and img.flags.writeable
    assert r.stack().shape == (1, 32, 40)


def test_scene_from_dict_with_numpy_values_and_properties():
    d = tomllib.loads(TINY_SCENE)
    d["camera"]["pixels"] = np.array([24, 20])
    d["object"][0]["radius_um"] = np.float64(6.0)
    del d["name"]
    s = raymatch.Scene.from_dict(d)
    assert s.name == "scene" and s.pixels == (24, 20) and s.object_names == ["drop"]
    s.defocus_um = [1.5]
    s.seed = 9
    assert s.defocus_um == [1.5] and s.seed == 9
    assert raymatch.simulate(s, rays=1000).images[0].shape == (20, 24)


def test_errors_carry_the_cli_message(exe, tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(TINY_SCENE.replace("radius_um = 10", "radius_um = 10\nradius_mm = 1"))
    cli = run_cli(exe, "simulate", bad, "-o", tmp_path / "out", "-q", check=False)
    assert cli.returncode != 0
    with pytest.raises(raymatch.Error) as e:
        raymatch.Scene.from_file(bad)
    assert cli.stderr.strip() == "raymatch: " + str(e.value)
    assert e.value.file == str(bad) and e.value.line > 0 and "radius_mm" in e.value.message
    # The same for TOML text: the location is '<string>:line:col'.
    with pytest.raises(raymatch.Error, match=r"^<string>:\d+:\d+: error: .*radius_mm"):
        raymatch.Scene.from_toml(bad.read_text())
    with pytest.raises(raymatch.Error, match=r"TOML syntax"):
        raymatch.Scene.from_toml("name = ")
    d = tomllib.loads(TINY_SCENE)
    d["camera"]["pixels"] = "many"
    with pytest.raises(raymatch.Error, match="pixels"):
        raymatch.Scene.from_dict(d)
    with pytest.raises(TypeError, match="object"):
        raymatch.Scene.from_dict({"camera": {"pixels": [object()]}})
    with pytest.raises(raymatch.Error, match=r"^<string>: error: focus position 1 um is listed twice"):
        raymatch.simulate(raymatch.Scene.from_toml(TINY_SCENE), defocus_um=[1, 1], rays=10)
    with pytest.raises(raymatch.Error):
        raymatch.Scene.from_file(tmp_path / "missing.toml")


def test_gil_released_while_tracing():
    """Another Python thread keeps running while a plane is traced."""
    scene = raymatch.Scene.from_toml(TINY_SCENE)
    done = {}

    def work():
        t0 = time.perf_counter()
        raymatch.simulate(scene, rays=20_000_000, defocus_um=[0], threads=1)
        done["seconds"] = time.perf_counter() - t0

    t = threading.Thread(target=work)
    ticks, last, max_gap = 0, time.perf_counter(), 0.0
    t.start()
    while t.is_alive():
        now = time.perf_counter()
        max_gap, last = max(max_gap, now - last), now
        ticks += 1
        time.sleep(0.001)
    t.join()
    assert done["seconds"] > 0.1, "trace too short to tell"
    # With the GIL held the loop would stall for the whole trace.
    assert max_gap < 0.5 * done["seconds"], (max_gap, done["seconds"], ticks)


def test_version_matches_cli(exe):
    out = run_cli(exe, "--version").stdout
    assert out.splitlines()[0] == "raymatch " + raymatch.__version__
    assert "Python module on" in out


def test_example_script_runs(tmp_path):
    """docs/examples/python_focus_scan.py end to end, at 10 photons per pixel."""
    import os
    import subprocess
    import sys
    from conftest import SOURCE_DIR
    env = dict(os.environ, RAYMATCH_EXAMPLE_PHOTONS="10")
    r = subprocess.run([sys.executable, SOURCE_DIR / "docs/examples/python_focus_scan.py", tmp_path],
                       env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "mse" in r.stdout and (tmp_path / "report" / "report.html").exists()
    assert (tmp_path / "focus_scan.png").exists() or (tmp_path / "focus_scan.npz").exists()


@pytest.mark.parametrize("optics,radius,sampling,key", [
    ("mie", 10, "[trace.mie]\nnodes_per_panel = 3\npanel_width = 0.1", "mie_terms"),
    ("physical", 3, "[trace.physical]\npolar_nodes = 1\nazimuths = 2", "field_rays")])
def test_image_models_bit_identical_to_cli(exe, tmp_path, optics, radius, sampling, key):
    # [trace] optics = "mie" (the exact wave image) and "physical": the Poisson counts of the
    # expected image, equal to the CLI's, with the sidecar naming the optics and its sampling.
    text = TINY_SCENE.replace("radius_um = 10", f"radius_um = {radius}").replace(
        "rays = 30000", f'photons_per_pixel = 400\noptics = "{optics}"\n{sampling}')
    scene_file = tmp_path / "tiny.toml"
    scene_file.write_text(text)
    index, cli_images, cli_sidecars = cli_scan(exe, scene_file, tmp_path / "cli", "--defocus-um",
                                               "2")
    r = raymatch.simulate(raymatch.Scene.from_file(scene_file), defocus_um=[2])
    np.testing.assert_array_equal(r.images[0], cli_images[0])
    assert r.sidecars[0]["optics"] == cli_sidecars[0]["optics"] == optics
    assert r.sidecars[0]["sampling"][key] > 0
    assert f"optics:{optics}" in r.effects
    assert abs(np.median(r.images[0][:4]) - 400) < 60  # the flat field's photons, away from the drop

