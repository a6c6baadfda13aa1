"""raymatch: ray-traced brightfield microscope images of transparent objects, from Python.

The functions call raymatch's C++ libraries (not the CLI): an image simulated here is
bit-identical to the one ``raymatch simulate`` writes for the same scene and seed. Lengths are in
micrometres (``_um``) unless a name says otherwise. Errors raise :class:`raymatch.Error` whose
text is the message the CLI prints after ``raymatch: ``. See docs/python.md.
"""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ._raymatch import (  # noqa: F401  (re-exported)
    Calibration,
    CompareError,
    Error,
    FocusScanResult,
    Scene,
    __version__,
    calibrate_corrector,
    calibrate_lightfield,
    compare,
    cw_ssim,
    ms_ssim,
    mse,
    poisson,
    psnr,
    ssim,
)
from . import _raymatch

__all__ = [
    "Calibration", "CompareError", "Error", "FocusScanResult", "RaymatchWarning", "Scene",
    "SimulationResult", "Stack", "__version__", "calibrate_corrector", "calibrate_lightfield",
    "compare", "cw_ssim", "fit", "focus_scan", "load_scene", "ms_ssim", "mse", "poisson", "psnr",
    "read_stack", "sensitivity", "simulate", "ssim",
]

# calibrate_sphere needs the pipeline library, which a build may leave out.
if hasattr(_raymatch, "calibrate_sphere"):
    calibrate_sphere = _raymatch.calibrate_sphere
    __all__.append("calibrate_sphere")


class RaymatchWarning(UserWarning):
    """A non-fatal note from loading a scene (the CLI prints these as 'raymatch: warning:')."""


def load_scene(scene: Any, base_dir: str | os.PathLike | None = None) -> Scene:
    """A :class:`Scene` from a Scene (returned as is), a dict, or a path to a scene file.

    TOML text goes through :meth:`Scene.from_toml` (a str here is always a path).
    """
    if isinstance(scene, Scene):
        return scene
    if isinstance(scene, dict):
        return Scene.from_dict(scene, base_dir)
    if isinstance(scene, (str, os.PathLike)):
        return Scene.from_file(scene)
    raise TypeError(f"scene: expected a raymatch.Scene, a dict or a path, got {type(scene).__name__}")


@dataclass
class SimulationResult:
    """One simulated focus scan: photon-count images (float32 holding integers, row 0 at the top,
    shape (rows, columns)) with each plane's sidecar, as ``raymatch simulate`` writes them."""

    images: list[np.ndarray]
    defocus_um: list[float]
    sidecars: list[dict]
    rays_per_image: int
    hits_per_pixel_per_ray: float  # from the photon-target pilot run, 0 when not used
    effects: list[str] = field(default_factory=list)
    # With the scene's [camera.readout]: each plane as the camera's code values (float32 holding
    # integers, as `simulate` writes <stem>_dn.tif); empty otherwise.
    code_values: list[np.ndarray] = field(default_factory=list)

    def stack(self) -> np.ndarray:
        """All planes as one (planes, rows, columns) array (a copy)."""
        return np.stack(self.images)


def simulate(scene: Any, rays: int | None = None, defocus_um: Sequence[float] | None = None,
             seed: int | None = None, photons_per_pixel: float | None = None, threads: int = 0,
             progress: bool = False, base_dir: str | os.PathLike | None = None) -> SimulationResult:
    """Traces a scene's focus scan, as ``raymatch simulate`` with the same options.

    scene: a :class:`Scene`, a dict (see :meth:`Scene.from_dict`) or a scene file path.
    rays: rays per image (default: the scene's ``[trace]``); defocus_um: focal-plane positions in
    um replacing ``[scan]`` (+ = towards the camera); seed: the random seed (same seed, same image
    for any thread count); photons_per_pixel: target mean hits per flat-field pixel (the ray count
    follows from a pilot run); threads: 0 = the scene's value, then all cores.
    The GIL is released while tracing. Raises :class:`Error` with the CLI's message.
    """
    s = load_scene(scene, base_dir)
    for w in s.warnings:
        warnings.warn(w, RaymatchWarning, stacklevel=2)
    images, z, sidecars, rays_per_image, hits, effects, code_values = _raymatch._simulate(
        s, rays=rays, defocus_um=None if defocus_um is None else [float(v) for v in defocus_um],
        seed=seed, photons_per_pixel=photons_per_pixel, threads=threads, progress=progress)
    return SimulationResult(images, z, sidecars, rays_per_image, hits, effects, code_values)


@dataclass
class Stack:
    """A focus stack: images labelled with their defocus in um (compare's Stack)."""

    defocus_um: list[float]
    images: list[np.ndarray]
    files: list[str] = field(default_factory=list)
    object_pixel_um: float = 0.0  # the camera pixel at the object (um); 0: unknown


def read_stack(index: str | os.PathLike) -> Stack:
    """Reads a stack index: a CSV 'defocus_um,file' or the simulator's <name>_scan.json. The
    object pixel comes from the planes' sidecars when every plane names one and they agree."""
    z, images, files, pixel_um = _raymatch._read_stack(index)
    return Stack(z, images, files, pixel_um)


