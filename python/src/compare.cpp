// Python bindings of the compare library: each measure with its options, the CLI's `compare`
// result as a dict, and the focus-scan test (apps/compare.cpp, apps/compare_scan.cpp).
#include "common.h"
#include "raymatch/compare/focus_scan.h"
#include "raymatch/compare/measures.h"

namespace raymatch::python {

namespace {

using compare::CompareError;
using compare::FailureKind;

struct Pair {
  Image a, b;
};

/// Both images as the library wants them; the same checks as `raymatch compare` (size, NaN).
Pair Images(const py::handle& a, const py::handle& b) {
  Pair p{FromArray(a, "a"), FromArray(b, "b")};
  compare::CheckComparable(p.a, p.b, "a vs b");
  return p;
}

compare::MsSsimOptions MsOptions(double data_range, int scales, const py::object& weights,
                                 double sigma, double k1, double k2) {
  compare::MsSsimOptions o;
  o.data_range = data_range;
  o.num_scales = scales;
  o.sigma = sigma;
  o.k1 = k1;
  o.k2 = k2;
  if (py::isinstance<py::str>(weights)) {
    const std::string w = weights.cast<std::string>();
    if (w == compare::MsSsimWeightsName(compare::MsSsimWeights::kMatlab)) {
      o.weights = compare::MsSsimWeights::kMatlab;
    } else if (w == compare::MsSsimWeightsName(compare::MsSsimWeights::kWang2003)) {
      o.weights = compare::MsSsimWeights::kWang2003;
    } else {
      throw CompareError(
          FailureKind::kInvalidInput,
          "ms_ssim weights must be 'matlab', 'wang2003' or a list of numbers, got '" + w + "'");
    }
  } else {
    o.weights = compare::MsSsimWeights::kCustom;
    o.custom_weights = weights.cast<std::vector<double>>();
  }
  return o;
}

compare::CwSsimOptions CwOptions(double data_range, int level, int orientations, double k,
                                 int guard_band, int window) {
  compare::CwSsimOptions o;
  o.data_range = data_range;
  o.level = level;
  o.orientations = orientations;
  o.k = k;
  o.guard_band = guard_band;
  o.window = window;
  return o;
}

py::dict MsToDict(const compare::MsSsimResult& r, const compare::MsSsimOptions& o) {
  py::list scales;
  for (const auto& s : r.scales) {
    py::dict d;
    d["width"] = s.width;
    d["height"] = s.height;
    d["weight"] = s.weight;
    d["cs"] = s.cs;
    d["ssim"] = s.ssim;
    scales.append(d);
  }
  py::dict d;
  d["value"] = r.ms_ssim;
  d["scales_used"] = r.num_scales;
  d["max_scales"] = r.max_scales;
  d["weights"] = compare::MsSsimWeightsName(o.weights);
  d["sigma_px"] = o.sigma;
  d["per_scale"] = scales;
  return d;
}

py::dict CwToDict(const compare::CwSsimResult& r, const compare::CwSsimOptions& o) {
  py::dict d;
  d["value"] = r.cw_ssim;
  d["level"] = r.level;
  d["max_level"] = r.max_level;
  d["orientations"] = o.orientations;
  d["k"] = o.k;
  d["window_px"] = o.window;
  d["per_orientation"] = r.per_orientation;
  return d;
}

py::dict PoissonToDict(const compare::PoissonResult& r) {
  py::dict d;
  d["chi2_per_pixel"] = r.chi2_per_pixel;
  d["deviance_per_pixel"] = r.deviance_per_pixel;
  d["clamped_pixels"] = r.clamped_pixels;
  return d;
}

const char* VerdictName(compare::Verdict v) {
  return v == compare::Verdict::kPass      ? "pass"
         : v == compare::Verdict::kWarning ? "warning"
                                           : "fail";
}

compare::Measure MeasureFromName(const std::string& n) {
  for (auto m : {compare::Measure::kMse, compare::Measure::kSsim, compare::Measure::kMsSsim,
                 compare::Measure::kCwSsim, compare::Measure::kPoissonChi2})
    if (n == compare::MeasureName(m)) return m;
  throw CompareError(
      FailureKind::kInvalidInput,
      "unknown measure '" + n + "'; expected mse, ssim, ms_ssim, cw_ssim or poisson_chi2");
}

compare::Stack MakeStack(const std::vector<double>& defocus_um, const py::iterable& images,
                         const std::vector<std::string>& files, double pixel_um, const char* what) {
  compare::Stack s;
  s.object_pixel_um = pixel_um;
  s.defocus_um = defocus_um;
  s.images = FromArrays(images, what);
  s.files = files;
  if (s.files.empty())
    for (size_t i = 0; i < s.images.size(); ++i)
      s.files.push_back(std::string(what) + "[" + std::to_string(i) + "]");
  if (s.images.size() != s.defocus_um.size() || s.files.size() != s.images.size())
    throw CompareError(FailureKind::kInvalidInput,
                       std::string(what) + ": " + std::to_string(s.images.size()) + " images but " +
                           std::to_string(s.defocus_um.size()) + " defocus values");
  return s;
}

}  // namespace

void BindCompare(py::module_& m) {
  const auto a = py::arg("a"), b = py::arg("b");
  m.def(
      "mse",
      [](const py::object& x, const py::object& y) {
        const Pair p = Images(x, y);
        return compare::MeanSquaredError(p.a, p.b);
      },
      a, b, "Mean squared difference, in (pixel value units)^2.");
  m.def(
      "psnr",
      [](const py::object& x, const py::object& y, double L) {
        const Pair p = Images(x, y);
        if (!(L > 0))
          throw CompareError(FailureKind::kInvalidInput, "data_range L must be > 0 (pixel units)");
        return compare::PeakSignalToNoiseRatio(p.a, p.b, L);
      },
      a, b, py::arg("data_range"),
      "10 log10(L^2 / MSE) in dB (capped at 999 dB for identical images).");
  m.def(
      "ssim",
      [](const py::object& x, const py::object& y, double L, double sigma, double k1, double k2,
         bool full) -> py::object {
        const Pair p = Images(x, y);
        compare::SsimOptions o;
        o.data_range = L;
        o.sigma = sigma;
        o.k1 = k1;
        o.k2 = k2;
        o.keep_map = full;
        compare::SsimResult r;
        {
          py::gil_scoped_release nogil;
          r = compare::Ssim(p.a, p.b, o);
        }
        if (!full) return py::float_(r.ssim);
        py::dict d;
        d["ssim"] = r.ssim;
        d["mean_luminance"] = r.mean_luminance;
        d["mean_cs"] = r.mean_cs;
        d["map"] = ToArray(std::move(r.map));
        return d;
      },
      a, b, py::arg("data_range"), py::arg("sigma") = 1.5, py::arg("k1") = 0.01,
      py::arg("k2") = 0.03, py::arg("full") = false,
      "SSIM exactly as MATLAB ssim() (Gaussian window sigma in pixels, replicate padding, mean "
      "over "
      "the whole map; docs/compare.md). full=True returns a dict with the map and the mean "
      "luminance and contrast-structure terms.");
  m.def(
      "ms_ssim",
      [](const py::object& x, const py::object& y, double L, int scales, const py::object& weights,
         double sigma, double k1, double k2) {
        const Pair p = Images(x, y);
        const auto o = MsOptions(L, scales, weights, sigma, k1, k2);
        compare::MsSsimResult r;
        {
          py::gil_scoped_release nogil;
          r = compare::MsSsim(p.a, p.b, o);
        }
        return MsToDict(r, o);
      },
      a, b, py::arg("data_range"), py::arg("scales") = 0, py::arg("weights") = "matlab",
      py::arg("sigma") = 1.5, py::arg("k1") = 0.01, py::arg("k2") = 0.03,
      "MS-SSIM as MATLAB multissim(); scales 0 = one below the most the size allows; weights "
      "'matlab', 'wang2003' or a list (normalised). Returns a dict with 'value' and per-scale "
      "terms.");
  m.def(
      "cw_ssim",
      [](const py::object& x, const py::object& y, double L, int level, int orientations, double k,
         int guard_band, int window) {
        const Pair p = Images(x, y);
        const auto o = CwOptions(L, level, orientations, k, guard_band, window);
        compare::CwSsimResult r;
        {
          py::gil_scoped_release nogil;
          r = compare::CwSsim(p.a, p.b, o);
        }
        return CwToDict(r, o);
      },
      a, b, py::arg("data_range"), py::arg("level") = 0, py::arg("orientations") = 16,
      py::arg("k") = 0.0, py::arg("guard_band") = 0, py::arg("window") = 7,
      "CW-SSIM as cwssim_index.m (level 0 = one below the maximum; k in (0..255-scaled "
      "coefficient)^2; guard_band in full-resolution pixels; window in band pixels).");
  m.def(
      "poisson",
      [](const py::object& x, const py::object& y) {
        const Pair p = Images(x, y);
        return PoissonToDict(compare::PoissonMeasures(p.a, p.b));
      },
      a, b,
      "Poisson chi-square and deviance per pixel of two photon-count images (~1 when they agree).");
  m.def(
      "compare",
      [](const py::object& x, const py::object& y, double L, int ms_scales,
         const py::object& ms_weights, double ms_sigma, int cw_level, int cw_orientations,
         double cw_k) {
        // apps/compare.cpp's RunCompare, the same JSON fields except the file names.
        const Pair p = Images(x, y);
        if (!(L > 0) || !std::isfinite(L))
          throw CompareError(
              FailureKind::kInvalidInput,
              "the data range L must be a number > 0 in pixel units, e.g. 4095 for 12-bit "
              "data or 65535 for 16-bit; got " +
                  std::to_string(L));
        compare::SsimOptions so;
        so.data_range = L;
        const auto mo = MsOptions(L, ms_scales, ms_weights, ms_sigma, 0.01, 0.03);
        const auto co = CwOptions(L, cw_level, cw_orientations, cw_k, 0, 7);
        compare::SsimResult ssim;
        compare::MsSsimResult ms;
        compare::CwSsimResult cw;
        compare::PoissonResult po;
        double mse = 0, psnr = 0;
        {
          py::gil_scoped_release nogil;
          ssim = compare::Ssim(p.a, p.b, so);
          ms = compare::MsSsim(p.a, p.b, mo);
          cw = compare::CwSsim(p.a, p.b, co);
          po = compare::PoissonMeasures(p.a, p.b);
          mse = compare::MeanSquaredError(p.a, p.b);
          psnr = compare::PeakSignalToNoiseRatio(p.a, p.b, L);
        }
        py::dict d;
        d["data_range"] = L;
        d["mse"] = mse;
        d["psnr_db"] = psnr;
        d["ssim"] = ssim.ssim;
        d["ms_ssim"] = MsToDict(ms, mo);
        d["cw_ssim"] = CwToDict(cw, co);
        d["poisson"] = PoissonToDict(po);
        return d;
      },
      a, b, py::arg("data_range"), py::arg("ms_ssim_scales") = 0,
      py::arg("ms_ssim_weights") = "matlab", py::arg("ms_ssim_sigma") = 1.5,
      py::arg("cw_ssim_level") = 0, py::arg("cw_ssim_orientations") = 16,
      py::arg("cw_ssim_k") = 0.0,
      "All measures of `raymatch compare A B -L data_range` as a dict (the CLI's JSON without the "
      "file names). data_range L is in pixel units (4095 for 12-bit data in 16-bit files).");

  m.def(
      "_read_stack",
      [](const py::object& path) {
        compare::Stack s = compare::ReadStack(PathArg(path));
        py::list images;
        for (auto& img : s.images) images.append(ToArray(std::move(img)));
        return py::make_tuple(s.defocus_um, images, s.files, s.object_pixel_um);
      },
      py::arg("index"));

  py::class_<compare::FocusScanResult>(m, "FocusScanResult",
                                       "Result of raymatch.focus_scan (docs/compare.md)")
      .def_property_readonly(
          "verdict", [](const compare::FocusScanResult& r) { return VerdictName(r.verdict); },
          "'pass', 'warning' (some primary measures fail) or 'fail'")
      .def_property_readonly(
          "exit_code",
          [](const compare::FocusScanResult& r) { return static_cast<int>(r.verdict); },
          "The exit status `raymatch compare-scan` gives: 0 pass, 1 warning, 2 fail")
      .def_readonly("message", &compare::FocusScanResult::message)
      .def_readonly("exp_defocus_um", &compare::FocusScanResult::exp_defocus_um)
      .def_readonly("sim_defocus_um", &compare::FocusScanResult::sim_defocus_um)
      .def_readonly("data_range", &compare::FocusScanResult::data_range)
      .def_readonly("shift_px", &compare::FocusScanResult::shift_px,
                    "(x, y) shift applied to the experiment, pixels")
      .def_readonly("sim_scale", &compare::FocusScanResult::sim_scale,
                    "factor applied to the simulation")
      .def_property_readonly("registration", &compare::FocusScanResult::RegistrationSummary)
      .def_property_readonly(
          "measures",
          [](const compare::FocusScanResult& r) {
            py::dict out;
            for (const auto& ms : r.measures) {
              py::dict d;
              d["matrix"] = ToMatrix(ms.matrix);
              d["best"] = ms.best;
              d["expected"] = ms.expected;
              d["passes"] = ms.passes;
              d["higher_is_better"] = compare::HigherIsBetter(ms.measure);
              out[compare::MeasureName(ms.measure)] = d;
            }
            return out;
          },
          "{measure: {'matrix' [experiment plane, simulation plane], 'best', 'expected', 'passes', "
          "'higher_is_better'}}")
      .def_property_readonly(
          "exp_images",
          [](py::object self) {
            py::list l;
            for (const auto& img : self.cast<const compare::FocusScanResult&>().exp_images)
              l.append(ViewArray(img, self));
            return l;
          },
          "Prepared experimental images (photons), read-only views")
      .def_property_readonly(
          "sim_images",
          [](py::object self) {
            py::list l;
            for (const auto& img : self.cast<const compare::FocusScanResult&>().sim_images)
              l.append(ViewArray(img, self));
            return l;
          },
          "Simulated images as compared (scaled), read-only views")
      .def(
          "to_dict", [](const compare::FocusScanResult& r) { return ToPython(r.ToJson()); },
          "The content of compare_scan.json")
      .def(
          "write_report",
          [](const compare::FocusScanResult& r, const py::object& dir, const std::string& title) {
            const std::string d = PathArg(dir);
            py::gil_scoped_release nogil;
            return compare::WriteFocusScanReport(r, d, title);
          },
          py::arg("directory"), py::arg("title") = "raymatch focus-scan test",
          "Writes what `raymatch compare-scan` writes (JSON, CSV, heatmaps, montage, report.html) "
          "into directory; returns the report's path.")
      .def("__repr__", [](const compare::FocusScanResult& r) {
        return std::string("<raymatch.FocusScanResult ") + VerdictName(r.verdict) + ": " +
               r.message + ">";
      });

  m.def(
      "_focus_scan",
      [](const std::vector<double>& exp_z, const py::iterable& exp_images,
         const std::vector<std::string>& exp_files, double exp_pixel_um,
         const std::vector<double>& sim_z, const py::iterable& sim_images,
         const std::vector<std::string>& sim_files, double sim_pixel_um, double L,
         const std::string& dark, const std::string& flat, double gain,
         std::optional<std::array<int, 4>> roi, bool register_shift, bool normalize, int ms_scales,
         const py::object& ms_weights, double ms_sigma, int cw_level, int cw_orientations,
         double cw_k, std::optional<std::vector<std::string>> measures,
         std::optional<std::vector<std::string>> primary, double pixel_um) {
        const compare::Stack e =
            MakeStack(exp_z, exp_images, exp_files, exp_pixel_um, "experiment");
        const compare::Stack s =
            MakeStack(sim_z, sim_images, sim_files, sim_pixel_um, "simulation");
        compare::FocusScanOptions o;
        o.object_pixel_um = pixel_um;
        o.prepare.roi = roi;
        o.prepare.dark_file = dark;
        o.prepare.flat_file = flat;
        o.prepare.gain_e_per_dn = gain;
        o.data_range = L;
        o.register_shift = register_shift;
        o.normalize_background = normalize;
        o.ms_ssim = MsOptions(0, ms_scales, ms_weights, ms_sigma, 0.01, 0.03);
        o.cw_ssim = CwOptions(0, cw_level, cw_orientations, cw_k, 0, 7);
        if (measures) {
          o.measures.clear();
          for (const auto& n : *measures) o.measures.push_back(MeasureFromName(n));
        }
        if (primary) {
          o.primary.clear();
          for (const auto& n : *primary) o.primary.push_back(MeasureFromName(n));
        }
        py::gil_scoped_release nogil;
        return compare::RunFocusScan(e, s, o);
      },
      py::arg("exp_defocus_um"), py::arg("exp_images"), py::arg("exp_files"),
      py::arg("exp_pixel_um"), py::arg("sim_defocus_um"), py::arg("sim_images"),
      py::arg("sim_files"), py::arg("sim_pixel_um"), py::arg("data_range"), py::arg("dark"),
      py::arg("flat"), py::arg("gain"), py::arg("roi"), py::arg("register_shift"),
      py::arg("normalize"), py::arg("ms_ssim_scales"), py::arg("ms_ssim_weights"),
      py::arg("ms_ssim_sigma"), py::arg("cw_ssim_level"), py::arg("cw_ssim_orientations"),
      py::arg("cw_ssim_k"), py::arg("measures"), py::arg("primary"), py::arg("pixel_um") = 0.0);
}

}  // namespace raymatch::python
