#!/usr/bin/env python3
"""Mutation campaign for fit files and pipeline files (issue 25; docs/reliability.md).

Builds small valid inputs, damages them one way at a time and runs `raymatch fit` / `raymatch
run` on each mutant as a user would. The damage: wrong types, missing images, images of the
wrong size, NaN/Inf pixels, corrupt TIFFs, images without usable light, bounds with lower >=
upper, a start outside its bounds, keys that are not numeric, missing or broken scenes, broken
meshes, damaged experiment folders and stack indexes, deleted, repeated and truncated lines,
garbage bytes. Each mutant must end in one of two ways:

* refused: a clean error (exit 1, never a signal, abort or sanitizer report) whose message names
  the damaged file (file:line:col, or the file) or the file that refers to it, with no output
  folder and no `*.partial-*` temporary left;
* accepted: complete outputs (`fit.json` that parses and holds no NaN/Infinity, or `run`'s
  `index.html`) and no temporary.

Anything else is counted as a crash, a hang (over the time limit), a partial output or an
unlocated refusal, and listed. Mutants are cheap (32 x 16 images, a few evaluations, `run` at
ray fraction 0.005), so the default 1200 mutants take minutes on 2 cores.

Usage: scripts/mutate-fit-pipeline.py [--raymatch build/release/apps/raymatch] [--count 1200]
       [--seed 1] [--jobs 2] [--work build/mutate] [--keep]
Exit status 0 when every mutant ended cleanly, 1 otherwise. Python 3 standard library only.
"""
import argparse
import json
import math
import os
import random
import re
import shutil
import struct
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# ---------------------------------------------------------------------------------------------
# Images: uncompressed 32-bit float TIFFs, one strip (what ReadImage reads through OIIO).

def write_tiff(path, w, h, pixels):
    data = struct.pack("<%df" % (w * h), *pixels)
    tags = [(256, 4, 1, w), (257, 4, 1, h), (258, 3, 1, 32), (259, 3, 1, 1), (262, 3, 1, 1),
            (273, 4, 1, 0), (277, 3, 1, 1), (278, 4, 1, h), (279, 4, 1, len(data)), (339, 3, 1, 3)]
    ifd_offset = 8
    data_offset = ifd_offset + 2 + 12 * len(tags) + 4
    out = bytearray(b"II*\x00" + struct.pack("<I", ifd_offset))
    out += struct.pack("<H", len(tags))
    for tag, typ, count, value in tags:
        if tag == 273:
            value = data_offset
        if typ == 3:
            out += struct.pack("<HHIHH", tag, typ, count, value, 0)
        else:
            out += struct.pack("<HHII", tag, typ, count, value)
    out += struct.pack("<I", 0)
    out += data
    with open(path, "wb") as f:
        f.write(out)


def poisson(rng, lam):
    if lam <= 0:
        return 0.0
    if lam > 60:
        return max(0.0, round(rng.gauss(lam, math.sqrt(lam))))
    l, k, p = math.exp(-lam), 0, 1.0
    while True:
        p *= rng.random()
        if p < l:
            return float(k)
        k += 1


def drop_image(w, h, level, seed, radius_px=6.0):
    """A brightfield-like image: a lit background with a dark disc and a bright rim."""
    rng = random.Random(seed)
    px = []
    for y in range(h):
        for x in range(w):
            r = math.hypot(x + 0.5 - w / 2, y + 0.5 - h / 2)
            mu = level * (0.35 if r < radius_px - 1 else 1.8 if r < radius_px + 0.5 else 1.0)
            px.append(poisson(rng, mu))
    return px


# ---------------------------------------------------------------------------------------------
# Base inputs.

FIT_SCENE = """name = "drop"
seed = 1
[source]
type = "cone"
half_angle_deg = 27
[[object]]
name = "drop"
type = "sphere"
center_um = [0, 0, 0]
radius_um = 6
index = 1.335
[objective]
focal_length_mm = 10
na = 0.42
[tube_lens]
focal_length_mm = 200
[camera]
pixels = [32, 16]
pixel_pitch_um = 20
[trace]
photons_per_pixel = 20
"""

