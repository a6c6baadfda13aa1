#pragma once
// The main job: calibrate -> simulate the experiment's focus scan -> compare -> report.
// The one library allowed to combine calibrate, simulate and compare (they depend on core only).
#include <array>
#include <cstdint>
#include <string>
#include <vector>

namespace raymatch::pipeline {

struct PipelineOptions {
  std::string pipeline_file;  ///< pipeline TOML (docs/pipeline.md)
  std::string output_dir;     ///< overrides the file's `output` when set
  double ray_fraction = 0;    ///< overrides [simulation] ray_fraction when > 0
  int threads = 0;
  bool progress = false;  ///< progress bars on stderr (`raymatch run`: on a TTY or --progress)
  bool steps = true;      ///< one line per step on stderr (`raymatch run -q`: off)
  bool force = false;     ///< recompute every step
};

/// One check of a run, as the summary at the top of index.html and on stdout shows it.
struct PipelineCheck {
  std::string name;     ///< "focus-scan test", "sphere calibration", "fit sphere", ...
  bool ok = true;       ///< passes; false: needs attention
  std::string result;   ///< what it found, one line
  std::string meaning;  ///< what that says about the model, one line
};

struct PipelineSummary {
  std::string report;  ///< index.html
  int verdict = 2;     ///< compare-scan verdict: 0 pass, 1 warning, 2 fail
  /// Every check of the run: the corrector calibration, the sphere calibration (when run), the
  /// focus-scan test, each fit.
  std::vector<PipelineCheck> checks;
  /// The run's exit status: 0 every check passes; 1 a check needs attention (a focus-scan
  /// warning, a model mismatch, a fit that did not converge); 2 the focus-scan test fails.
  int status = 2;
  std::string Overall() const;  ///< one line: "all N checks pass" or what needs attention
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

/// A pipeline file (docs/pipeline.md). Folders are resolved against the file's folder and must
/// exist; fit files must exist.
struct PipelineFile {
  std::string output = "out/pipeline";  ///< relative to the working directory
  std::string lightfield, flatfield;    ///< [calibration] lightfield, corrector
  /// [calibration] sphere: a drop's focus-scan folder for `calibrate sphere` (empty: none), and
  /// sphere_planes_um: the planes it fits (empty: its default pair); sphere_optics: its image
  /// model ("rays" or "mie").
  std::string sphere;
  std::vector<double> sphere_planes_um;
  std::string sphere_optics = "rays";
  std::string experiment;  ///< [experiment] scan
  std::string merging;     ///< [experiment] mesh_object (empty: none)
  double extrapolate_to_deg = 0;
  int zones = 9;
  double smoothness = 0;
  double ray_fraction = 1;  ///< of the photon-matched ray count
  uint64_t seed = 1;
  std::string partial_reflection = "unpolarized";
  std::vector<std::string> fits;  ///< fit files (docs/fit.md) run with this calibration
};

/// Strict reader of a pipeline file; throws Error "file:line:col: error: ..." (unknown keys,
/// wrong types, missing folders).
PipelineFile ReadPipelineFile(const std::string& path);

/// An experiment folder's metadata.toml (docs/sample-data-format.md): the focus scan's CSV, the
/// dark frame, the nominal size and the camera gain (paths joined to the folder, not checked).
struct ExperimentMetadata {
  std::string scan_csv, dark;
  double diameter_um = 0;  ///< nominal diameter
  double temperature_K = 293.15;
  double gain = 1;          ///< photons per code value after dark subtraction
  double read_noise_e = 0;  ///< [camera] read_noise_e (0 when not given)
  int bit_depth = 16;       ///< [camera] bit_depth: saturation at 2^bits - 1
};
ExperimentMetadata ReadExperimentMetadata(const std::string& folder);

/// A mesh-object folder's metadata.toml: one in-focus image of a non-spherical object and its
/// mesh (paths joined to the folder, not checked).
struct MeshObjectMetadata {
  std::string image, dark, mesh;  ///< mesh: absolute
  double defocus_um = 0;
  std::array<double, 3> rotation_deg{0, 0, 0};
  double gain = 1;
};
MeshObjectMetadata ReadMeshObjectMetadata(const std::string& folder);

/// Runs the pipeline; throws raymatch::Error on bad input.
PipelineSummary RunPipeline(const PipelineOptions& options);

}  // namespace raymatch::pipeline
