#include "raymatch/pipeline/fit_cost.h"

#include <toml++/toml.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <iostream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "raymatch/compare/plot.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"
#include "raymatch/core/provenance.h"
#include "raymatch/fit/fit.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/tracer.h"

namespace fs = std::filesystem;

namespace raymatch::pipeline {
namespace {

/// A number for CSV and JSON: never NaN or infinity (empty in CSV, null in JSON).
std::string Num(double v) {
  if (!std::isfinite(v)) return "";
  std::ostringstream s;
  s.precision(6);
  s << v;
  return s.str();
}
nlohmann::json JNum(double v) { return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(); }

/// The settings: the fit file as written, then each listed value of each knob alone.
std::vector<FitCostSetting> Settings(const FitCostOptions& o) {
  std::vector<FitCostSetting> s;
  const auto Add = [&](const std::string& knob, double v) {
    s.emplace_back();
    s.back().knob = knob, s.back().value = v;
  };
  Add("as written", NAN);  // no value of its own: empty in the CSV, null in the JSON
  for (double v : o.ray_factors) Add("ray_factor", v);
  for (int v : o.jacobian_seeds) Add("jacobian_seeds", v);
  for (int v : o.repeat_seeds) Add("repeat_seeds", v);
  for (double v : o.last_fractions) Add("last_fraction", v);
  return s;
}

/// The fit file at one setting; throws Error for a value the fit file could not take (its keys'
/// ranges, fit.h).
fit::FitSpec AtSetting(fit::FitSpec spec, const FitCostSetting& s) {
  const auto bad = [&](const std::string& why) {
    throw Error("raymatch bench fit: " + s.knob + " " + Num(s.value) + ": " + why);
  };
  if (s.knob == "ray_factor") {
    if (!(s.value >= fit::kMinRayFactor && s.value <= fit::kMaxRayFactor))
      bad("expected a ray factor in [1/1024, 1024]");
    spec.rays.ray_factor = s.value;
  } else if (s.knob == "jacobian_seeds") {
    if (s.value < fit::kMinJacobianSeeds || s.value > fit::kMaxJacobianSeeds)
      bad("expected 2 to 64 derivative sets");
    spec.rays.jacobian_seeds = int(s.value);
  } else if (s.knob == "repeat_seeds") {
    if (s.value < 0 || s.value == 1 || s.value > fit::kMaxRepeatSeeds)
      bad("expected 0 (none) or 2 to 1000 repeated fits");
    spec.repeat_seeds = int(s.value);
  } else if (s.knob == "last_fraction") {
    if (!(s.value > 0 && s.value <= 1)) bad("expected a fraction in (0, 1]");
    if (spec.rays.fractions.size() > 1 &&
        s.value < spec.rays.fractions[spec.rays.fractions.size() - 2])
      bad("below the schedule's previous fraction");
    spec.rays.fractions.back() = s.value;
  }
  return spec;
}

/// The truth's value of each fitted key: the truth scene's for scene keys; for an image's
/// defocus the fit file's own (the experiment is traced there), for its background 0.
std::vector<double> TruthValues(const fit::FitSpec& spec, const toml::table& truth,
                                const std::string& truth_file) {
  std::vector<double> v;
  for (const fit::Parameter& p : spec.parameters) {
    const auto image = fit::ParseImageKey(p.key, spec.images.size());
    if (!image)
      v.push_back(fit::SceneValue(truth, p.key, truth_file));
    else
      v.push_back(image->second == "defocus_um" ? spec.images[image->first].defocus_um : 0.0);
  }
  return v;
}

/// Realisation k's planes: the truth traced at each image's defocus, photon-matched, with the
/// ray streams of seed `seed`.
std::vector<Image> Experiment(const simulate::Scene& truth_scene, const fit::FitSpec& spec,
                              uint64_t seed, int threads) {
  simulate::Scene s = truth_scene;
  s.trace.seed = seed;
  const simulate::Simulator sim(s);
  simulate::RunControl ctl;
  ctl.threads = threads;
  std::vector<Image> planes;
  for (size_t i = 0; i < spec.images.size(); ++i)
    planes.push_back(
        sim.TracePlane(spec.images[i].defocus_um, uint32_t(i), sim.RaysPerImage(), ctl).counts);
  return planes;
}

/// The fit sizes its rays by its images' photons (FitSpec::RaysPerPhoton) and the study replaces
/// them by the truth's: a truth whose flat field is far from the images' (a scene without
/// `[trace] photons_per_pixel` traces the default ray count) would study other fits than the
/// file's. Throws Error when the two differ by more than a factor 3.
void CheckTruthExposure(const fit::FitSpec& spec, const simulate::Scene& truth,
                        const std::string& truth_file) {
  const simulate::Simulator sim(truth);
  double hits_per_pixel_per_ray = 0;
  sim.RaysForPhotonTarget(1, &hits_per_pixel_per_ray);
  const double flat = double(sim.RaysPerImage()) * hits_per_pixel_per_ray;
  for (const fit::FitImage& im : spec.images) {
    const double level = BorderMedian(im.photons);
    if (level > 0 && flat > level / 3 && flat < level * 3) continue;
    throw Error(truth_file + ": its flat field gives " + Num(flat) + " photons per pixel, but " +
                im.file + " has " + Num(level) +
                " (the median of its border): set [trace] photons_per_pixel in the truth scene to "
                "the experiments' flat-field level, so its planes are the fit file's");
  }
}

/// The Cramer-Rao bound is the truth's and the photons', the same at every setting: each
/// parameter's is the mean over every fit that computed one (a fit whose derivative sets' halves
/// give no positive-definite information has none), so all settings are judged by one bound.
void Summarise(FitCostResult& r) {
  const size_t P = r.keys.size();
  r.cramer_rao.assign(P, 0);
  std::vector<int> with(P, 0);
  for (const FitCostFit& f : r.fits)
    for (size_t i = 0; i < P; ++i)
      if (f.crb[i] > 0) r.cramer_rao[i] += f.crb[i], ++with[i];
  for (size_t i = 0; i < P; ++i) r.cramer_rao[i] = with[i] ? r.cramer_rao[i] / with[i] : NAN;
  for (size_t si = 0; si < r.settings.size(); ++si) {
    FitCostSetting& s = r.settings[si];
    std::vector<double> mean(P, 0), ms(P, 0), mz(P, 0);
    for (const FitCostFit& f : r.fits) {
      if (f.setting != si) continue;
      ++s.fits, s.flagged += f.mismatch ? 1 : 0;
      s.mean_seconds += f.seconds, s.max_seconds = std::max(s.max_seconds, f.seconds);
      for (size_t i = 0; i < P; ++i) {
        const double e = f.best[i] - r.truth[i];
        mean[i] += e, ms[i] += e * e;
        mz[i] += f.sigma[i] > 0 ? (e / f.sigma[i]) * (e / f.sigma[i]) : INFINITY;
      }
    }
    if (s.fits == 0) continue;
    s.mean_seconds /= s.fits;
    for (size_t i = 0; i < P; ++i) {
      s.mean_error_over_crb.push_back(mean[i] / s.fits / r.cramer_rao[i]);
      s.rms_error_over_crb.push_back(std::sqrt(ms[i] / s.fits) / r.cramer_rao[i]);
      s.rms_error_over_sigma.push_back(std::sqrt(mz[i] / s.fits));
    }
  }
}

void WriteOutputs(const FitCostOptions& o, FitCostResult& r) {
  const fs::path out(o.output_dir);
  std::ostringstream csv, fits;
  csv << "knob,value,fits,flagged,mean_seconds,max_seconds";
  fits << "knob,value,realisation,seconds,converged,mismatch";
  for (const std::string& k : r.keys) {
    csv << "," << k << "_mean_error_over_crb," << k << "_rms_error_over_crb," << k
        << "_rms_error_over_sigma";
    fits << "," << k << "_best," << k << "_sigma," << k << "_cramer_rao";
  }
  csv << "\n", fits << "\n";
  nlohmann::json js = nlohmann::json::array();
  for (const FitCostSetting& s : r.settings) {
    csv << '"' << s.knob << "\"," << Num(s.value) << "," << s.fits << "," << s.flagged << ","
        << Num(s.mean_seconds) << "," << Num(s.max_seconds);
    nlohmann::json per = nlohmann::json::array();
    for (size_t i = 0; i < s.rms_error_over_crb.size(); ++i) {
      csv << "," << Num(s.mean_error_over_crb[i]) << "," << Num(s.rms_error_over_crb[i]) << ","
          << Num(s.rms_error_over_sigma[i]);
      per.push_back({{"key", r.keys[i]},
                     {"mean_error_over_crb", JNum(s.mean_error_over_crb[i])},
                     {"rms_error_over_crb", JNum(s.rms_error_over_crb[i])},
                     {"rms_error_over_sigma", JNum(s.rms_error_over_sigma[i])}});
    }
    csv << "\n";
    js.push_back({{"knob", s.knob},
                  {"value", JNum(s.value)},
                  {"fits", s.fits},
                  {"flagged", s.flagged},
                  {"mean_seconds", s.mean_seconds},
                  {"max_seconds", s.max_seconds},
                  {"parameters", per}});
  }
  for (const FitCostFit& f : r.fits) {
    const FitCostSetting& s = r.settings[f.setting];
    fits << '"' << s.knob << "\"," << Num(s.value) << "," << f.realisation << "," << Num(f.seconds)
         << "," << f.converged << "," << f.mismatch;
    for (size_t i = 0; i < f.best.size(); ++i)
      fits << "," << Num(f.best[i]) << "," << Num(f.sigma[i]) << "," << Num(f.crb[i]);
    fits << "\n";
  }
  r.csv = (out / "fit_cost.csv").string(), r.fits_csv = (out / "fits.csv").string();
  WriteTextFileAtomic(r.csv, csv.str());
  WriteTextFileAtomic(r.fits_csv, fits.str());
  const nlohmann::json j = {{"provenance", ProvenanceJson()},
                            {"fit_file", o.fit_file},
                            {"truth_scene", o.truth_scene},
                            {"calibration", o.calibration},
                            {"realisations", o.realisations},
                            {"seed_base", o.seed_base},
                            {"keys", r.keys},
                            {"truth", r.truth},
                            {"cramer_rao",
                             [&] {
                               nlohmann::json c = nlohmann::json::array();
                               for (double v : r.cramer_rao) c.push_back(JNum(v));
                               return c;
                             }()},
                            {"settings", js}};
  WriteTextFileAtomic(out / "fit_cost.json", j.dump(2) + "\n");

  // One panel per knob: each parameter's RMS error in Cramer-Rao bounds against the mean time
  // per fit, the fit file as written in every panel.
  std::vector<compare::PlotPanel> panels;
  for (const std::string knob : {"ray_factor", "jacobian_seeds", "repeat_seeds", "last_fraction"}) {
    std::vector<size_t> idx{0};
    for (size_t si = 1; si < r.settings.size(); ++si)
      if (r.settings[si].knob == knob) idx.push_back(si);
    if (idx.size() < 2) continue;
    std::sort(idx.begin(), idx.end(), [&](size_t a, size_t b) {
      return r.settings[a].mean_seconds < r.settings[b].mean_seconds;
    });
    compare::PlotPanel p;
    p.title = "RMS error against time per fit, varying " + knob + " (";
    for (size_t si = 1; si < r.settings.size(); ++si)
      if (r.settings[si].knob == knob) p.title += Num(r.settings[si].value) + ", ";
    p.title += "and as written)";
    p.xlabel = "mean time per fit (s)";
    p.ylabel = "RMS error / Cramer-Rao bound";
    p.log_x = true;
    for (size_t i = 0; i < r.keys.size(); ++i) {
      compare::Series s;
      s.points = s.joined = true;
      s.label = r.keys[i];
      for (size_t si : idx)
        if (std::isfinite(r.settings[si].rms_error_over_crb[i]))
          s.x.push_back(std::max(r.settings[si].mean_seconds, 1e-3)),
              s.y.push_back(r.settings[si].rms_error_over_crb[i]);
      p.series.push_back(s);
    }
    panels.push_back(p);
  }
  if (!panels.empty()) {
    r.plot = (out / "fit_cost.png").string();
    compare::WritePlot(r.plot, panels, 760, 400);
  }
}

}  // namespace

FitCostResult RunFitCostStudy(const FitCostOptions& o) {
  if (o.realisations < 2)
    throw Error("raymatch bench fit: --realisations " + std::to_string(o.realisations) +
                ": expected 2 or more (an RMS over realisations)");
  const fit::FitSpec base = fit::LoadFitSpec(o.fit_file, "", o.calibration);
  if (base.error != fit::ErrorFunction::kPoisson || base.exact_images() || !base.cramer_rao)
    throw Error(o.fit_file + ": raymatch bench fit needs a Poisson ray-model fit with cramer_rao");
  toml::table truth_table;
  try {
    truth_table = toml::parse_file(o.truth_scene);
  } catch (const toml::parse_error& e) {
    throw Error(o.truth_scene + ": " + std::string(e.description()));
  }
  if (!o.calibration.empty())
    truth_table.insert_or_assign("calibration", fs::absolute(o.calibration).string());
  const simulate::Scene truth_scene = simulate::LoadScene(truth_table, o.truth_scene);
  FitCostResult r;
  for (const fit::Parameter& p : base.parameters) r.keys.push_back(p.key);
  r.truth = TruthValues(base, truth_table, o.truth_scene);
  r.settings = Settings(o);
  std::vector<fit::FitSpec> specs;
  for (const FitCostSetting& s : r.settings) specs.push_back(AtSetting(base, s));
  for (const fit::FitImage& im : base.images)
    if (im.photons.width != truth_scene.camera.nx || im.photons.height != truth_scene.camera.ny)
      throw Error(im.file + ": " + std::to_string(im.photons.width) + " x " +
                  std::to_string(im.photons.height) + " pixels, but the truth scene " +
                  o.truth_scene + " images " + std::to_string(truth_scene.camera.nx) + " x " +
                  std::to_string(truth_scene.camera.ny));
  CheckTruthExposure(base, truth_scene, o.truth_scene);
  fs::create_directories(o.output_dir);
  fit::FitOptions fo;
  fo.threads = o.threads;
  for (int k = 0; k < o.realisations; ++k) {
    const std::vector<Image> planes = Experiment(truth_scene, base, o.seed_base + k, o.threads);
    for (size_t si = 0; si < specs.size(); ++si) {
      fit::FitSpec spec = specs[si];
      spec.seed = base.seed + uint64_t(k);  // independent ray streams per realisation
      for (size_t i = 0; i < spec.images.size(); ++i) {
        spec.images[i].photons = planes[i];
        spec.images[i].usable = Image();
        spec.images[i].excluded_pixels = 0;
      }
      const fit::FitResult fr = fit::RunFit(spec, fo);
      FitCostFit f;
      f.setting = si, f.realisation = k, f.seconds = fr.total_seconds;
      f.converged = fr.converged, f.mismatch = fr.goodness.mismatch;
      for (const fit::ParameterResult& p : fr.parameters)
        f.best.push_back(p.best), f.sigma.push_back(p.sigma), f.crb.push_back(p.sigma_cramer_rao);
      r.fits.push_back(f);
      if (o.progress)
        std::cerr << "raymatch bench fit: realisation " << k + 1 << "/" << o.realisations << ", "
                  << r.settings[si].knob << (si ? " " + Num(r.settings[si].value) : std::string())
                  << ": " << Num(fr.total_seconds) << " s"
                  << (fr.converged ? "" : ", not converged") << std::endl;
    }
  }
  Summarise(r);
  WriteOutputs(o, r);
  return r;
}

}  // namespace raymatch::pipeline
