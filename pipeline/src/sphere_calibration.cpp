// `raymatch calibrate sphere` (sphere_calibration.h): the fit is an ordinary fit file and scene,
// written into the work folder so that a user can read, re-run and change it.
#include "raymatch/pipeline/sphere_calibration.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <sstream>

#include "generated_toml.h"
#include "raymatch/compare/focus_scan.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/calibration_file.h"
#include "raymatch/core/error.h"
#include "raymatch/core/html.h"
#include "raymatch/core/provenance.h"
#include "raymatch/fit/fit.h"
#include "raymatch/pipeline/pipeline.h"
#include "raymatch/simulate/water.h"

namespace fs = std::filesystem;

namespace raymatch::pipeline {

using internal::Sig10;
using internal::WriteToml;

namespace {

constexpr double kDeg = M_PI / 180.0;

struct Free {  // a fitted key: its start value is the scene's
  std::string key;
  double lower, upper, step;
};

/// The planes: given (each must be in the scan), or the two nearest -R/2 and +R/2.
std::vector<size_t> ChoosePlanes(const compare::Stack& scan, const std::string& scan_csv,
                                 double radius, const std::vector<double>& given_um) {
  std::vector<size_t> planes;
  auto nearest = [&](double d) {
    size_t best = 0;
    for (size_t i = 1; i < scan.defocus_um.size(); ++i)
      if (std::abs(scan.defocus_um[i] - d) < std::abs(scan.defocus_um[best] - d)) best = i;
    return best;
  };
  if (given_um.empty()) {
    planes = {nearest(-radius / 2), nearest(radius / 2)};
    if (planes[0] == planes[1]) planes.pop_back();
  } else {
    for (double d : given_um) {
      const size_t i = nearest(d);
      if (std::abs(scan.defocus_um[i] - d) > 1e-6)
        throw Error(FileLocation{scan_csv},
                    "no plane at defocus " + std::to_string(d) + " um in the scan");
      planes.push_back(i);
    }
  }
  return planes;
}

struct Start {  // the scene's start values and the fitted keys
  double n_water = 0, psf_sigma_um = 0, edge_deg = 0, width_deg = 1.0;
  std::vector<Free> free;
};

// Start values: the nominal drop on the axis, water's index (IAPWS R9-97) at the metadata's
// temperature and the calibration's wavelength, the edge 1 deg beyond the NA and 1 deg wide,
// a diffraction-limited PSF (Gaussian approximation of the Airy core, sigma = 0.21 lambda/NA;
// Zhang, Zerubia and Olivo-Marin, Appl. Opt. 46, 1819 (2007)) for the rays. The wave model
// images diffraction itself, so its PSF is only the camera's blur beyond it: a small start,
// 0.05 lambda/NA, away from zero, where a Gaussian blur's derivative in sigma vanishes.
Start StartValues(const CalibrationData& base, const ExperimentMetadata& ex, double radius,
                  const SphereCalibrationOptions& o) {
  Start s;
  s.n_water = simulate::WaterRefractiveIndex(
                  ex.temperature_K,
                  simulate::WaterDensityTanaka(std::clamp(ex.temperature_K, 273.15, 313.15)),
                  base.wavelength_um)
                  .n;
  const double na_deg = std::asin(base.na_limit) / kDeg;
  s.psf_sigma_um = (o.optics == "mie" ? 0.05 : 0.21) * base.wavelength_um / base.na;
  s.edge_deg = na_deg + 1;
  s.free = {{"object.drop.center_um[0]", -radius / 4, radius / 4, 0.2},
            {"object.drop.center_um[1]", -radius / 4, radius / 4, 0.2},
            {"object.drop.center_um[2]", -radius / 4, radius / 4, 0.4},
            {"object.drop.radius_um", 0.9 * radius, 1.1 * radius, 0.2},
            {"object.drop.index", s.n_water - 0.03, s.n_water + 0.03, 0.002},
            {"light_field_edge.half_angle_deg", na_deg - 2, na_deg + 8, 0.2}};
  if (o.fit_width) s.free.push_back({"light_field_edge.width_deg", 0.2, 4, 0.2});
  if (o.fit_psf) s.free.push_back({"camera.psf_sigma_um", 0, 4 * s.psf_sigma_um, 0.05});
  if (o.fit_tilt)
    for (int a = 0; a < 2; ++a)
      s.free.push_back({"light_field_edge.tilt_deg[" + std::to_string(a) + "]", -3, 3, 0.2});
  return s;
}

/// The scene at the start values and the fit file, in the work folder.
void WriteSceneAndFitFile(const fs::path& work, const SphereCalibrationOptions& o,
                          const ExperimentMetadata& ex, const compare::Stack& scan,
                          const std::vector<size_t>& planes, double radius, const Start& start) {
  const toml::table scene{
      {"name", "sphere_calibration"},
      {"seed", 1},
      {"calibration", fs::absolute(o.base).string()},
      {"object", toml::array{toml::table{{"name", "drop"},
                                         {"type", "sphere"},
                                         {"center_um", toml::array{0, 0, 0}},
                                         {"radius_um", Sig10(radius)},
                                         {"index", Sig10(start.n_water)}}}},
      {"light_field_edge", toml::table{{"half_angle_deg", Sig10(start.edge_deg)},
                                       {"width_deg", Sig10(start.width_deg)},
                                       {"tilt_deg", toml::array{0, 0}}}},
      {"camera", toml::table{{"pixels", toml::array{scan.images[0].width, scan.images[0].height}},
                             {"psf_sigma_um", Sig10(start.psf_sigma_um)}}},
      {"trace", toml::table{{"partial_reflection", "unpolarized"}}}};
  WriteToml(work / "scene.toml",
            "# Written by `raymatch calibrate sphere`: the drop of " +
                fs::absolute(o.scan_folder).string() + " at its start values.\n# index: water, " +
                "IAPWS R9-97 at " + std::to_string(ex.temperature_K) + " K.",
            scene);
  toml::array images, parameters;
  // The read noise of the images as fitted: subtracting the dark frame (one read-out, as the
  // corrector's calibration takes it too) adds its read noise, so the variance doubles.
  const double read_noise_e = ex.read_noise_e * (ex.dark.empty() ? 1 : std::sqrt(2.0));
  for (size_t i : planes) {
    toml::table im{{"file", fs::absolute(scan.files[i]).string()},
                   {"defocus_um", Sig10(scan.defocus_um[i])},
                   {"gain_e_per_dn", Sig10(ex.gain)},
                   {"read_noise_e", Sig10(read_noise_e)},
                   {"saturation_dn", std::ldexp(1.0, ex.bit_depth) - 1}};
    if (!ex.dark.empty()) im.insert("dark", fs::absolute(ex.dark).string());
    images.push_back(std::move(im));
  }
  for (const Free& f : start.free)
    parameters.push_back(toml::table{{"key", f.key},
                                     {"lower", Sig10(f.lower)},
                                     {"upper", Sig10(f.upper)},
                                     {"step", Sig10(f.step)}});
  toml::table fit{{"scene", "scene.toml"},
                  {"method", "lm"},
                  {"error", "poisson"},
                  {"seed", int64_t(o.seed)},
                  {"image", std::move(images)},
                  {"parameter", std::move(parameters)},
                  {"uncertainty", toml::table{{"repeat_seeds", 0}, {"slice_points", 0}}}};
  if (o.optics == "rays") {
    toml::array fractions;
    for (double f : o.fractions) fractions.push_back(Sig10(f));
    fit.insert("rays", toml::table{{"ray_factor", Sig10(o.ray_factor)},
                                   {"fractions", std::move(fractions)}});
  } else {
    fit.insert("optics", o.optics);  // an exact image: no ray levels
  }
  WriteToml(work / "fit.toml",
            "# Written by `raymatch calibrate sphere` (docs/calibration.md): the drop's five "
            "parameters and\n# the light field's edge beyond the NA and the PSF, from " +
                std::to_string(planes.size()) + " planes jointly.",
            fit);
}

/// The base calibration with the fitted edge, PSF and tilt, and a record of the fit.
void WriteCalibratedFile(const SphereCalibrationOptions& o, const CalibrationData& base,
                         const compare::Stack& scan, const std::vector<size_t>& planes,
                         const fit::FitResult& fr, const SphereCalibrationResult& res) {
  CalibrationData out = base;
  out.edge_half_angle_deg = res.edge_half_angle_deg;
  out.edge_width_deg = res.edge_width_deg;
  out.psf_sigma_um = res.psf_sigma_um;
  out.edge_tilt_deg = {res.edge_tilt_deg[0], res.edge_tilt_deg[1]};
  // The measured map's note ends with what lies beyond the NA; that is now the fitted edge.
  const size_t beyond = out.light_field_note.find("; zero beyond it");
  if (beyond != std::string::npos) out.light_field_note.resize(beyond);
  std::ostringstream edge;
  edge << "; beyond the NA: a soft edge fitted by calibrate sphere (half radiance at "
       << res.edge_half_angle_deg << " deg, width " << res.edge_width_deg << " deg)";
  out.light_field_note += edge.str();
  // The nuisances' sigmas, for fits that free them with the calibration as a prior. The value
  // lies within the fit's bounds, and a log-concave density (a Gaussian likelihood cut at the
  // bounds) there has a sigma of at most the uniform's, (upper - lower) / sqrt(12): the sigma
  // written is the fit's, or that where the fit's is wider or was not determined (an
  // information matrix that is not positive definite: a dim or short calibration).
  out.key_sigma.clear();
  for (const fit::ParameterResult& p : fr.parameters)
    if (p.key.starts_with("light_field_edge.") || p.key == "camera.psf_sigma_um") {
      const double uniform = (p.upper - p.lower) / std::sqrt(12.0);
      out.key_sigma[p.key] = p.sigma > 0 ? std::min(p.sigma, uniform) : uniform;
    }
  out.provenance = ProvenanceJson();
  for (auto& [k, v] : base.provenance.items())
    if (!out.provenance.contains(k)) out.provenance[k] = v;
  std::ostringstream rec;
  rec.precision(6);
  rec << "fit of " << fs::absolute(o.scan_folder).string() << " planes";
  for (size_t i : planes) rec << " " << scan.defocus_um[i];
  rec << " um with the " << (o.optics == "mie" ? "wave model (optics mie)" : "rays") << ": "
      << fit::StatusName(fr.status) << "; " << fr.goodness.verdict << ";";
  for (const auto& v : res.values)
    rec << " " << v.key << " = " << FormatValue(v.value, v.sigma) << " +- "
        << FormatUncertainty(v.sigma) << ";";
  out.provenance["sphere_calibration"] = rec.str();
  out.provenance["sphere_calibration_base"] = fs::absolute(o.base).string();
  WriteCalibrationFile(o.output, out);
}

}  // namespace

std::string SphereCalibrationResult::Brief() const {
  std::ostringstream os;
  os.precision(6);
  os << "sphere calibration: " << status << " (" << seconds << " s)\n";
  for (const auto& v : values)
    os << "  " << v.key << " = " << FormatValue(v.value, v.sigma) << " +- "
       << FormatUncertainty(v.sigma) << " (Cramer-Rao " << FormatUncertainty(v.cramer_rao) << ")"
       << (v.at_bound ? "  AT BOUND" : "") << "\n";
  os << "  goodness of fit: " << goodness << "\n";
  return os.str();
}

SphereCalibrationResult CalibrateSphere(const SphereCalibrationOptions& o) {
  const auto t0 = std::chrono::steady_clock::now();
  if (o.optics != "rays" && o.optics != "mie")
    throw Error("calibrate sphere: optics must be \"rays\" or \"mie\", not \"" + o.optics + "\"");
  auto say = [&](const std::string& s) {
    if (o.say) o.say(s);
  };
  const CalibrationData base = ReadCalibrationFile(o.base);
  if (!base.has_light_field() || !(base.na_limit > 0))
    throw Error(FileLocation{o.base},
                "calibrate sphere needs a calibration whose light field was measured through "
                "the objective (na_limit > 0): its continuation beyond the NA is what it fits");
  const ExperimentMetadata ex = ReadExperimentMetadata(o.scan_folder);
  const compare::Stack scan = compare::ReadStack(ex.scan_csv);
  const double radius = ex.diameter_um / 2;

  const std::vector<size_t> planes = ChoosePlanes(scan, ex.scan_csv, radius, o.planes_um);
  const Start start = StartValues(base, ex, radius, o);
  const fs::path work = o.work_dir.empty() ? fs::path(o.output).parent_path() /
                                                 (fs::path(o.output).stem().string() + "_sphere")
                                           : fs::path(o.work_dir);
  EnsureDirectory(work);
  WriteSceneAndFitFile(work, o, ex, scan, planes, radius, start);

  std::ostringstream msg;
  msg << "sphere calibration: " << start.free.size() << " parameters from " << planes.size()
      << " planes (";
  for (size_t k = 0; k < planes.size(); ++k) msg << (k ? ", " : "") << scan.defocus_um[planes[k]];
  msg << " um) of " << o.scan_folder << (o.optics == "mie" ? ", wave model" : ", rays");
  say(msg.str());
  const fit::FitSpec spec = fit::LoadFitSpec((work / "fit.toml").string());
  fit::FitOptions fo;
  fo.threads = o.threads;
  fo.progress = o.progress;
  const fit::FitResult fr = fit::RunFit(spec, fo);

  SphereCalibrationResult res;
  res.report = fit::WriteFitOutputs(spec, fr, work.string());
  res.status = fit::StatusName(fr.status);
  res.goodness = fr.goodness.verdict;
  res.mismatch = fr.goodness.mismatch;
  for (const auto& p : fr.parameters) {
    res.values.push_back({p.key, p.best, p.sigma, p.sigma_cramer_rao, p.at_bound});
    if (p.key == "light_field_edge.half_angle_deg") res.edge_half_angle_deg = p.best;
    if (p.key == "light_field_edge.width_deg") res.edge_width_deg = p.best;
    if (p.key == "camera.psf_sigma_um") res.psf_sigma_um = p.best;
    for (int a = 0; a < 2; ++a)
      if (p.key == "light_field_edge.tilt_deg[" + std::to_string(a) + "]")
        res.edge_tilt_deg[a] = p.best;
  }
  if (!o.fit_width) res.edge_width_deg = start.width_deg;
  if (!o.fit_psf) res.psf_sigma_um = start.psf_sigma_um;

  WriteCalibratedFile(o, base, scan, planes, fr, res);
  res.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return res;
}

}  // namespace raymatch::pipeline
