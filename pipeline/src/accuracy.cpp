#include "raymatch/pipeline/accuracy.h"

#include <cmath>
#include <filesystem>
#include <iostream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "raymatch/compare/focus_scan.h"
#include "raymatch/compare/plot.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/provenance.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/tracer.h"

namespace fs = std::filesystem;

namespace raymatch::pipeline {
using compare::Series;
using compare::WritePlot;

namespace {

/// MSE, SSIM, MS-SSIM, CW-SSIM and Poisson chi^2 between two images of the same exposure.
std::vector<double> Measures(const Image& a, const Image& b, double L) {
  compare::SsimOptions so;
  so.data_range = L;
  compare::MsSsimOptions mo;
  mo.data_range = L;
  compare::CwSsimOptions co;
  co.data_range = L;
  return {compare::MeanSquaredError(a, b), compare::Ssim(a, b, so).ssim,
          compare::MsSsim(a, b, mo).ms_ssim, compare::CwSsim(a, b, co).cw_ssim,
          compare::PoissonMeasures(a, b).chi2_per_pixel};
}

Image Scaled(const Image& img, double f) {
  Image o = img;
  for (float& v : o.pixels) v = float(v * f);
  return o;
}

}  // namespace

AccuracyResult RunAccuracyStudy(const AccuracyOptions& o) {
  AccuracyResult res;
  res.measures = {"mse", "ssim", "ms_ssim", "cw_ssim", "poisson_chi2"};
  const simulate::Scene scene = simulate::LoadScene(o.scene_file);
  const simulate::Simulator sim(scene);
  const uint64_t full = sim.RaysPerImage();
  simulate::RunControl ctl;
  ctl.threads = o.threads;
  std::cerr << "raymatch bench accuracy: reference with " << o.reference_factor << " x " << full
            << " rays" << std::endl;
  const simulate::PlaneResult ref =
      sim.TracePlane(o.defocus_um, 1000, uint64_t(full * o.reference_factor), ctl);
  const Image ref_img = Scaled(ref.counts, 1 / o.reference_factor);  // photon-matched level
  double L = 0;
  for (float v : ref_img.pixels) L = std::max(L, double(v));
  Image exp_img;
  if (!o.experiment_csv.empty()) {
    const compare::Stack st = compare::ReadStack(o.experiment_csv);
    size_t k = 0;
    for (size_t i = 1; i < st.defocus_um.size(); ++i)
      if (std::abs(st.defocus_um[i] - o.defocus_um) < std::abs(st.defocus_um[k] - o.defocus_um))
        k = i;
    compare::Stack one{{st.defocus_um[k]}, {st.images[k]}, {st.files[k]}};
    compare::Stack rs{{o.defocus_um}, {ref_img}, {"reference"}};
    compare::FocusScanOptions fo;  // prepare + register the experiment against the reference
    fo.prepare.dark_file = o.dark_file;
    fo.prepare.gain_e_per_dn = o.gain_e_per_dn;
    fo.measures = {compare::Measure::kMse};
    const compare::FocusScanResult fr = compare::RunFocusScan(one, rs, fo);
    exp_img = Scaled(fr.exp_images[0], 1 / fr.sim_scale);  // to the simulation's exposure
  }
  for (int d = 1; d <= o.max_divisor; d *= 2) {
    AccuracyRow row;
    row.fraction = 1.0 / d;
    row.rays = std::max<uint64_t>(1, full / d);
    const simulate::PlaneResult r = sim.TracePlane(o.defocus_um, uint32_t(d), row.rays, ctl);
    row.seconds = r.seconds;
    row.rays_per_second = r.rays / std::max(r.seconds, 1e-9);
    const Image img = Scaled(r.counts, double(full) / row.rays);
    const double mean = ComputeStats(r.counts).mean;
    row.relative_shot_noise = mean > 0 ? 1 / std::sqrt(mean) : 0;
    row.vs_reference = Measures(img, ref_img, L);
    if (!exp_img.empty()) row.vs_experiment = Measures(img, exp_img, L);
    std::cerr << "  fraction 1/" << d << ": " << row.rays << " rays, " << row.seconds << " s"
              << std::endl;
    res.rows.push_back(row);
  }
  EnsureDirectory(o.output_dir);
  std::ostringstream csv;
  csv << "fraction,rays,seconds,rays_per_second,relative_shot_noise";
  for (const auto& m : res.measures) csv << ",ref_" << m;
  if (!exp_img.empty())
    for (const auto& m : res.measures) csv << ",exp_" << m;
  csv << "\n";
  nlohmann::json rows = nlohmann::json::array();
  for (const AccuracyRow& r : res.rows) {
    csv << r.fraction << "," << r.rays << "," << r.seconds << "," << r.rays_per_second << ","
        << r.relative_shot_noise;
    for (double v : r.vs_reference) csv << "," << v;
    for (double v : r.vs_experiment) csv << "," << v;
    csv << "\n";
    rows.push_back({{"fraction", r.fraction},
                    {"rays", r.rays},
                    {"seconds", r.seconds},
                    {"rays_per_second", r.rays_per_second},
                    {"relative_shot_noise", r.relative_shot_noise},
                    {"vs_reference", r.vs_reference},
                    {"vs_experiment", r.vs_experiment}});
  }
  res.csv = (fs::path(o.output_dir) / "accuracy.csv").string();
  WriteTextFileAtomic(res.csv, csv.str());
  const nlohmann::json j = {{"provenance", ProvenanceJson()}, {"scene", o.scene_file},
                            {"defocus_um", o.defocus_um},     {"photon_matched_rays", full},
                            {"measures", res.measures},       {"rows", rows}};
  WriteTextFileAtomic(fs::path(o.output_dir) / "accuracy.json", j.dump(2) + "\n");
  // Accuracy against time: MS-SSIM and the Poisson chi^2 per pixel (both measures), against the
  // reference and, when given, the experiment, over the tracing time of each ray fraction.
  compare::PlotPanel ms, chi;
  ms.title = "MS-SSIM against tracing time (one point per ray fraction 1, 1/2, 1/4, ...)";
  ms.ylabel = "MS-SSIM (dimensionless; 1 = identical)";
  chi.title = "Poisson χ² per pixel against tracing time";
  chi.ylabel = "χ² per pixel (dimensionless)";
  for (compare::PlotPanel* p : {&ms, &chi}) {
    p->xlabel = "tracing time (s)";
    p->log_x = true;
    p->series.resize(exp_img.empty() ? 1 : 2);
    for (compare::Series& s : p->series) s.points = s.joined = true;
    std::ostringstream ref;
    ref << "vs the reference (" << o.reference_factor << " x the photon-matched rays)";
    p->series[0].label = ref.str();
    if (p->series.size() > 1) p->series[1].label = "vs the experiment";
  }
  for (const AccuracyRow& r : res.rows) {
    const double t = std::max(r.seconds, 1e-6);
    for (compare::PlotPanel* p : {&ms, &chi}) {
      const size_t k = p == &ms ? 2 : 4;
      p->series[0].x.push_back(t), p->series[0].y.push_back(r.vs_reference[k]);
      if (p->series.size() > 1)
        p->series[1].x.push_back(t), p->series[1].y.push_back(r.vs_experiment[k]);
    }
  }
  res.plot = (fs::path(o.output_dir) / "accuracy.png").string();
  WritePlot(res.plot, {ms, chi}, 760, 400);
  return res;
}

}  // namespace raymatch::pipeline
