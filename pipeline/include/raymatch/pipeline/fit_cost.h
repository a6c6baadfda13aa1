#pragma once
// What accuracy costs in time, for fits: one fit file run over independent noise realisations
// of a known truth at each of several settings that trade time for accuracy (the ray factor,
// the derivative sets, the repeated fits, the last ray fraction), with per setting the mean
// and RMS error in Cramer-Rao bounds, RMS(error / sigma) and the time per fit.
#include <cstdint>
#include <string>
#include <vector>

namespace raymatch::pipeline {

struct FitCostOptions {
  /// The fit (docs/fit.md). Its [[image]] entries give each plane's defocus and size; their
  /// pixels are replaced by the truth's photon counts.
  std::string fit_file;
  /// The scene that makes the experiments: each plane traced photon-matched with the ray
  /// streams of seed `seed_base + k` (ray counting is photon counting: no model mismatch).
  std::string truth_scene;
  std::string calibration;  ///< optional: for the fit's scene and the truth's
  int realisations = 8;
  uint64_t seed_base = 100;
  /// Each value is one setting, the fit file's others as written; the fit file as written is
  /// the first setting.
  std::vector<double> ray_factors;
  std::vector<int> jacobian_seeds, repeat_seeds;
  std::vector<double> last_fractions;  ///< replaces the schedule's last (final) fraction
  int threads = 0;
  bool progress = true;  ///< a line per fit on stderr
  std::string output_dir = "fit-cost";
};

struct FitCostSetting {
  std::string
      knob;  ///< "as written", "ray_factor", "jacobian_seeds", "repeat_seeds", "last_fraction"
  double value = 0;           ///< NaN for "as written"
  int fits = 0, flagged = 0;  ///< flagged: goodness of fit "model mismatch"
  double mean_seconds = 0, max_seconds = 0;
  /// Per parameter, over the realisations; the errors in FitCostResult::cramer_rao.
  std::vector<double> mean_error_over_crb, rms_error_over_crb, rms_error_over_sigma;
};

/// One fit of one realisation at one setting.
struct FitCostFit {
  size_t setting = 0;
  int realisation = 0;
  double seconds = 0;
  bool converged = false, mismatch = false;
  std::vector<double> best, sigma, crb;
};

struct FitCostResult {
  std::vector<std::string> keys;
  std::vector<double> truth;       ///< per parameter
  std::vector<double> cramer_rao;  ///< per parameter: the mean bound of the fits that have one
  std::vector<FitCostSetting> settings;
  std::vector<FitCostFit> fits;
  std::string csv, fits_csv, plot;
};

/// Runs the study and writes OUT/fit_cost.csv (a row per setting), fits.csv (a row per fit),
/// fit_cost.json and fit_cost.png (RMS error in Cramer-Rao bounds against the time per fit).
/// Throws Error on bad input (a plane's size unlike the truth's camera, a key the truth scene
/// lacks) before any fit runs.
FitCostResult RunFitCostStudy(const FitCostOptions& options);

}  // namespace raymatch::pipeline