FIT_FILE = """scene = "scene.toml"
seed = 5
method = "lm"
error = "poisson"
max_evaluations = 6
[[image]]
file = "exp.tif"
defocus_um = -4
dark = "dark.tif"
gain_e_per_dn = 1.0
[[parameter]]
key = "object.drop.radius_um"
lower = 5
upper = 7
start = 6
step = 0.2
[[parameter]]
key = "object.drop.center_um[2]"
lower = -3
upper = 3
step = 0.5
[rays]
ray_factor = 1
fractions = [0.25]
[uncertainty]
repeat_seeds = 0
cramer_rao = false
slice_points = 0
"""

# The pipeline's fit: the sample's sphere fit, made cheap (one parameter, few evaluations).
PIPELINE_FIT = """scene = "sphere_scene.toml"
method = "lm"
seed = 5
max_evaluations = 4
[[image]]
file = "../drop46/drop_z-10um.tif"
defocus_um = -10
dark = "../drop46/dark.tif"
gain_e_per_dn = 1.0989011
[[parameter]]
key = "object.drop.radius_um"
lower = 21
upper = 25
step = 0.2
[rays]
fractions = [0.0625]
[uncertainty]
repeat_seeds = 0
cramer_rao = false
slice_points = 0
"""

PIPELINE = """output = "out/pipeline"
[calibration]
lightfield = "lightfield"
corrector = "flatfield"
zones = 9
extrapolate_to_deg = 0
smoothness = 0
[experiment]
scan = "drop46"
mesh_object = "merging"
[simulation]
ray_fraction = 0.005
seed = 1
partial_reflection = "unpolarized"
[fit]
files = ["fit/cheap.toml"]
"""

TETRA = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n"
BAD_MESHES = {
    "open": "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\n",
    "face index out of range": "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 9\nf 2 3 4\nf 1 4 3\n",
    "NaN vertex": TETRA.replace("v 1 0 0", "v nan 0 0"),
    "deleted vertex line": TETRA.replace("v 0 0 1\n", ""),
    "coincident copies": TETRA + TETRA.replace("f 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n",
                                               "f 5 7 6\nf 5 6 8\nf 6 7 8\nf 5 8 7\n"),
    "garbage": "\x01\x02 not a mesh \x7f\n",
}

WRONG_VALUES = ['"abc"', "true", "[1, 2]", "{ a = 1 }", '"3"', "1979-05-27", "-1", "0", "nan",
                "inf", "-inf", "1e308", "9223372036854775807", "[]", '""', "0.5", "[[1], [2]]"]
NON_NUMERIC_KEYS = ["object.drop.name", "object.drop.type", "camera", "object.drop.center_um",
                    "object.nosuch.radius_um", "image[5].defocus_um", "object.drop.radius_um[0]",
                    "", "..", "object[99].radius_um", "source.type", "image[0].file",
                    "object.drop.center_um[3]", "object.drop.center_um[-1]", "trace"]


def make_fit_base(d):
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, "scene.toml"), "w") as f:
        f.write(FIT_SCENE)
    with open(os.path.join(d, "fit.toml"), "w") as f:
        f.write(FIT_FILE)
    write_tiff(os.path.join(d, "exp.tif"), 32, 16, [v + 3.0 for v in drop_image(32, 16, 20, 1)])
    write_tiff(os.path.join(d, "dark.tif"), 32, 16, [3.0] * 512)


def make_pipeline_base(d):
    os.makedirs(d, exist_ok=True)
    for sub in ("lightfield", "flatfield", "drop46", "merging", "fit"):
        if not os.path.exists(os.path.join(d, sub)):
            shutil.copytree(os.path.join(ROOT, "datasets-sample", sub), os.path.join(d, sub))
    with open(os.path.join(d, "fit", "cheap.toml"), "w") as f:
        f.write(PIPELINE_FIT)
    with open(os.path.join(d, "pipeline.toml"), "w") as f:
        f.write(PIPELINE)


# ---------------------------------------------------------------------------------------------
# Text mutations.

def value_lines(text):
    return [i for i, l in enumerate(text.split("\n")) if re.match(r"^\s*[A-Za-z_]+\s*=", l)]


def set_value(text, rng, value=None, key=None):
    lines = text.split("\n")
    idx = [i for i in value_lines(text) if key is None or lines[i].split("=")[0].strip() == key]
    i = rng.choice(idx)
    k = lines[i].split("=")[0].strip()
    v = value if value is not None else rng.choice(WRONG_VALUES)
    lines[i] = "%s = %s" % (k, v)
    return "\n".join(lines), "%s = %s (line %d)" % (k, v, i + 1)


