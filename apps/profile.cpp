// raymatch profile: the paper's Fig. 8 view, two images' counts summed over a band of rows and
// their difference with the +-1 standard-deviation shot-noise band (docs/sensitivity.md).
#include <filesystem>
#include <iostream>

#include "commands.h"
#include "raymatch/compare/band_profile.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/tracer.h"

namespace raymatch::apps {

namespace {

struct ProfileCliOptions {
  std::string a, b, rows, output = "profile";
  bool scenes = false, b_expected = false;
  double defocus_um = 0, pixel_um = 0;
};

/// An image file, or with --scenes a scene traced at --defocus-um with its own rays; B's seed is
/// its scene's + 1, so that the two images' shot noise is independent, as the band assumes.
Image Load(const std::string& path, const ProfileCliOptions& o, double* pixel_um,
           uint64_t seed_offset) {
  if (!o.scenes) return ReadImage(path);
  simulate::Scene s = simulate::LoadScene(path);
  s.trace.seed += seed_offset;
  const simulate::Simulator sim(s);
  *pixel_um = sim.object_pixel_um();
  return sim.TracePlane(o.defocus_um, 0, sim.RaysPerImage()).counts;
}

int RunProfileCommand(const ProfileCliOptions& o) {
  int r0 = 0, r1 = 0;
  const size_t colon = o.rows.find(':');
  try {
    size_t used = 0;
    if (colon == std::string::npos) throw std::invalid_argument("rows");
    r0 = std::stoi(o.rows.substr(0, colon), &used);
    if (used != colon) throw std::invalid_argument("rows");
    r1 = std::stoi(o.rows.substr(colon + 1), &used);
    if (used != o.rows.size() - colon - 1) throw std::invalid_argument("rows");
  } catch (const std::exception&) {
    throw Error("--rows: expected R0:R1 (rows R0 to R1 - 1, counted from the top), got '" + o.rows +
                "'");
  }
  double pixel_a = o.pixel_um, pixel_b = o.pixel_um;
  const Image a = Load(o.a, o, &pixel_a, 0), b = Load(o.b, o, &pixel_b, 1);
  const compare::BandProfile p = compare::RowBandProfile(a, b, r0, r1, !o.b_expected);
  const std::filesystem::path out(o.output);
  if (out.has_parent_path()) EnsureDirectory(out.parent_path());  // named on failure
  compare::WriteBandProfile(o.output, p, o.pixel_um > 0 ? o.pixel_um : pixel_a,
                            std::filesystem::path(o.a).filename().string(),
                            std::filesystem::path(o.b).filename().string());
  std::cout << "rows " << r0 << "-" << r1 - 1 << " summed over " << p.columns
            << " columns: chi-square of B - A against its shot noise " << p.chi2 << " (about "
            << p.columns << " when the noise explains it); " << o.output << ".csv, " << o.output
            << ".png\n";
  return 0;
}

}  // namespace

void RegisterProfile(CLI::App& app, int* exit_code) {
  auto o = std::make_shared<ProfileCliOptions>();
  CLI::App* c = app.add_subcommand(
      "profile",
      "The paper's Fig. 8 view: the counts of two images (photon counts, e.g. TIFFs from "
      "simulate) summed over a band of rows, column by column, and their difference B - A with "
      "the +-1 standard-deviation shot-noise band sqrt(sum A + sum B). Writes OUTPUT.csv and "
      "OUTPUT.png. docs/sensitivity.md.");
  c->add_option("a", o->a, "image A (or a scene with --scenes)")
      ->required()
      ->check(CLI::ExistingFile);
  c->add_option("b", o->b, "image B (or a scene with --scenes)")
      ->required()
      ->check(CLI::ExistingFile);
  c->add_option("--rows", o->rows, "band of rows R0:R1 (R1 not included; row 0 at the top)")
      ->required();
  c->add_flag("--scenes", o->scenes,
              "A and B are scene files: trace each at --defocus-um with its own rays (B with its "
              "scene's seed + 1: independent shot noise)");
  c->add_option("--defocus-um", o->defocus_um, "focus position for --scenes, um")
      ->capture_default_str();
  c->add_flag("--b-expected", o->b_expected,
              "B is an expectation without noise (e.g. a fit's best image): the band is "
              "sqrt(sum A)");
  c->add_option("--pixel-um", o->pixel_um,
                "pixel size at the object, um, for the x axis (default: columns; with --scenes "
                "the scene's)");
  c->add_option("-o,--output", o->output, "output path without extension")->capture_default_str();
  c->callback(
      [o, exit_code] { *exit_code = RunGuarded([&] { return RunProfileCommand(*o); }, 1); });
}

}  // namespace raymatch::apps
