#pragma once
// The main job: calibrate -> simulate the experiment's focus scan -> compare -> report.
// The one library allowed to combine calibrate, simulate and compare (they depend on core only).
#include <string>
#include <vector>

namespace raymatch::pipeline {

struct PipelineOptions {
  std::string pipeline_file;     ///< pipeline TOML (docs/pipeline.md)
  std::string output_dir;        ///< overrides the file's `output` when set
  double ray_fraction = 0;       ///< overrides [simulation] ray_fraction when > 0
  int threads = 0;
  bool progress = true;
  bool force = false;            ///< recompute every step
};

struct PipelineSummary {
  std::string report;            ///< index.html
  int verdict = 2;               ///< compare-scan verdict: 0 pass, 1 warning, 2 fail
  double cone_half_angle_deg = 0;
  std::vector<double> transmissions, transmission_sigma;
  std::vector<double> exp_defocus_um;
  std::vector<std::vector<double>> best_match_um;  ///< [measure][experiment plane]
  std::vector<std::string> measures;
  double photons_per_pixel = 0;
  std::vector<std::pair<std::string, double>> step_seconds;
  std::vector<std::string> reused;  ///< steps skipped because their inputs were unchanged
  std::vector<std::pair<std::string, std::string>> fits;  ///< fit name, status
};

/// Runs the pipeline; throws raymatch::Error on bad input.
PipelineSummary RunPipeline(const PipelineOptions& options);

}  // namespace raymatch::pipeline
