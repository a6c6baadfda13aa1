// raymatch calibrate lightfield|corrector|sphere|zemax-export|zemax-import: measured illumination
// and angular losses -> one calibration file (docs/calibration.md). Thin: options -> library call.
#include <iostream>

#include "commands.h"
#include "raymatch/calibrate/corrector.h"
#include "raymatch/calibrate/lightfield.h"
#include "raymatch/calibrate/zemax_source.h"
#include "raymatch/core/calibration_file.h"
#ifdef RAYMATCH_HAVE_PIPELINE
#include "raymatch/pipeline/sphere_calibration.h"
#endif

namespace raymatch::apps {

namespace {
void PrintWarnings(const std::vector<std::string>& warnings) {
  for (const auto& w : warnings) std::cerr << "warning: " << w << "\n";
}
}  // namespace

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
      "Light-field source from a pinhole image and light-cone images at known defocus, or from\n"
      "images of a camera focused at infinity with an mrcal .cameramodel.\n"
      "FOLDER holds the images and metadata.toml (docs/calibration.md).");
  l->add_option("folder", lf->folder, "Input folder")->required()->check(CLI::ExistingDirectory);
  l->add_option("-o,--output", lf->output, "Calibration file to write (TOML + sidecar)")
      ->capture_default_str();
  l->add_option("--map-size", lf->o.map_size, "Angular map cells per side")
      ->capture_default_str()
      ->check(CLI::Range(4, 4096));
  l->add_option("--extent", lf->o.extent, "Map half-width in direction cosines (0 = 1.15 NA)")
      ->check(CLI::Range(0.0, 1.0));
  l->add_option("--extrapolate-to-deg", lf->o.extrapolate_to_deg,
                "Continue the radiance beyond the objective NA up to this half-angle (deg)")
      ->check(CLI::Range(0.0, 89.0));
  l->callback([lf, exit_code] {
    *exit_code = RunGuarded([&] {
      const auto s =
          calibrate::CalibrateLightField(calibrate::ReadLightFieldInput(lf->folder), lf->o);
      WriteCalibrationFile(lf->output, s.data);
      std::cout << s.BriefReport() << "wrote " << lf->output << "\n";
      PrintWarnings(s.warnings);
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
      "cone image (same lamp exposure). --base adds the corrector to an existing calibration\n"
      "(its light field and optics are kept) and writes a new file.");
  c->add_option("folder", co->folder, "Input folder")->required()->check(CLI::ExistingDirectory);
  c->add_option("-o,--output", co->output, "Calibration file to write")->capture_default_str();
  c->add_option("--base", co->base, "Existing calibration file to extend (e.g. from lightfield)")
      ->check(CLI::ExistingFile);
  c->add_option("--zones", co->o.zones, "Central disc + rings")
      ->capture_default_str()
      ->check(CLI::Range(2, 64));
  c->add_option("--smoothness", co->o.smoothness,
                "Second-difference penalty weight on the zone transmissions (dimensionless)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  c->add_option("--distance-mm", co->o.distance_mm,
                "Corrector plane distance from the focal plane, mm (default: the working distance)")
      ->check(CLI::NonNegativeNumber);
  c->callback([co, exit_code] {
    *exit_code = RunGuarded([&] {
      CalibrationData base;
      if (!co->base.empty()) base = ReadCalibrationFile(co->base);
      const auto s = calibrate::CalibrateCorrector(calibrate::ReadFlatFieldInput(co->folder), co->o,
                                                   co->base.empty() ? nullptr : &base);
      WriteCalibrationFile(co->output, s.data);
      std::cout << s.BriefReport() << "wrote " << co->output << "\n";
      PrintWarnings(s.warnings);
      return 0;
    });
  });

#ifdef RAYMATCH_HAVE_PIPELINE
  auto sp = std::make_shared<pipeline::SphereCalibrationOptions>();
  CLI::App* sc = cal->add_subcommand(
      "sphere",
      "Fit the focus scan of a spherical drop (several planes jointly) for its five parameters "
      "and\n"
      "the nuisances no image through the objective shows: the light field's soft edge beyond the\n"
      "NA (half-angle, width and axis tilt [x, y], deg) and the camera PSF (Gaussian sigma at the "
      "object plane, um).\n"
      "Writes --base plus these into a new calibration file (docs/calibration.md, \"Sphere\n"
      "calibration\"); the fit's files and report go to <output stem>_sphere/.");
  sc->add_option("folder", sp->scan_folder,
                 "Experiment folder: metadata.toml with the scan CSV, dark frame, nominal diameter")
      ->required()
      ->check(CLI::ExistingDirectory);
  sc->add_option("--base", sp->base,
                 "Calibration to extend (light field measured through the objective, corrector)")
      ->required()
      ->check(CLI::ExistingFile);
  sp->output = "calibration.toml";
  sc->add_option("-o,--output", sp->output, "Calibration file to write")->capture_default_str();
  sc->add_option("--planes-um", sp->planes_um,
                 "Defocus values (um) of the scan's planes to fit jointly (default: the two "
                 "nearest -R/2 and +R/2)");
  sc->add_option("--fractions", sp->fractions,
                 "Ray fractions of the fit's levels (of the photon-matched rays)")
      ->capture_default_str();
  sc->add_option("--work-dir", sp->work_dir,
                 "Folder for the fit file, scene and report (default: <output stem>_sphere/)");
  sc->add_flag("--fit-width", sp->fit_width,
               "Also fit the edge width (default: fixed at 1 deg; with two planes it is hardly "
               "separable from the half-angle and tilt)");
  sc->add_flag("!--fixed-psf", sp->fit_psf,
               "Keep the PSF at its start instead of fitting it (0.21 lambda/NA with the rays, a "
               "diffraction-limited Airy core; 0.05 lambda/NA with mie)");
  sc->add_flag("!--fixed-tilt", sp->fit_tilt,
               "Keep the edge's axis on the optical axis instead of fitting its tilt");
  sc->add_option("--optics", sp->optics,
                 "Image model of the fit: rays (a Gaussian PSF stands in for diffraction) or mie "
                 "(the exact wave image of the drop, docs/wave-optics.md; the PSF is then the "
                 "camera's blur beyond diffraction)")
      ->check(CLI::IsMember({"rays", "mie"}))
      ->capture_default_str();
  sc->add_option("--threads", sp->threads, "Threads (0 = all cores)")->capture_default_str();
  sc->callback([sp, exit_code] {
    *exit_code = RunGuarded([&] {
      sp->progress = true;
      sp->say = [](const std::string& s) { std::cerr << s << "\n"; };
      const pipeline::SphereCalibrationResult r = pipeline::CalibrateSphere(*sp);
      std::cout << r.Brief() << "report: " << r.report << "\nwrote " << sp->output << "\n";
      if (r.mismatch)
        std::cerr << "warning: the fit reports a model mismatch; the calibration may be biased\n";
      for (const auto& v : r.values)
        if (!(v.sigma > 0)) {
          std::cerr << "warning: no uncertainty for " << v.key
                    << " (the information matrix is not positive "
                       "definite: too few rays for this many parameters; more rays (--fractions) "
                       "or fewer "
                       "free nuisances)\n";
          break;
        }
      return 0;
    });
  });
#endif

  struct ZeOpts {
    std::string calibration, output;
    calibrate::ZemaxExportOptions o;
  };
  auto ze = std::make_shared<ZeOpts>();
  CLI::App* zx = cal->add_subcommand(
      "zemax-export", "Write a calibration's light field as a Zemax binary source file (.DAT)");
  zx->add_option("calibration", ze->calibration, "Calibration file")
      ->required()
      ->check(CLI::ExistingFile);
  zx->add_option("-o,--output", ze->output, "Zemax source file to write")->required();
  zx->add_option("--rays", ze->o.num_rays, "Number of rays")->capture_default_str();
  zx->add_option("--seed", ze->o.seed, "Random seed")->capture_default_str();
  zx->add_option("--field-radius-um", ze->o.field_radius_um,
                 "Field disc radius at the object plane, um (default: the calibration's)");
  zx->add_option("--flux", ze->o.flux, "Total source flux (W)")->capture_default_str();
  zx->callback([ze, exit_code] {
    *exit_code = RunGuarded([&] {
      calibrate::WriteZemaxSourceFile(
          ze->output, calibrate::SampleZemaxSource(ReadCalibrationFile(ze->calibration), ze->o));
      std::cout << "wrote " << ze->output << " (" << ze->o.num_rays << " rays, units mm)\n";
      return 0;
    });
  });

  struct ZiOpts {
    std::string source, base, output = "calibration.toml", ray_list;
    calibrate::ZemaxImportOptions o;
  };
  auto zi = std::make_shared<ZiOpts>();
  CLI::App* zm = cal->add_subcommand(
      "zemax-import",
      "Replace the light field of a calibration (--base: optics, corrector) with one from a Zemax\n"
      "binary source file, and write a new calibration file.");
  zm->add_option("source", zi->source, "Zemax source file (.DAT/.SDF)")
      ->required()
      ->check(CLI::ExistingFile);
  zm->add_option("--base", zi->base, "Calibration file giving the optics")
      ->required()
      ->check(CLI::ExistingFile);
  zm->add_option("-o,--output", zi->output, "Calibration file to write")->capture_default_str();
  zm->add_option("--map-size", zi->o.map_size, "Angular map cells per side")
      ->capture_default_str()
      ->check(CLI::Range(2, 4096));
  zm->add_option("--extent", zi->o.extent,
                 "Map half-width in direction cosines (0 = from the rays)")
      ->check(CLI::Range(0.0, 1.0));
  zm->add_option("--ray-list", zi->ray_list,
                 "Also write the rays as a .npy ray list (N x 5: x_um, y_um, u, v, weight) for a\n"
                 "scene source of type \"ray_list\": exact rays, no separable-map assumption");
  zm->callback([zi, exit_code] {
    *exit_code = RunGuarded([&] {
      const calibrate::ZemaxSourceFile zf = calibrate::ReadZemaxSourceFile(zi->source);
      const auto s =
          calibrate::ImportZemaxLightField(zf, zi->o, ReadCalibrationFile(zi->base), zi->source);
      if (!zi->ray_list.empty()) {
        uint64_t skipped = 0;
        const NdArray rays = calibrate::ZemaxRayList(zf, &skipped);
        WriteNpy(zi->ray_list, rays);
        std::cout << "wrote " << rays.shape[0] << " rays to " << zi->ray_list
                  << (skipped ? " (" + std::to_string(skipped) + " not towards +z skipped)"
                              : std::string())
                  << "\n";
      }
      WriteCalibrationFile(zi->output, s.data);
      std::cout << s.data.light_field_note << "\nwrote " << zi->output << "\n";
      PrintWarnings(s.warnings);
      return 0;
    });
  });
}

}  // namespace raymatch::apps
