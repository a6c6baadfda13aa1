#include "raymatch/pipeline/pipeline.h"

#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <exception>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iomanip>
#include <iostream>
#include <nlohmann/json.hpp>
#include <optional>
#include <sstream>

#include "generated_toml.h"
#include "raymatch/calibrate/corrector.h"
#include "raymatch/calibrate/lightfield.h"
#include "raymatch/compare/focus_scan.h"
#include "raymatch/compare/plot.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/calibration_file.h"
#include "raymatch/core/error.h"
#include "raymatch/core/html.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/provenance.h"
#include "raymatch/core/toml_reader.h"
#include "raymatch/fit/fit.h"
#include "raymatch/pipeline/sphere_calibration.h"
#include "raymatch/simulate/geometry.h"
#include "raymatch/simulate/scan.h"
#include "raymatch/simulate/scene.h"
#include "run_report.h"

namespace fs = std::filesystem;

namespace raymatch::pipeline {

PipelineFile ReadPipelineFile(const std::string& path) {
  const toml::table t = ParseTomlFile(path);
  TomlReader r(t, path, "");
  const fs::path base = fs::path(path).parent_path();
  auto rel = [&](TomlReader& rd, const std::string& key) {
    const std::string p = (base / rd.String(key)).lexically_normal().string();
    if (!fs::is_directory(p)) rd.Fail(key, "folder not found: " + p);
    return p;
  };
  PipelineFile c;
  c.output = r.String("output", "out/pipeline");
  TomlReader cal = r.Table("calibration");
  c.lightfield = rel(cal, "lightfield");
  c.flatfield = rel(cal, "corrector");
  c.extrapolate_to_deg = cal.InRange("extrapolate_to_deg", 0, 89, 0);
  c.zones = int(cal.Integer("zones", 9, 1, 64));
  c.smoothness = cal.Number("smoothness", 0);
  if (cal.Has("sphere")) c.sphere = rel(cal, "sphere");
  // The sphere calibration's settings, each refused without the drop it would calibrate with.
  auto sphere_setting = [&](const std::string& key) {
    if (!cal.Has(key)) return false;
    if (!cal.Has("sphere")) cal.Fail(key, "needs 'sphere' (the drop's focus-scan folder)");
    return true;
  };
  if (sphere_setting("sphere_planes_um"))
    c.sphere_planes_um = cal.Numbers("sphere_planes_um", 1, 64);
  if (sphere_setting("sphere_optics"))
    c.sphere_optics = cal.Choice("sphere_optics", {"rays", "mie"});
  cal.Finish();
  TomlReader ex = r.Table("experiment");
  c.experiment = rel(ex, "scan");
  if (ex.Has("mesh_object")) c.merging = rel(ex, "mesh_object");
  ex.Finish();
  if (r.Has("simulation")) {
    TomlReader s = r.Table("simulation");
    c.ray_fraction = s.InRange("ray_fraction", 0, 100, 1, true, false);
    c.seed = uint64_t(s.Integer("seed", 1, 0, INT64_MAX));
    c.partial_reflection =
        s.Choice("partial_reflection", {"off", "unpolarized", "polarized"}, "unpolarized");
    s.Finish();
  }
  if (r.Has("fit")) {
    TomlReader f = r.Table("fit");
    // Each fit file's scene takes the calibration made here (its `calibration` key is replaced).
    for (const std::string& file : f.Strings("files")) {
      const std::string p = (base / file).lexically_normal().string();
      if (!fs::is_regular_file(p)) f.Fail("files", "fit file not found: " + p);
      c.fits.push_back(p);
    }
    f.Finish();
  }
  r.Finish();
  return c;
}

namespace {

/// The [camera] and [optics] tables of an experiment folder's metadata: the gain (photons per
/// code value) and the read noise (electrons rms, for fits' likelihood) are used; the other
/// datasheet values are accepted, and the optics are informational (the calibration's optics
/// are used).
double ReadCameraGain(TomlReader& r, double* read_noise_e = nullptr, int* bit_depth = nullptr) {
  TomlReader cam = r.Table("camera");
  const double gain = cam.Positive("gain_e_per_dn", 1.0);
  cam.Positive("pixel_pitch_um", 1), cam.Number("well_capacity_e", 0);
  const int bits = static_cast<int>(cam.Integer("bit_depth", 16, 1, 32));
  const double read = cam.InRange("read_noise_e", 0, 1e4, 0);
  if (read_noise_e) *read_noise_e = read;
  if (bit_depth) *bit_depth = bits;
  cam.Finish();
  r.Table("optics");
  return gain;
}

compare::PrepareOptions Preparation(const std::string& dark_file, double gain) {
  compare::PrepareOptions p;
  p.dark_file = dark_file;
  p.gain_e_per_dn = gain;
  return p;
}

/// An experimental image in photons (dark-subtracted, times the gain), as compare-scan
/// prepares it.
Image Prepared(const Image& raw, const compare::PrepareOptions& p, const std::string& file) {
  Image dark;
  if (!p.dark_file.empty()) dark = ReadImage(p.dark_file);
  try {
    return compare::PrepareExperiment(raw, p, dark.empty() ? nullptr : &dark, nullptr);
  } catch (const Error& e) {  // e.g. a dark frame of another size: name both files
    throw Error(FileLocation{file},
                (p.dark_file.empty() ? "" : "with dark frame " + p.dark_file + ": ") + e.message());
  }
}

}  // namespace

ExperimentMetadata ReadExperimentMetadata(const std::string& folder) {
  const std::string path = (fs::path(folder) / "metadata.toml").string();
  const toml::table t = ParseTomlFile(path);
  TomlReader r(t, path, "");
  ExperimentMetadata e;
  e.scan_csv = (fs::path(folder) / r.String("scan")).string();
  if (r.Has("dark")) e.dark = (fs::path(folder) / r.String("dark")).string();
  r.String("object", "");
  e.diameter_um = r.Positive("nominal_diameter_um");
  e.temperature_K = r.InRange("temperature_K", 261.15, 773.15, 293.15);
  e.gain = ReadCameraGain(r, &e.read_noise_e, &e.bit_depth);
  r.Finish();
  return e;
}

MeshObjectMetadata ReadMeshObjectMetadata(const std::string& folder) {
  const std::string mp = (fs::path(folder) / "metadata.toml").string();
  const toml::table mt = ParseTomlFile(mp);
  TomlReader mr(mt, mp, "");
  MeshObjectMetadata m;
  m.image = (fs::path(folder) / mr.String("image")).string();
  m.defocus_um = mr.Number("defocus_um", 0);
  if (mr.Has("dark")) m.dark = (fs::path(folder) / mr.String("dark")).string();
  m.mesh = fs::absolute(fs::path(folder) / mr.String("mesh")).string();
  m.rotation_deg = mr.Vec3("mesh_rotation_deg", {0, 0, 0});
  m.gain = ReadCameraGain(mr);
  mr.Finish();
  return m;
}

namespace {

/// Checksums of a folder's files (sorted), for step reuse.
std::string FolderStamp(const std::string& folder) {
  std::vector<std::string> files;
  for (const auto& e : fs::directory_iterator(folder))
    if (e.is_regular_file()) files.push_back(e.path().string());
  std::sort(files.begin(), files.end());
  std::string s;
  for (const auto& f : files) s += fs::path(f).filename().string() + ":" + FileChecksum(f) + ";";
  return s;
}

/// A step is reused when its stamp file holds the same input description and its outputs exist.
bool Reusable(const fs::path& stamp, const std::string& inputs,
              const std::vector<fs::path>& outputs) {
  std::ifstream in(stamp);
  std::stringstream ss;
  ss << in.rdbuf();
  if (!in || ss.str() != inputs) return false;
  for (const auto& o : outputs)
    if (!fs::exists(o)) return false;
  return true;
}

/// The mesh object's mesh, read and checked as the simulation will use it (closed, finite,
/// usable triangles), before anything is written.
void CheckMeshFile(const MeshObjectMetadata& m, const std::string& folder) {
  simulate::ObjectSpec o;
  o.shape = simulate::ShapeType::kMesh;
  o.mesh_file = m.mesh;
  o.where = FileLocation{(fs::path(folder) / "metadata.toml").string()};
  if (!fs::is_regular_file(m.mesh)) throw Error(o.where, "mesh file not found: " + m.mesh);
  const simulate::Geometry check({o});
}

/// The fit files, read and checked before the calibration exists: each is loaded as the fit
/// will load it (scene, images, keys, bounds, the images' light) with a stand-in calibration
/// that has the light-field folder's optics and a uniform light field, in a scratch folder;
/// with a sphere calibration in the pipeline (`sphere`), also its edge beyond the NA, PSF and
/// the uncertainties of the keys it fits (fits may free them with `prior = "calibration"`).
void CheckFitFiles(const std::vector<std::string>& fits, const calibrate::LightFieldInput& lf,
                   bool sphere) {
  if (fits.empty()) return;
  CalibrationData d;
  d.objective_focal_mm = lf.optics.objective_focal_mm;
  d.working_distance_mm = lf.optics.working_distance_mm;
  d.na = lf.optics.na;
  d.tube_focal_mm = lf.optics.tube_focal_mm;
  d.pixel_pitch_um = lf.camera.pixel_pitch_um;
  d.wavelength_um = lf.optics.wavelength_um;
  d.angular_map = Image(8, 8, 1.f);
  d.angular_extent = std::clamp(lf.optics.acceptance_sin(), 0.05, 0.95);
  if (sphere) {
    d.na_limit = d.angular_extent;
    d.edge_half_angle_deg = std::asin(d.na_limit) * 180 / M_PI + 1, d.edge_width_deg = 1;
    d.psf_sigma_um = 0.21 * d.wavelength_um / std::max(d.na, 0.01);
    for (const char* k : {"light_field_edge.half_angle_deg", "light_field_edge.tilt_deg[0]",
                          "light_field_edge.tilt_deg[1]", "camera.psf_sigma_um"})
      d.key_sigma[k] = 1;
  }
  std::error_code ec;
  const fs::path scratch =
      fs::temp_directory_path(ec) / ("raymatch-run-check-" + std::to_string(::getpid()));
  fs::create_directories(scratch, ec);
  if (ec) return;  // no scratch space: the fits are checked when they run
  struct Cleanup {
    fs::path dir;
    ~Cleanup() {
      std::error_code e;
      fs::remove_all(dir, e);
    }
  } cleanup{scratch};
  const std::string cal = (scratch / "calibration.toml").string();
  WriteCalibrationFile(cal, d);
  for (const std::string& file : fits) fit::LoadFitSpec(file, "", cal);
}

/// A field of a JSON report this command wrote earlier (a reused step's summary), or with
/// `member` a member of an object field; a string as it is, a boolean as "true" / "false". Any
/// damage is an error naming the file and the field, never a JSON library exception.
std::string ReportField(const fs::path& file, const std::string& field,
                        const std::string& member = "") {
  std::ifstream in(file);
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(in);
  } catch (const std::exception& e) {
    throw Error(FileLocation{file.string()},
                std::string("not valid JSON (") + e.what() +
                    "); delete it or run with --force to recompute the step");
  }
  const std::string name = field + (member.empty() ? "" : "." + member);
  const nlohmann::json* v = j.is_object() && j.contains(field) ? &j[field] : nullptr;
  if (v && !member.empty()) v = v->is_object() && v->contains(member) ? &(*v)[member] : nullptr;
  if (!v || !(v->is_string() || v->is_boolean() || v->is_number()))
    throw Error(FileLocation{file.string()}, "field '" + name +
                                                 "' is missing or of the wrong type; delete the "
                                                 "file or run with --force to recompute the step");
  if (v->is_number()) return v->dump();  // the shortest text that reads back as the same double
  return v->is_boolean() ? (v->get<bool>() ? "true" : "false") : v->get<std::string>();
}

/// Every input of a run, read and checked before the output folder is made: a
/// refused input leaves no folder and no file.
struct RunInputs {
  PipelineFile cfg;
  calibrate::LightFieldInput lf;
  calibrate::FlatFieldInput ff;
  ExperimentMetadata ex;
  compare::Stack exp;
  compare::PrepareOptions prep;
  Image mid;  ///< the middle plane, prepared (its border gives the exposure)
  std::optional<MeshObjectMetadata> mesh;
  Image mesh_image;
};

RunInputs ReadRunInputs(const PipelineOptions& opt) {
  RunInputs in;
  in.cfg = ReadPipelineFile(opt.pipeline_file);
  in.lf = calibrate::ReadLightFieldInput(in.cfg.lightfield);
  in.ff = calibrate::ReadFlatFieldInput(in.cfg.flatfield);
  in.ex = ReadExperimentMetadata(in.cfg.experiment);
  in.exp = compare::ReadStack(in.ex.scan_csv);
  in.prep = Preparation(in.ex.dark, in.ex.gain);
  const size_t m = in.exp.images.size() / 2;
  in.mid = Prepared(in.exp.images[m], in.prep, in.exp.files[m]);
  if (!in.cfg.merging.empty()) {
    in.mesh = ReadMeshObjectMetadata(in.cfg.merging);
    in.mesh_image = Prepared(ReadImage(in.mesh->image), Preparation(in.mesh->dark, in.mesh->gain),
                             in.mesh->image);
    CheckMeshFile(*in.mesh, in.cfg.merging);
  }
  CheckFitFiles(in.cfg.fits, in.lf, !in.cfg.sphere.empty());
  return in;
}

/// A step of the main job whose outputs are kept between runs: reused when its inputs (the
/// stamp's content) are unchanged and its outputs exist.
struct Step {
  std::string name;               ///< in the timing table and PipelineSummary::reused
  std::string stamp;              ///< file under the output folder
  std::string inputs;             ///< the stamp's content
  std::vector<fs::path> outputs;  ///< must exist for a reuse
  std::string reuse_message;
  std::function<void()> run, reuse;  ///< reuse (may be empty): read back what run would make
};

class StepRunner {
 public:
  StepRunner(fs::path out, const PipelineOptions& opt, PipelineSummary* sum)
      : out_(std::move(out)), opt_(opt), sum_(sum) {}

