// Focus-scan outputs: JSON, CSV, PNG heatmaps and montage, and a self-contained HTML report.
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "raymatch/compare/focus_scan.h"
#include "raymatch/compare/plot.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/html.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/provenance.h"

namespace fs = std::filesystem;

namespace raymatch::compare {

namespace {

/// The colour bar's label: the measure's name, its unit and which way is better.
std::string MeasureAxisLabel(Measure m) {
  switch (m) {
    case Measure::kMse:
      return "MSE (photons² per pixel; lower = better)";
    case Measure::kSsim:
      return "SSIM (dimensionless; 1 = identical)";
    case Measure::kMsSsim:
      return "MS-SSIM (dimensionless; 1 = identical)";
    case Measure::kCwSsim:
      return "CW-SSIM (dimensionless; 1 = identical)";
    case Measure::kPoissonChi2:
      return "Poisson χ² per pixel (dimensionless; 1 = shot noise)";
  }
  return MeasureName(m);
}

/// Cell edges around sorted centres (half-way between neighbours; the ends extended by half a
/// step). Listed in the order given.
std::vector<double> Edges(const std::vector<double>& z) {
  const size_t n = z.size();
  std::vector<double> e(n + 1);
  if (n == 1) return {z[0] - 2.5, z[0] + 2.5};
  for (size_t i = 1; i < n; ++i) e[i] = 0.5 * (z[i - 1] + z[i]);
  e[0] = z[0] - 0.5 * (z[1] - z[0]);
  e[n] = z[n - 1] + 0.5 * (z[n - 1] - z[n - 2]);
  return e;
}

std::string Um(double z) {
  std::ostringstream os;
  os.precision(4);
  os << (z > 0 ? "+" : "") << z << " µm";
  return os.str();
}

/// Heatmap of a matrix: x = simulation defocus, y = experiment defocus (both um, increasing to
/// the right and upwards), the measure's values on a colour bar (viridis, reversed for
/// distances so that bright is always the better match), each row's best match boxed and the
/// cell of the same defocus dotted, the measure's verdict in the title.
void Heatmap(const FocusScanResult& r, const MeasureScan& m, const std::string& path) {
  const int ne = int(m.matrix.size()), ns = int(m.matrix[0].size());
  MapPlot p;
  p.image = Image(ns, ne);
  for (int i = 0; i < ne; ++i)  // image row 0 (top) = the last experiment plane
    for (int j = 0; j < ns; ++j) p.image.at(j, ne - 1 - i) = float(m.matrix[i][j]);
  p.x_edges = Edges(r.sim_defocus_um);
  p.y_edges = Edges(r.exp_defocus_um);
  std::reverse(p.y_edges.begin(), p.y_edges.end());
  p.map = HigherIsBetter(m.measure) ? ColourMap::kViridis : ColourMap::kViridisReversed;
  p.title = std::string(MeasureName(m.measure)) + ": " + (m.passes ? "passes" : "fails") +
            (m.primary ? " (counts towards the verdict)" : " (informational, not in the verdict)");
  p.xlabel = "simulation defocus (µm)";
  p.ylabel = "experiment defocus (µm)";
  p.colour_label = MeasureAxisLabel(m.measure);
  for (int i = 0; i < ne; ++i) {
    p.markers.push_back({r.sim_defocus_um[m.expected[i]], r.exp_defocus_um[i], false});
    p.markers.push_back({r.sim_defocus_um[m.best[i]], r.exp_defocus_um[i], true});
  }
  p.marker_legend = "white box: best match in the row; red dot: same defocus";
  p.max_side_px = std::clamp(40 * std::max(ne, ns), 280, 520);
  WriteMap(path, p);
}

/// The simulation plane nearest in defocus to experiment plane i.
int NearestSim(const FocusScanResult& r, int i) {
  int best = 0;
  for (size_t j = 1; j < r.sim_defocus_um.size(); ++j)
    if (std::abs(r.sim_defocus_um[j] - r.exp_defocus_um[i]) <
        std::abs(r.sim_defocus_um[best] - r.exp_defocus_um[i]))
      best = int(j);
  return best;
}

/// Experiment (upper row) above the simulation at the nearest defocus (lower row), one grey
/// scale; at most 9 planes to a pair of rows, so that many planes wrap into further pairs.
void Montage(const FocusScanResult& r, const std::string& path) {
  constexpr int kPerRow = 9;
  ImageGrid g;
  const int n = int(r.exp_images.size());
  for (int i = 0; i < n; ++i) {
    if (i % kPerRow == 0) {
      g.rows.emplace_back(), g.rows.emplace_back();
      g.tile_labels.emplace_back(), g.tile_labels.emplace_back();
      g.row_labels.push_back("experiment"), g.row_labels.push_back("simulation");
    }
    const int j = NearestSim(r, i);
    g.rows[g.rows.size() - 2].push_back(r.exp_images[i]);
    g.rows.back().push_back(r.sim_images[j]);
    std::string label = Um(r.exp_defocus_um[i]);
    if (r.sim_defocus_um[j] != r.exp_defocus_um[i])
      label += " (sim " + Um(r.sim_defocus_um[j]) + ")";
    g.tile_labels[g.tile_labels.size() - 2].push_back(label);
  }
  g.lo = 0, g.hi = r.data_range > 0 ? r.data_range : 1;
  g.map = ColourMap::kGrey;
  std::ostringstream t;
  t.precision(5);
  t << "Experiment (upper row) and simulation (lower row), labelled by defocus\none grey scale for "
       "all tiles: 0 to L = "
    << g.hi << " photons per pixel";
  g.title = t.str();
  g.colour_label = "photons per pixel";
  g.tile_px = 120;
  WriteImageGrid(path, g);
}

/// Per experimental plane: the residual map (sim - exp) / sqrt(sim + exp) and the radial
/// profiles (azimuthal means about the image centre) with one pixel's shot-noise band; the
/// residual's mean square (PerPlaneGoodness) goes into the map's title.
void PlaneFigures(const FocusScanResult& r, int i, double ms, const std::string& residual_png,
                  const std::string& profile_png) {
  const Image& e = r.exp_images[i];
  const Image& s = r.sim_images[NearestSim(r, i)];
  const int w = e.width, h = e.height;
  Image residual(w, h);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      // Shot-noise variance: exp for the experiment, sim_scale x sim for the simulation scaled
      // by sim_scale (sim + exp when photon-matched, sim_scale = 1).
      const double a = s.at(x, y), b = e.at(x, y), d = r.sim_scale * a + b;
      residual.at(x, y) = float(d > 0 ? (a - b) / std::sqrt(d) : 0.0);
    }
  MapPlot p = ResidualMapPlot(residual, r.object_pixel_um);
  std::ostringstream t;
  t.precision(3);
  t << "z = " << Um(r.exp_defocus_um[i]) << ": residual, mean square " << ms;
  if (!(r.sim_scale > 0.98 && r.sim_scale < 1.02)) t << "; s = " << r.sim_scale;
  p.title = t.str();
  p.colour_label = r.sim_scale > 0.98 && r.sim_scale < 1.02 ? "(sim − exp) / √(sim + exp)  (σ)"
                                                            : "(sim − exp) / √(s·sim + exp)  (σ)";
  WriteMap(residual_png, p);

