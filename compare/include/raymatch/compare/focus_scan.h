#pragma once
// The focus-scan test (paper sections II.B-C): every experimental plane against every simulated
// plane, for every measure; a measure passes when each experimental plane's best match is the
// simulated plane of the same defocus, within one step.
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "raymatch/compare/measures.h"

namespace raymatch::compare {

/// A focus stack: images labelled with their defocus (micrometres, docs/conventions.md).
struct Stack {
  std::vector<double> defocus_um;
  std::vector<Image> images;
  std::vector<std::string> files;
  /// The camera pixel at the object in micrometres, from the planes' sidecars (simulate's
  /// `image.object_pixel_um`) when every plane names one and they agree; 0: unknown.
  double object_pixel_um = 0;
};

/// Reads a stack index: a CSV "defocus_um,file" (header allowed) or the simulator's JSON index
/// ({"planes": [{"defocus_um": .., "image": .., "sidecar": ..}]}). Paths are relative to the
/// index. A `sidecar` (JSON field or CSV column) that exists is read for the object pixel; one
/// that is not valid JSON, or whose `image.object_pixel_um` is not a positive number, is a file
/// error; a missing one leaves the pixel size unknown. Throws
/// CompareError: kFileError for missing files and for an index that cannot be read as one (not
/// JSON, a field of the wrong type, a defocus that is not a whole finite number), naming the
/// file and the field or line; kInvalidInput for an empty stack or NaN pixels; kSizeMismatch
/// for images of different sizes within the stack.
Stack ReadStack(const std::string& index_path);

/// Turning camera images into photon counts.
struct PrepareOptions {
  std::optional<std::array<int, 4>> roi;  ///< x, y, width, height in pixels (crop first)
  std::string dark_file;                  ///< subtracted (code values) when given
  std::string flat_file;                  ///< flat field (dark-subtracted): divide by flat/mean
  double gain_e_per_dn = 1;               ///< photons per code value after dark subtraction
};

/// Crop, dark subtraction, flat-field normalisation and conversion to photon counts.
Image PrepareExperiment(const Image& raw, const PrepareOptions& options, const Image* dark,
                        const Image* flat);

enum class Measure { kMse, kSsim, kMsSsim, kCwSsim, kPoissonChi2 };
const char* MeasureName(Measure m);  ///< "mse", "ssim", "ms_ssim", "cw_ssim", "poisson_chi2"
bool HigherIsBetter(Measure m);      ///< similarity (true) or distance (false)

struct FocusScanOptions {
  PrepareOptions prepare;            ///< applied to the experimental stack
  double data_range = 0;             ///< L; 0 = the largest pixel of both stacks
  bool register_shift = true;        ///< sub-pixel phase correlation at the middle plane
  bool normalize_background = true;  ///< scale simulation to the experiment's median
  /// MS-SSIM and CW-SSIM settings; data_range is set by the scan (the L above), and
  /// num_scales / level 0 mean one below the maximum for the image size (the paper's choice).
  MsSsimOptions ms_ssim;
  CwSsimOptions cw_ssim;
  std::vector<Measure> measures = {Measure::kMse, Measure::kSsim, Measure::kMsSsim,
                                   Measure::kCwSsim, Measure::kPoissonChi2};
  /// Measures whose failure fails the test (the paper: MSE, MS-SSIM and CW-SSIM pass, SSIM not).
  std::vector<Measure> primary = {Measure::kMse, Measure::kMsSsim, Measure::kCwSsim};
  /// The camera pixel at the object plane (um) for the report's axes; 0: the simulated stack's,
  /// else the experimental stack's (from their sidecars), else pixels.
  double object_pixel_um = 0;
};

struct MeasureScan {
  Measure measure;
  std::vector<std::vector<double>> matrix;  ///< [experiment plane][simulation plane]
  std::vector<int> best;                    ///< best simulation plane per experiment plane
  std::vector<int> expected;                ///< simulation plane nearest in defocus
  bool passes = false;
  bool primary = false;  ///< one of FocusScanOptions::primary (in the verdict)
};

enum class Verdict { kPass = 0, kWarning = 1, kFail = 2 };

struct FocusScanResult {
  std::vector<double> exp_defocus_um, sim_defocus_um;
  std::vector<MeasureScan> measures;
  double data_range = 0;
  std::array<double, 2> shift_px{};  ///< applied to the experiment (x, y); 0 where not significant
  /// The registration's estimate before the significance test, its shot-noise standard error
  /// (infinite where the images hold no measurable gradient) and per axis whether it was
  /// applied (|estimate| > 3 sigma). Nothing applied when registration is off.
  std::array<double, 2> shift_estimate_px{};
  std::array<double, 2> shift_sigma_px{};
  std::array<bool, 2> shift_applied{};
  bool registration_run = false;
  std::string RegistrationSummary() const;  ///< one line for reports
  double sim_scale = 1;                     ///< factor applied to the simulation
  MsSsimOptions ms_ssim;                    ///< settings used (data_range = L, num_scales resolved)
  CwSsimOptions cw_ssim;                    ///< settings used (data_range = L, level resolved)
  Verdict verdict = Verdict::kFail;
  std::string message;
  std::vector<Image> exp_images, sim_images;  ///< prepared, for reports
  /// The camera pixel at the object plane (um), for the report's axes (FocusScanOptions'
  /// precedence); 0: not known (pixels).
  double object_pixel_um = 0;
  nlohmann::json ToJson() const;
};

/// Runs the focus-scan test. Throws CompareError on bad input.
FocusScanResult RunFocusScan(const Stack& experiment, const Stack& simulation,
                             const FocusScanOptions& options);

/// Goodness of fit of one experimental plane against the simulated plane nearest in defocus:
/// the mean square of (sim - exp) / sqrt(s sim + exp) over its pixels (s = sim_scale), 1 +-
/// sqrt(2 / N) for two Poisson images of one mean; a misfit 3 standard deviations above.
struct PlaneGoodness {
  double exp_defocus_um = 0, sim_defocus_um = 0;
  double mean_square = 0, expected_sd = 0, z = 0;
  bool misfit = false;
};
/// Per experimental plane (needs the result's exp_images and sim_images).
std::vector<PlaneGoodness> PerPlaneGoodness(const FocusScanResult& r);
/// One line for a summary: "residuals within the shot noise in 5 of 9 planes (misfit at +5,
/// +10 um)"; empty without planes. `misfits` (may be null) gets whether any plane is one.
std::string PlaneGoodnessSummary(const std::vector<PlaneGoodness>& planes, bool* misfits = nullptr);

/// Writes compare_scan.json, <measure>_matrix.csv, best_match.csv, heatmap_<measure>.png,
/// montage.png and a self-contained report.html into `dir`. Returns the report path.
std::string WriteFocusScanReport(const FocusScanResult& r, const std::string& dir,
                                 const std::string& title);

}  // namespace raymatch::compare
