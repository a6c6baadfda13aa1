#pragma once
// The main job's report: the calibration's figures and index.html (pipeline.cpp gathers what
// they show). Not installed.
#include <filesystem>
#include <string>

#include "raymatch/compare/focus_scan.h"
#include "raymatch/compare/plot.h"
#include "raymatch/core/calibration_file.h"
#include "raymatch/fit/fit.h"
#include "raymatch/pipeline/pipeline.h"

namespace raymatch::pipeline::internal {

/// What index.html shows.
struct RunReport {
  std::filesystem::path out;  ///< the output folder (figures/ goes into it)
  std::string sphere_folder;  ///< [calibration] sphere (empty: none)
  const CalibrationData* cal = nullptr;
  std::string lf_report, co_report, sp_report;  ///< the calibration steps' brief reports
  const compare::FocusScanResult* scan = nullptr;
  const PipelineSummary* sum = nullptr;  ///< sum->report: where index.html goes
  double ray_fraction = 1;
  std::string mesh_html, fit_html;  ///< the mesh object's and the fits' sections (may be empty)
};

/// A PNG embedded in the HTML (data URI), so the report is one self-contained file.
std::string Img(const std::string& png, const std::string& alt = "");

/// The light field's radial profile: the angular map's azimuthal mean in rings of one map pixel
/// (relative to its largest ring, with each ring's standard error) against the angle to the
/// axis, and, where the sphere calibration set an edge beyond the NA, that soft edge continued
/// from the map's reference ring and the NA's angle (the map's cut).
compare::PlotPanel RadialProfilePanel(const CalibrationData& cal);

/// figures/: the light field's angular map and radial profile, its spatial map (when the
/// calibration has one) and the corrector's zone transmissions. Returns the spatial map's HTML
/// (empty without one).
std::string WriteCalibrationFigures(const CalibrationData& cal, const std::filesystem::path& fig);

/// The figures and index.html (written last, atomically).
void WriteRunReport(const RunReport& r);

/// One fit's section of index.html: status, parameters with sigma, Cramer-Rao bound and the
/// profile-likelihood interval where the fit computed one, the goodness of fit.
std::string FitSectionHtml(const std::string& stem, const fit::FitSpec& spec,
                           const fit::FitResult& result);

}  // namespace raymatch::pipeline::internal