def set_key_value(text, key, value, nth=0):
    lines = text.split("\n")
    hits = [i for i, l in enumerate(lines) if l.split("=")[0].strip() == key]
    i = hits[min(nth, len(hits) - 1)]
    lines[i] = "%s = %s" % (key, value)
    return "\n".join(lines)


def delete_line(text, rng):
    lines = text.split("\n")
    i = rng.randrange(len(lines))
    gone = lines.pop(i)
    return "\n".join(lines), "deleted line %d (%s)" % (i + 1, gone.strip())


def duplicate_line(text, rng):
    lines = text.split("\n")
    i = rng.randrange(len(lines))
    lines.insert(i, lines[i])
    return "\n".join(lines), "repeated line %d (%s)" % (i + 1, lines[i].strip())


def truncate(text, rng):
    n = rng.randrange(len(text))
    return text[:n], "truncated at byte %d" % n


def garbage(text, rng):
    n = rng.randrange(len(text))
    junk = "".join(chr(rng.choice([0, 1, 7, 0x7f, 0x22, 0x5b, 0x3d, 0x0a, 0xe9, 0x27])) for _ in range(rng.randint(1, 6)))
    return text[:n] + junk + text[n:], "garbage bytes at %d" % n


# ---------------------------------------------------------------------------------------------
# Mutants. A mutant is a folder holding the inputs, the command to run in it, its kind and the
# file names (any of which) a refusal must name.

class Mutant:
    def __init__(self, number, tool, what, blame):
        self.number, self.tool, self.what, self.blame = number, tool, what, blame


def write(path, text, binary=False):
    with open(path, "wb" if binary else "w", newline="" if not binary else None) as f:
        f.write(text)


