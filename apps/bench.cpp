// raymatch bench accuracy: what accuracy costs in time (docs/performance.md).
#include <iostream>

#include "commands.h"
#include "raymatch/pipeline/accuracy.h"

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
  a->add_option("scene", o->scene_file, "Scene (e.g. out/sample/scene.toml from raymatch run)")->required()->check(CLI::ExistingFile);
  a->add_option("--experiment", o->experiment_csv, "Experimental stack (defocus_um,file)");
  a->add_option("--dark", o->dark_file, "Experiment dark frame");
  a->add_option("--gain", o->gain_e_per_dn, "Photons per code value")->capture_default_str();
  a->add_option("--defocus-um", o->defocus_um, "Plane studied")->capture_default_str();
  a->add_option("--max-divisor", o->max_divisor, "Smallest fraction 1/N")->capture_default_str();
  a->add_option("--reference-factor", o->reference_factor, "Reference rays / photon-matched rays")->capture_default_str();
  a->add_option("--threads", o->threads, "Worker threads");
  a->add_option("-o,--output", o->output_dir, "Output folder")->capture_default_str();
  a->callback([o, exit_code] {
    *exit_code = RunGuarded([&] {
      const auto r = pipeline::RunAccuracyStudy(*o);
      std::cout << "fraction  rays  seconds  rays/s  rel.noise  MS-SSIM(ref)";
      if (!r.rows.empty() && !r.rows[0].vs_experiment.empty()) std::cout << "  MS-SSIM(exp)";
      std::cout << "\n";
      for (const auto& row : r.rows) {
        std::cout << row.fraction << "  " << row.rays << "  " << row.seconds << "  " << row.rays_per_second
                  << "  " << row.relative_shot_noise << "  " << row.vs_reference[2];
        if (!row.vs_experiment.empty()) std::cout << "  " << row.vs_experiment[2];
        std::cout << "\n";
      }
      std::cout << "wrote " << r.csv << " and " << r.plot << "\n";
      return 0;
    });
  });
}

}  // namespace raymatch::apps