  // The profiles' radius at the object (um) when the pixel's size there is known, else in pixels.
  const double px = r.object_pixel_um > 0 ? r.object_pixel_um : 1.0;
  const std::string unit = r.object_pixel_um > 0 ? "um at the object" : "px";

  // Radial profiles in 1-px rings about the image centre (pixel centres at +0.5).
  const int nr = std::max(1, std::min(w, h) / 2);
  std::vector<double> se(nr, 0), ss(nr, 0), n(nr, 0);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      const int k = int(std::hypot(x + 0.5 - 0.5 * w, y + 0.5 - 0.5 * h));
      if (k < nr) se[k] += e.at(x, y), ss[k] += s.at(x, y), n[k] += 1;
    }
  Series ex, sim;
  ex.label = "experiment ± 1σ shot noise of one pixel (√N)";
  sim.label = "simulation ± 1σ shot noise of one pixel";
  for (int k = 0; k < nr; ++k) {
    if (n[k] == 0) continue;
    const double me = se[k] / n[k], msim = ss[k] / n[k];
    // The simulation was scaled by sim_scale: its variance is sim_scale times its value.
    const double sde = std::sqrt(std::max(0.0, me)),
                 sds = std::sqrt(std::max(0.0, r.sim_scale * msim));
    for (Series* q : {&ex, &sim}) q->x.push_back((k + 0.5) * px);
    ex.y.push_back(me), ex.band_lo.push_back(me - sde), ex.band_hi.push_back(me + sde);
    sim.y.push_back(msim), sim.band_lo.push_back(msim - sds), sim.band_hi.push_back(msim + sds);
  }
  PlotPanel panel;
  panel.series = {ex, sim};
  panel.title = "z = " + Um(r.exp_defocus_um[i]) + ": radial profile (azimuthal mean)";
  panel.xlabel = "radius from the image centre (" + unit + ")";
  panel.ylabel = "photons per pixel";
  WritePlot(profile_png, {panel}, 560, 380);
}

