// Python bindings of the calibrate and fit libraries (apps/calibrate.cpp, apps/fit.cpp).
#include "common.h"
#include "raymatch/calibrate/corrector.h"
#include "raymatch/calibrate/lightfield.h"
#include "raymatch/core/calibration_file.h"
#include "raymatch/fit/fit.h"
#include "raymatch/fit/sensitivity.h"
#ifdef RAYMATCH_HAVE_PIPELINE
#include "raymatch/pipeline/sphere_calibration.h"
#endif

namespace raymatch::python {

namespace {

py::dict ConeToDict(const calibrate::ConeFit& c) {
  py::dict d;
  d["apex_x_um"] = c.apex_x_um;
  d["apex_y_um"] = c.apex_y_um;
  d["apex_z_um"] = c.apex_z_um;
  d["tilt_x"] = c.tilt_x;
  d["tilt_y"] = c.tilt_y;
  d["half_angle_deg"] = c.half_angle_deg;
  d["rms_center_residual_um"] = c.rms_center_residual_um;
  d["rms_radius_residual_um"] = c.rms_radius_residual_um;
  d["radius_um"] = c.radius_um;
  d["center_x_um"] = c.center_x_um;
  d["center_y_um"] = c.center_y_um;
  d["cut_by_na"] = c.cut_by_na;
  return d;
}

}  // namespace

void BindCalibrate(py::module_& m) {
  using CD = CalibrationData;
  py::class_<CD>(
      m, "Calibration",
      "A calibration file's content (docs/calibration-format.md): light field, corrector, "
      "optics. Images are read-only NumPy views.")
      .def(py::init<>())
      .def_static(
          "read", [](const py::object& p) { return ReadCalibrationFile(PathArg(p)); },
          py::arg("path"), "Reads a calibration file strictly (with its sidecars).")
      .def(
          "write", [](const CD& d, const py::object& p) { WriteCalibrationFile(PathArg(p), d); },
          py::arg("path"), "Writes the TOML file and its sidecar TIFFs (atomically).")
      .def_property_readonly("has_light_field", &CD::has_light_field)
      .def_property_readonly("has_corrector", &CD::has_corrector)
      .def_property_readonly(
          "angular_map",
          [](py::object self) { return ViewArray(self.cast<const CD&>().angular_map, self); },
          "Angular radiance over direction cosines (u, v) in [-angular_extent, angular_extent]^2; "
          "columns u increasing, rows v decreasing")
      .def_readonly("angular_extent", &CD::angular_extent)
      .def_readonly("field_radius_um", &CD::field_radius_um)
      .def_readonly("na_limit", &CD::na_limit)
      .def_readonly("cone_half_angle_deg", &CD::cone_half_angle_deg)
      .def_property_readonly(
          "spatial_map",
          [](py::object self) { return ViewArray(self.cast<const CD&>().spatial_map, self); },
          "Relative irradiance at the object plane (empty = uniform)")
      .def_property_readonly(
          "field_size_um",
          [](const CD& d) { return py::make_tuple(d.field_size_um[0], d.field_size_um[1]); })
      .def_readonly("light_field_note", &CD::light_field_note)
      .def_readonly("ring_outer_mm", &CD::ring_outer_mm)
      .def_readonly("transmissions", &CD::transmissions)
      .def_readonly("transmission_sigma", &CD::transmission_sigma)
      .def_readonly("corrector_distance_mm", &CD::corrector_distance_mm)
      .def_readonly("objective_focal_mm", &CD::objective_focal_mm)
      .def_readonly("working_distance_mm", &CD::working_distance_mm)
      .def_readonly("na", &CD::na)
      .def_readonly("tube_focal_mm", &CD::tube_focal_mm)
      .def_readonly("pixel_pitch_um", &CD::pixel_pitch_um)
      .def_readonly("wavelength_um", &CD::wavelength_um)
      .def_readonly("edge_half_angle_deg", &CD::edge_half_angle_deg,
                    "The light field's soft edge beyond the NA (deg; 0: none)")
      .def_readonly("edge_width_deg", &CD::edge_width_deg)
      .def_property_readonly(
          "edge_tilt_deg",
          [](const CD& d) { return py::make_tuple(d.edge_tilt_deg[0], d.edge_tilt_deg[1]); })
      .def_readonly("psf_sigma_um", &CD::psf_sigma_um,
                    "The camera PSF's Gaussian sigma at the object plane (um; 0: none)")
      .def_readonly("uncertainty", &CD::key_sigma,
                    "The sigmas of the scene keys a sphere calibration fitted ([uncertainty])")
      .def_property_readonly("provenance", [](const CD& d) { return ToPython(d.provenance); });

  m.def(
      "calibrate_lightfield",
      [](const py::object& folder, int map_size, double extent, double extrapolate_to_deg) {
        calibrate::LightFieldOptions o;
        o.map_size = map_size;
        o.extent = extent;
        o.extrapolate_to_deg = extrapolate_to_deg;
        const std::string f = PathArg(folder);
        calibrate::LightFieldSummary s;
        {
          py::gil_scoped_release nogil;
          s = calibrate::CalibrateLightField(calibrate::ReadLightFieldInput(f), o);
        }
        py::dict d;
        d["calibration"] = std::move(s.data);
        d["report"] = s.BriefReport();
        d["pinhole_x_um"] = s.pinhole_x_um;
        d["pinhole_y_um"] = s.pinhole_y_um;
        d["pinhole_diameter_um"] = s.pinhole_diameter_um;
        d["cone"] = ConeToDict(s.cone);
        d["warnings"] = s.warnings;
        return d;
      },
      py::arg("folder"), py::arg("map_size") = 64, py::arg("extent") = 0.0,
      py::arg("extrapolate_to_deg") = 0.0,
      "`raymatch calibrate lightfield FOLDER`: the light-field source from a pinhole image and "
      "cone "
      "images (FOLDER/metadata.toml, docs/calibration.md). map_size: angular map cells per side; "
      "extent: map half-width in direction cosines (0 = 1.15 NA); extrapolate_to_deg: continue the "
      "radiance beyond the NA up to this half-angle (deg). Returns a dict: 'calibration' (write it "
      "with .write(path)), 'report', 'cone' fit, pinhole position (um), 'warnings'.");

  m.def(
      "calibrate_corrector",
      [](const py::object& folder, int zones, double smoothness, double distance_mm,
         const py::object& base) {
        calibrate::CorrectorOptions o;
        o.zones = zones;
        o.smoothness = smoothness;
        o.distance_mm = distance_mm;
        const std::string f = PathArg(folder);
        std::optional<CalibrationData> b;
        if (py::isinstance<CalibrationData>(base))
          b = base.cast<CalibrationData>();
        else if (!base.is_none())
          b = ReadCalibrationFile(PathArg(base));
        calibrate::CorrectorSummary s;
        {
          py::gil_scoped_release nogil;
          s = calibrate::CalibrateCorrector(calibrate::ReadFlatFieldInput(f), o, b ? &*b : nullptr);
        }
        py::dict d;
        d["report"] = s.BriefReport();
        d["calibration"] = std::move(s.data);
        d["transmissions"] = s.fit.transmissions;
        d["sigma"] = s.fit.sigma;
        d["gain"] = s.fit.gain;
        d["gain_sigma"] = s.fit.gain_sigma;
        d["reduced_chi2"] = s.fit.reduced_chi2;
        d["undetermined"] = s.fit.undetermined;
        d["message"] = s.fit.message;
        d["signal"] = s.signal;
        d["weights"] = ToMatrix(s.weights);
        d["warnings"] = s.warnings;
        return d;
      },
      py::arg("folder"), py::arg("zones") = 9, py::arg("smoothness") = 0.0,
      py::arg("distance_mm") = 0.0, py::arg("base") = py::none(),
      "`raymatch calibrate corrector FOLDER`: angular-corrector zone transmissions from a "
      "flat-field iris series. zones: central disc + rings; smoothness: second-difference penalty "
      "weight (dimensionless); distance_mm: corrector plane from the focal plane in mm (0 = the "
      "working distance); base: a calibration (path or Calibration) whose light field and optics "
      "are kept. Returns a dict: 'calibration', 'transmissions', 'sigma', 'gain', 'weights', ...");

#ifdef RAYMATCH_HAVE_PIPELINE
  m.def(
      "calibrate_sphere",
      [](const py::object& folder, const py::object& base, const py::object& output,
         const std::vector<double>& planes_um, const std::vector<double>& fractions,
         double ray_factor, bool fit_width, bool fit_psf, bool fit_tilt, const std::string& optics,
         uint64_t seed, int threads, const py::object& work_dir, bool progress) {
        pipeline::SphereCalibrationOptions o;
        o.scan_folder = PathArg(folder);
        o.base = PathArg(base);
        o.output = PathArg(output);
        if (!work_dir.is_none()) o.work_dir = PathArg(work_dir);
        o.planes_um = planes_um, o.fractions = fractions, o.ray_factor = ray_factor;
        o.fit_width = fit_width, o.fit_psf = fit_psf, o.fit_tilt = fit_tilt;
        o.optics = optics, o.seed = seed, o.threads = threads, o.progress = progress;
        pipeline::SphereCalibrationResult r;
        {
          py::gil_scoped_release nogil;
          if (progress)  // the messages print with the GIL held
            o.say = [](const std::string& line) {
              py::gil_scoped_acquire gil;
              py::print(line);
            };
          r = pipeline::CalibrateSphere(o);
        }
        py::list values;
        for (const auto& v : r.values) {
          py::dict d;
          d["key"] = v.key, d["value"] = v.value, d["sigma"] = v.sigma;
          d["cramer_rao"] = v.cramer_rao, d["at_bound"] = v.at_bound;
          values.append(d);
        }
        py::dict d;
        d["calibration"] = ReadCalibrationFile(o.output);
        d["values"] = values;
        d["edge_half_angle_deg"] = r.edge_half_angle_deg;
        d["edge_width_deg"] = r.edge_width_deg;
        d["edge_tilt_deg"] = py::make_tuple(r.edge_tilt_deg[0], r.edge_tilt_deg[1]);
        d["psf_sigma_um"] = r.psf_sigma_um;
        d["status"] = r.status;
        d["goodness"] = r.goodness;
        d["model_mismatch"] = r.mismatch;
        d["report"] = r.report;
        d["brief"] = r.Brief();
        d["seconds"] = r.seconds;
        return d;
      },
      py::arg("folder"), py::arg("base"), py::arg("output"),
      py::arg("planes_um") = std::vector<double>{},
      py::arg("fractions") = std::vector<double>{0.0625, 0.25}, py::arg("ray_factor") = 1.0,
      py::arg("fit_width") = false, py::arg("fit_psf") = true, py::arg("fit_tilt") = true,
      py::arg("optics") = "rays", py::arg("seed") = 5, py::arg("threads") = 0,
      py::arg("work_dir") = py::none(), py::arg("progress") = false,
      "`raymatch calibrate sphere FOLDER --base BASE -o OUTPUT`: the focus scan of a drop of known "
      "shape fitted for its position, radius and index and for the light field's edge beyond the "
      "NA (half-angle, width, tilt; deg) and the camera PSF (um), written into a copy of BASE "
      "(docs/calibration.md, 'Sphere calibration'). planes_um: defocus values (um) to fit "
      "(default the two nearest -R/2 and +R/2); fractions: ray fractions of the fit's levels; "
      "ray_factor: rays per photon at fraction 1; optics: 'rays' or 'mie'; work_dir: the fit's "
      "files and report (default <output stem>_sphere/). Returns a dict: 'calibration' (the "
      "written file, read back), 'values' (key, value, sigma, cramer_rao, at_bound), the edge and "
      "PSF, 'status', 'goodness', 'model_mismatch', 'report', 'brief'.");
#endif
}

namespace {

py::dict DesignDict(const fit::DesignChoice& c) {
  py::dict d;
  d["defocus_um"] = c.defocus_um;
  d["crb"] = c.crb;
  d["objective"] = c.objective;
  return d;
}

}  // namespace

void BindSensitivity(py::module_& m) {
  m.def(
      "_sensitivity",
      [](const py::object& scene, const std::vector<std::string>& keys,
         const std::vector<double>& steps, const std::vector<double>& defocus_um,
         double photons_per_pixel, double ray_factor, int sets, bool known_exposure,
         double read_noise_e, int design_planes, const std::vector<std::string>& design_keys,
         uint64_t seed, int threads, const std::string& calibration, const std::string& output) {
        fit::SensitivitySpec spec = fit::SensitivitySceneSpec(PathArg(scene), calibration);
        spec.keys = keys, spec.steps = steps, spec.defocus_um = defocus_um;
        spec.photons_per_pixel = photons_per_pixel, spec.ray_factor = ray_factor;
        spec.sets = sets, spec.exposure_nuisance = !known_exposure;
        spec.read_noise_e = read_noise_e, spec.design_planes = design_planes;
        spec.design_keys = design_keys, spec.seed = seed, spec.threads = threads;
        fit::SensitivityResult r;
        std::string report;
        {
          py::gil_scoped_release nogil;
          r = fit::RunSensitivity(spec);
          if (!output.empty()) report = fit::WriteSensitivityOutputs(spec, r, output);
        }
        py::list ks;
        for (const auto& k : r.keys) {
          py::dict d;
          d["key"] = k.key, d["unit"] = k.unit, d["value"] = k.value, d["step"] = k.step;
          d["crb"] = k.crb, d["crb_mc_error"] = k.crb_mc_error;
          d["crb_exposure_known"] = k.crb_exposure_known, d["crb_per_image"] = k.crb_per_image;
          ks.append(d);
        }
        py::list mu, dmu;
        for (auto& img : r.mu) mu.append(ToArray(std::move(img)));
        for (auto& per : r.dmu) {
          py::list l;
          for (auto& img : per) l.append(ToArray(std::move(img)));
          dmu.append(l);
        }
        py::dict d;
        d["keys"] = ks;
        d["fisher"] = ToMatrix(r.fisher);
        d["correlation"] = ToMatrix(r.correlation);
        d["exposure_relative_crb"] = r.exposure_relative_crb;
        d["defocus_um"] = r.defocus_um;
        d["mu"] = mu;
        d["dmu"] = dmu;
        d["photons_per_pixel"] = r.photons_per_pixel;
        d["rays_per_image"] = r.rays_per_image;
        d["evaluations"] = r.evaluations;
        d["seconds"] = r.seconds;
        if (design_planes > 0) {
          py::list best, top;
          for (const auto& c : r.design_best) best.append(DesignDict(c));
          for (const auto& c : r.design_top) top.append(DesignDict(c));
          py::dict design;
          design["keys"] = r.design_keys;
          design["best_per_count"] = best;
          design["top"] = top;
          design["choices_compared"] = r.design_choices;
          d["design"] = design;
        }
        d["report"] = report.empty() ? py::object(py::none()) : py::object(py::str(report));
        return d;
      },
      py::arg("scene"), py::arg("keys"), py::arg("steps"), py::arg("defocus_um"),
      py::arg("photons_per_pixel"), py::arg("ray_factor"), py::arg("sets"),
      py::arg("known_exposure"), py::arg("read_noise_e"), py::arg("design_planes"),
      py::arg("design_keys"), py::arg("seed"), py::arg("threads"), py::arg("calibration"),
      py::arg("output"));
}

void BindFit(py::module_& m) {
  m.def(
      "_fit",
      [](const py::object& fit_file, const std::string& scene, const std::string& calibration,
         int threads, bool progress, const std::string& output) {
        const std::string path = PathArg(fit_file);
        fit::FitResult r;
        std::string report;
        {
          py::gil_scoped_release nogil;
          const fit::FitSpec spec = fit::LoadFitSpec(path, scene, calibration);
          fit::FitOptions fo;
          fo.threads = threads;
          fo.progress = progress;
          r = fit::RunFit(spec, fo);
          if (!output.empty()) report = fit::WriteFitOutputs(spec, r, output);
        }
        py::list params;
        for (const auto& p : r.parameters) {
          py::dict d;
          d["key"] = p.key;
          d["unit"] = p.unit;
          d["start"] = p.start;
          d["best"] = p.best;
          d["lower"] = p.lower;
          d["upper"] = p.upper;
          d["sigma"] = p.sigma;
          d["sigma_statistical"] = p.sigma_statistical;
          d["sigma_curvature"] = p.sigma_curvature;
          d["sigma_derivatives"] = p.sigma_derivatives;
          d["sigma_simulation"] = p.sigma_simulation;
          d["score_derivative"] = p.score_derivative;
          d["sigma_repeat"] = p.sigma_repeat;
          d["sigma_cramer_rao"] = p.sigma_cramer_rao;
          d["sigma_expected"] = p.sigma_expected;
          if (p.prior_sigma > 0)
            d["prior"] = py::dict(py::arg("mean") = p.prior_mean, py::arg("sigma") = p.prior_sigma,
                                  py::arg("from") = p.prior_from);
          d["at_bound"] = p.at_bound;
          d["slice_x"] = p.slice_x;
          d["slice_error"] = p.slice_error;
          d["slice_noise"] = p.slice_noise;
          if (!p.profile_t.empty()) {
            py::dict pl;
            pl["reason"] = p.profile_reason;
            pl["lower"] = p.profile_lower;
            pl["upper"] = p.profile_upper;
            pl["lower_open"] = p.profile_lower_open;
            pl["upper_open"] = p.profile_upper_open;
            pl["t_sigma"] = p.profile_t;
            pl["delta_deviance"] = p.profile_delta;
            d["profile_likelihood"] = pl;
          } else {
            d["profile_likelihood"] = py::none();
          }
          params.append(d);
        }
        py::list evals;
        for (const auto& e : r.evaluations) {
          py::dict d;
          d["theta"] = e.theta;
          d["error"] = e.error;
          d["ray_fraction"] = e.ray_fraction;
          d["bin"] = e.bin;
          d["rays"] = e.rays;
          d["seed"] = e.seed;
          d["seconds"] = e.seconds;
          d["stage"] = fit::StageName(e.stage);
          evals.append(d);
        }
        py::list best, resid;
        for (auto& img : r.best_images) best.append(ToArray(std::move(img)));
        for (auto& img : r.residuals) resid.append(ToArray(std::move(img)));
        py::dict seconds;
        for (const auto& [k, v] : r.seconds) seconds[py::str(k)] = v;
        py::dict d;
        d["converged"] = r.converged;
        d["status"] = fit::StatusName(r.status);
        d["message"] = r.message;
        d["parameters"] = params;
        d["correlation"] = ToMatrix(r.correlation);
        d["crb_correlation"] = ToMatrix(r.crb_correlation);
        d["best_error"] = r.best_error;
        if (r.final_steps_q >= 0) d["final_steps_q"] = r.final_steps_q;
        if (r.goodness.pixels > 0) {
          const fit::GoodnessOfFit& g = r.goodness;
          py::dict gd;
          gd["deviance"] = g.deviance;
          gd["estimate_deviance"] = g.estimate_deviance;
          gd["step_to_tested_point"] = g.step;
          gd["expected_deviance"] = g.expected;
          gd["expected_deviance_sd"] = g.sd;
          gd["deviance_z"] = g.z;
          gd["reduced_deviance"] = g.reduced;
          gd["pixels"] = g.pixels;
          gd["block_chi2"] = g.block_chi2;
          gd["blocks"] = g.blocks;
          gd["block_z"] = g.block_z;
          gd["neighbour_correlation"] = g.neighbour_correlation;
          gd["neighbour_z"] = g.neighbour_z;
          gd["model_mismatch"] = g.mismatch;
          gd["sigma_inflation"] = g.sigma_inflation;
          gd["template_sets"] = g.template_sets;
          gd["verdict"] = g.verdict;
          d["goodness_of_fit"] = gd;
        }
        d["evaluations"] = evals;
        d["best_images"] = best;
        d["residuals"] = resid;
        d["grid_axes"] = r.grid_axes;
        d["grid_errors"] = r.grid_errors;
        d["seconds"] = seconds;
        d["total_seconds"] = r.total_seconds;
        d["report"] = report;
        return d;
      },
      py::arg("fit_file"), py::arg("scene"), py::arg("calibration"), py::arg("threads"),
      py::arg("progress"), py::arg("output"));
}

}  // namespace raymatch::python