  void Say(const std::string& m) const {
    if (opt_.steps) std::cerr << "raymatch run: " << m << std::endl;
  }

  /// A step that runs every time: timed.
  void Timed(const std::string& name, const std::function<void()>& run) {
    const auto t0 = std::chrono::steady_clock::now();
    run();
    sum_->step_seconds.push_back(
        {name, std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count()});
  }

  /// A stamped step: reused, or run (timed) and stamped.
  void Run(const Step& s) {
    if (!opt_.force && Reusable(out_ / s.stamp, s.inputs, s.outputs)) {
      Say(s.reuse_message);
      if (s.reuse) s.reuse();
      sum_->reused.push_back(s.name);
      return;
    }
    // A step's stamp goes before it rewrites its outputs and comes back after the last one, so
    // an interrupted step is never taken for finished (and reused) by the next run.
    RemoveStaleOutput(out_ / s.stamp);
    Timed(s.name, s.run);
    WriteTextFileAtomic(out_ / s.stamp, s.inputs);
  }

 private:
  fs::path out_;
  const PipelineOptions& opt_;
  PipelineSummary* sum_;
};

/// The sphere calibration's check, from its brief report (made now or read back).
PipelineCheck SphereCheck(const std::string& status, const std::string& goodness, bool mismatch) {
  PipelineCheck c;
  c.name = "sphere calibration";
  const bool converged = status == fit::StatusName(fit::FitStatus::kConverged);
  c.ok = converged && !mismatch && !goodness.empty();
  c.result = std::string(converged ? "converged" : "did not converge") + "; " +
             (mismatch           ? "model mismatch"
              : goodness.empty() ? "no goodness of fit"
                                 : "consistent with the noise");
  c.meaning = c.ok ? "the light field beyond the NA and the PSF describe the calibration drop's "
                     "images within their noise"
              : mismatch
                  ? "the calibration drop's images are not described within their noise: the "
                    "edge beyond the NA and the PSF may be biased, and with them every fitted index"
                  : "the edge beyond the NA and the PSF are not determined: fitted indices rest "
                    "on their defaults";
  return c;
}

/// The corrector calibration's check: its reduced chi-square against the flat fields' stated
/// noise (calibrate::FitTransmissions).
PipelineCheck CorrectorCheck(const calibrate::TransmissionFit& f) {
  PipelineCheck c;
  c.name = "corrector calibration";
  c.ok = f.dof > 0 && !f.mismatch && f.undetermined.empty();
  std::ostringstream r;
  r.precision(3);
  if (f.dof > 0)
    r << "reduced chi^2 " << f.reduced_chi2 << " for " << f.dof << " degrees of freedom ("
      << std::fixed << std::setprecision(1) << f.chi2_z << " sd)";
  else
    r << "as many unknowns as flat fields";
  if (!f.undetermined.empty()) r << "; " << f.undetermined.size() << " zones receive no light";
  c.result = r.str();
  c.meaning =
      f.dof <= 0   ? "no test of the zone model: add iris settings or smoothness"
      : f.mismatch ? "the zone model does not describe the flat fields within their noise: the "
                     "transmissions may be biased beyond their (inflated) sigmas"
      : !f.undetermined.empty()
          ? "zones no flat field illuminates hold their neighbour's transmission"
      : f.chi2_z < -3 ? "the flat fields scatter less than their stated noise: the transmissions' "
                        "sigmas are scaled down to the scatter"
                      : "the zone transmissions describe the flat fields within their noise";
  return c;
}

/// A check as the reports of reused steps keep it (field `field` of a JSON report) and back.
PipelineCheck ReadCheck(const fs::path& file, const std::string& field) {
  return {ReportField(file, field, "name"), ReportField(file, field, "ok") == "true",
          ReportField(file, field, "result"), ReportField(file, field, "meaning")};
}

nlohmann::json CheckJson(const PipelineCheck& c) {
  return {{"name", c.name}, {"ok", c.ok}, {"result", c.result}, {"meaning", c.meaning}};
}

/// A fit's check: converged, every sigma determined, and the goodness of fit.
PipelineCheck FitCheck(const std::string& stem, const fit::FitResult& r) {
  PipelineCheck c;
  c.name = "fit " + stem;
  bool sigmas = !r.parameters.empty();
  for (const fit::ParameterResult& p : r.parameters)
    sigmas = sigmas && std::isfinite(p.sigma) && p.sigma > 0;
  const bool graded = r.goodness.pixels > 0;
  c.ok = r.converged && (!graded || (sigmas && !r.goodness.mismatch));
  c.result = std::string(fit::StatusName(r.status));
  if (graded)
    c.result += std::string(sigmas ? "" : "; uncertainties not determined") +
                (r.goodness.mismatch ? "; model mismatch" : "; consistent with the noise");
  const std::string misfit = "the model does not describe the images within their noise";
  c.meaning = !r.converged ? "no estimate: see the fit's report"
              : !graded    ? "a grid search: its minimum, with no statistical test"
              : !sigmas    ? "the images do not determine every parameter (information matrix not "
                             "positive definite): values without error bars" +
                              (r.goodness.mismatch ? "; and " + misfit : std::string())
              : r.goodness.mismatch
                  ? misfit + ": values may be biased beyond their (inflated) sigmas"
                  : "the model describes the images within their noise; values with sigmas";
  return c;
}

/// The drop's keys in the sphere calibration's fit, and their fields in calibration_report.json's
/// "sphere_drop".
constexpr std::array<std::pair<const char*, const char*>, 5> kDropKeys{{
    {"object.drop.center_um[0]", "x_um"},
    {"object.drop.center_um[1]", "y_um"},
    {"object.drop.center_um[2]", "z_um"},
    {"object.drop.radius_um", "radius_um"},
    {"object.drop.index", "index"},
}};

/// The drop as the sphere calibration found it: x, y, z (um), radius (um), index (kDropKeys).
using CalibratedDrop = std::array<double, 5>;

/// The calibration step's results (made or read back).
struct Calibration {
  CalibrationData data;
  std::string lf_report, co_report, sp_report;
  /// The sphere calibration fit's status name, goodness-of-fit verdict and mismatch flag.
  std::string sp_status, sp_goodness;
  bool sp_mismatch = false;
  std::optional<CalibratedDrop> drop;  ///< with a sphere calibration
  PipelineCheck corrector;             ///< the corrector fit's check
};

/// Bumped when the calibration's model or file changes so that a calibration made by an older
/// raymatch is not reused (2: the edge model from 3 map pixels inside the NA cut and the
/// [uncertainty] table; 3: the sphere fit's verdict as fields of calibration_report.json; 4: the
/// calibrated drop in it, which the focus scan's simulation takes; 5: the corrector's check in
/// it, and the sphere fit's goodness of fit taken at the template's best point).
constexpr int kCalibrationModel = 5;

std::string CalibrationInputs(const RunInputs& in) {
  const PipelineFile& cfg = in.cfg;
  std::string s =
      "model " + std::to_string(kCalibrationModel) + "|" + FolderStamp(cfg.lightfield) + "|" +
      FolderStamp(cfg.flatfield) + "|" + (in.lf.flat.empty() ? "" : FileChecksum(in.lf.flat)) +
      "|" + std::to_string(cfg.extrapolate_to_deg) + "|" + std::to_string(cfg.zones) + "|" +
      std::to_string(cfg.smoothness) + "|" + (cfg.sphere.empty() ? "" : FolderStamp(cfg.sphere));
  for (double d : cfg.sphere_planes_um) s += "|" + std::to_string(d);
  if (cfg.sphere_optics != "rays") s += "|" + cfg.sphere_optics;
  return s;
}

/// Bumped when what a fit step keeps for reuse (run_step.json) changes, or what a fit makes of
/// the same inputs (its estimate, images or verdict), so that no earlier raymatch's fit is reused.
constexpr int kFitStepModel = 3;  // 3: the goodness of fit at the template's best point

/// What a fit of the main job depends on: this raymatch, the fit file, its scene and every
/// file the scene reads (this run's calibration among them), the images and dark frames.
std::string FitInputs(const fit::FitSpec& spec) {
  std::vector<std::string> files{spec.file, spec.scene_file};
  const simulate::Scene scene = simulate::LoadScene(spec.scene, spec.scene_file);
  files.insert(files.end(), scene.input_files.begin(), scene.input_files.end());
  for (const fit::FitImage& im : spec.images) {
    files.push_back(im.file);
    if (!im.dark_file.empty()) files.push_back(im.dark_file);
  }
  std::string s = "fit step " + std::to_string(kFitStepModel) + "|" +
                  ProvenanceJson().value("version", std::string()) + "\n";
  for (const std::string& f : files) s += fs::absolute(f).string() + ":" + FileChecksum(f) + "\n";
  return s;
}

/// A fit step's part of the run: its status, its check and its section of index.html.
struct FitStep {
  std::string status;
  PipelineCheck check;
  std::string html;
};

void WriteFitStep(const fs::path& file, const FitStep& f) {
  const nlohmann::json j{{"status", f.status}, {"check", CheckJson(f.check)}, {"html", f.html}};
  WriteTextFileAtomic(file, j.dump(1) + "\n");
}

FitStep ReadFitStep(const fs::path& file) {
  FitStep f;
  f.status = ReportField(file, "status");
  f.check = ReadCheck(file, "check");
  f.html = ReportField(file, "html");
  return f;
}

/// Light field, corrector and (with a sphere folder) the sphere calibration into cal_file and
/// its brief reports into cal_report (JSON); intermediate files go to `out`.
void Calibrate(const RunInputs& in, const fs::path& out, const fs::path& cal_file,
               const fs::path& cal_report, const PipelineOptions& opt, const StepRunner& steps,
               Calibration* c) {
  const PipelineFile& cfg = in.cfg;
  steps.Say("calibrating the light field (" + cfg.lightfield + ")");
  calibrate::LightFieldOptions lo;
  lo.extrapolate_to_deg = cfg.extrapolate_to_deg;
  const calibrate::LightFieldSummary lf = calibrate::CalibrateLightField(in.lf, lo);
  steps.Say("fitting the corrector (" + cfg.flatfield + ")");
  calibrate::CorrectorOptions copt;
  copt.zones = cfg.zones;
  copt.smoothness = cfg.smoothness;
  const calibrate::CorrectorSummary co = calibrate::CalibrateCorrector(in.ff, copt, &lf.data);
  for (const auto& w : lf.warnings) std::cerr << "raymatch run: warning: " << w << "\n";
  for (const auto& w : co.warnings) std::cerr << "raymatch run: warning: " << w << "\n";
  c->lf_report = lf.BriefReport();
  c->co_report = co.BriefReport();
  c->corrector = CorrectorCheck(co.fit);
  c->data = co.data;
  if (cfg.sphere.empty()) {
    WriteCalibrationFile(cal_file.string(), co.data);
  } else {
    // The light field and corrector go to calibration_base.toml; the sphere calibration adds
    // the edge beyond the NA and the PSF and writes calibration.toml.
    const fs::path base_file = out / "calibration_base.toml";
    WriteCalibrationFile(base_file.string(), co.data);
    steps.Say("calibrating with the drop of " + cfg.sphere + " (light field beyond the NA, PSF)");
    SphereCalibrationOptions so;
    so.scan_folder = cfg.sphere;
    so.base = base_file.string();
    so.output = cal_file.string();
    so.work_dir = (out / "sphere_calibration").string();
    so.planes_um = cfg.sphere_planes_um;
    so.optics = cfg.sphere_optics;
    so.threads = opt.threads;
    so.progress = opt.progress;
    so.say = [&](const std::string& m) { steps.Say(m); };
    const SphereCalibrationResult sr = CalibrateSphere(so);
    c->sp_report = sr.Brief();
    c->sp_status = sr.status, c->sp_goodness = sr.goodness, c->sp_mismatch = sr.mismatch;
    CalibratedDrop drop{};
    for (const SphereCalibrationValue& v : sr.values)
      for (size_t i = 0; i < drop.size(); ++i)
        if (v.key == kDropKeys[i].first) drop[i] = v.value;
    c->drop = drop;
    if (sr.mismatch)
      std::cerr << "raymatch run: warning: the sphere calibration reports a model mismatch\n";
    c->data = ReadCalibrationFile(cal_file.string());
    // The light field's report ends with what lies beyond the NA: now the fitted edge.
    calibrate::LightFieldSummary calibrated = lf;
    calibrated.data.light_field_note = c->data.light_field_note;
    c->lf_report = calibrated.BriefReport();
  }
  nlohmann::json rep{{"light_field", c->lf_report},
                     {"corrector", c->co_report},
                     {"corrector_check", CheckJson(c->corrector)}};
  if (!c->sp_report.empty()) {
    rep["sphere"] = c->sp_report;
    rep["sphere_fit"] = {
        {"status", c->sp_status}, {"goodness", c->sp_goodness}, {"mismatch", c->sp_mismatch}};
    for (size_t i = 0; i < kDropKeys.size(); ++i)
      rep["sphere_drop"][kDropKeys[i].second] = (*c->drop)[i];
  }
  WriteTextFileAtomic(cal_report, rep.dump(2) + "\n");
}

using internal::Sig10;
using internal::WriteToml;

/// The scene of the experiment's focus scan: the drop as the sphere calibration found it (its
/// position, radius and index), else the nominal drop on the axis; the experiment's image size
/// and planes, the exposure recovered from the middle plane's background times the ray fraction.
toml::table ExperimentScene(const RunInputs& in, const std::optional<CalibratedDrop>& calibrated,
                            double photons_per_pixel) {
  toml::array planes;
  for (double d : in.exp.defocus_um) planes.push_back(d);  // every digit: distinct file names
  toml::table drop{{"name", "drop"}, {"type", "sphere"}};
  if (calibrated) {
    const CalibratedDrop& c = *calibrated;
    drop.insert("center_um", toml::array{Sig10(c[0]), Sig10(c[1]), Sig10(c[2])});
    drop.insert("radius_um", Sig10(c[3]));
    drop.insert("index", Sig10(c[4]));
  } else {
    drop.insert("radius_um", Sig10(in.ex.diameter_um / 2));
    drop.insert("material", "water");
    drop.insert("temperature_K", Sig10(in.ex.temperature_K));
  }
  return toml::table{
      {"name", "sim"},
      {"calibration", "calibration.toml"},
      {"seed", int64_t(in.cfg.seed)},
      {"object", toml::array{std::move(drop)}},
      {"camera",
       toml::table{{"pixels", toml::array{in.exp.images[0].width, in.exp.images[0].height}}}},
      {"trace", toml::table{{"photons_per_pixel", Sig10(photons_per_pixel)},
                            {"partial_reflection", in.cfg.partial_reflection}}},
      {"scan", toml::table{{"defocus_um", planes}}}};
}

/// The mesh object (e.g. merging drops), in focus: simulated and compared; its HTML section.
std::string MeshObject(const RunInputs& in, const fs::path& out, const PipelineOptions& opt,
                       double photons_per_pixel) {
  const MeshObjectMetadata& mm = *in.mesh;
  const Image& e = in.mesh_image;
  const auto& rot = mm.rotation_deg;
  const toml::table scene{
      {"name", "mesh_object"},
      {"calibration", "calibration.toml"},
      {"seed", int64_t(in.cfg.seed)},
      {"object", toml::array{toml::table{
                     {"type", "mesh"},
                     {"file", mm.mesh},
                     {"rotation_deg", toml::array{Sig10(rot[0]), Sig10(rot[1]), Sig10(rot[2])}},
                     {"material", "water"},
                     {"temperature_K", Sig10(in.ex.temperature_K)}}}},
      {"camera", toml::table{{"pixels", toml::array{e.width, e.height}}}},
      {"trace", toml::table{{"photons_per_pixel", Sig10(photons_per_pixel)}}},
      {"scan", toml::table{{"defocus_um", toml::array{Sig10(mm.defocus_um)}}}}};
  WriteToml(out / "mesh_object.toml", "# Written by raymatch run: the mesh object, in focus.",
            scene);
  simulate::ScanOptions so;
  so.output_dir = (out / "mesh_object").string();
  so.control.threads = opt.threads;
  const simulate::ScanSummary ss =
      simulate::RunScan(simulate::LoadScene((out / "mesh_object.toml").string()), so);
  const compare::Stack es{{mm.defocus_um}, {e}, {mm.image}};
  const compare::FocusScanResult mr =
      compare::RunFocusScan(es, compare::ReadStack(ss.index_json), compare::FocusScanOptions{});
  compare::WriteFocusScanReport(mr, (out / "mesh_object/compare").string(), "mesh object");
  std::ostringstream hh;
  hh.precision(4);
  hh << "<h2>Non-spherical object (mesh), in focus</h2><p>" << mm.image << " vs a simulation of "
     << mm.mesh << ":";
  for (const auto& m : mr.measures)
    hh << " " << compare::MeasureName(m.measure) << " = " << m.matrix[0][0] << ";";
  hh << "</p>"
     << internal::Img((out / "mesh_object/compare/montage.png").string(), "mesh object montage");
  return hh.str();
}

/// A reused calibration step's results, read back from its files.
Calibration ReadCalibration(const fs::path& cal_file, const fs::path& cal_report, bool sphere) {
  Calibration cal;
  cal.data = ReadCalibrationFile(cal_file.string());
  cal.lf_report = ReportField(cal_report, "light_field");
  cal.co_report = ReportField(cal_report, "corrector");
  cal.corrector = ReadCheck(cal_report, "corrector_check");
  if (sphere) {
    cal.sp_report = ReportField(cal_report, "sphere");
    cal.sp_status = ReportField(cal_report, "sphere_fit", "status");
    cal.sp_goodness = ReportField(cal_report, "sphere_fit", "goodness");
    cal.sp_mismatch = ReportField(cal_report, "sphere_fit", "mismatch") == "true";
    CalibratedDrop drop{};
    for (size_t i = 0; i < drop.size(); ++i)
      drop[i] = std::stod(ReportField(cal_report, "sphere_drop", kDropKeys[i].second));
    cal.drop = drop;
  }
  return cal;
}

/// The fit files of `[fit] files`, each run (or reused) with the calibration; their report
/// sections go into `report`, their statuses into `sum`, and their checks are returned.
std::vector<PipelineCheck> RunFits(const PipelineFile& cfg, const fs::path& out,
                                   const fs::path& cal_file, const PipelineOptions& opt,
                                   StepRunner& steps, PipelineSummary* sum_out,
                                   internal::RunReport* report_out) {
  PipelineSummary& sum = *sum_out;
  internal::RunReport& report = *report_out;
  std::vector<PipelineCheck> fit_checks;
  for (const std::string& file : cfg.fits) {
    const std::string stem = fs::path(file).stem().string();
    const fit::FitSpec spec = fit::LoadFitSpec(file, "", fs::absolute(cal_file).string());
    const fs::path fit_dir = out / "fit" / stem, kept = fit_dir / "run_step.json";
    FitStep done;
    steps.Run({"fit " + stem,
               ".fit_" + stem + ".stamp",
               FitInputs(spec),
               {fit_dir / "fit.json", kept},
               "fit " + stem + " unchanged: reusing " + (fit_dir / "fit.json").string(),
               [&] {
                 steps.Say("fitting " + file);
                 fit::FitOptions fo;
                 fo.threads = opt.threads;
                 fo.progress = opt.progress;
                 const fit::FitResult r = fit::RunFit(spec, fo);
                 fit::WriteFitOutputs(spec, r, fit_dir.string());
                 done = {fit::StatusName(r.status), FitCheck(stem, r),
                         internal::FitSectionHtml(stem, spec, r)};
                 WriteFitStep(kept, done);
               },
               [&] { done = ReadFitStep(kept); }});
    report.fit_html += done.html;
    sum.fits.push_back({stem, done.status});
    fit_checks.push_back(done.check);
  }
  if (!report.fit_html.empty())
    report.fit_html = "<h2>Fits: 3D properties from the images</h2>" + report.fit_html;
  return fit_checks;
}

/// The focus-scan test as one of the run's checks.
PipelineCheck FocusScanCheck(const compare::FocusScanResult& fr) {
  PipelineCheck c;
  c.name = "focus-scan test";
  c.ok = fr.verdict == compare::Verdict::kPass;
  std::string passing, failing;
  for (const auto& m : fr.measures) {
    std::string& list = m.passes ? passing : failing;
    list += (list.empty() ? "" : ", ") + std::string(compare::MeasureName(m.measure));
  }
  // Beside it, each plane's residuals against the shot noise (compare/report.html): the
  // focus-scan test does not grade them, the reader should still see them.
  bool misfit = false;
  const std::string planes = compare::PlaneGoodnessSummary(compare::PerPlaneGoodness(fr), &misfit);
  c.result = std::string(fr.verdict == compare::Verdict::kPass      ? "pass"
                         : fr.verdict == compare::Verdict::kWarning ? "warning"
                                                                    : "fail") +
             (passing.empty() ? "" : ": " + passing + " match each plane to its defocus") +
             (failing.empty() ? "" : "; not " + failing);
  if (!planes.empty()) c.result += "; " + planes;
  c.meaning =
      !misfit
          ? "the simulated focus positions agree with the experiment's, and every plane's "
            "residuals are within the shot noise (compare/report.html)"
          : "the simulated focus positions agree with the experiment's, but the simulation does "
            "not describe every pixel of the planes named within the shot noise (residual "
            "maps: compare/report.html); a fit's goodness of fit says which model is missing "
            "what";
  if (fr.verdict != compare::Verdict::kPass)
    c.meaning =
        "the simulated focus positions do not all agree with the experiment's (not "
        "every measure matches each plane to its defocus)";
  return c;
}

}  // namespace

