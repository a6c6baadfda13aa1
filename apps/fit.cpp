// raymatch fit: optimise simulations against experimental images to extract 3D properties.
#include "raymatch/fit/fit.h"

#include <iostream>

#include "commands.h"
#include "mpi_session.h"
#include "raymatch/core/error.h"
#include "raymatch/core/html.h"

namespace raymatch::apps {

namespace {

struct FitCliOptions {
  std::string fit_file, output = "fit-out", scene, calibration;
  int threads = 0;
  bool quiet = false;
};

int RunFitCommand(const FitCliOptions& o) {
  const fit::FitSpec spec = fit::LoadFitSpec(o.fit_file, o.scene, o.calibration);
  fit::FitOptions fo;
  fo.threads = o.threads;
  fo.progress = !o.quiet;
  const fit::FitResult r = fit::RunFit(spec, fo);
  const std::string report = fit::WriteFitOutputs(spec, r, RankOutput(o.output));
  std::cout << "fit " << fit::StatusName(r.status) << ": " << r.message << "\n";
  for (const auto& p : r.parameters) {
    std::cout << "  " << p.key << " = " << FormatValue(p.best, p.sigma)
              << (p.unit.empty() ? "" : " " + p.unit) << "  +- " << FormatUncertainty(p.sigma)
              << "  (Cramer-Rao bound " << FormatUncertainty(p.sigma_cramer_rao);
    if (spec.repeat_seeds >= 2)
      std::cout << ", repeat-seed scatter " << FormatUncertainty(p.sigma_repeat);
    std::cout << ")" << (p.at_bound ? "  AT BOUND" : "");
    if (p.prior_sigma > 0)
      std::cout << "  (prior from the " << p.prior_from << ": " << p.prior_mean << " +- "
                << p.prior_sigma << ")";
    std::cout << "\n";
  }
  for (const auto& p : r.parameters)
    if (!p.profile_t.empty())
      std::cout << "  profile-likelihood 68 % interval of " << p.key << ": ["
                << (p.profile_lower_open ? "<= " : "") << p.profile_lower << ", "
                << (p.profile_upper_open ? ">= " : "") << p.profile_upper << "] ("
                << p.profile_reason << ")\n";
  if (r.goodness.pixels > 0)
    std::cout << (r.goodness.mismatch ? "WARNING: " : "goodness of fit: ") << r.goodness.verdict
              << "\n";
  std::cout << r.evaluations.size() << " evaluations, " << r.total_seconds
            << " s; report: " << report << "\n";
  if (r.status == fit::FitStatus::kFlat) {
    std::cerr << "raymatch fit: error: " << r.message << "\n";
    return 3;
  }
  if (!r.converged) return 1;
  return r.goodness.mismatch ? 4 : 0;
}

}  // namespace

void RegisterFit(CLI::App& app, int* exit_code) {
  auto o = std::make_shared<FitCliOptions>();
  CLI::App* c = app.add_subcommand(
      "fit",
      "Optimise simulated images against experimental ones to extract 3D properties (positions "
      "and lengths in micrometres, angles in degrees, indices absolute), with uncertainties and "
      "the Cramer-Rao bound. The fit file is documented in docs/fit.md.\n"
      "Exit status: 0 converged and consistent with the noise, 1 bad input or not converged, 2 "
      "usage error, 3 the error function is flat (the parameters do not change the image), 4 "
      "converged with a model mismatch (the goodness of fit: the model does not describe the "
      "images within their noise; outputs written, sigmas inflated).");
  c->add_option("fit_file", o->fit_file, "fit file (TOML)")->required()->check(CLI::ExistingFile);
  c->add_option("-o,--output", o->output,
                "output folder (created): fit.json, evaluations.csv, images, report.html")
      ->capture_default_str();
  c->add_option("--scene", o->scene, "scene file to use instead of the fit file's `scene`");
  c->add_option("--calibration", o->calibration,
                "calibration file (light field, corrector, optics) to use in the scene, e.g. "
                "out/sample/calibration.toml from `raymatch run`");
  c->add_option("-t,--threads", o->threads,
                "worker threads (0 = the fit file's value, then all cores)")
      ->check(CLI::Range(0, 4096));
  c->add_flag("-q,--quiet", o->quiet, "no progress on stderr");
  c->callback([o, exit_code] { *exit_code = RunGuarded([&] { return RunFitCommand(*o); }, 1); });
}

}  // namespace raymatch::apps
