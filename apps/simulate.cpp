// raymatch simulate: trace a scene's focus scan into photon-count images.
#include <unistd.h>

#include <iostream>
#include <sstream>

#include "commands.h"
#include "mpi_session.h"
#include "raymatch/core/error.h"
#include "raymatch/simulate/scan.h"
#include "raymatch/simulate/scene.h"

namespace raymatch::apps {

namespace {

struct SimulateCliOptions {
  std::string scene_file;
  std::string output_dir = "out";
  uint64_t rays = 0;
  double photons_per_pixel = 0;
  int64_t seed = -1;
  int threads = 0;
  std::vector<double> defocus_um;
  bool quiet = false;
  bool progress = false;
  bool no_png = false;
  bool no_simd = false;
  bool compare_optics = false;
};

int RunSimulate(const SimulateCliOptions& o) {
  simulate::Scene scene = simulate::LoadScene(o.scene_file);
  if (o.seed >= 0) scene.trace.seed = static_cast<uint64_t>(o.seed);
  if (!o.defocus_um.empty()) scene.defocus_um = o.defocus_um;
  if (o.photons_per_pixel > 0) {
    scene.trace.photons_per_pixel = o.photons_per_pixel;
    scene.trace.rays = 0;
  }
  if (o.threads > 0) scene.trace.threads = o.threads;
  simulate::ValidateScene(scene);
  for (const auto& w : scene.warnings) std::cerr << "raymatch: warning: " << w << "\n";
  simulate::ScanOptions so;
  so.output_dir = RankOutput(o.output_dir);
  so.control.progress = o.progress || (!o.quiet && isatty(STDERR_FILENO));
  so.control.simd = !o.no_simd;
  if (o.rays > 0) so.rays = o.rays;
  so.write_png = !o.no_png;
  if (o.compare_optics) {
    const auto planes = simulate::CompareOptics(scene, so);
    if (!o.quiet) {
      std::cout << "raymatch simulate --compare-optics: rays against the exact wave image at "
                << scene.trace.photons_per_pixel
                << " photons per pixel (chi-square per pixel 1: within the shot noise)\n";
      for (const auto& p : planes) {
        std::cout << "  z = " << p.defocus_um << " um: chi-square per pixel " << p.chi2_per_pixel
                  << ", largest |z| " << p.max_abs_z << "  (" << p.z_image << ")\n";
        if (p.physical)
          std::cout << "           physical optics: excess chi-square per pixel " << p.chi2_physical
                    << " (0: exact), largest |z| " << p.max_abs_z_physical << "  ("
                    << p.z_physical_image << ")\n";
      }
    }
    return 0;
  }
  const simulate::ScanSummary s = simulate::RunScan(scene, so);
  if (!o.quiet) {
    std::cout << "raymatch simulate: " << s.planes.size() << " plane(s), " << s.rays_per_image
              << " rays per image, " << s.seconds << " s\n";
    for (const auto& p : s.planes)
      std::cout << "  z = " << p.defocus_um << " um: " << p.image << "  (mean " << p.mean_counts
                << " counts, " << p.seconds << " s)\n";
    std::cout << "  index: " << s.index_json << "\n";
  }
  return 0;
}

}  // namespace

void RegisterSimulate(CLI::App& app, int* exit_code) {
  auto opt = std::make_shared<SimulateCliOptions>();
  CLI::App* sub = app.add_subcommand(
      "simulate",
      "Trace a scene (TOML, see docs/scene-format.md) into photon-count images, one per focus\n"
      "plane. Writes <name>_z<defocus>um.tif (float32 counts), .png preview and .json sidecar,\n"
      "plus <name>_scan.json/.csv; with [camera.readout] also <stem>_dn.tif, the camera's 16-bit\n"
      "code values (read noise, gain, dark level, full well, bit depth). Lengths in micrometres.");
  sub->add_option("scene", opt->scene_file, "Scene file (.toml)")
      ->required()
      ->check(CLI::ExistingFile);
  sub->add_option("-o,--output", opt->output_dir, "Output directory (created if missing)")
      ->capture_default_str();
  sub->add_option("--rays", opt->rays, "Rays per image (overrides the scene)");
  sub->add_option("--photons-per-pixel", opt->photons_per_pixel,
                  "Target mean hits per flat-field pixel = camera signal (0..1) x well capacity "
                  "(e-); the ray count follows from a pilot run");
  sub->add_option("--seed", opt->seed,
                  "Random seed (same seed -> same image for any thread count)");
  sub->add_option("--threads", opt->threads, "Worker threads (default: all cores)");
  sub->add_option("--defocus-um", opt->defocus_um,
                  "Focal-plane positions in um, replacing [scan] (+ = towards the camera)")
      ->delimiter(',');
  sub->add_flag("--progress", opt->progress, "Always show progress on stderr (default: on a TTY)");
  sub->add_flag("-q,--quiet", opt->quiet, "No summary and no progress");
  sub->add_flag("--no-png", opt->no_png, "Skip PNG previews");
  sub->add_flag("--no-simd", opt->no_simd,
                "Trace one ray at a time instead of in SIMD packets (the same image bit for bit, "
                "several times slower; for comparisons and timing)");
  sub->add_flag("--compare-optics", opt->compare_optics,
                "For a sphere: the exact wave image (optics = \"mie\"), the ray image at the same "
                "photons per pixel and z = (rays - wave) / sqrt(wave) per plane (<stem>_mie.tif, "
                "_rays.tif, _z.tif/.png, <name>_optics.csv): where rays can be trusted; with "
                "optics = \"physical\" also the physical-optics image and its z "
                "(_physical.tif, _z_physical.tif/.png)");
  sub->callback([opt, exit_code] { *exit_code = RunGuarded([&] { return RunSimulate(*opt); }); });
}

}  // namespace raymatch::apps