def fit_mutant(rng, d, base):
    """Damages a copy of the fit base in `d`; returns (description, blame names)."""
    for f in os.listdir(base):
        shutil.copy(os.path.join(base, f), d)
    fit = FIT_FILE
    op = rng.choice(["type", "type", "missing image", "wrong size", "nan pixels", "bounds",
                     "start", "key", "scene", "delete", "repeat", "truncate", "garbage", "light",
                     "corrupt tiff", "values", "tables"])
    blame = ["fit.toml"]
    if op == "type":
        fit, what = set_value(fit, rng)
    elif op == "missing image":
        which = rng.choice(["file", "dark"])
        name = rng.choice(['"nothere.tif"', '"."', '""', '"scene.toml"', '"sub/"'])
        fit, what = set_value(fit, rng, name, which)
    elif op == "wrong size":
        w, h = rng.choice([(31, 16), (32, 15), (1, 1), (64, 32), (16, 32), (33, 17)])
        which = rng.choice(["exp.tif", "dark.tif"])
        write_tiff(os.path.join(d, which), w, h, drop_image(w, h, 20, rng.randrange(1000)))
        what = "%s is %d x %d" % (which, w, h)
        blame.append(which)
    elif op == "nan pixels":
        which = rng.choice(["exp.tif", "dark.tif"])
        px = drop_image(32, 16, 20, 7) if which == "exp.tif" else [3.0] * 512
        bad = rng.choice([float("nan"), float("inf"), float("-inf")])
        count = rng.choice([1, 5, 512])
        for i in rng.sample(range(512), count):
            px[i] = bad
        write_tiff(os.path.join(d, which), 32, 16, px)
        what = "%s: %d pixel(s) %r" % (which, count, bad)
        blame.append(which)
    elif op == "bounds":
        k = rng.choice([0, 1])
        lo, hi = [("5", "7"), ("-3", "3")][k]
        choice = rng.choice(["swap", "equal", "nan"])
        new_lo, new_hi = {"swap": (hi, lo), "equal": (lo, lo), "nan": ("nan", hi)}[choice]
        fit = set_key_value(fit, "lower", new_lo, k)
        fit = set_key_value(fit, "upper", new_hi, k)
        what = "parameter %d: lower %s, upper %s" % (k + 1, new_lo, new_hi)
    elif op == "start":
        s = rng.choice(["7.5", "4.9", "-100", "1e300", "nan", "inf"])
        fit = set_key_value(fit, "start", s)
        what = "start = %s (bounds 5..7)" % s
    elif op == "key":
        k = rng.choice(NON_NUMERIC_KEYS)
        fit = set_key_value(fit, "key", '"%s"' % k, rng.choice([0, 1]))
        what = "key = %s" % k
        blame.append("scene.toml")
    elif op == "scene":
        choice = rng.choice(["missing", "folder", "image", "truncated", "bad mesh", "unknown key",
                             "size", "garbage"])
        what = "scene: " + choice
        blame.append("scene.toml")
        if choice == "missing":
            fit = set_key_value(fit, "scene", '"missing.toml"')
            blame.append("missing.toml")
        elif choice == "folder":
            fit = set_key_value(fit, "scene", '"."')
        elif choice == "image":
            fit = set_key_value(fit, "scene", '"exp.tif"')
            blame.append("exp.tif")
        elif choice == "truncated":
            write(os.path.join(d, "scene.toml"), FIT_SCENE[:rng.randrange(len(FIT_SCENE))])
        elif choice == "bad mesh":
            kind = rng.choice(sorted(BAD_MESHES))
            write(os.path.join(d, "m.obj"), BAD_MESHES[kind])
            write(os.path.join(d, "scene.toml"), FIT_SCENE.replace(
                'type = "sphere"\ncenter_um = [0, 0, 0]\nradius_um = 6\nindex = 1.335\n',
                'type = "mesh"\nfile = "m.obj"\nscale_um = 10\nindex = 1.335\n'))
            what += " (%s)" % kind
            blame.append("m.obj")
        elif choice == "unknown key":
            write(os.path.join(d, "scene.toml"), FIT_SCENE.replace("[trace]\n", "[trace]\nrayz = 5\n"))
        elif choice == "size":
            write(os.path.join(d, "scene.toml"), FIT_SCENE.replace("[32, 16]", "[64, 32]"))
            blame.append("exp.tif")
        else:
            t, _ = garbage(FIT_SCENE, rng)
            write(os.path.join(d, "scene.toml"), t)
    elif op == "delete":
        fit, what = delete_line(fit, rng)
    elif op == "repeat":
        fit, what = duplicate_line(fit, rng)
    elif op == "truncate":
        fit, what = truncate(fit, rng)
    elif op == "garbage":
        fit, what = garbage(fit, rng)
    elif op == "light":
        choice = rng.choice(["black", "saturated", "dim", "bright", "dark above image"])
        what = "image: " + choice
        blame.append("exp.tif")
        if choice == "black":
            write_tiff(os.path.join(d, "exp.tif"), 32, 16, [0.0] * 512)
            write_tiff(os.path.join(d, "dark.tif"), 32, 16, [0.0] * 512)
        elif choice == "saturated":
            px = drop_image(32, 16, 20, 3)
            write_tiff(os.path.join(d, "exp.tif"), 32, 16, [4095.0 if i % 4 else v for i, v in enumerate(px)])
        elif choice == "dim":
            write_tiff(os.path.join(d, "exp.tif"), 32, 16, [v / 10 + 3 for v in drop_image(32, 16, 20, 4)])
        elif choice == "bright":
            write_tiff(os.path.join(d, "exp.tif"), 32, 16, drop_image(32, 16, 400, 5))
        else:
            write_tiff(os.path.join(d, "dark.tif"), 32, 16, [1000.0] * 512)
            blame.append("dark.tif")
    elif op == "corrupt tiff":
        which = rng.choice(["exp.tif", "dark.tif"])
        p = os.path.join(d, which)
        raw = open(p, "rb").read()
        choice = rng.choice(["truncated", "random", "empty", "header flip"])
        if choice == "truncated":
            raw = raw[:rng.randrange(len(raw))]
        elif choice == "random":
            raw = bytes(rng.randrange(256) for _ in range(600))
        elif choice == "empty":
            raw = b""
        else:
            raw = bytearray(raw)
            for _ in range(4):
                raw[rng.randrange(8, 130)] = rng.randrange(256)
            raw = bytes(raw)
        write(p, raw, binary=True)
        what = "%s: %s" % (which, choice)
        blame.append(which)
    elif op == "values":
        key, val = rng.choice([("defocus_um", "1e300"), ("gain_e_per_dn", "0"), ("gain_e_per_dn", "-1"),
                               ("max_evaluations", "0"), ("ray_factor", "1e-9"), ("fractions", "[2]"),
                               ("fractions", "[0.5, 0.25]"), ("fractions", "[]"), ("step", "0"),
                               ("step", "-0.1"), ("repeat_seeds", "1"), ("seed", "-5"),
                               ("method", '"newton"'), ("error", '"l1"'), ("slice_points", "1e9")])
        fit = set_key_value(fit, key, val)
        what = "%s = %s" % (key, val)
    else:  # tables
        choice = rng.choice(["no image", "a parameter removed", "image twice", "table as key"])
        what = choice
        if choice == "no image":
            fit = re.sub(r"\[\[image\]\]\n(.*\n){4}", "", fit)
        elif choice == "a parameter removed":
            fit = re.sub(r"\[\[parameter\]\]\n(.*\n){3,5}?(?=\[)", "", fit)
        elif choice == "image twice":
            fit = fit.replace("[[parameter]]", "[[image]]\nfile = \"exp.tif\"\ndefocus_um = -4\n[[parameter]]", 1)
        else:
            fit = fit.replace("[rays]", "rays = 5\n[rays]")
    write(os.path.join(d, "fit.toml"), fit)
    return what, blame


