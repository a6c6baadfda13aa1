// Fit outputs: fit.json, evaluations.csv, best/residual images, plots and report.html.
#include "report.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <sstream>

#include "numbers.h"
#include "raymatch/compare/plot.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/html.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/provenance.h"
#include "raymatch/fit/fit.h"

namespace raymatch::fit {

namespace fs = std::filesystem;

namespace internal {

compare::MapPlot GridLandscapeMap(const FitSpec& spec, const FitResult& res) {
  const int nx = int(res.grid_axes[1].size()), ny = int(res.grid_axes[0].size());
  Image m(nx, ny);
  for (int r = 0; r < ny; ++r)
    for (int c = 0; c < nx; ++c)
      m.at(c, r) = static_cast<float>(res.grid_errors[size_t(r) * nx + c]);
  // Each grid node is a cell centred on its value; the cells' edges are midway between nodes.
  auto edges = [](const std::vector<double>& v) {
    std::vector<double> e(v.size() + 1);
    const double h = v.size() > 1 ? v[1] - v[0] : 1;
    e.front() = v.front() - 0.5 * h;
    for (size_t k = 1; k < v.size(); ++k) e[k] = 0.5 * (v[k - 1] + v[k]);
    e.back() = v.back() + 0.5 * (v.size() > 1 ? v.back() - v[v.size() - 2] : 1);
    return e;
  };
  auto label = [&](size_t k) {
    const ParameterResult& p = res.parameters[k];
    return spec.parameters[k].key + (p.unit.empty() ? "" : " (" + p.unit + ")");
  };
  compare::MapPlot mp;
  mp.image = m;
  mp.x_edges = edges(res.grid_axes[1]);
  mp.y_edges = edges(res.grid_axes[0]);
  mp.title = "grid scan: " + std::string(ErrorFunctionName(spec.error)) + " at each node";
  mp.xlabel = label(1);
  mp.ylabel = label(0);
  mp.colour_label =
      std::string(spec.error == ErrorFunction::kPoisson ? "Poisson deviance"
                                                        : ErrorFunctionName(spec.error)) +
      " (lower = better)";
  mp.markers.push_back({res.parameters[1].best, res.parameters[0].best, true});
  mp.marker_legend = "square: the estimate";
  return mp;
}

double MeanSquare(const Image& image) {
  double s = 0;
  for (float v : image.pixels) s += double(v) * v;
  return s / double(std::max<size_t>(1, image.size()));
}

compare::MapPlot ResidualMap(const FitResult& res, size_t k) {
  compare::MapPlot p = compare::ResidualMapPlot(res.residuals.at(k), res.object_pixel_um);
  p.title = "residual, mean square " + Num(MeanSquare(p.image), 4);
  p.colour_label = "(sim − exp) / σ";
  return p;
}

}  // namespace internal

namespace {

using internal::J;
using internal::Num;

nlohmann::json Matrix(const std::vector<std::vector<double>>& m) {
  nlohmann::json a = nlohmann::json::array();
  for (const auto& row : m) {
    nlohmann::json r = nlohmann::json::array();
    for (double v : row) r.push_back(J(v));
    a.push_back(r);
  }
  return a;
}

}  // namespace

/// The goodness-of-fit paragraph: a red box for a model mismatch.
static std::string GoodnessHtml(const GoodnessOfFit& g) {
  if (g.pixels == 0) return "";
  std::ostringstream h;
  h << "<h2>Goodness of fit</h2>\n<p style=\"padding:6px;border:2px solid "
    << (g.mismatch ? "#c00;background:#fee" : "#6a6;background:#efe") << "\"><b>"
    << HtmlEscape(g.verdict)
    << "</b></p>\n<table><tr><th>measure</th><th>value</th><th>expected for a correct model</th>"
       "<th>standard deviations</th></tr>\n<tr><td style=\"text-align:left\">Poisson deviance ("
    << g.pixels << " pixels)</td><td>" << Num(g.deviance, 6) << "</td><td>" << Num(g.expected, 6)
    << " +- " << Num(g.sd, 3) << "</td><td>" << Num(g.z, 3)
    << "</td></tr>\n<tr><td style=\"text-align:left\">"
    << "chi-square of residuals summed over " << g.block_px << " x " << g.block_px
    << " pixel blocks</td><td>" << Num(g.block_chi2, 5) << "</td><td>" << g.blocks << " +- "
    << Num(std::sqrt(2.0 * double(g.blocks)), 3) << "</td><td>" << Num(g.block_z, 3)
    << "</td></tr>\n<tr><td style=\"text-align:left\">"
    << "correlation of neighbouring residuals</td><td>" << Num(g.neighbour_correlation, 3)
    << "</td><td>0</td><td>" << Num(g.neighbour_z, 3)
    << "</td></tr></table>\n<p>Sigma inflation factor " << Num(g.sigma_inflation, 3)
    << " (applied to the reported sigma when the model does not describe "
       "the image; see docs/fit.md, \"Goodness of fit\"). The model image tested: "
    << (g.template_sets > 1 ? "the mean of " + std::to_string(g.template_sets) +
                                  " independent ray-stream sets' images at the estimate"
                            : std::string("the main ray streams' image at the estimate"))
    << (g.step.empty()
            ? std::string()
            : "; the tests are taken one weighted least-squares step from it along the fit's "
              "derivative images, where that template and the experiment agree best (deviance " +
                  Num(g.estimate_deviance, 6) + " at the estimate itself)")
    << ".</p>\n";
  return h.str();
}

namespace {

nlohmann::json GoodnessJson(const GoodnessOfFit& g) {
  nlohmann::json step = nlohmann::json::array();
  for (double v : g.step) step.push_back(J(v));
  return {{"deviance", J(g.deviance)},
          {"estimate_deviance", J(g.estimate_deviance)},
          {"step_to_tested_point", step},
          {"expected_deviance", J(g.expected)},
          {"expected_deviance_sd", J(g.sd)},
          {"deviance_z", J(g.z)},
          {"reduced_deviance", J(g.reduced)},
          {"pixels", g.pixels},
          {"block_pixels", g.block_px},
          {"blocks", g.blocks},
          {"block_chi2", J(g.block_chi2)},
          {"block_z", J(g.block_z)},
          {"neighbour_correlation", J(g.neighbour_correlation)},
          {"neighbour_z", J(g.neighbour_z)},
          {"model_mismatch", g.mismatch},
          {"sigma_inflation", J(g.sigma_inflation)},
          {"template_sets", g.template_sets},
          {"verdict", g.verdict}};
}

nlohmann::json ProfileJson(const ParameterResult& p) {
  if (p.profile_reason.empty() || p.profile_t.empty()) return nullptr;
  return {{"reason", p.profile_reason},
          {"lower", J(p.profile_lower)},
          {"upper", J(p.profile_upper)},
          {"lower_sigmas", J(p.profile_lower_sigmas)},
          {"upper_sigmas", J(p.profile_upper_sigmas)},
          {"lower_open", p.profile_lower_open},
          {"upper_open", p.profile_upper_open},
          {"t_sigma", p.profile_t},
          {"delta_deviance", p.profile_delta}};
}

/// An uncertainty that is 0 when it was not computed: null then, as "not computed" in the
/// report and on the terminal.
nlohmann::json Uncertainty(double v) { return v > 0 ? J(v) : nlohmann::json(nullptr); }

nlohmann::json ParameterJson(const ParameterResult& p) {
  return {{"key", p.key},
          {"unit", p.unit},
          {"start", p.start},
          {"best", J(p.best)},
          {"lower", p.lower},
          {"upper", p.upper},
          {"at_bound", p.at_bound},
          {"sigma", Uncertainty(p.sigma)},
          {"sigma_statistical", Uncertainty(p.sigma_statistical)},
          {"sigma_curvature", Uncertainty(p.sigma_curvature)},
          {"sigma_derivatives", J(p.sigma_derivatives)},
          {"sigma_simulation", J(p.sigma_simulation)},
          {"score_derivative", p.score_derivative},
          {"sigma_repeat_seeds", Uncertainty(p.sigma_repeat)},
          {"sigma_cramer_rao", Uncertainty(p.sigma_cramer_rao)},
          {"sigma_expected_with_simulation_noise", Uncertainty(p.sigma_expected)},
          {"slice", {{"x", p.slice_x}, {"error", p.slice_error}, {"noise", J(p.slice_noise)}}},
          {"profile_likelihood", ProfileJson(p)},
          {"prior", p.prior_sigma > 0 ? nlohmann::json{{"mean", p.prior_mean},
                                                       {"sigma", p.prior_sigma},
                                                       {"from", p.prior_from}}
                                      : nlohmann::json()}};
}

/// fit.json: everything the fit did and found.
nlohmann::json FitJson(const FitSpec& spec, const FitResult& res) {
  nlohmann::json j;
  j["provenance"] = ProvenanceJson();
  j["fit_file"] = spec.file;
  j["fit_file_checksum"] = FileChecksum(spec.file);
  j["scene_file"] = spec.scene_file;
  j["scene_file_checksum"] = FileChecksum(spec.scene_file);
  j["method"] = MethodName(spec.method);
  j["error_function"] = ErrorFunctionName(spec.error);
  j["seed"] = spec.seed;
  j["status"] = StatusName(res.status);
  j["converged"] = res.converged;
  j["message"] = res.message;
  j["best_error"] = J(res.best_error);
  if (res.final_steps_q >= 0) j["final_steps_q"] = J(res.final_steps_q);
  if (res.goodness.pixels > 0) j["goodness_of_fit"] = GoodnessJson(res.goodness);
  j["optics"] = spec.optics;
  const bool focused = res.focused_region_radius_um > 0;  // null where not narrowed
  j["rays"] = {{"ray_factor", spec.rays.ray_factor},
               {"fractions", spec.rays.fractions},
               {"common_random_numbers", spec.rays.common_random_numbers},
               {"photon_matched_rays_per_image", res.photon_matched_rays},
               {"reuse_background", spec.rays.reuse_background},
               {"fit_exposure", spec.rays.fit_exposure},
               {"region_center_um", res.region_center_um},
               {"region_radius_um", J(res.region_radius_um)},
               {"focused_region_center_um",
                focused ? nlohmann::json(res.focused_region_center_um) : nlohmann::json(nullptr)},
               {"focused_region_radius_um",
                focused ? J(res.focused_region_radius_um) : nlohmann::json(nullptr)},
               {"retraced_ray_fraction", J(res.near_ray_fraction)}};
  for (const FitImage& im : spec.images)
    j["images"].push_back(
        {{"file", im.file},
         {"defocus_um", im.defocus_um},
         {"dark", im.dark_file},
         {"gain_e_per_dn", im.gain_e_per_dn},
         {"read_noise_e", im.read_noise_e},
         {"saturation_dn", im.saturation_dn},
         {"excluded_pixels", im.excluded_pixels}});  // saturated or clipped: not in the likelihood
  for (const ParameterResult& p : res.parameters) j["parameters"].push_back(ParameterJson(p));
  j["correlation_curvature"] = Matrix(res.correlation);
  j["correlation_cramer_rao"] = Matrix(res.crb_correlation);
  if (!res.grid_axes.empty()) j["grid"] = {{"axes", res.grid_axes}, {"errors", res.grid_errors}};
  for (const auto& [k, v] : res.seconds) j["seconds"][k] = v;
  j["seconds"]["total"] = res.total_seconds;
  for (const Evaluation& e : res.evaluations)
    j["evaluations"].push_back({{"stage", StageName(e.stage)},
                                {"theta", e.theta},
                                {"ray_fraction", e.ray_fraction},
                                {"bin", e.bin},
                                {"rays", e.rays},
                                {"seed", e.seed},
                                {"error", J(e.error)},
                                {"seconds", e.seconds}});
  return j;
}

/// evaluations.csv: one row per evaluation of the error function.
std::string EvaluationsCsv(const FitSpec& spec, const FitResult& res) {
  std::ostringstream csv;
  csv.precision(10);
  csv << "index,stage";
  for (const Parameter& p : spec.parameters) csv << "," << p.key;
  csv << ",ray_fraction,bin,rays,seed,error,seconds\n";
  size_t idx = 0;
  for (const Evaluation& e : res.evaluations) {
    csv << idx++ << "," << StageName(e.stage);
    for (double v : e.theta) csv << "," << v;
    csv << "," << e.ray_fraction << "," << e.bin << "," << e.rays << "," << e.seed << "," << e.error
        << "," << e.seconds << "\n";
  }
  return csv.str();
}

/// Per experimental image: the best expected image and the residual map (TIFF + PNG); returns
/// the report's HTML for them.
std::string WriteImages(const FitSpec& spec, const FitResult& res, const fs::path& dir) {
  std::string imgs;
  for (size_t k = 0; k < res.best_images.size(); ++k) {
    const std::string stem = "image" + std::to_string(k);
    nlohmann::json meta = {{"what", "expected photons per pixel at the fit optimum"},
                           {"fit_file", spec.file},
                           {"image", spec.images[k].file},
                           {"provenance", ProvenanceJson()}};
    WriteFloatImage((dir / (stem + "_best.tif")).string(), res.best_images[k], meta.dump());
    meta["what"] = "residual (sim - exp) / sqrt(sim (1 + 1/(ray_factor x fraction)))";
    WriteFloatImage((dir / (stem + "_residual.tif")).string(), res.residuals[k], meta.dump());
    double mx = 0;
    for (float v : spec.images[k].photons.pixels) mx = std::max(mx, double(v));
    WritePngPreview((dir / (stem + "_experiment.png")).string(), spec.images[k].photons, 0, mx);
    WritePngPreview((dir / (stem + "_best.png")).string(), res.best_images[k], 0, mx);
    compare::WriteMap((dir / (stem + "_residual.png")).string(), internal::ResidualMap(res, k));
    const double chi2 = internal::MeanSquare(res.residuals[k]);
    imgs += "<h3>" + HtmlEscape(spec.images[k].file) + " (defocus " +
            Num(spec.images[k].defocus_um) +
            " um)</h3><table><tr><td>experiment</td><td>simulation at the optimum</td><td>residual "
            "(blue -4 ... red +4 sigma); mean square " +
            Num(chi2, 4) + "</td></tr><tr><td>" +
            EmbeddedPng((dir / (stem + "_experiment.png")).string()) + "</td><td>" +
            EmbeddedPng((dir / (stem + "_best.png")).string()) + "</td><td>" +
            EmbeddedPng((dir / (stem + "_residual.png")).string()) + "</td></tr></table>\n";
  }
  return imgs;
}

/// The error along one parameter through the optimum, with the optimum marked and, for the
/// Poisson deviance, the parabola the curvature's sigma implies (the deviance rises by
/// ((x - best) / sigma)^2 about a quadratic optimum).
void WriteSlicePlot(const FitSpec& spec, const ParameterResult& p, const fs::path& png) {
  compare::Series s;
  s.x = p.slice_x, s.y = p.slice_error;
  s.points = true, s.joined = true;
  s.label = "error (two ray-stream sets), +- its ray noise";
  if (p.slice_noise > 0) s.yerr.assign(s.x.size(), p.slice_noise);
  compare::Series dot;
  dot.points = true;
  dot.label = "estimate";
  dot.x = {p.best};
  // On the curve at the best value (the slice is centred on it; between two samples, linear).
  double at_best = p.slice_error.front();
  for (size_t k = 1; k < p.slice_x.size(); ++k)
    if (p.slice_x[k - 1] <= p.best && p.best <= p.slice_x[k]) {
      const double w = p.slice_x[k] > p.slice_x[k - 1]
                           ? (p.best - p.slice_x[k - 1]) / (p.slice_x[k] - p.slice_x[k - 1])
                           : 0;
      at_best = p.slice_error[k - 1] + w * (p.slice_error[k] - p.slice_error[k - 1]);
    }
  if (p.best > p.slice_x.back()) at_best = p.slice_error.back();
  dot.y = {at_best};
  std::vector<compare::Series> series{s, dot};
  const double sc = p.sigma_curvature;
  if (spec.error == ErrorFunction::kPoisson && std::isfinite(sc) && sc > 0) {
    compare::Series q;
    q.label = "parabola of sigma (curvature)";
    const double lo = p.slice_x.front(), hi = p.slice_x.back();
    for (int k = 0; k <= 40; ++k) {
      const double x = lo + (hi - lo) * k / 40.0;
      q.x.push_back(x);
      q.y.push_back(at_best + (x - p.best) * (x - p.best) / (sc * sc));
    }
    series.push_back(q);
  }
  compare::WritePlot(png.string(), series, "error along " + p.key + " through the optimum",
                     p.key + (p.unit.empty() ? "" : " (" + p.unit + ")"),
                     ErrorFunctionName(spec.error));
}

/// Slices per parameter and the grid landscape (1 or 2 axes); returns the report's HTML for them.
std::string WritePlots(const FitSpec& spec, const FitResult& res, const fs::path& dir) {
  std::string plots;
  bool slices = false;
  for (const ParameterResult& p : res.parameters) slices = slices || p.slice_x.size() >= 2;
  if (slices)
    plots +=
        "<p>Slices: the error along one parameter with the others at the estimate, the mean of "
        "two independent ray-stream sets, with error bars of one standard deviation of that "
        "mean's ray noise (from the two sets' differences). With fixed ray streams such a curve "
        "is a staircase (rays crossing pixel edges), so its lowest sample need not be the "
        "estimate: the estimate is the root of the final steps' estimating equation over "
        "independent ray-stream sets (docs/design/fit-estimator.md, \"Finite rays\"). For the "
        "Poisson deviance the smooth curve is the parabola the curvature's sigma implies; a "
        "slice that departs from it by much more than its error bars is a sign to check the "
        "estimate or its sigma (a profile interval, more rays).</p>\n";
  for (size_t i = 0; i < res.parameters.size(); ++i) {
    if (res.parameters[i].slice_x.size() < 2) continue;
    const fs::path png = dir / ("slice_" + std::to_string(i) + ".png");
    WriteSlicePlot(spec, res.parameters[i], png);
    plots += EmbeddedPng(png.string()) + "\n";
  }
  if (res.grid_axes.size() == 1) {
    compare::Series s;
    s.x = res.grid_axes[0], s.y = res.grid_errors;
    compare::WritePlot((dir / "landscape.png").string(), {s}, "grid scan", spec.parameters[0].key,
                       ErrorFunctionName(spec.error));
    plots += EmbeddedPng((dir / "landscape.png").string()) + "\n";
  } else if (res.grid_axes.size() == 2) {
    const compare::MapPlot mp = internal::GridLandscapeMap(spec, res);
    compare::WriteMap((dir / "landscape.png").string(), mp);
    plots += EmbeddedPng((dir / "landscape.png").string()) + "\n";
  }
  return plots;
}

/// The parameter table and the correlation matrix of report.html.
std::string ParametersHtml(const FitSpec& spec, const FitResult& res) {
  std::ostringstream h;
  h << "<h2>Parameters</h2><table><tr><th>key</th><th>unit</th><th>start</th><th>best</th>"
       "<th>sigma (reported)</th><th>curvature only</th><th>repeat seeds (simulation noise)</th>"
       "<th>Cramer-Rao bound</th><th>CRB incl. simulation noise</th><th>profile-likelihood 68 % "
       "interval</th><th>bounds</th></tr>\n";
  for (const ParameterResult& p : res.parameters)
    h << "<tr><td style=\"text-align:left\">" << HtmlEscape(p.key)
      << (p.prior_sigma > 0
              ? "<br><small>prior " + Num(p.prior_mean, 8) + " &plusmn; " + Num(p.prior_sigma, 3) +
                    " (" + HtmlEscape(p.prior_from) + ")</small>"
              : std::string())
      << "</td><td>" << p.unit << "</td><td>" << Num(p.start) << "</td><td>"
      << FormatValue(p.best, p.sigma, 8) << (p.at_bound ? " (at bound)" : "") << "</td><td>"
      << FormatUncertainty(p.sigma) << "</td><td>" << FormatUncertainty(p.sigma_curvature)
      << "</td><td>" << FormatUncertainty(p.sigma_repeat) << "</td><td>"
      << FormatUncertainty(p.sigma_cramer_rao) << "</td><td>" << FormatUncertainty(p.sigma_expected)
      << "</td><td"
      << (p.profile_t.empty() ? ">not needed"
                              : " title=\"" + HtmlEscape(p.profile_reason) + "\">[" +
                                    (p.profile_lower_open ? "&le; " : "") +
                                    FormatValue(p.profile_lower, p.sigma, 8) + ", " +
                                    (p.profile_upper_open ? "&ge; " : "") +
                                    FormatValue(p.profile_upper, p.sigma, 8) + "]")
      << "</td><td>[" << Num(p.lower) << ", " << Num(p.upper) << "]</td></tr>\n";
  h << "</table>\n";
  if (!res.correlation.empty()) {
    // The columns numbered as the rows (the keys are too long to head 7-10 columns).
    h << "<h2>Correlations (of the reported sigmas' covariance)</h2><table><tr><th></th>";
    for (size_t i = 0; i < spec.parameters.size(); ++i)
      h << "<th title='" << HtmlEscape(spec.parameters[i].key) << "'>" << i + 1 << "</th>";
    h << "</tr>";
    for (size_t i = 0; i < res.correlation.size(); ++i) {
      h << "<tr><th>" << i + 1 << " " << HtmlEscape(spec.parameters[i].key) << "</th>";
      for (size_t k = 0; k < res.correlation[i].size(); ++k)
        h << "<td>" << Num(res.correlation[i][k], 3) << "</td>";
      h << "</tr>";
    }
    h << "</table>\n";
  }
  return h.str();
}

}  // namespace

std::string WriteFitOutputs(const FitSpec& spec, const FitResult& res, const std::string& dir_s) {
  const fs::path dir(dir_s);
  EnsureDirectory(dir);
  WriteTextFileAtomic(dir / "fit.json", FitJson(spec, res).dump(2) + "\n");
  WriteTextFileAtomic(dir / "evaluations.csv", EvaluationsCsv(spec, res));
  const std::string imgs = WriteImages(spec, res, dir);
  const std::string plots = WritePlots(spec, res, dir);

  std::ostringstream h;
  h << "<!doctype html><html><head><meta charset=\"utf-8\"><title>raymatch fit</title><style>"
       "body{font-family:sans-serif;max-width:1360px;margin:2em "
       "auto}table{border-collapse:collapse;display:block;overflow-x:auto;max-width:100%}"
       "td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}img{image-rendering:pixelated;"
       "max-width:100%}</style></head><body>\n<h1>raymatch fit</h1>\n<p>"
    << HtmlEscape(spec.file) << ": " << MethodName(spec.method) << " on "
    << ErrorFunctionName(spec.error) << ", status <b>" << HtmlEscape(StatusName(res.status))
    << "</b>: " << HtmlEscape(res.message) << ". " << res.evaluations.size() << " evaluations in "
    << Num(res.total_seconds, 3) << " s; best error " << Num(res.best_error) << ".</p>\n"
    << GoodnessHtml(res.goodness) << ParametersHtml(spec, res);
  h << "<h2>Images</h2>\n"
    << imgs << "<h2>Error function</h2>\n"
    << plots << "<h2>Time</h2><table>";
  for (const auto& [k, v] : res.seconds)
    h << "<tr><td style=\"text-align:left\">" << HtmlEscape(k) << "</td><td>" << Num(v, 3)
      << " s</td></tr>";
  h << "</table>\n<p>";
  if (spec.optics == "physical")
    h << "Images: physical optics (optics = \"physical\", docs/physical-optics.md): rays that "
         "carry their field, no simulation noise. ";
  else if (spec.exact_images())
    h << "Images: the exact wave model of the sphere (optics = \"mie\", docs/wave-optics.md): "
         "no rays, no simulation noise. ";
  else
    h << "Rays: " << res.photon_matched_rays << " photon-matched rays per image x ray factor "
      << spec.rays.ray_factor << "; re-traced share per evaluation "
      << Num(res.near_ray_fraction, 3)
      << " (rays that can meet an object; the others traced once). ";
  h << "Every evaluation: evaluations.csv; everything: fit.json.</p></body></html>\n";
  const fs::path report = dir / "report.html";
  WriteTextFileAtomic(report, h.str());
  return report.string();
}

}  // namespace raymatch::fit
