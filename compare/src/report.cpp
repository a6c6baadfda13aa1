// Focus-scan outputs: JSON, CSV, PNG heatmaps and montage, and a self-contained HTML report.
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "raymatch/compare/focus_scan.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/html.h"
#include "bgr_png.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/provenance.h"

namespace fs = std::filesystem;

namespace raymatch::compare {

namespace {


/// Heatmap of a matrix (rows: experiment, columns: simulation), viridis, best cells outlined.
void Heatmap(const MeasureScan& m, const std::string& path) {
  const int ne = int(m.matrix.size()), ns = int(m.matrix[0].size()), cell = 28;
  double lo = 1e300, hi = -1e300;
  for (auto& row : m.matrix)
    for (double v : row) lo = std::min(lo, v), hi = std::max(hi, v);
  cv::Mat g(ne, ns, CV_8U);
  for (int i = 0; i < ne; ++i)
    for (int j = 0; j < ns; ++j) {
      double t = hi > lo ? (m.matrix[i][j] - lo) / (hi - lo) : 1.0;
      if (!HigherIsBetter(m.measure)) t = 1 - t;  // bright = good for every measure
      g.at<uchar>(i, j) = cv::saturate_cast<uchar>(t * 255);
    }
  cv::Mat c, big;
  cv::applyColorMap(g, c, cv::COLORMAP_VIRIDIS);
  cv::resize(c, big, cv::Size(ns * cell, ne * cell), 0, 0, cv::INTER_NEAREST);
  for (int i = 0; i < ne; ++i) {
    cv::rectangle(big, cv::Rect(m.best[i] * cell + 2, i * cell + 2, cell - 4, cell - 4),
                  cv::Scalar(255, 255, 255), 2);
    cv::rectangle(big, cv::Rect(m.expected[i] * cell + 9, i * cell + 9, cell - 18, cell - 18),
                  cv::Scalar(0, 0, 255), cv::FILLED);
  }
  WriteBgrPng(path, big);
}

/// Experiment (top row) and simulation at the nearest defocus (bottom row), same grey scale.
void Montage(const FocusScanResult& r, const std::string& path) {
  const int w = r.exp_images[0].width, h = r.exp_images[0].height, n = int(r.exp_images.size());
  cv::Mat out(2 * h + 4, n * (w + 4), CV_8UC3, cv::Scalar(40, 40, 40));
  const double L = r.data_range;
  for (int i = 0; i < n; ++i) {
    int best = 0;
    for (size_t j = 1; j < r.sim_defocus_um.size(); ++j)
      if (std::abs(r.sim_defocus_um[j] - r.exp_defocus_um[i]) <
          std::abs(r.sim_defocus_um[best] - r.exp_defocus_um[i]))
        best = int(j);
    for (int row = 0; row < 2; ++row) {
      const Image& img = row == 0 ? r.exp_images[i] : r.sim_images[best];
      for (int y = 0; y < h; ++y)
        for (int x = 0; x < w; ++x) {
          const uchar v = cv::saturate_cast<uchar>(img.at(x, y) / L * 255);
          out.at<cv::Vec3b>(row * (h + 4) + y, i * (w + 4) + x) = cv::Vec3b(v, v, v);
        }
    }
  }
  WriteBgrPng(path, out);
}

std::string Fmt(double v) {
  std::ostringstream os;
  os.precision(6);
  os << v;
  return os.str();
}

}  // namespace

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
      "img{image-rendering:pixelated;max-width:100%}</style></head><body>"
      "<h1>" + title + "</h1>";
  const char* verdict = r.verdict == Verdict::kPass ? "pass" : r.verdict == Verdict::kWarning ? "warning" : "fail";
  html += "<p><b>Verdict: <span class='" + std::string(r.verdict == Verdict::kPass ? "pass" : "fail") +
          "'>" + verdict + "</span></b> &mdash; " + r.message + "</p>";
  html += "<p>Dynamic range L = " + Fmt(r.data_range) + "; MS-SSIM " +
          std::to_string(r.ms_ssim.num_scales) + " scales (" + MsSsimWeightsName(r.ms_ssim.weights) +
          " weights); CW-SSIM level " + std::to_string(r.cw_ssim.level) + ", " +
          std::to_string(r.cw_ssim.orientations) + " orientations, K " + Fmt(r.cw_ssim.k) +
          "; " + r.RegistrationSummary() + "; simulation scaled by " + Fmt(r.sim_scale) + ".</p>";
  Montage(r, (d / "montage.png").string());
  html += "<h2>Experiment (top) and simulation (bottom)</h2><p>Defocus (um): ";
  for (double z : r.exp_defocus_um) html += Fmt(z) + " ";
  html += "</p>" + EmbeddedPng((d / "montage.png").string());
  html += "<h2>Cross-similarity (rows: experiment z, columns: simulation z)</h2>"
          "<p>Bright = better match; white box = best match; red dot = same defocus.</p>";
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
    Heatmap(m, png);
    html += "<h3>" + name + " <span class='" + (m.passes ? "pass'>passes" : "fail'>fails") +
            "</span></h3>" + EmbeddedPng(png) + "<table><tr><th>exp z \\ sim z</th>";
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
  html += "<p style='color:#777'>raymatch compare-scan, " + UtcTimestamp() + ": " + CommandLine() +
          "</p></body></html>\n";
  const std::string report = (d / "report.html").string();
  WriteTextFileAtomic(report, html);
  return report;
}

}  // namespace raymatch::compare