def pipeline_mutant(rng, d, base):
    """Damages a pipeline in `d` (unchanged sample folders linked, damaged ones copied)."""
    pipe = PIPELINE
    op = rng.choice(["type", "type", "folder", "fit file", "fit", "fit", "experiment", "mesh object",
                     "calibration metadata", "delete", "repeat", "truncate", "garbage", "values"])
    damaged = set()

    def own(sub):
        if sub not in damaged:
            damaged.add(sub)
            shutil.copytree(os.path.join(base, sub), os.path.join(d, sub))
        return os.path.join(d, sub)

    blame = ["pipeline.toml"]
    what = op
    if op == "type":
        pipe, what = set_value(pipe, rng)
    elif op == "folder":
        key = rng.choice(["lightfield", "corrector", "scan", "mesh_object"])
        val = rng.choice(['"nothere"', '"drop46/scan.csv"', '""', '"pipeline.toml"'])
        pipe = set_key_value(pipe, key, val)
        what = "%s = %s" % (key, val)
    elif op == "fit file":
        val = rng.choice(['["nothere.toml"]', '["fit"]', '[""]', '"fit/cheap.toml"', "[1]",
                          '["fit/cheap.toml", "fit/cheap.toml", 3]'])
        pipe = set_key_value(pipe, "files", val)
        what = "files = %s" % val
    elif op == "fit":
        fd = own("fit")
        blame.append("cheap.toml")
        fit = PIPELINE_FIT
        choice = rng.choice(["type", "missing image", "wrong size", "nan pixels", "bounds", "start",
                             "key", "missing scene", "black image", "delete", "garbage"])
        what = "fit: " + choice
        if choice == "type":
            fit, w = set_value(fit, rng)
            what += " " + w
        elif choice == "missing image":
            fit = set_key_value(fit, "file", '"../drop46/nothere.tif"')
        elif choice == "wrong size":
            write_tiff(os.path.join(fd, "small.tif"), 80, 60, drop_image(80, 60, 2500, 1, 12))
            fit = set_key_value(fit, "file", '"small.tif"')
            fit = fit.replace('dark = "../drop46/dark.tif"\n', "")
            blame.append("small.tif")
        elif choice == "nan pixels":
            px = drop_image(160, 120, 2500, 2, 23)
            px[rng.randrange(len(px))] = float("nan")
            write_tiff(os.path.join(fd, "nan.tif"), 160, 120, px)
            fit = set_key_value(fit, "file", '"nan.tif"').replace('dark = "../drop46/dark.tif"\n', "")
            blame.append("nan.tif")
        elif choice == "bounds":
            fit = set_key_value(set_key_value(fit, "lower", "25"), "upper", "21")
        elif choice == "start":
            fit = fit.replace("step = 0.2", "step = 0.2\nstart = 30")
        elif choice == "key":
            fit = set_key_value(fit, "key", '"%s"' % rng.choice(NON_NUMERIC_KEYS))
            blame.append("sphere_scene.toml")
        elif choice == "missing scene":
            fit = set_key_value(fit, "scene", '"nothere.toml"')
            blame.append("nothere.toml")
        elif choice == "black image":
            write_tiff(os.path.join(fd, "black.tif"), 160, 120, [0.0] * (160 * 120))
            fit = set_key_value(fit, "file", '"black.tif"').replace('dark = "../drop46/dark.tif"\n', "")
            blame.append("black.tif")
        elif choice == "delete":
            fit, w = delete_line(fit, rng)
            what += " " + w
        else:
            fit, w = garbage(fit, rng)
            what += " " + w
        write(os.path.join(fd, "cheap.toml"), fit)
    elif op == "experiment":
        ed = own("drop46")
        choice = rng.choice(["nan defocus", "inf defocus", "text defocus", "missing image",
                             "wrong size image", "nan pixels", "metadata type", "metadata delete",
                             "no planes", "missing scan", "dark wrong size"])
        what = "experiment: " + choice
        if choice in ("nan defocus", "inf defocus", "text defocus"):
            csv = open(os.path.join(ed, "scan.csv")).read().split("\n")
            i = rng.randrange(1, len([l for l in csv if l]))
            rest = csv[i].split(",", 1)[1]
            csv[i] = {"nan defocus": "nan", "inf defocus": "-inf", "text defocus": "ten"}[choice] + "," + rest
            write(os.path.join(ed, "scan.csv"), "\n".join(csv))
            blame.append("scan.csv")
        elif choice == "missing image":
            os.remove(os.path.join(ed, "drop_z+05um.tif"))
            blame.append("drop_z+05um.tif")
        elif choice == "wrong size image":
            write_tiff(os.path.join(ed, "drop_z+05um.tif"), 80, 60, drop_image(80, 60, 2500, 3, 12))
            blame.append("drop_z+05um.tif")
        elif choice == "nan pixels":
            px = drop_image(160, 120, 2500, 4, 23)
            px[100] = float("nan")
            write_tiff(os.path.join(ed, "drop_z+05um.tif"), 160, 120, px)
            blame.append("drop_z+05um.tif")
        elif choice == "metadata type":
            t, w = set_value(open(os.path.join(ed, "metadata.toml")).read(), rng)
            write(os.path.join(ed, "metadata.toml"), t)
            what += " " + w
            blame.append("metadata.toml")
        elif choice == "metadata delete":
            t, w = delete_line(open(os.path.join(ed, "metadata.toml")).read(), rng)
            write(os.path.join(ed, "metadata.toml"), t)
            what += " " + w
            blame.append("metadata.toml")
        elif choice == "dark wrong size":
            write_tiff(os.path.join(ed, "dark.tif"), 80, 60, [100.0] * 4800)
            blame.append("dark.tif")
        elif choice == "no planes":
            write(os.path.join(ed, "scan.csv"), "defocus_um,file\n")
            blame.append("scan.csv")
        else:
            os.remove(os.path.join(ed, "scan.csv"))
            blame += ["scan.csv", "metadata.toml"]
    elif op == "mesh object":
        md = own("merging")
        choice = rng.choice(sorted(BAD_MESHES) + ["missing image", "metadata type", "missing mesh"])
        what = "mesh object: " + choice
        if choice in BAD_MESHES:
            write(os.path.join(md, "merging_drops.obj"), BAD_MESHES[choice])
            blame.append("merging_drops.obj")
        elif choice == "missing image":
            os.remove(os.path.join(md, "merging_z+00um.tif"))
            blame.append("merging_z+00um.tif")
        elif choice == "missing mesh":
            os.remove(os.path.join(md, "merging_drops.obj"))
            blame.append("merging_drops.obj")
        else:
            t, w = set_value(open(os.path.join(md, "metadata.toml")).read(), rng)
            write(os.path.join(md, "metadata.toml"), t)
            what += " " + w
            blame.append("metadata.toml")
    elif op == "calibration metadata":
        sub = rng.choice(["lightfield", "flatfield"])
        cd = own(sub)
        meta = open(os.path.join(cd, "metadata.toml")).read()
        choice = rng.choice(["type", "delete", "missing image"])
        what = "%s: %s" % (sub, choice)
        blame.append("metadata.toml")
        if choice == "type":
            meta, w = set_value(meta, rng)
            what += " " + w
        elif choice == "delete":
            meta, w = delete_line(meta, rng)
            what += " " + w
        else:
            tifs = sorted(f for f in os.listdir(cd) if f.endswith(".tif"))
            gone = rng.choice(tifs)
            os.remove(os.path.join(cd, gone))
            what += " " + gone
            blame.append(gone)
        write(os.path.join(cd, "metadata.toml"), meta)
    elif op == "delete":
        pipe, what = delete_line(pipe, rng)
    elif op == "repeat":
        pipe, what = duplicate_line(pipe, rng)
    elif op == "truncate":
        pipe, what = truncate(pipe, rng)
    elif op == "garbage":
        pipe, what = garbage(pipe, rng)
    else:
        key, val = rng.choice([("zones", "0"), ("zones", "65"), ("zones", "-1"), ("zones", "nan"),
                               ("ray_fraction", "0"), ("ray_fraction", "-1"), ("ray_fraction", "nan"),
                               ("extrapolate_to_deg", "90"), ("smoothness", "nan"), ("smoothness", "-1"),
                               ("seed", "-1"), ("partial_reflection", '"sometimes"')])
        pipe = set_key_value(pipe, key, val)
        what = "%s = %s" % (key, val)
    for sub in ("lightfield", "flatfield", "drop46", "merging", "fit"):
        if sub not in damaged:
            os.symlink(os.path.join(base, sub), os.path.join(d, sub))
    write(os.path.join(d, "pipeline.toml"), pipe)
    return what, blame