std::string Fmt(double v) {
  std::ostringstream os;
  os.precision(6);
  os << v;
  return os.str();
}

}  // namespace

std::vector<PlaneGoodness> PerPlaneGoodness(const FocusScanResult& r) {
  std::vector<PlaneGoodness> out;
  for (int i = 0; i < int(r.exp_images.size()) && !r.sim_images.empty(); ++i) {
    const Image& e = r.exp_images[i];
    const int j = NearestSim(r, i);
    const Image& s = r.sim_images[j];
    PlaneGoodness g;
    g.exp_defocus_um = r.exp_defocus_um[i], g.sim_defocus_um = r.sim_defocus_um[j];
    for (size_t q = 0; q < e.size(); ++q) {
      const double a = s.pixels[q], b = e.pixels[q], d = r.sim_scale * a + b;
      if (d > 0) g.mean_square += (a - b) * (a - b) / d;
    }
    const double n = double(std::max<size_t>(1, e.size()));
    g.mean_square /= n;
    g.expected_sd = std::sqrt(2 / n);
    g.z = (g.mean_square - 1) / g.expected_sd;
    g.misfit = g.z > 3;
    out.push_back(g);
  }
  return out;
}

std::string PlaneGoodnessSummary(const std::vector<PlaneGoodness>& planes, bool* misfits) {
  std::string at;
  size_t within = 0;
  for (const PlaneGoodness& g : planes) {
    if (!g.misfit) {
      ++within;
      continue;
    }
    std::ostringstream z;
    z << std::showpos << g.exp_defocus_um;
    at += (at.empty() ? "" : ", ") + z.str();
  }
  if (misfits) *misfits = !at.empty();
  if (planes.empty()) return "";
  return "residuals within the shot noise in " + std::to_string(within) + " of " +
         std::to_string(planes.size()) + " planes" +
         (at.empty() ? "" : " (misfit at " + at + " um)");
}

