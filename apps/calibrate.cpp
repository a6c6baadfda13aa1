// raymatch calibrate lightfield|corrector: measured illumination and angular losses -> one
// calibration file (docs/calibration.md).
#include <iostream>

#include "commands.h"
#include "raymatch/calibrate/corrector.h"
#include "raymatch/calibrate/lightfield.h"
#include "raymatch/core/calibration_file.h"

namespace raymatch::apps {

void RegisterCalibrate(CLI::App& app, int* exit_code) {
  CLI::App* cal = app.add_subcommand(
      "calibrate", "Calibrate the microscope model from measurements (docs/calibration.md)");
  cal->require_subcommand(1);

  struct LfOpts {
    std::string folder, output = "calibration.toml";
    calibrate::LightFieldOptions o;
  };
  auto lf = std::make_shared<LfOpts>();
  CLI::App* l = cal->add_subcommand(
      "lightfield",
      "Light-field source from a pinhole image and light-cone images at known defocus.\n"
      "FOLDER holds the images and metadata.toml (docs/sample-data-format.md).");
  l->add_option("folder", lf->folder, "Input folder")->required()->check(CLI::ExistingDirectory);
  l->add_option("-o,--output", lf->output, "Calibration file to write (TOML + sidecars)")->capture_default_str();
  l->add_option("--map-size", lf->o.map_size, "Angular map cells per side")->capture_default_str();
  l->add_option("--extrapolate-to-deg", lf->o.extrapolate_to_deg,
                "Continue the radiance beyond the objective NA up to this half-angle (deg)");
  l->callback([lf, exit_code] {
    *exit_code = RunGuarded([&] {
      const auto s = calibrate::CalibrateLightField(calibrate::ReadLightFieldInput(lf->folder), lf->o);
      WriteCalibrationFile(lf->output, s.data);
      std::cout << s.BriefReport() << "wrote " << lf->output << "\n";
      return 0;
    });
  });

  struct CoOpts {
    std::string folder, output = "calibration.toml", base;
    calibrate::CorrectorOptions o;
  };
  auto co = std::make_shared<CoOpts>();
  CLI::App* c = cal->add_subcommand(
      "corrector",
      "Angular-corrector zone transmissions from a flat-field iris series, each flat with its\n"
      "cone image (same lamp exposure). --base adds the corrector to an existing calibration.");
  c->add_option("folder", co->folder, "Input folder")->required()->check(CLI::ExistingDirectory);
  c->add_option("-o,--output", co->output, "Calibration file to write")->capture_default_str();
  c->add_option("--base", co->base, "Existing calibration file to extend (e.g. from lightfield)");
  c->add_option("--zones", co->o.zones, "Central disc + rings")->capture_default_str();
  c->add_option("--smoothness", co->o.smoothness, "Second-difference penalty weight")->capture_default_str();
  c->add_option("--distance-mm", co->o.distance_mm, "Corrector plane from the focal plane (default: WD)");
  c->callback([co, exit_code] {
    *exit_code = RunGuarded([&] {
      CalibrationData base;
      if (!co->base.empty()) base = ReadCalibrationFile(co->base);
      const auto s = calibrate::CalibrateCorrector(calibrate::ReadFlatFieldInput(co->folder), co->o,
                                                   co->base.empty() ? nullptr : &base);
      WriteCalibrationFile(co->output, s.data);
      std::cout << s.BriefReport() << "wrote " << co->output << "\n";
      return 0;
    });
  });
}

}  // namespace raymatch::apps
