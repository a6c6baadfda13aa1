// raymatch sensitivity: how precisely images could determine scene keys (Cramer-Rao bounds), and
// which focal planes to record (docs/sensitivity.md).
#include "raymatch/fit/sensitivity.h"

#include <cmath>
#include <iostream>

#include "commands.h"
#include "raymatch/core/error.h"

namespace raymatch::apps {

namespace {

struct SensitivityCliOptions {
  std::string scene, output = "sensitivity-out", calibration, design;
  std::vector<std::string> keys, design_keys, defocus;
  std::vector<double> steps;
  double photons_per_pixel = 0, ray_factor = 4, read_noise_e = 0;
  int sets = 4, threads = 0;
  uint64_t seed = 1;
  bool known_exposure = false, quiet = false;
};

/// "-10,0,10" items, each a number or a range "from:step:to" (both ends included).
std::vector<double> FocusList(const std::vector<std::string>& items) {
  std::vector<double> out;
  for (const std::string& it : items) {
    const size_t a = it.find(':');
    try {
      if (a == std::string::npos) {
        out.push_back(std::stod(it));
        continue;
      }
      const size_t b = it.find(':', a + 1);
      if (b == std::string::npos) throw std::invalid_argument("range");
      const double from = std::stod(it.substr(0, a)), step = std::stod(it.substr(a + 1, b - a - 1)),
                   to = std::stod(it.substr(b + 1));
      if (!(step > 0) || to < from || (to - from) / step > 1000)
        throw std::invalid_argument("range");
      for (double z = from; z <= to + 1e-9 * step; z += step) out.push_back(z);
    } catch (const std::exception&) {
      throw Error("--defocus-um: '" + it +
                  "' is neither a focus position in um nor a range from:step:to (step > 0, at "
                  "most 1000 planes)");
    }
  }
  return out;
}

int RunSensitivityCommand(const SensitivityCliOptions& o) {
  fit::SensitivitySpec spec = fit::SensitivitySceneSpec(o.scene, o.calibration);
  spec.keys = o.keys;
  spec.steps = o.steps;
  if (!spec.steps.empty() && spec.steps.size() != spec.keys.size())
    throw Error("--steps: give one step per key (" + std::to_string(spec.keys.size()) + ")");
  spec.defocus_um = FocusList(o.defocus);
  spec.photons_per_pixel = o.photons_per_pixel;
  spec.ray_factor = o.ray_factor;
  spec.sets = o.sets;
  spec.exposure_nuisance = !o.known_exposure;
  spec.read_noise_e = o.read_noise_e;
  spec.seed = o.seed;
  spec.threads = o.threads;
  if (!o.design.empty()) {
    int n = 0;
    try {
      if (o.design.rfind("planes=", 0) != 0) throw std::invalid_argument("design");
      size_t used = 0;
      n = std::stoi(o.design.substr(7), &used);
      if (used != o.design.size() - 7 || n < 1) throw std::invalid_argument("design");
    } catch (const std::exception&) {
      throw Error("--design: expected planes=N (N >= 1), got '" + o.design + "'");
    }
    spec.design_planes = n;
  }
  spec.design_keys = o.design_keys;
  const fit::SensitivityResult r = fit::RunSensitivity(spec, !o.quiet);
  const std::string report = fit::WriteSensitivityOutputs(spec, r, o.output);
  std::cout << "Cramer-Rao bounds (" << r.mu.size() << " image(s), " << r.photons_per_pixel
            << " photons per flat-field pixel, exposure "
            << (spec.exposure_nuisance ? "unknown" : "known") << "):\n";
  for (const auto& k : r.keys)
    std::cout << "  " << k.key << " = " << k.value << (k.unit.empty() ? "" : " " + k.unit)
              << ":  +- " << k.crb << "  (Monte Carlo error of the bound " << k.crb_mc_error
              << ")\n";
  for (const auto& k : r.keys)
    if (!(k.crb_mc_error <= 0.05 * k.crb))
      std::cout << "WARNING: the bound of " << k.key << " has a Monte Carlo error of "
                << 100 * k.crb_mc_error / k.crb
                << " % of itself: its derivative images are noisy; raise --ray-factor or --sets "
                   "(or --steps)\n";
  if (!r.design_best.empty()) {
    std::cout << "design (geometric mean of the bounds of the design keys, one image's photons "
                 "shared):\n";
    for (const auto& c : r.design_best) {
      std::cout << "  " << c.defocus_um.size() << " plane(s) at";
      for (double d : c.defocus_um) std::cout << " " << d;
      std::cout << " um: " << c.objective << "\n";
    }
  }
  std::cout << r.evaluations << " evaluations, " << r.seconds << " s; report: " << report << "\n";
  return 0;
}

}  // namespace

void RegisterSensitivity(CLI::App& app, int* exit_code) {
  auto o = std::make_shared<SensitivityCliOptions>();
  CLI::App* c = app.add_subcommand(
      "sensitivity",
      "How precisely images of a scene could determine scene keys, before or without an "
      "experiment: the Fisher information and Cramer-Rao bounds (one standard deviation, in the "
      "key's unit: um, deg, absolute index ...) at the scene's values, their correlations, the "
      "bounds' own Monte Carlo error, and per key the map d mu / d key (photons per pixel per "
      "unit). With --design planes=N: the N focus positions among --defocus-um that minimise "
      "the bounds for one image's photons. docs/sensitivity.md.");
  c->add_option("scene", o->scene, "scene file (TOML)")->required()->check(CLI::ExistingFile);
  c->add_option("--keys", o->keys,
                "scene keys, comma-separated, in the fit's syntax (docs/fit.md): e.g. "
                "object.drop.center_um[2],object.drop.radius_um,object.drop.index")
      ->required()
      ->delimiter(',');
  c->add_option("--steps", o->steps,
                "central-difference span per key, in its unit (default: 0.2 um, 0.5 deg, 0.002 "
                "for an index, else 1 % of the value)")
      ->delimiter(',');
  c->add_option("--defocus-um", o->defocus,
                "focus positions of the images, um (+ = towards the camera): a list and/or ranges "
                "from:step:to, e.g. -20:5:20 (default: the scene's)")
      ->delimiter(',');
  c->add_option("--photons-per-pixel", o->photons_per_pixel,
                "photons per flat-field pixel of each image (default: the scene's [trace] "
                "photons_per_pixel)");
  c->add_option("--ray-factor", o->ray_factor,
                "rays traced per photon for the derivative images (more: a smaller Monte Carlo "
                "error of the bounds)")
      ->capture_default_str()
      ->check(CLI::Range(1.0 / 64, 1024.0));
  c->add_option("--sets", o->sets,
                "independent ray-stream sets (even, >= 4); the bounds' Monte Carlo error is a "
                "delete-one jackknife over them")
      ->capture_default_str();
  c->add_flag("--known-exposure", o->known_exposure,
              "take each image's photon count as known (default: a nuisance, as fits find it)");
  c->add_option("--read-noise-e", o->read_noise_e, "camera read noise, electrons rms")
      ->check(CLI::Range(0.0, 1e4));
  c->add_option("--design", o->design,
                "experiment design: planes=N chooses N of the --defocus-um positions");
  c->add_option("--design-keys", o->design_keys,
                "keys whose bounds the design minimises (default: all)")
      ->delimiter(',');
  c->add_option("--calibration", o->calibration,
                "calibration file (light field, corrector, optics) to use in the scene");
  c->add_option("-o,--output", o->output,
                "output folder (created): sensitivity.json, dmu_*.tif/.png, report.html")
      ->capture_default_str();
  c->add_option("--seed", o->seed, "first ray-stream seed")->capture_default_str();
  c->add_option("-t,--threads", o->threads, "worker threads (0 = all cores)")
      ->check(CLI::Range(0, 4096));
  c->add_flag("-q,--quiet", o->quiet, "no progress on stderr");
  c->callback(
      [o, exit_code] { *exit_code = RunGuarded([&] { return RunSensitivityCommand(*o); }, 1); });
}

}  // namespace raymatch::apps