def _as_stack(x: Any, what: str) -> Stack:
    if isinstance(x, (str, os.PathLike)):
        return read_stack(x)
    if isinstance(x, (Stack, SimulationResult)):
        return Stack(list(x.defocus_um), list(x.images), list(getattr(x, "files", [])),
                     float(getattr(x, "object_pixel_um", 0.0)))
    if isinstance(x, tuple) and len(x) == 2:
        z, images = x
        if isinstance(images, np.ndarray) and images.ndim == 3:
            images = list(images)
        return Stack([float(v) for v in z], list(images), [])
    raise TypeError(f"{what}: expected a stack index path, a raymatch.Stack, a SimulationResult "
                    f"or a (defocus_um, images) tuple, got {type(x).__name__}")


def focus_scan(experiment: Any, simulation: Any, data_range: float = 0.0, *,
               dark: str | os.PathLike | None = None, flat: str | os.PathLike | None = None,
               gain: float = 1.0, roi: Sequence[int] | None = None, register: bool = True,
               normalize: bool = True, ms_ssim_scales: int = 0,
               ms_ssim_weights: str | Sequence[float] = "matlab", ms_ssim_sigma: float = 1.5,
               cw_ssim_level: int = 0, cw_ssim_orientations: int = 16, cw_ssim_k: float = 0.0,
               measures: Sequence[str] | None = None, primary: Sequence[str] | None = None,
               pixel_um: float = 0.0,
               report_dir: str | os.PathLike | None = None) -> FocusScanResult:
    """The focus-scan test of ``raymatch compare-scan``: every experimental plane against every
    simulated plane for each measure; a measure passes when every best match is the plane of the
    same defocus within one step.

    experiment, simulation: a stack index path (CSV or _scan.json), a :class:`Stack`, a
    :class:`SimulationResult` or a ``(defocus_um, images)`` tuple. data_range: L in photons (0 =
    the largest pixel of both stacks). dark/flat: files applied to the experiment (code values);
    gain: photons per code value; roi: (x, y, width, height) in pixels. pixel_um: the camera
    pixel at the object in um for the report's axes (0: the simulation's stack's, then the
    experiment's, as read from the sidecars; pixels when neither has one). report_dir: also
    write the CLI's report (JSON, CSV, PNGs, report.html) there.
    """
    e = _as_stack(experiment, "experiment")
    s = _as_stack(simulation, "simulation")
    r = _raymatch._focus_scan(
        e.defocus_um, e.images, e.files, e.object_pixel_um, s.defocus_um, s.images, s.files,
        s.object_pixel_um, float(data_range),
        os.fspath(dark) if dark is not None else "", os.fspath(flat) if flat is not None else "",
        float(gain), None if roi is None else tuple(int(v) for v in roi), register, normalize,
        ms_ssim_scales, ms_ssim_weights, ms_ssim_sigma, cw_ssim_level, cw_ssim_orientations,
        cw_ssim_k, None if measures is None else list(measures),
        None if primary is None else list(primary), float(pixel_um))
    if report_dir is not None:
        r.write_report(report_dir)
    return r


def fit(fit_file: str | os.PathLike, scene: str | os.PathLike | None = None,
        calibration: str | os.PathLike | None = None, threads: int = 0, progress: bool = False,
        output: str | os.PathLike | None = None) -> dict:
    """Runs ``raymatch fit`` on a fit file (docs/fit.md) and returns the result as a dict:
    converged, status, message, parameters (best value, sigma, Cramer-Rao bound, ... per key,
    units from the key's suffix), correlation, evaluations, best_images, residuals, timings.

    scene / calibration override the fit file's; output: also write fit.json, images and
    report.html there (the dict's 'report'). Raises :class:`Error` on bad input, and when the
    error function is flat (the parameters do not change the image), as the CLI fails then.
    """
    r = _raymatch._fit(fit_file, os.fspath(scene) if scene is not None else "",
                       os.fspath(calibration) if calibration is not None else "", threads,
                       progress, os.fspath(output) if output is not None else "")
    if r["status"] == "flat":
        raise Error(r["message"])
    return r


def sensitivity(scene: str | os.PathLike, keys: list[str], steps: list[float] | None = None,
                defocus_um: list[float] | None = None, photons_per_pixel: float = 0,
                ray_factor: float = 4, sets: int = 4, known_exposure: bool = False,
                read_noise_e: float = 0, design_planes: int = 0,
                design_keys: list[str] | None = None, seed: int = 1, threads: int = 0,
                calibration: str | os.PathLike | None = None,
                output: str | os.PathLike | None = None) -> dict:
    """Runs ``raymatch sensitivity`` (docs/sensitivity.md): the Cramer-Rao bounds of scene keys
    (fit key syntax) at the scene's values. Returns a dict: keys (value, step, crb, crb_mc_error,
    crb_exposure_known, crb_per_image per key; units from the key's suffix), fisher,
    correlation, exposure_relative_crb, defocus_um, mu (expected photons per image), dmu
    (per image, per key: d mu / d key, photons per pixel per unit), and with design_planes > 0
    'design' (best_per_count, top: defocus_um, crb, objective). output: also write
    sensitivity.json, the maps and report.html there ('report'). Raises :class:`Error` on bad
    input."""
    return _raymatch._sensitivity(
        scene, list(keys), list(steps or []), list(defocus_um or []), photons_per_pixel,
        ray_factor, sets, known_exposure, read_noise_e, design_planes, list(design_keys or []),
        seed, threads, os.fspath(calibration) if calibration is not None else "",
        os.fspath(output) if output is not None else "")