# ---------------------------------------------------------------------------------------------
# Running and judging one mutant.

CRASH_MARKS = ("terminate called", "Sanitizer", "runtime error:", "Segmentation fault", "Aborted",
               "core dumped", "double free", "std::bad_alloc")


def partials(d):
    found = []
    for root, dirs, files in os.walk(d):
        found += [os.path.join(root, f) for f in files + dirs if ".partial-" in f]
    return found


def judge(m, d, raymatch, timeout):
    out = os.path.join(d, "out")
    if m.tool == "fit":
        cmd = [raymatch, "fit", "fit.toml", "-q", "-t", "1", "-o", out]
    else:
        cmd = [raymatch, "run", "pipeline.toml", "-q", "--threads", "1", "--ray-fraction", "0.005", "-o", out]
    t0 = time.time()
    try:
        p = subprocess.run(cmd, cwd=d, capture_output=True, text=True, errors="replace", timeout=timeout)
    except subprocess.TimeoutExpired:
        return "hang", "over %d s" % timeout, time.time() - t0
    secs = time.time() - t0
    err = p.stderr
    if p.returncode < 0 or p.returncode >= 128 or any(k in err for k in CRASH_MARKS):
        return "crash", "exit %d: %s" % (p.returncode, err.strip()[-400:]), secs
    left = partials(d)
    if left:
        return "partial", "temporaries left: %s" % left[:3], secs
    error_lines = [l for l in err.split("\n") if "error" in l]
    if m.tool == "fit" and p.returncode == 3 and os.path.exists(os.path.join(out, "fit.json")):
        error_lines = []  # a flat error function: reported with complete outputs (exit 3)
    if error_lines:  # refused
        if p.returncode == 0:
            return "partial", "exit 0 after an error: " + error_lines[0], secs
        if os.path.exists(out):
            return "partial", "refused but left %s: %s" % (out, error_lines[0]), secs
        if not any(b in err for b in m.blame):
            return "unlocated", "message names none of %s: %s" % (m.blame, error_lines[0]), secs
        return "refused", error_lines[0][:300], secs
    # Accepted: the outputs must be complete.
    if m.tool == "fit":
        fj = os.path.join(out, "fit.json")
        if not os.path.exists(fj):
            return "partial", "exit %d without an error and without fit.json" % p.returncode, secs
        text = open(fj).read()
        try:
            json.loads(text)
        except ValueError as e:
            return "partial", "fit.json does not parse: %s" % e, secs
        if re.search(r"\bNaN\b|\bnan\b|Infinity", text):
            return "partial", "NaN/Infinity in fit.json", secs
        return "accepted", "exit %d" % p.returncode, secs
    if not os.path.exists(os.path.join(out, "index.html")):
        return "partial", "exit %d without an error and without index.html" % p.returncode, secs
    return "accepted", "verdict %d" % p.returncode, secs


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--raymatch", default=os.path.join(ROOT, "build/release/apps/raymatch"))
    ap.add_argument("--count", type=int, default=1200, help="mutants in all (default 1200)")
    ap.add_argument("--pipeline-share", type=float, default=0.4, help="share of pipeline mutants")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--timeout", type=int, default=120, help="seconds before a mutant counts as a hang")
    ap.add_argument("--work", default=os.path.join(ROOT, "build/mutate"))
    ap.add_argument("--keep", action="store_true", help="keep every mutant's folder (default: failures only)")
    args = ap.parse_args()
    raymatch = os.path.abspath(args.raymatch)
    if not os.access(raymatch, os.X_OK):
        sys.exit("no raymatch executable at %s (build it or give --raymatch)" % raymatch)
    work = os.path.abspath(args.work)
    shutil.rmtree(work, ignore_errors=True)
    # A copy of the executable: a rebuild during the campaign must not change (or remove) it.
    os.makedirs(work)
    shutil.copy2(raymatch, os.path.join(work, "raymatch"))
    raymatch = os.path.join(work, "raymatch")
    fit_base, pipe_base = os.path.join(work, "base-fit"), os.path.join(work, "base-pipeline")
    make_fit_base(fit_base)
    make_pipeline_base(pipe_base)

    # The controls: both base inputs are accepted.
    for tool, base in (("fit", fit_base), ("run", pipe_base)):
        d = os.path.join(work, "control-" + tool)
        shutil.copytree(base, d, symlinks=True)
        verdict, detail, secs = judge(Mutant(0, tool, "control", []), d, raymatch, args.timeout)
        print("control %s: %s (%s, %.1f s)" % (tool, verdict, detail, secs), flush=True)
        if verdict != "accepted":
            sys.exit("the unmutated %s input is not accepted; fix the campaign first" % tool)

    rng = random.Random(args.seed)
    mutants = []
    for n in range(1, args.count + 1):
        tool = "run" if rng.random() < args.pipeline_share else "fit"
        d = os.path.join(work, "m%05d-%s" % (n, tool))
        os.makedirs(d)
        mrng = random.Random(rng.randrange(1 << 30))
        if tool == "fit":
            what, blame = fit_mutant(mrng, d, fit_base)
        else:
            what, blame = pipeline_mutant(mrng, d, pipe_base)
        m = Mutant(n, tool, what, blame)
        m.dir = d
        mutants.append(m)

    t0 = time.time()
    results = {}

    def one(m):
        verdict, detail, secs = judge(m, m.dir, raymatch, args.timeout)
        if verdict in ("refused", "accepted") and not args.keep:
            shutil.rmtree(m.dir, ignore_errors=True)
        return m, verdict, detail, secs

    counts = {}
    slowest = (0, None)
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        for i, (m, verdict, detail, secs) in enumerate(pool.map(one, mutants), 1):
            key = (m.tool, verdict)
            counts[key] = counts.get(key, 0) + 1
            results[m.number] = (m, verdict, detail)
            if secs > slowest[0]:
                slowest = (secs, m)
            if verdict not in ("refused", "accepted"):
                print("FINDING m%05d %s [%s] %s: %s" % (m.number, m.tool, m.what, verdict, detail), flush=True)
            if i % 100 == 0:
                print("%d/%d mutants, %.0f s" % (i, len(mutants), time.time() - t0), flush=True)
    elapsed = time.time() - t0
    bad = {"crash": 0, "hang": 0, "partial": 0, "unlocated": 0}
    for (tool, verdict), c in counts.items():
        if verdict in bad:
            bad[verdict] += c
    print("\nmutants: %d (fit %d, run %d) in %.0f s with %d jobs; slowest %.1f s (m%05d %s: %s)" % (
        len(mutants), sum(c for (t, v), c in counts.items() if t == "fit"),
        sum(c for (t, v), c in counts.items() if t == "run"), elapsed, args.jobs, slowest[0],
        slowest[1].number, slowest[1].tool, slowest[1].what))
    for tool in ("fit", "run"):
        print("  %s: refused %d, accepted %d, crashes %d, hangs %d, partial outputs %d, unlocated refusals %d" % (
            tool, counts.get((tool, "refused"), 0), counts.get((tool, "accepted"), 0),
            counts.get((tool, "crash"), 0), counts.get((tool, "hang"), 0),
            counts.get((tool, "partial"), 0), counts.get((tool, "unlocated"), 0)))
    print("findings kept under %s" % work if any(bad.values()) else "no findings")
    return 1 if any(bad.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