std::string WriteFocusScanReport(const FocusScanResult& r, const std::string& dir,
                                 const std::string& title) {
  EnsureDirectory(dir);
  const fs::path d(dir);
  nlohmann::json j = r.ToJson();
  j["provenance"] = ProvenanceJson();
  WriteTextFileAtomic(d / "compare_scan.json", j.dump(2) + "\n");
  std::ostringstream best;
  best << "experiment_defocus_um";
  for (const MeasureScan& m : r.measures) best << "," << MeasureName(m.measure);
  best << "\n";
  for (size_t i = 0; i < r.exp_defocus_um.size(); ++i) {
    best << r.exp_defocus_um[i];
    for (const MeasureScan& m : r.measures) best << "," << r.sim_defocus_um[m.best[i]];
    best << "\n";
  }
  WriteTextFileAtomic(d / "best_match.csv", best.str());
  std::string html =
      "<!doctype html><html><head><meta charset='utf-8'><title>" + title +
      "</title><style>body{font-family:sans-serif;margin:2em;max-width:1100px}"
      "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 6px;"
      "font-size:12px;text-align:right}.pass{color:#070}.fail{color:#b00}"
      "img{max-width:100%}table.planes td{border:none;vertical-align:top}</style></head><body>"
      "<h1>" +
      title + "</h1>";
  const char* verdict = r.verdict == Verdict::kPass      ? "pass"
                        : r.verdict == Verdict::kWarning ? "warning"
                                                         : "fail";
  html += "<p><b>Verdict: <span class='" +
          std::string(r.verdict == Verdict::kPass ? "pass" : "fail") + "'>" + verdict +
          "</span></b> &mdash; " + r.message + "</p>";
  // What the verdict does not say: whether each matched simulation describes its plane.
  const std::vector<PlaneGoodness> goodness = PerPlaneGoodness(r);
  bool misfits = false;
  const std::string planes = PlaneGoodnessSummary(goodness, &misfits);
  if (!planes.empty())
    html += "<p><b>Goodness of fit per plane:</b> <span class='" +
            std::string(misfits ? "fail" : "pass") + "'>" + planes +
            "</span> (table under \"Per plane\"). The verdict above says which simulated plane "
            "each experimental plane matches best, not that the simulation describes it" +
            (misfits ? ": where a plane's residuals exceed the shot noise, the model lacks "
                       "something (its residual map shows where)."
                     : ".") +
            "</p>";
  html += "<p>Dynamic range L = " + Fmt(r.data_range) + "; MS-SSIM " +
          std::to_string(r.ms_ssim.num_scales) + " scales (" +
          MsSsimWeightsName(r.ms_ssim.weights) + " weights); CW-SSIM level " +
          std::to_string(r.cw_ssim.level) + ", " + std::to_string(r.cw_ssim.orientations) +
          " orientations, K " + Fmt(r.cw_ssim.k) + "; " + r.RegistrationSummary() +
          "; simulation scaled by " + Fmt(r.sim_scale) + ".</p>";
  Montage(r, (d / "montage.png").string());
  html +=
      "<h2>Experiment (top) and simulation (bottom)</h2><p>Each tile is labelled by its "
      "defocus; one grey scale for all tiles, 0 to L = " +
      Fmt(r.data_range) + " photons per pixel (the simulation scaled by " + Fmt(r.sim_scale) +
      ").</p>" +
      EmbeddedPng((d / "montage.png").string(), "experiment above simulation per defocus");
  html +=
      "<h2>Cross-similarity</h2><p>Rows: experiment defocus, columns: simulation defocus. "
      "Bright = better match for every measure (the colour bar gives the measure's values); "
      "white box = best match in the row; red dot = the simulation plane of the same "
      "defocus.</p>";
  for (const MeasureScan& m : r.measures) {
    const std::string name = MeasureName(m.measure);
    std::ostringstream csv;
    csv << "experiment_defocus_um";
    for (double z : r.sim_defocus_um) csv << "," << z;
    csv << "\n";
    for (size_t i = 0; i < m.matrix.size(); ++i) {
      csv << r.exp_defocus_um[i];
      for (double v : m.matrix[i]) csv << "," << v;
      csv << "\n";
    }
    WriteTextFileAtomic(d / (name + "_matrix.csv"), csv.str());
    const std::string png = (d / ("heatmap_" + name + ".png")).string();
    Heatmap(r, m, png);
    html += "<h3>" + name + " <span class='" + (m.passes ? "pass'>passes" : "fail'>fails") +
            "</span>" + (m.primary ? "" : " <small>(informational, not in the verdict)</small>") +
            "</h3>" + EmbeddedPng(png, name + " heatmap") + "<table><tr><th>exp z \\ sim z</th>";
    for (double z : r.sim_defocus_um) html += "<th>" + Fmt(z) + "</th>";
    html += "</tr>";
    for (size_t i = 0; i < m.matrix.size(); ++i) {
      html += "<tr><th>" + Fmt(r.exp_defocus_um[i]) + "</th>";
      for (size_t jj = 0; jj < m.matrix[i].size(); ++jj)
        html += std::string("<td") + (int(jj) == m.best[i] ? " style='background:#ffd'" : "") +
                ">" + Fmt(m.matrix[i][jj]) + "</td>";
      html += "</tr>";
    }
    html += "</table>";
  }
  html +=
      "<h2>Per plane: residuals and radial profiles</h2><p>Left: (sim &minus; exp) / "
      "&radic;(s&middot;sim + exp) per pixel, in shot-noise standard deviations (blue: "
      "simulation too dark, red: too bright; clamped at &plusmn;4), where s = " +
      Fmt(r.sim_scale) +
      " is the factor the simulation was scaled by (s = 1 when photon-matched: (sim &minus; "
      "exp) / &radic;(sim + exp)). Right: azimuthal means about the image "
      "centre with one pixel's &plusmn;1&sigma; shot-noise band. Each experimental plane is "
      "paired with the simulation plane nearest in defocus.</p>";
  std::string figures = "<table class='planes'>";
  std::string fit_table =
      "<p>Goodness of fit per plane: the focus-scan test says each plane is matched to the "
      "right defocus; this says whether that simulation describes the plane within the shot "
      "noise. For two independent Poisson images of one mean the mean square residual is 1 with "
      "a standard deviation of &radic;(2/N) over N pixels; 3 standard deviations above is a "
      "misfit.</p><table><tr><th>experiment z (um)</th><th>simulation z (um)</th><th>mean "
      "square residual</th><th>expected</th><th>standard deviations</th><th>verdict</th></tr>";
  for (int i = 0; i < int(r.exp_images.size()); ++i) {
    const std::string res = (d / ("plane_" + std::to_string(i) + "_residual.png")).string();
    const std::string prof = (d / ("plane_" + std::to_string(i) + "_profile.png")).string();
    const PlaneGoodness& g = goodness[size_t(i)];
    PlaneFigures(r, i, g.mean_square, res, prof);
    std::ostringstream row;
    row.precision(3);
    row << "<tr><td>" << g.exp_defocus_um << "</td><td>" << g.sim_defocus_um << "</td><td>"
        << g.mean_square << "</td><td>1 &plusmn; " << g.expected_sd << "</td><td>" << g.z
        << "</td><td>" << (g.misfit ? "misfit beyond the shot noise" : "within the shot noise")
        << "</td></tr>";
    fit_table += row.str();
    figures += "<tr><td>" + EmbeddedPng(res, "residual at " + Fmt(r.exp_defocus_um[i]) + " um") +
               "</td><td>" +
               EmbeddedPng(prof, "radial profile at " + Fmt(r.exp_defocus_um[i]) + " um") +
               "</td></tr>";
  }
  html += fit_table + "</table>" + figures + "</table>";
  html += "<p style='color:#777'>raymatch compare-scan, " + UtcTimestamp() + ": " + CommandLine() +
          "</p></body></html>\n";
  const std::string report = (d / "report.html").string();
  WriteTextFileAtomic(report, html);
  return report;
}

}  // namespace raymatch::compare