PipelineSummary RunPipeline(const PipelineOptions& opt) {
  const RunInputs in = ReadRunInputs(opt);
  const PipelineFile& cfg = in.cfg;
  const fs::path out = opt.output_dir.empty() ? fs::path(cfg.output) : fs::path(opt.output_dir);
  // A run that fails later (an input that only the calibration or the simulation can judge)
  // removes the output folder again when it made it: all in it would be this failed run's.
  struct RemoveIfFailed {
    fs::path dir;
    bool armed;
    int exceptions = std::uncaught_exceptions();
    ~RemoveIfFailed() {
      std::error_code ec;
      if (armed && std::uncaught_exceptions() > exceptions) fs::remove_all(dir, ec);
    }
  } remove_if_failed{out, !fs::exists(out)};
  EnsureDirectory(out);
  PipelineSummary sum;
  // index.html describes one complete run: removed now, written last, so that an interrupted
  // or failed run leaves no report mixing this run's files with the previous one's.
  sum.report = (out / "index.html").string();
  RemoveStaleOutput(sum.report);
  StepRunner steps(out, opt, &sum);

  // 1. Calibration.
  const fs::path cal_file = out / "calibration.toml", cal_report = out / "calibration_report.json";
  Calibration cal;
  steps.Run({"calibrate",
             ".calibration.stamp",
             CalibrationInputs(in),
             {cal_file, cal_report},
             "calibration inputs unchanged: reusing " + cal_file.string(),
             [&] { Calibrate(in, out, cal_file, cal_report, opt, steps, &cal); },
             [&] { cal = ReadCalibration(cal_file, cal_report, !cfg.sphere.empty()); }});
  sum.cone_half_angle_deg = cal.data.cone_half_angle_deg;
  sum.transmissions = cal.data.transmissions;
  sum.transmission_sigma = cal.data.transmission_sigma;

  // 2. Scene for the experiment.
  sum.photons_per_pixel = BorderMedian(in.mid);
  const double frac = opt.ray_fraction > 0 ? opt.ray_fraction : cfg.ray_fraction;
  const fs::path scene_file = out / "scene.toml";
  WriteToml(scene_file,
            "# Written by raymatch run: the experiment's focus scan, simulated with the "
            "calibration.\n# photons_per_pixel: the background's photons x ray fraction " +
                std::to_string(frac) + ".\n# The drop: " +
                (cal.drop ? "as the sphere calibration found it (position, radius, index)."
                          : "the nominal diameter on the axis, water at the metadata's "
                            "temperature."),
            ExperimentScene(in, cal.drop, sum.photons_per_pixel * frac));

  // 3. Simulation (reused when scene and calibration are unchanged).
  const fs::path sim_dir = out / "simulation", sim_index = sim_dir / "sim_scan.json";
  const std::string sim_inputs =
      ReadFileBytes(scene_file.string()) + "|" + FileChecksum(cal_file.string());
  steps.Run({"simulate",
             ".simulation.stamp",
             sim_inputs,
             {sim_index},
             "simulation unchanged: reusing " + sim_index.string(),
             [&] {
               steps.Say("simulating " + std::to_string(in.exp.defocus_um.size()) + " planes at " +
                         std::to_string(sum.photons_per_pixel * frac) + " photons per pixel");
               simulate::ScanOptions so;
               so.output_dir = sim_dir.string();
               so.control.progress = opt.progress;
               so.control.threads = opt.threads;
               simulate::RunScan(simulate::LoadScene(scene_file.string()), so);
             },
             {}});  // (a reuse reads nothing back: compare reads the images)

  // 4. Focus-scan comparison.
  compare::FocusScanResult fr;
  steps.Timed("compare", [&] {
    steps.Say("comparing the focus scans");
    compare::FocusScanOptions fo;
    fo.prepare = in.prep;
    fr = compare::RunFocusScan(in.exp, compare::ReadStack(sim_index.string()), fo);
    const simulate::Scene scene = simulate::LoadScene(scene_file.string());
    fr.object_pixel_um =
        scene.camera.pixel_pitch_um / std::abs(simulate::Magnification(scene.optics));
    compare::WriteFocusScanReport(fr, (out / "compare").string(), "focus-scan test");
  });
  sum.verdict = int(fr.verdict);
  sum.exp_defocus_um = fr.exp_defocus_um;
  for (const auto& m : fr.measures) {
    sum.measures.push_back(compare::MeasureName(m.measure));
    std::vector<double> b;
    for (int j : m.best) b.push_back(fr.sim_defocus_um[j]);
    sum.best_match_um.push_back(b);
  }

  // 4b. A non-spherical object (e.g. merging drops given as a mesh), in focus.
  internal::RunReport report;
  if (in.mesh)
    steps.Timed("mesh object", [&] {
      steps.Say("simulating the mesh object (" + cfg.merging + ")");
      report.mesh_html = MeshObject(in, out, opt, sum.photons_per_pixel * frac);
    });

  // 4c. Fits (docs/fit.md) with this calibration: 3D properties from single images.
  std::vector<PipelineCheck> fit_checks = RunFits(cfg, out, cal_file, opt, steps, &sum, &report);

  // The checks, and the run's one verdict: never "pass" while a check needs attention.
  sum.checks.push_back(cal.corrector);
  if (!cfg.sphere.empty())
    sum.checks.push_back(SphereCheck(cal.sp_status, cal.sp_goodness, cal.sp_mismatch));
  sum.checks.push_back(FocusScanCheck(fr));
  for (PipelineCheck& c : fit_checks) sum.checks.push_back(std::move(c));
  sum.status = sum.verdict;
  for (const PipelineCheck& c : sum.checks)
    if (!c.ok) sum.status = std::max(sum.status, 1);

  // 5. Report.
  report.out = out;
  report.sphere_folder = cfg.sphere;
  report.cal = &cal.data;
  report.lf_report = cal.lf_report, report.co_report = cal.co_report,
  report.sp_report = cal.sp_report;
  report.scan = &fr;
  report.sum = &sum;
  report.ray_fraction = frac;
  internal::WriteRunReport(report);
  return sum;
}

std::string PipelineSummary::Overall() const {
  std::string attention;
  size_t n = 0;
  for (const PipelineCheck& c : checks)
    if (!c.ok) attention += (n++ ? ", " : "") + c.name;
  if (n == 0) return "pass: all " + std::to_string(checks.size()) + " checks pass";
  return std::string(status >= 2 ? "fail" : "attention") + ": " + std::to_string(n) + " of " +
         std::to_string(checks.size()) + " checks need attention (" + attention + ")";
}

}  // namespace raymatch::pipeline
