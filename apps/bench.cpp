// raymatch bench accuracy | fit | fit-grid: what accuracy costs in time (docs/performance.md).
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <iostream>
#include <sstream>

#include "commands.h"
#include "mpi_session.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/fit/fit.h"
#include "raymatch/pipeline/accuracy.h"
#include "raymatch/pipeline/fit_cost.h"

namespace raymatch::apps {

void RegisterBench(CLI::App& app, int* exit_code) {
  CLI::App* bench = app.add_subcommand("bench", "Whole-run benchmarks");
  bench->require_subcommand(1);
  auto o = std::make_shared<pipeline::AccuracyOptions>();
  CLI::App* a = bench->add_subcommand(
      "accuracy",
      "Trace one focus plane of SCENE at ray fractions 1, 1/2, ... 1/max of the photon-matched\n"
      "count; report wall time, rays/s, relative shot noise and MSE/SSIM/MS-SSIM/CW-SSIM/Poisson\n"
      "against a high-ray reference and (with --experiment) the experiment. Writes accuracy.csv,\n"
      "accuracy.json and accuracy.png.");
  a->add_option("scene", o->scene_file, "Scene (e.g. out/sample/scene.toml from raymatch run)")
      ->required()
      ->check(CLI::ExistingFile);
  a->add_option("--experiment", o->experiment_csv, "Experimental stack (defocus_um,file)");
  a->add_option("--dark", o->dark_file, "Experiment dark frame");
  a->add_option("--gain", o->gain_e_per_dn, "Photons per code value")->capture_default_str();
  a->add_option("--defocus-um", o->defocus_um, "Focal-plane position of the plane studied, um")
      ->capture_default_str();
  a->add_option("--max-divisor", o->max_divisor, "Smallest fraction 1/N")->capture_default_str();
  a->add_option("--reference-factor", o->reference_factor, "Reference rays / photon-matched rays")
      ->capture_default_str();
  a->add_option("--threads", o->threads, "Worker threads");
  a->add_option("-o,--output", o->output_dir, "Output folder")->capture_default_str();
  a->callback([o, exit_code] {
    *exit_code = RunGuarded([&] {
      pipeline::AccuracyOptions ao = *o;
      ao.output_dir = RankOutput(ao.output_dir);
      const auto r = pipeline::RunAccuracyStudy(ao);
      std::cout << "fraction  rays  seconds  rays/s  rel.noise  MS-SSIM(ref)";
      if (!r.rows.empty() && !r.rows[0].vs_experiment.empty()) std::cout << "  MS-SSIM(exp)";
      std::cout << "\n";
      for (const auto& row : r.rows) {
        std::cout << row.fraction << "  " << row.rays << "  " << row.seconds << "  "
                  << row.rays_per_second << "  " << row.relative_shot_noise << "  "
                  << row.vs_reference[2];
        if (!row.vs_experiment.empty()) std::cout << "  " << row.vs_experiment[2];
        std::cout << "\n";
      }
      std::cout << "wrote " << r.csv << " and " << r.plot << "\n";
      return 0;
    });
  });

  auto fc = std::make_shared<pipeline::FitCostOptions>();
  CLI::App* f = bench->add_subcommand(
      "fit",
      "What accuracy costs in time for a fit: FIT_FILE over --realisations independent noise\n"
      "realisations of --truth (each plane traced photon-matched with seed SEED_BASE + k, so\n"
      "there is no model mismatch) at the fit file's settings and at each value of the lists\n"
      "below, one knob at a time; per setting the mean and RMS error in Cramer-Rao bounds,\n"
      "RMS(error / sigma) and the time per fit. The fit file's images give each plane's defocus\n"
      "and size (their pixels are replaced; no camera read-out). Writes fit_cost.csv,\n"
      "fits.csv, fit_cost.json and fit_cost.png (RMS error / bound against seconds per fit).");
  f->add_option("fit_file", fc->fit_file, "Fit file (docs/fit.md), error = \"poisson\"")
      ->required()
      ->check(CLI::ExistingFile);
  f->add_option("--truth", fc->truth_scene,
                "Scene that makes the experiments (the truth); its [trace] photons_per_pixel\n"
                "is the experiments' flat-field level (refused 3x off the fit images' border)")
      ->required()
      ->check(CLI::ExistingFile);
  f->add_option("--calibration", fc->calibration, "Calibration for the fit's and the truth's scene")
      ->check(CLI::ExistingFile);
  f->add_option("-k,--realisations", fc->realisations, "Noise realisations (>= 2)")
      ->capture_default_str();
  f->add_option("--seed-base", fc->seed_base, "Experiment k's ray streams: seed SEED_BASE + k")
      ->capture_default_str();
  f->add_option("--ray-factors", fc->ray_factors, "Settings: simulated rays per photon")
      ->delimiter(',');
  f->add_option("--jacobian-seeds", fc->jacobian_seeds, "Settings: derivative sets (2-64)")
      ->delimiter(',');
  f->add_option("--repeat-seeds", fc->repeat_seeds, "Settings: repeated final fits (0 or >= 2)")
      ->delimiter(',');
  f->add_option("--last-fractions", fc->last_fractions,
                "Settings: the final ray fraction (of the photon-matched rays)")
      ->delimiter(',');
  f->add_option("--threads", fc->threads, "Worker threads (0: all cores)");
  f->add_option("-o,--output", fc->output_dir, "Output folder")->capture_default_str();
  f->callback([fc, exit_code] {
    *exit_code = RunGuarded([&] {
      pipeline::FitCostOptions fo = *fc;
      fo.output_dir = RankOutput(fo.output_dir);
      const auto r = pipeline::RunFitCostStudy(fo);
      std::cout << "setting  fits  s/fit";
      for (const std::string& k : r.keys) std::cout << "  " << k << " (mean, RMS /CRB; RMS /sigma)";
      std::cout << "\n";
      for (const auto& s : r.settings) {
        std::ostringstream v;
        v << s.value;
        std::cout << s.knob << (s.knob == "as written" ? "" : " " + v.str()) << "  " << s.fits
                  << "  " << s.mean_seconds;
        const auto N = [](double x) {  // "-" where no bound or sigma gave a number
          std::ostringstream t;
          t.precision(3);
          if (std::isfinite(x)) t << x;
          return std::isfinite(x) ? t.str() : std::string("-");
        };
        for (size_t i = 0; i < s.rms_error_over_crb.size(); ++i)
          std::cout << "  " << N(s.mean_error_over_crb[i]) << ", " << N(s.rms_error_over_crb[i])
                    << "; " << N(s.rms_error_over_sigma[i]);
        std::cout << "\n";
      }
      std::cout << "wrote " << r.csv << ", " << r.fits_csv
                << (r.plot.empty() ? "" : " and " + r.plot) << "\n";
      return 0;
    });
  });

  struct GridOptions {
    std::string fit_file, calibration, output = "bench-fit-grid";
    std::vector<double> fractions{1.0 / 1024, 1.0 / 256, 1.0 / 64, 1.0 / 16, 0.25, 1.0};
    std::vector<std::string> errors{"poisson", "mse", "ms-ssim", "cw-ssim"};
    int threads = 0;
  };
  auto g = std::make_shared<GridOptions>();
  CLI::App* gs = bench->add_subcommand(
      "fit-grid",
      "The paper's Fig. 9 study: evaluate a grid fit file at each ray fraction with each error\n"
      "function; report evaluations per second and where each optimum lands. Writes\n"
      "OUTPUT/grid_study.csv.");
  gs->add_option("fit_file", g->fit_file, "Fit file with method = \"grid\" (docs/fit.md)")
      ->required()
      ->check(CLI::ExistingFile);
  gs->add_option("--calibration", g->calibration, "Calibration file for the fit's scene");
  gs->add_option("--fractions", g->fractions, "Ray fractions (of the photon-matched rays)")
      ->delimiter(',');
  gs->add_option("--errors", g->errors, "Error functions: poisson, mse, ssim, ms-ssim, cw-ssim")
      ->delimiter(',');
  gs->add_option("--threads", g->threads, "Worker threads");
  gs->add_option("-o,--output", g->output, "Output folder")->capture_default_str();
  gs->callback([g, exit_code] {
    *exit_code = RunGuarded([&] {
      const fit::FitSpec spec = fit::LoadFitSpec(g->fit_file, "", g->calibration);
      std::vector<fit::ErrorFunction> errors;
      for (const std::string& e : g->errors) {
        const std::vector<std::pair<std::string, fit::ErrorFunction>> names = {
            {"poisson", fit::ErrorFunction::kPoisson},
            {"mse", fit::ErrorFunction::kMse},
            {"ssim", fit::ErrorFunction::kSsim},
            {"ms-ssim", fit::ErrorFunction::kMsSsim},
            {"cw-ssim", fit::ErrorFunction::kCwSsim}};
        auto it =
            std::find_if(names.begin(), names.end(), [&](const auto& n) { return n.first == e; });
        if (it == names.end()) throw Error("--errors: unknown error function '" + e + "'");
        errors.push_back(it->second);
      }
      fit::FitOptions fo;
      fo.threads = g->threads;
      const auto rows = fit::RunGridStudy(spec, g->fractions, errors, fo);
      std::ostringstream csv;
      csv << "error,fraction,bin,evaluations,seconds,evaluations_per_second";
      for (const auto& p : spec.parameters) csv << "," << p.key;
      csv << "\n";
      for (const auto& r : rows) {
        csv << r.error << "," << r.fraction << "," << r.bin << "," << r.evaluations << ","
            << r.seconds << "," << r.evaluations / std::max(r.seconds, 1e-9);
        for (double v : r.best) csv << "," << v;
        csv << "\n";
      }
      const std::string out = RankOutput(g->output);
      EnsureDirectory(out);
      WriteTextFileAtomic(std::filesystem::path(out) / "grid_study.csv", csv.str());
      std::cout << csv.str() << "wrote " << g->output << "/grid_study.csv\n";
      return 0;
    });
  });
}

}  // namespace raymatch::apps
