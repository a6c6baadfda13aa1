// raymatch run: the main job (calibrate -> simulate -> compare -> report).
#include <unistd.h>

#include <iostream>

#include "commands.h"
#include "mpi_session.h"
#include "raymatch/core/cluster.h"
#include "raymatch/pipeline/pipeline.h"

namespace raymatch::apps {

void RegisterRun(CLI::App& app, int* exit_code) {
  auto o = std::make_shared<pipeline::PipelineOptions>();
  CLI::App* sub = app.add_subcommand(
      "run",
      "The main job from one pipeline file (docs/pipeline.md): calibrate the light field and the\n"
      "corrector, simulate the experiment's focus scan with that calibration, run the focus-scan\n"
      "test, run the fits and write index.html. Unchanged steps are reused.\n"
      "Exit: 0 every check passes; 1 a check needs attention (a focus-scan warning, a model\n"
      "mismatch in the corrector or sphere calibration or a fit, a fit not converged or\n"
      "without sigmas); 2 the focus-scan test fails; 3 and above: an error.");
  sub->add_option("pipeline", o->pipeline_file, "Pipeline file (.toml)")
      ->required()
      ->check(CLI::ExistingFile);
  sub->add_option("-o,--output", o->output_dir, "Output folder (default: the file's `output`)");
  sub->add_option("--ray-fraction", o->ray_fraction,
                  "Fraction of the photon-matched ray count (e.g. 0.0625 for a quick look)");
  sub->add_option("--threads", o->threads, "Worker threads (default: all cores)");
  sub->add_flag("--force", o->force, "Recompute every step");
  auto progress = std::make_shared<bool>(false), quiet = std::make_shared<bool>(false);
  sub->add_flag("--progress", *progress, "Always show progress bars on stderr (default: on a TTY)");
  sub->add_flag("-q,--quiet", *quiet, "No summary, no step messages and no progress");
  sub->callback([o, progress, quiet, exit_code] {
    // As `simulate`: progress bars (carriage returns) only on a terminal unless asked for, so
    // that a log file holds lines; the one-line step messages stay unless --quiet.
    o->progress = *progress || (!*quiet && isatty(STDERR_FILENO));
    o->steps = !*quiet;
    *exit_code = RunGuarded(
        [&] {
          pipeline::PipelineOptions po = *o;
          po.output_dir = RankOutput(po.output_dir);
          // Under MPI every rank runs every step: reuse decisions from each rank's own folder
          // could differ, and the ranks must trace the same images in the same order.
          if (GetCluster().size > 1) po.force = true;
          const auto s = pipeline::RunPipeline(po);
          if (*quiet) return s.status;
          std::cout << "raymatch run: cone half-angle " << s.cone_half_angle_deg
                    << " deg; exposure " << s.photons_per_pixel
                    << " photons/pixel\nverdict: " << s.Overall() << "\n";
          for (const pipeline::PipelineCheck& c : s.checks)
            std::cout << "  " << (c.ok ? "ok    " : "CHECK ") << c.name << ": " << c.result << "\n";
          std::cout << "  report: " << s.report << "\n";
          return s.status;
        },
        3);
  });
}

}  // namespace raymatch::apps
