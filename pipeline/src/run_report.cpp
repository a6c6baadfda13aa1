// The main job's report: the calibration's figures and index.html (run_report.h).
#include "run_report.h"

#include <algorithm>
#include <cmath>
#include <sstream>

#include "raymatch/compare/plot.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/html.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/provenance.h"
#include "raymatch/simulate/scene.h"

namespace fs = std::filesystem;

namespace raymatch::pipeline::internal {
using compare::Series;
using compare::WritePlot;

std::string Img(const std::string& png, const std::string& alt) { return EmbeddedPng(png, alt); }

namespace {

/// A map centred on the axis (+-half_x, +-half_y), colours from 0 to its maximum; `relative`:
/// divided by the maximum first.
void WriteMapPlot(const fs::path& png, const Image& image, bool relative, double half_x,
                  double half_y, const std::string& title, const std::string& xlabel,
                  const std::string& ylabel, const std::string& colour_label) {
  compare::MapPlot p;
  p.image = image;
  double mx = 0;
  for (float v : p.image.pixels) mx = std::max(mx, double(v));
  if (relative && mx > 0)
    for (float& v : p.image.pixels) v = float(v / mx);
  p.lo = 0, p.hi = relative || !(mx > 0) ? 1 : mx;
  p.x_left = -half_x, p.x_right = half_x;
  p.y_top = half_y, p.y_bottom = -half_y;
  p.title = title, p.xlabel = xlabel, p.ylabel = ylabel, p.colour_label = colour_label;
  p.max_side_px = 360;
  compare::WriteMap(png.string(), p);
}

}  // namespace

compare::PlotPanel RadialProfilePanel(const CalibrationData& cal) {
  // Azimuthal mean in rings of one map pixel, with the standard error of each ring's mean.
  const Image& m = cal.angular_map;
  const int n = m.width;
  std::vector<double> sum_r(n / 2, 0), sum2(n / 2, 0), cnt(n / 2, 0);
  for (int y = 0; y < n; ++y)
    for (int x = 0; x < n; ++x) {
      const double u = (2 * (x + 0.5) / n - 1), vv = (1 - 2 * (y + 0.5) / n);
      const int k = int(std::hypot(u, vv) * n / 2);
      if (k < n / 2)
        sum_r[k] += m.at(x, y), sum2[k] += double(m.at(x, y)) * m.at(x, y), cnt[k] += 1;
    }
  Series s;
  s.points = true;
  s.label = "azimuthal mean ± 1 standard error";
  double mx = 0;
  for (int k = 0; k < n / 2; ++k)
    if (cnt[k] > 0) mx = std::max(mx, sum_r[k] / cnt[k]);
  for (int k = 0; k < n / 2; ++k)
    if (cnt[k] > 0) {
      const double mean = sum_r[k] / cnt[k];
      const double var =
          cnt[k] > 1 ? std::max(0.0, (sum2[k] - cnt[k] * mean * mean) / (cnt[k] - 1)) : 0.0;
      s.x.push_back(std::asin(std::min(1.0, (k + 0.5) / (n / 2) * cal.angular_extent)) * 180 /
                    M_PI);
      s.y.push_back(mx > 0 ? mean / mx : mean);
      s.yerr.push_back((mx > 0 ? 1 / mx : 1) * std::sqrt(var / cnt[k]));
    }
  compare::PlotPanel p;
  p.series = {s};
  if (cal.edge_half_angle_deg > 0 && cal.edge_width_deg > 0 && cal.na_limit > 0 && s.x.size() > 1) {
    // The sphere calibration's edge beyond the NA: the map's reference ring inside the cut
    // continued under the soft edge, relative to its value at that ring (the tilt, a fraction
    // of a degree, left out of this azimuthal mean).
    const double deg = 180 / M_PI;
    const double ring = std::asin(std::max(0.0, cal.na_limit - simulate::kEdgeRingPixels * 2 *
                                                                   cal.angular_extent / n)) *
                        deg;
    const double cut = std::asin(std::min(1.0, cal.na_limit)) * deg;
    auto edge = [&](double t) {
      return simulate::LightFieldSoftEdge(t, cal.edge_half_angle_deg, cal.edge_width_deg);
    };
    size_t j = 1;
    while (j + 1 < s.x.size() && s.x[j] < ring) ++j;
    const double f = std::clamp((ring - s.x[j - 1]) / (s.x[j] - s.x[j - 1]), 0.0, 1.0);
    const double level = s.y[j - 1] + f * (s.y[j] - s.y[j - 1]);
    Series e;
    e.label = "edge beyond the NA (sphere calibration)";
    const double end = cal.edge_half_angle_deg + 3 * cal.edge_width_deg;
    for (int k = 0; k <= 60; ++k) {
      const double t = ring + (end - ring) * k / 60.0;
      e.x.push_back(t);
      e.y.push_back(level * edge(t) / edge(ring));
    }
    Series na;
    na.label = "objective's NA (the map's cut)";
    na.x = {cut, cut};
    na.y = {0, 1.05};
    p.series.push_back(e);
    p.series.push_back(na);
  }
  p.title = "light field: radial profile (cone edge " + FormatValue(cal.cone_half_angle_deg, 0, 4) +
            "°" +
            (cal.edge_half_angle_deg > 0
                 ? "; edge beyond the NA " + FormatValue(cal.edge_half_angle_deg, 0, 4) + "°"
                 : std::string()) +
            ")";
  p.xlabel = "angle to the optical axis (degrees)";
  p.ylabel = "radiance (relative to the maximum)";
  return p;
}

std::string WriteCalibrationFigures(const CalibrationData& cal, const fs::path& fig) {
  // Angular map over direction cosines (u right, v up), relative to its maximum.
  WriteMapPlot(fig / "angular_map.png", cal.angular_map, true, cal.angular_extent,
               cal.angular_extent, "light field: angular radiance", "direction cosine u (x, right)",
               "direction cosine v (y, up)", "radiance (relative to the maximum)");
  std::string spatial_html;
  if (!cal.spatial_map.empty()) {
    WriteMapPlot(fig / "spatial_map.png", cal.spatial_map, false, 0.5 * cal.field_size_um[0],
                 0.5 * cal.field_size_um[1],
                 "light field: spatial map at the object plane (from the flat field)", "x (µm)",
                 "y (µm)", "relative irradiance");
    spatial_html =
        "<p>Spatial map: relative irradiance at the object plane from the flat field.</p>" +
        Img((fig / "spatial_map.png").string(), "spatial map");
  }
  WritePlot((fig / "radial_profile.png").string(), {RadialProfilePanel(cal)}, 560, 380);
  {
    // Zone transmissions against the zone's radius on the corrector (mid-ring), +-1 sigma.
    Series s;
    s.points = true;
    s.label = "transmission ± 1σ (fit)";
    const bool radii = cal.ring_outer_mm.size() == cal.transmissions.size();
    for (size_t j = 0; j < cal.transmissions.size(); ++j) {
      s.x.push_back(radii ? 0.5 * ((j ? cal.ring_outer_mm[j - 1] : 0.0) + cal.ring_outer_mm[j])
                          : double(j));
      s.y.push_back(cal.transmissions[j]);
      s.yerr.push_back(j < cal.transmission_sigma.size() ? cal.transmission_sigma[j] : 0.0);
    }
    compare::PlotPanel p;
    p.series = {s};
    p.title = "corrector: zone transmissions";
    p.xlabel = radii ? "zone mid-radius on the corrector (mm)" : "zone (0 = central disc)";
    p.ylabel = "transmission T (fraction)";
    WritePlot((fig / "transmissions.png").string(), {p}, 560, 380);
  }
  return spatial_html;
}

void WriteRunReport(const RunReport& r) {
  const fs::path& out = r.out;
  const CalibrationData& cal = *r.cal;
  const compare::FocusScanResult& fr = *r.scan;
  const PipelineSummary& sum = *r.sum;
  const fs::path fig = out / "figures";
  EnsureDirectory(fig);
  const std::string spatial_html = WriteCalibrationFigures(cal, fig);
  const std::string &lf_report = r.lf_report, &co_report = r.co_report, &sp_report = r.sp_report;
  const double frac = r.ray_fraction;
  std::ostringstream h;
  h.precision(4);
  h << "<!doctype html><html><head><meta charset='utf-8'><title>raymatch run</title><style>"
       "body{font-family:sans-serif;margin:2em;max-width:1100px}td,th{border:1px solid #ccc;"
       "padding:2px 6px;font-size:12px}table{border-collapse:collapse;display:block;"
       "overflow-x:auto;max-width:100%}img{max-width:100%}"
       "pre{white-space:pre-wrap;overflow-wrap:anywhere}"
       ".pass{color:#070}.fail{color:#b00}</style></head><body><h1>raymatch: calibrate, simulate, "
       "compare</h1>"
    << "<p>" << ProvenanceJson()["date_utc"].get<std::string>() << " &mdash; <code>"
    << CommandLine() << "</code></p><h2>Verdict: <span class='"
    << (sum.status == 0 ? "pass" : "fail") << "'>" << HtmlEscape(sum.Overall())
    << "</span></h2><table><tr><th>check</th><th>result</th><th>what it means</th></tr>";
  for (const PipelineCheck& c : sum.checks)
    h << "<tr><td>" << HtmlEscape(c.name) << "</td><td class='" << (c.ok ? "pass" : "fail") << "'>"
      << HtmlEscape(c.result) << "</td><td>" << HtmlEscape(c.meaning) << "</td></tr>";
  h << "</table><p>Exit status of <code>raymatch run</code>: " << sum.status
    << " (0 every check passes, 1 a check needs attention, 2 the focus-scan test fails).</p>"
    << "<h2>Measured light field</h2><pre>" << HtmlEscape(lf_report) << "</pre>"
    << (cal.edge_half_angle_deg > 0
            ? "<p>Beyond the NA the simulation does not use zero: the sphere calibration's soft "
              "edge, half radiance at " +
                  FormatValue(cal.edge_half_angle_deg, 0, 4) + " deg, width " +
                  FormatValue(cal.edge_width_deg, 0, 4) + " deg (Sphere calibration, below).</p>"
            : std::string())
    << Img((fig / "angular_map.png").string(), "angular map") << " "
    << Img((fig / "radial_profile.png").string(), "light-field radial profile")
    << "<p>Angular map over direction cosines (u right, v up), +-" << cal.angular_extent
    << "; radial profile: azimuthal means in rings of one map pixel, error bars one standard error "
       "of each ring's mean.</p>"
    << spatial_html << "<h2>Corrector</h2><pre>" << HtmlEscape(co_report) << "</pre>"
    << Img((fig / "transmissions.png").string(), "corrector transmissions")
    << "<p>Error bars: one standard deviation from the fit's covariance.</p>"
    << (sp_report.empty()
            ? std::string()
            : "<h2>Sphere calibration</h2><p>The light field beyond the NA and the PSF from the "
              "drop of " +
                  HtmlEscape(r.sphere_folder) +
                  " (<a href='sphere_calibration/report.html'>fit report</a>)</p><pre>" +
                  HtmlEscape(sp_report) + "</pre>")
    << "<h2>Experiment (top) and simulation (bottom)</h2><p>Exposure recovered from the "
       "background: "
    << sum.photons_per_pixel << " photons per pixel; simulated with ray fraction " << frac << ". "
    << fr.RegistrationSummary() << ".</p>" << Img((out / "compare/montage.png").string(), "montage")
    << "<p>Residual maps and radial profiles per plane: <a "
       "href='compare/report.html'>compare/report.html</a>.</p>"
    << "<h2>Focus-scan test</h2><table><tr><th>measure</th><th>verdict</th><th>best simulated z "
       "per experimental z (um)</th></tr>";
  for (size_t i = 0; i < fr.measures.size(); ++i) {
    h << "<tr><td>" << sum.measures[i] << "</td><td class='"
      << (fr.measures[i].passes ? "pass'>pass" : "fail'>fail") << "</td><td>";
    for (double z : sum.best_match_um[i]) h << z << " ";
    h << "</td></tr>";
  }
  h << "</table>";
  h << r.mesh_html << r.fit_html;
  for (const auto& m : fr.measures)
    h << "<h3>" << compare::MeasureName(m.measure) << "</h3>"
      << Img((out / ("compare/heatmap_" + std::string(compare::MeasureName(m.measure)) + ".png"))
                 .string(),
             std::string(compare::MeasureName(m.measure)) + " heatmap");
  h << "<h2>Timing</h2><table>";
  for (const auto& [name, s] : sum.step_seconds)
    h << "<tr><td>" << name << "</td><td>" << s << " s</td></tr>";
  for (const auto& step : sum.reused)
    h << "<tr><td>" << step << "</td><td>reused (inputs unchanged)</td></tr>";
  h << "</table><p>Files: <code>calibration.toml</code>, <code>scene.toml</code>, "
       "<code>simulation/</code>, "
       "<code>compare/</code> (report.html, CSV, JSON), <code>figures/</code>.</p></body></html>\n";
  WriteTextFileAtomic(sum.report, h.str());
}

std::string FitSectionHtml(const std::string& stem, const fit::FitSpec& spec,
                           const fit::FitResult& fr2) {
  std::ostringstream hh;
  hh.precision(6);
  hh << "<h3><a href='fit/" << stem << "/report.html'>" << stem
     << "</a>: " << fit::MethodName(spec.method) << " on " << fit::ErrorFunctionName(spec.error)
     << ", " << fit::StatusName(fr2.status) << " (" << fr2.evaluations.size() << " evaluations, "
     << fr2.total_seconds
     << " s)</h3><table><tr><th>parameter</th><th>best</th>"
        "<th>sigma</th><th>Cramer-Rao bound</th><th>profile-likelihood 68 % interval</th></tr>";
  for (const auto& p : fr2.parameters) {
    hh << "<tr><td>" << p.key;
    if (p.prior_sigma > 0)
      hh << "<br><small>prior " << p.prior_mean << " &plusmn; " << p.prior_sigma << " ("
         << HtmlEscape(p.prior_from) << ")</small>";
    hh << "</td><td>" << FormatValue(p.best, p.sigma) << " " << p.unit << "</td><td>"
       << FormatUncertainty(p.sigma) << "</td><td>" << FormatUncertainty(p.sigma_cramer_rao)
       << "</td><td>";
    if (p.profile_t.empty())
      hh << "not needed";
    else
      hh << "[" << (p.profile_lower_open ? "&le; " : "") << p.profile_lower << ", "
         << (p.profile_upper_open ? "&ge; " : "") << p.profile_upper << "] ("
         << HtmlEscape(p.profile_reason) << ")";
    hh << "</td></tr>";
  }
  hh << "</table>";
  if (fr2.goodness.pixels > 0)
    hh << "<p style='padding:4px;border:2px solid " << (fr2.goodness.mismatch ? "#c00" : "#6a6")
       << "'>Goodness of fit: " << fr2.goodness.verdict << "</p>";
  return hh.str();
}

}  // namespace raymatch::pipeline::internal
