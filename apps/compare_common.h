#pragma once
// Exit codes shared by `compare` and `compare-scan` (OIIO idiff style, docs/compare.md).
#include <CLI/CLI.hpp>
#include <cmath>
#include <functional>
#include <iostream>
#include <map>
#include <string>

#include "raymatch/compare/measures.h"
#include "raymatch/core/atomic_file.h"

namespace raymatch::apps {

enum CompareExit { kOk = 0, kWarn = 1, kFail = 2, kSizeMismatch = 3, kFileError = 4 };

/// A data range L: a finite number > 0 (or also 0 when `zero_means_auto`). CLI11's own
/// PositiveNumber/Range checks print the double range with a 300-digit upper bound.
inline CLI::Validator DataRangeCheck(bool zero_means_auto) {
  return CLI::Validator(
      [zero_means_auto](std::string& s) -> std::string {
        double v = 0;
        std::size_t used = 0;
        try {
          v = std::stod(s, &used);
        } catch (const std::exception&) {
          used = 0;
        }
        const bool ok =
            used == s.size() && std::isfinite(v) && (v > 0 || (zero_means_auto && v == 0));
        if (ok) return "";
        return "the data range L must be a number " +
               std::string(zero_means_auto ? ">= 0 (0 = automatic)" : "> 0") +
               " in pixel units, e.g. 4095 for 12-bit data or 65535 for 16-bit; got '" + s + "'";
      },
      zero_means_auto ? "L >= 0" : "L > 0");
}

/// The MS-SSIM and CW-SSIM settings both subcommands take.
inline void AddMultiscaleOptions(CLI::App* sub, compare::MsSsimOptions* ms,
                                 compare::CwSsimOptions* cw) {
  using compare::MsSsimWeights;
  const std::map<std::string, MsSsimWeights> weight_names = {
      {compare::MsSsimWeightsName(MsSsimWeights::kMatlab), MsSsimWeights::kMatlab},
      {compare::MsSsimWeightsName(MsSsimWeights::kWang2003), MsSsimWeights::kWang2003}};
  sub->add_option("--ms-ssim-scales", ms->num_scales,
                  "MS-SSIM scales M (default: one below the most multissim accepts for the size)");
  sub->add_option("--ms-ssim-weights", ms->weights,
                  "MS-SSIM scale weights: matlab = multissim's fspecial('gaussian',[1 M],1), "
                  "wang2003 = [0.0448 0.2856 0.3001 0.2363 0.1333] (M <= 5)")
      ->transform(CLI::CheckedTransformer(weight_names).description(""))
      ->type_name("{matlab,wang2003}")
      ->default_str("matlab");
  sub->add_option("--ms-ssim-sigma", ms->sigma, "Gaussian window sigma in pixels (MS-SSIM)")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  sub->add_option("--cw-ssim-level", cw->level,
                  "CW-SSIM pyramid level, 1 = finest (default: one below the maximum)");
  sub->add_option("--cw-ssim-orientations", cw->orientations, "CW-SSIM orientations (1..16)")
      ->check(CLI::Range(1, 16))
      ->capture_default_str();
  sub->add_option("--cw-ssim-k", cw->k,
                  "CW-SSIM constant K, in (coefficient of an image scaled to 0..255)^2 "
                  "(cwssim_index's K; 0 = its default)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
}

inline int RunCompareGuarded(const std::function<int()>& fn) {
  try {
    return fn();
  } catch (const compare::CompareError& e) {
    RemoveCreatedEmptyDirectories();  // nothing written: no empty report folder either
    std::cerr << "raymatch: " << e.what() << "\n";
    switch (e.kind()) {
      case compare::FailureKind::kSizeMismatch:
        return kSizeMismatch;
      case compare::FailureKind::kFileError:
        return kFileError;
      default:
        return kFail;
    }
  } catch (const Error& e) {
    RemoveCreatedEmptyDirectories();
    std::cerr << "raymatch: " << e.what() << "\n";
    return kFileError;
  }
}

}  // namespace raymatch::apps
