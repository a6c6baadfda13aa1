#pragma once
// What an image can tell before (or without) an experiment: the Fisher information and the
// Cramer-Rao bounds of any numeric scene keys at a scene's values, from derivative images
// traced with common random numbers; and experiment design, the focal planes that minimise the
// bounds of named keys for a photon budget (docs/sensitivity.md).
//
// Noise model as in fits (fit.h): a pixel of image k holds a Poisson count of mean mu_k(theta)
// (plus, with read noise, a variance r^2 in photons^2: the shifted-Poisson likelihood), so the
// information is I_ij = sum_k sum_q dmu_qi dmu_qj / (mu_q + r_k^2). With the exposure as a nuisance
// (as a fit with fit_exposure finds it), each image's log-exposure, whose derivative image is
// mu itself, is a further parameter, and the keys' bounds are those of the Schur complement.
#include <toml++/toml.h>

#include <cstdint>
#include <string>
#include <vector>

#include "raymatch/core/image.h"

namespace raymatch::fit {

struct SensitivitySpec {
  std::string scene_file;
  toml::table scene;               ///< the parsed scene (calibration key set when given)
  std::vector<std::string> keys;   ///< the fit's key syntax (docs/fit.md), image[i].* included
  std::vector<double> steps;       ///< central-difference span per key (empty/0: a default)
  std::vector<double> defocus_um;  ///< the images' focus positions (empty: the scene's)
  double photons_per_pixel = 0;    ///< flat-field photons per pixel (0: the scene's)
  double ray_factor = 4;           ///< rays traced per photon for the derivative images
  int sets = 4;                    ///< independent ray-stream sets (even, >= 4): the bound's
                                   ///< Monte Carlo error is a delete-one jackknife over them
  bool exposure_nuisance = true;   ///< each image's exposure unknown (profiled out)
  double read_noise_e = 0;         ///< camera read noise, electrons (= photons) rms
  uint64_t seed = 1;
  int threads = 0;
  /// Experiment design: choose `design_planes` of the images (the candidates) that minimise the
  /// geometric mean of the bounds of `design_keys` (empty: all keys), the photon budget of one
  /// image shared among the chosen planes. 0: no design.
  int design_planes = 0;
  std::vector<std::string> design_keys;
};

struct SensitivityKey {
  std::string key, unit;
  double value = 0, step = 0;
  double crb = 0;                 ///< Cramer-Rao bound (exposure a nuisance when asked), all images
  double crb_mc_error = 0;        ///< the bound's own Monte Carlo standard error (jackknife)
  double crb_exposure_known = 0;  ///< the bound when every exposure is known
  std::vector<double> crb_per_image;  ///< each image alone (its full photon count)
};

/// One choice of planes of the design, at one image's photon budget shared among them.
struct DesignChoice {
  std::vector<double> defocus_um;
  std::vector<double> crb;  ///< per key (all keys, in order)
  double objective = 0;     ///< geometric mean of the design keys' bounds
};

struct SensitivityResult {
  std::vector<SensitivityKey> keys;
  std::vector<std::vector<double>> fisher;       ///< keys x keys (nuisances profiled out)
  std::vector<std::vector<double>> correlation;  ///< from the inverse of `fisher`
  double exposure_relative_crb = 0;  ///< bound of an image's exposure / exposure (first image)
  std::vector<double> defocus_um;
  std::vector<Image> mu;                ///< expected photons per image
  std::vector<std::vector<Image>> dmu;  ///< [image][key] d mu / d key (photons per unit)
  double photons_per_pixel = 0;
  double object_pixel_um = 0;   ///< the camera's pixel at the object plane
  uint64_t rays_per_image = 0;  ///< rays traced per image and evaluation
  size_t evaluations = 0;
  std::vector<DesignChoice> design_best;  ///< the best choice of 1 .. design_planes planes
  std::vector<DesignChoice> design_top;   ///< the best 10 choices of design_planes planes
  size_t design_choices = 0;              ///< how many choices of design_planes were compared
  std::vector<std::string> design_keys;
  double seconds = 0;
};

/// A spec for the scene file `scene` (its path made absolute and the file parsed), with
/// `calibration` (when not empty) set as the scene's calibration file; the rest at defaults.
SensitivitySpec SensitivitySceneSpec(const std::string& scene, const std::string& calibration = "");

/// Default central-difference span for a key: 0.2 um for lengths, 0.5 deg for angles, 0.002 for
/// indices, 0.5 photons for backgrounds, else 1 % of |value| (at least 1e-3).
double DefaultSensitivityStep(const std::string& key, double value);

/// Computes the information. Throws Error on bad input (unknown keys, no photon count).
SensitivityResult RunSensitivity(const SensitivitySpec& spec, bool progress = false);

/// sensitivity.json, derivative maps (TIFF float + labelled PNG per key and image) and
/// report.html into `dir` (created; files written whole or not at all). Returns the report.
std::string WriteSensitivityOutputs(const SensitivitySpec& spec, const SensitivityResult& r,
                                    const std::string& dir);

/// The design's selection over given per-image information matrices (each keys x keys, nuisances
/// profiled out, at the full budget of one image): every choice of `planes` of them, the budget
/// shared (information / planes). Public for tests.
std::vector<DesignChoice> RankDesigns(
    const std::vector<std::vector<std::vector<double>>>& per_image,
    const std::vector<double>& defocus_um, int planes, const std::vector<size_t>& design_keys,
    size_t* compared);

}  // namespace raymatch::fit
