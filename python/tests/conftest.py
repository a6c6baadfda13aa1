"""Shared fixtures: the CLI next to the module (RAYMATCH_EXE, set by ctest) and tiny scenes."""
import json
import os
import pathlib
import subprocess

import pytest

SOURCE_DIR = pathlib.Path(os.environ.get("RAYMATCH_SOURCE_DIR",
                                         pathlib.Path(__file__).resolve().parents[2]))

# A 20 um water-like drop under a 27 deg cone, 40 x 32 pixels of 1 um at the object: a few
# thousand rays trace in milliseconds, and the drop's image changes clearly with defocus.
TINY_SCENE = """\
name = "tiny"
seed = 3

[source]
type = "cone"
half_angle_deg = 27

[[object]]
name = "drop"
type = "sphere"
center_um = [0.5, -1, 0]
radius_um = 10
index = 1.333

[objective]
focal_length_mm = 10
na = 0.42
working_distance_mm = 20

[tube_lens]
focal_length_mm = 200

[camera]
pixels = [40, 32]
pixel_pitch_um = 20

[trace]
rays = 30000

[scan]
defocus_um = [-6, 0, 6]
"""


@pytest.fixture(scope="session")
def exe():
    path = os.environ.get("RAYMATCH_EXE")
    if not path or not os.path.exists(path):
        pytest.skip("RAYMATCH_EXE (the built raymatch CLI) not set: run through ctest")
    return path


@pytest.fixture
def tiny_scene_file(tmp_path):
    p = tmp_path / "tiny.toml"
    p.write_text(TINY_SCENE)
    return p


def run_cli(exe, *args, check=True):
    """Runs the CLI; returns the CompletedProcess (text)."""
    r = subprocess.run([exe, *map(str, args)], capture_output=True, text=True)
    if check and r.returncode != 0:
        raise AssertionError(f"raymatch {' '.join(map(str, args))} exited {r.returncode}:\n{r.stderr}")
    return r


def read_json(path):
    return json.loads(pathlib.Path(path).read_text())
