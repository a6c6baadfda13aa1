#include "raymatch/pipeline/pipeline.h"
#include "raymatch/pipeline/sphere_calibration.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <exception>
#include <filesystem>
#include <unistd.h>
#include <fstream>
#include <iostream>
#include <optional>
#include <sstream>

#include <nlohmann/json.hpp>

#include "raymatch/compare/plot.h"
#include "raymatch/fit/fit.h"
#include "raymatch/calibrate/corrector.h"
#include "raymatch/calibrate/lightfield.h"
#include "raymatch/compare/focus_scan.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/calibration_file.h"
#include "raymatch/core/error.h"
#include "raymatch/core/html.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/provenance.h"
#include "raymatch/core/toml_reader.h"
#include "raymatch/simulate/geometry.h"
#include "raymatch/simulate/scan.h"
#include "raymatch/simulate/scene.h"

namespace fs = std::filesystem;

namespace raymatch::pipeline {
using compare::Series;
using compare::WritePlot;

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
  if (cal.Has("sphere_planes_um")) {
    if (!cal.Has("sphere")) cal.Fail("sphere_planes_um", "needs 'sphere' (the drop's focus-scan folder)");
    c.sphere_planes_um = cal.Numbers("sphere_planes_um", 1, 64);
  }
  cal.Finish();
  TomlReader ex = r.Table("experiment");
  c.experiment = rel(ex, "scan");
  if (ex.Has("mesh_object")) c.merging = rel(ex, "mesh_object");
  ex.Finish();
  if (r.Has("simulation")) {
    TomlReader s = r.Table("simulation");
    c.ray_fraction = s.InRange("ray_fraction", 0, 100, 1, true, false);
    c.seed = uint64_t(s.Integer("seed", 1, 0, INT64_MAX));
    c.partial_reflection = s.Choice("partial_reflection", {"off", "unpolarized", "polarized"}, "unpolarized");
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
    throw Error(FileLocation{file}, (p.dark_file.empty() ? "" : "with dark frame " + p.dark_file + ": ") + e.message());
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
bool Reusable(const fs::path& stamp, const std::string& inputs, const std::vector<fs::path>& outputs) {
  std::ifstream in(stamp);
  std::stringstream ss;
  ss << in.rdbuf();
  if (!in || ss.str() != inputs) return false;
  for (const auto& o : outputs)
    if (!fs::exists(o)) return false;
  return true;
}

std::string Img(const std::string& png, const std::string& alt = "") { return EmbeddedPng(png, alt); }

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
/// that has the light-field folder's optics and a uniform light field, in a scratch folder.
void CheckFitFiles(const std::vector<std::string>& fits, const calibrate::LightFieldInput& lf) {
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
  std::error_code ec;
  const fs::path scratch = fs::temp_directory_path(ec) /
                           ("raymatch-run-check-" + std::to_string(::getpid()));
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

/// A string field of a JSON report this command wrote earlier (a reused step's summary): any
/// damage is an error naming the file and the field, never a JSON library exception.
std::string ReportField(const fs::path& file, const std::string& field) {
  std::ifstream in(file);
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(in);
  } catch (const std::exception& e) {
    throw Error(FileLocation{file.string()}, std::string("not valid JSON (") + e.what() +
                                                 "); delete it or run with --force to recompute the step");
  }
  if (!j.is_object() || !j.contains(field) || !j[field].is_string())
    throw Error(FileLocation{file.string()}, "field '" + field + "' is missing or not a string; delete the "
                                             "file or run with --force to recompute the step");
  return j[field].get<std::string>();
}

}  // namespace

PipelineSummary RunPipeline(const PipelineOptions& opt) {
  using clock = std::chrono::steady_clock;
  const PipelineFile cfg = ReadPipelineFile(opt.pipeline_file);
  const fs::path out = opt.output_dir.empty() ? fs::path(cfg.output) : fs::path(opt.output_dir);
  // Every input is read and checked before the output folder is made (issue 25): a refused
  // input leaves no folder and no file.
  const calibrate::LightFieldInput lf_in = calibrate::ReadLightFieldInput(cfg.lightfield);
  const calibrate::FlatFieldInput ff_in = calibrate::ReadFlatFieldInput(cfg.flatfield);
  const ExperimentMetadata ex = ReadExperimentMetadata(cfg.experiment);
  const compare::Stack exp = compare::ReadStack(ex.scan_csv);
  const compare::PrepareOptions prep = Preparation(ex.dark, ex.gain);
  const Image mid = Prepared(exp.images[exp.images.size() / 2], prep, exp.files[exp.files.size() / 2]);
  std::optional<MeshObjectMetadata> mesh_meta;
  Image mesh_image;
  if (!cfg.merging.empty()) {
    mesh_meta = ReadMeshObjectMetadata(cfg.merging);
    mesh_image = Prepared(ReadImage(mesh_meta->image), Preparation(mesh_meta->dark, mesh_meta->gain), mesh_meta->image);
    CheckMeshFile(*mesh_meta, cfg.merging);
  }
  CheckFitFiles(cfg.fits, lf_in);
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
  auto say = [&](const std::string& m) {
    if (opt.steps) std::cerr << "raymatch run: " << m << std::endl;
  };
  auto timed = [&](const std::string& name, const std::function<void()>& fn) {
    const auto t0 = clock::now();
    fn();
    sum.step_seconds.push_back({name, std::chrono::duration<double>(clock::now() - t0).count()});
  };

  // 1. Calibration.
  const fs::path cal_file = out / "calibration.toml";
  const std::string cal_inputs =
      FolderStamp(cfg.lightfield) + "|" + FolderStamp(cfg.flatfield) + "|" +
      (lf_in.flat.empty() ? "" : FileChecksum(lf_in.flat)) + "|" + std::to_string(cfg.extrapolate_to_deg) +
      "|" + std::to_string(cfg.zones) + "|" + std::to_string(cfg.smoothness) + "|" +
      (cfg.sphere.empty() ? "" : FolderStamp(cfg.sphere)) + [&] {
        std::string planes;
        for (double d : cfg.sphere_planes_um) planes += "|" + std::to_string(d);
        return planes;
      }();
  const fs::path cal_report = out / "calibration_report.json";
  std::string lf_report, co_report, sp_report;
  CalibrationData cal;
  if (!opt.force && Reusable(out / ".calibration.stamp", cal_inputs, {cal_file, cal_report})) {
    say("calibration inputs unchanged: reusing " + cal_file.string());
    cal = ReadCalibrationFile(cal_file.string());
    lf_report = ReportField(cal_report, "light_field");
    co_report = ReportField(cal_report, "corrector");
    if (!cfg.sphere.empty()) sp_report = ReportField(cal_report, "sphere");
    sum.reused.push_back("calibrate");
  } else {
    // A step's stamp goes before it rewrites its outputs and comes back after the last one, so an
    // interrupted step is never taken for finished (and reused) by the next run.
    RemoveStaleOutput(out / ".calibration.stamp");
    timed("calibrate", [&] {
      say("calibrating the light field (" + cfg.lightfield + ")");
      calibrate::LightFieldOptions lo;
      lo.extrapolate_to_deg = cfg.extrapolate_to_deg;
      const calibrate::LightFieldSummary lf = calibrate::CalibrateLightField(lf_in, lo);
      say("fitting the corrector (" + cfg.flatfield + ")");
      calibrate::CorrectorOptions copt;
      copt.zones = cfg.zones;
      copt.smoothness = cfg.smoothness;
      const calibrate::CorrectorSummary co =
          calibrate::CalibrateCorrector(ff_in, copt, &lf.data);
      for (const auto& w : lf.warnings) std::cerr << "raymatch run: warning: " << w << "\n";
      for (const auto& w : co.warnings) std::cerr << "raymatch run: warning: " << w << "\n";
      lf_report = lf.BriefReport();
      co_report = co.BriefReport();
      cal = co.data;
      if (cfg.sphere.empty()) {
        WriteCalibrationFile(cal_file.string(), co.data);
      } else {
        // The light field and corrector go to calibration_base.toml; the sphere calibration
        // adds the edge beyond the NA and the PSF and writes calibration.toml.
        const fs::path base_file = out / "calibration_base.toml";
        WriteCalibrationFile(base_file.string(), co.data);
        say("calibrating with the drop of " + cfg.sphere + " (light field beyond the NA, PSF)");
        SphereCalibrationOptions so;
        so.scan_folder = cfg.sphere;
        so.base = base_file.string();
        so.output = cal_file.string();
        so.work_dir = (out / "sphere_calibration").string();
        so.planes_um = cfg.sphere_planes_um;
        so.threads = opt.threads;
        so.progress = opt.progress;
        so.say = say;
        const SphereCalibrationResult sr = CalibrateSphere(so);
        sp_report = sr.Brief();
        if (sr.mismatch) std::cerr << "raymatch run: warning: the sphere calibration reports a model mismatch\n";
        cal = ReadCalibrationFile(cal_file.string());
      }
      nlohmann::json rep{{"light_field", lf_report}, {"corrector", co_report}};
      if (!sp_report.empty()) rep["sphere"] = sp_report;
      WriteTextFileAtomic(cal_report, rep.dump(2) + "\n");
      WriteTextFileAtomic(out / ".calibration.stamp", cal_inputs);
    });
  }
  sum.cone_half_angle_deg = cal.cone_half_angle_deg;
  sum.transmissions = cal.transmissions;
  sum.transmission_sigma = cal.transmission_sigma;

  // 2. Scene for the experiment: nominal drop, the experiment's image size and planes, the
  // exposure recovered from the background of the middle plane.
  sum.photons_per_pixel = BorderMedian(mid);
  const double frac = opt.ray_fraction > 0 ? opt.ray_fraction : cfg.ray_fraction;
  std::ostringstream sc;
  sc.precision(10);
  sc << "# Written by raymatch run: the experiment's focus scan, simulated with the calibration.\n"
     << "name = \"sim\"\ncalibration = \"calibration.toml\"\nseed = " << cfg.seed << "\n\n"
     << "[[object]]\nname = \"drop\"\ntype = \"sphere\"\nradius_um = " << ex.diameter_um / 2
     << "\nmaterial = \"water\"\ntemperature_K = " << ex.temperature_K << "\n\n[camera]\npixels = ["
     << exp.images[0].width << ", " << exp.images[0].height << "]\n\n[trace]\nphotons_per_pixel = "
     << sum.photons_per_pixel * frac << "   # background photons x ray fraction " << frac
     << "\npartial_reflection = \"" << cfg.partial_reflection << "\"\n\n[scan]\ndefocus_um = [";
  sc.precision(17);  // every distinct focus position stays distinct (plane file names)
  for (size_t i = 0; i < exp.defocus_um.size(); ++i) sc << (i ? ", " : "") << exp.defocus_um[i];
  sc << "]\n";
  const fs::path scene_file = out / "scene.toml";
  WriteTextFileAtomic(scene_file, sc.str());

  // 3. Simulation (reused when scene and calibration are unchanged).
  const fs::path sim_dir = out / "simulation", sim_index = sim_dir / "sim_scan.json";
  const std::string sim_inputs = ReadFileBytes(scene_file.string()) + "|" + FileChecksum(cal_file.string());
  if (!opt.force && Reusable(out / ".simulation.stamp", sim_inputs, {sim_index})) {
    say("simulation unchanged: reusing " + sim_index.string());
    sum.reused.push_back("simulate");
  } else {
    RemoveStaleOutput(out / ".simulation.stamp");
    timed("simulate", [&] {
      say("simulating " + std::to_string(exp.defocus_um.size()) + " planes at " +
          std::to_string(sum.photons_per_pixel * frac) + " photons per pixel");
      simulate::Scene scene = simulate::LoadScene(scene_file.string());
      simulate::ScanOptions so;
      so.output_dir = sim_dir.string();
      so.control.progress = opt.progress;
      so.control.threads = opt.threads;
      simulate::RunScan(scene, so);
      WriteTextFileAtomic(out / ".simulation.stamp", sim_inputs);
    });
  }

  // 4. Focus-scan comparison.
  compare::FocusScanResult fr;
  timed("compare", [&] {
    say("comparing the focus scans");
    compare::FocusScanOptions fo;
    fo.prepare = prep;
    fr = compare::RunFocusScan(exp, compare::ReadStack(sim_index.string()), fo);
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
  std::string merging_html;
  if (!cfg.merging.empty()) {
    timed("mesh object", [&] {
      say("simulating the mesh object (" + cfg.merging + ")");
      const MeshObjectMetadata& mm = *mesh_meta;
      const std::string& image = mm.image;
      const std::string& mesh = mm.mesh;
      const double dz = mm.defocus_um;
      const auto& rot = mm.rotation_deg;
      const Image& e = mesh_image;
      std::ostringstream ms;
      ms.precision(10);
      ms << "name = \"mesh_object\"\ncalibration = \"calibration.toml\"\nseed = " << cfg.seed
         << "\n\n[[object]]\ntype = \"mesh\"\nfile = \"" << mesh << "\"\nrotation_deg = [" << rot[0] << ", "
         << rot[1] << ", " << rot[2] << "]\nmaterial = \"water\"\ntemperature_K = " << ex.temperature_K
         << "\n\n[camera]\npixels = [" << e.width << ", " << e.height << "]\n\n[trace]\nphotons_per_pixel = "
         << sum.photons_per_pixel * frac << "\n\n[scan]\ndefocus_um = [" << dz << "]\n";
      WriteTextFileAtomic(out / "mesh_object.toml", ms.str());
      simulate::ScanOptions so;
      so.output_dir = (out / "mesh_object").string();
      so.control.threads = opt.threads;
      const simulate::ScanSummary ss = simulate::RunScan(simulate::LoadScene((out / "mesh_object.toml").string()), so);
      const compare::Stack es{{dz}, {e}, {image}};
      const compare::Stack sst = compare::ReadStack(ss.index_json);
      compare::FocusScanOptions fo;
      const compare::FocusScanResult mr2 = compare::RunFocusScan(es, sst, fo);
      compare::WriteFocusScanReport(mr2, (out / "mesh_object/compare").string(), "mesh object");
      std::ostringstream hh;
      hh.precision(4);
      hh << "<h2>Non-spherical object (mesh), in focus</h2><p>" << image << " vs a simulation of "
         << mesh << ":";
      for (const auto& m : mr2.measures) hh << " " << compare::MeasureName(m.measure) << " = " << m.matrix[0][0] << ";";
      hh << "</p>" << Img((out / "mesh_object/compare/montage.png").string(), "mesh object montage");
      merging_html = hh.str();
    });
  }

  // 4c. Fits (docs/fit.md) with this calibration: 3D properties from single images.
  std::string fit_html;
  for (const std::string& file : cfg.fits) {
    const std::string stem = fs::path(file).stem().string();
    timed("fit " + stem, [&] {
      say("fitting " + file);
      const fit::FitSpec spec = fit::LoadFitSpec(file, "", fs::absolute(cal_file).string());
      fit::FitOptions fo;
      fo.threads = opt.threads;
      fo.progress = opt.progress;
      const fit::FitResult fr2 = fit::RunFit(spec, fo);
      const std::string report = fit::WriteFitOutputs(spec, fr2, (out / "fit" / stem).string());
      std::ostringstream hh;
      hh.precision(6);
      hh << "<h3><a href='fit/" << stem << "/report.html'>" << stem << "</a>: " << fit::MethodName(spec.method)
         << " on " << fit::ErrorFunctionName(spec.error) << ", " << fit::StatusName(fr2.status) << " (" << fr2.evaluations.size()
         << " evaluations, " << fr2.total_seconds << " s)</h3><table><tr><th>parameter</th><th>best</th>"
            "<th>sigma</th><th>Cramer-Rao bound</th></tr>";
      for (const auto& p : fr2.parameters)
        hh << "<tr><td>" << p.key << "</td><td>" << p.best << " " << p.unit << "</td><td>" << p.sigma
           << "</td><td>" << p.sigma_cramer_rao << "</td></tr>";
      hh << "</table>";
      if (fr2.goodness.pixels > 0)
        hh << "<p style='padding:4px;border:2px solid " << (fr2.goodness.mismatch ? "#c00" : "#6a6")
           << "'>Goodness of fit: " << fr2.goodness.verdict << "</p>";
      fit_html += hh.str();
      sum.fits.push_back({stem, fit::StatusName(fr2.status)});
    });
  }
  if (!fit_html.empty()) fit_html = "<h2>Fits: 3D properties from the images</h2>" + fit_html;

  // 5. Report.
  const fs::path fig = out / "figures";
  EnsureDirectory(fig);
  {
    // Angular map over direction cosines (u right, v up), relative to its maximum.
    compare::MapPlot p;
    p.image = cal.angular_map;
    double mx = 0;
    for (float v : p.image.pixels) mx = std::max(mx, double(v));
    if (mx > 0)
      for (float& v : p.image.pixels) v = float(v / mx);
    p.lo = 0, p.hi = 1;
    p.x_left = -cal.angular_extent, p.x_right = cal.angular_extent;
    p.y_top = cal.angular_extent, p.y_bottom = -cal.angular_extent;
    p.title = "light field: angular radiance";
    p.xlabel = "direction cosine u (x, right)";
    p.ylabel = "direction cosine v (y, up)";
    p.colour_label = "radiance (relative to the maximum)";
    p.max_side_px = 360;
    compare::WriteMap((fig / "angular_map.png").string(), p);
  }
  std::string spatial_html;
  if (!cal.spatial_map.empty()) {
    compare::MapPlot p;
    p.image = cal.spatial_map;
    double mx = 0;
    for (float v : p.image.pixels) mx = std::max(mx, double(v));
    p.lo = 0, p.hi = mx > 0 ? mx : 1;
    p.x_left = -0.5 * cal.field_size_um[0], p.x_right = 0.5 * cal.field_size_um[0];
    p.y_top = 0.5 * cal.field_size_um[1], p.y_bottom = -0.5 * cal.field_size_um[1];
    p.title = "light field: spatial map at the object plane (from the flat field)";
    p.xlabel = "x (µm)";
    p.ylabel = "y (µm)";
    p.colour_label = "relative irradiance";
    p.max_side_px = 360;
    compare::WriteMap((fig / "spatial_map.png").string(), p);
    spatial_html = "<p>Spatial map: relative irradiance at the object plane from the flat field.</p>" +
                   Img((fig / "spatial_map.png").string(), "spatial map");
  }
  {
    // Azimuthal mean in rings of one map pixel, with the standard error of each ring's mean.
    const Image& m = cal.angular_map;
    const int n = m.width;
    std::vector<double> sum_r(n / 2, 0), sum2(n / 2, 0), cnt(n / 2, 0);
    for (int y = 0; y < n; ++y)
      for (int x = 0; x < n; ++x) {
        const double u = (2 * (x + 0.5) / n - 1), vv = (1 - 2 * (y + 0.5) / n);
        const int k = int(std::hypot(u, vv) * n / 2);
        if (k < n / 2) sum_r[k] += m.at(x, y), sum2[k] += double(m.at(x, y)) * m.at(x, y), cnt[k] += 1;
      }
    Series s;
    s.points = true;
    s.label = "azimuthal mean ± 1 standard error";
    double mx = 0;
    for (int k = 0; k < n / 2; ++k)
      if (cnt[k] > 0) mx = std::max(mx, sum_r[k] / cnt[k]);
    for (int k = 0; k < n / 2; ++k)
      if (cnt[k] > 0) {
        const double mean = sum_r[k] / cnt[k];
        const double var = cnt[k] > 1 ? std::max(0.0, (sum2[k] - cnt[k] * mean * mean) / (cnt[k] - 1)) : 0.0;
        s.x.push_back(std::asin(std::min(1.0, (k + 0.5) / (n / 2) * cal.angular_extent)) * 180 / M_PI);
        s.y.push_back(mx > 0 ? mean / mx : mean);
        s.yerr.push_back((mx > 0 ? 1 / mx : 1) * std::sqrt(var / cnt[k]));
      }
    compare::PlotPanel p;
    p.series = {s};
    p.title = "light field: radial profile (cone edge " + std::to_string(cal.cone_half_angle_deg).substr(0, 5) + "°)";
    p.xlabel = "angle to the optical axis (degrees)";
    p.ylabel = "radiance (relative to the maximum)";
    WritePlot((fig / "radial_profile.png").string(), {p}, 560, 380);
  }
  {
    // Zone transmissions against the zone's radius on the corrector (mid-ring), +-1 sigma.
    Series s;
    s.points = true;
    s.label = "transmission ± 1σ (fit)";
    const bool radii = cal.ring_outer_mm.size() == cal.transmissions.size();
    for (size_t j = 0; j < cal.transmissions.size(); ++j) {
      s.x.push_back(radii ? 0.5 * ((j ? cal.ring_outer_mm[j - 1] : 0.0) + cal.ring_outer_mm[j]) : double(j));
      s.y.push_back(cal.transmissions[j]);
      s.yerr.push_back(j < cal.transmission_sigma.size() ? cal.transmission_sigma[j] : 0.0);
    }
    compare::PlotPanel p;
    p.series = {s};
    p.title = "corrector: zone transmissions";
    p.xlabel = radii ? "zone mid-radius on the corrector (mm)" : "zone (0 = central disc)";
    p.ylabel = "transmission T (fraction)";
    WritePlot((fig / "transmissions.png").string(), {p}, 560, 380);
  }
  std::ostringstream h;
  h.precision(4);
  h << "<!doctype html><html><head><meta charset='utf-8'><title>raymatch run</title><style>"
       "body{font-family:sans-serif;margin:2em;max-width:1100px}td,th{border:1px solid #ccc;"
       "padding:2px 6px;font-size:12px}table{border-collapse:collapse}img{max-width:100%}"
       ".pass{color:#070}.fail{color:#b00}</style></head><body><h1>raymatch: calibrate, simulate, compare</h1>"
    << "<p>" << ProvenanceJson()["date_utc"].get<std::string>() << " &mdash; <code>" << CommandLine()
    << "</code></p><h2>Verdict: <span class='" << (fr.verdict == compare::Verdict::kPass ? "pass'>pass" : "fail'>" + std::string(fr.verdict == compare::Verdict::kWarning ? "warning" : "fail"))
    << "</span></h2><p>" << fr.message << "</p>"
    << "<h2>Measured light field</h2><pre>" << lf_report << "</pre>"
    << Img((fig / "angular_map.png").string(), "angular map") << " "
    << Img((fig / "radial_profile.png").string(), "light-field radial profile")
    << "<p>Angular map over direction cosines (u right, v up), +-" << cal.angular_extent
    << "; radial profile: azimuthal means in rings of one map pixel, error bars one standard error "
       "of each ring's mean.</p>"
    << spatial_html
    << "<h2>Corrector</h2><pre>" << co_report << "</pre>"
    << (sp_report.empty() ? std::string()
                          : "<h2>Sphere calibration</h2><p>The light field beyond the NA and the PSF from the drop of " +
                                HtmlEscape(cfg.sphere) + " (<a href='sphere_calibration/report.html'>fit report</a>)</p><pre>" +
                                HtmlEscape(sp_report) + "</pre>") << Img((fig / "transmissions.png").string(), "corrector transmissions")
    << "<p>Error bars: one standard deviation from the fit's covariance.</p>"
    << "<h2>Experiment (top) and simulation (bottom)</h2><p>Exposure recovered from the "
       "background: " << sum.photons_per_pixel << " photons per pixel; simulated with ray fraction "
    << frac << ". " << fr.RegistrationSummary() << ".</p>"
    << Img((out / "compare/montage.png").string(), "montage")
    << "<p>Residual maps and radial profiles per plane: <a href='compare/report.html'>compare/report.html</a>.</p>"
    << "<h2>Focus-scan test</h2><table><tr><th>measure</th><th>verdict</th><th>best simulated z per experimental z (um)</th></tr>";
  for (size_t i = 0; i < fr.measures.size(); ++i) {
    h << "<tr><td>" << sum.measures[i] << "</td><td class='" << (fr.measures[i].passes ? "pass'>pass" : "fail'>fail") << "</td><td>";
    for (double z : sum.best_match_um[i]) h << z << " ";
    h << "</td></tr>";
  }
  h << "</table>";
  h << merging_html << fit_html;
  for (const auto& m : fr.measures)
    h << "<h3>" << compare::MeasureName(m.measure) << "</h3>"
      << Img((out / ("compare/heatmap_" + std::string(compare::MeasureName(m.measure)) + ".png")).string(),
             std::string(compare::MeasureName(m.measure)) + " heatmap");
  h << "<h2>Timing</h2><table>";
  for (const auto& [name, s] : sum.step_seconds) h << "<tr><td>" << name << "</td><td>" << s << " s</td></tr>";
  for (const auto& r : sum.reused) h << "<tr><td>" << r << "</td><td>reused (inputs unchanged)</td></tr>";
  h << "</table><p>Files: <code>calibration.toml</code>, <code>scene.toml</code>, <code>simulation/</code>, "
       "<code>compare/</code> (report.html, CSV, JSON), <code>figures/</code>.</p></body></html>\n";
  WriteTextFileAtomic(sum.report, h.str());
  return sum;
}

}  // namespace raymatch::pipeline
