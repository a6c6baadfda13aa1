#pragma once
// What accuracy costs in time: one focus plane traced at ray fractions 1, 1/2, ... of the
// photon-matched count, each compared with a high-ray reference and with the experiment.
#include <string>
#include <vector>

namespace raymatch::pipeline {

struct AccuracyOptions {
  std::string scene_file;      ///< simulation scene (photon-matched via photons_per_pixel)
  std::string experiment_csv;  ///< optional experimental stack (defocus_um,file)
  std::string dark_file;       ///< experiment dark frame
  double gain_e_per_dn = 1;
  double defocus_um = 0;        ///< the plane studied
  int max_divisor = 1024;       ///< fractions 1 ... 1/max_divisor (powers of two)
  double reference_factor = 4;  ///< reference = this x the photon-matched ray count
  int threads = 0;
  std::string output_dir = "accuracy";
};

struct AccuracyRow {
  double fraction = 1;
  unsigned long long rays = 0;
  double seconds = 0, rays_per_second = 0, relative_shot_noise = 0;
  std::vector<double> vs_reference, vs_experiment;  ///< per measure (see `measures`)
};

struct AccuracyResult {
  std::vector<std::string> measures;
  std::vector<AccuracyRow> rows;
  std::string csv, plot;
};

/// Runs the study and writes accuracy.csv, accuracy.json and accuracy.png.
AccuracyResult RunAccuracyStudy(const AccuracyOptions& options);

}  // namespace raymatch::pipeline
