// raymatch sensitivity: the Fisher information and Cramer-Rao bounds of scene keys at the
// scene's values, and the choice of focal planes (sensitivity.h, docs/sensitivity.md).
#include "raymatch/fit/sensitivity.h"

#include <Eigen/Dense>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <numeric>
#include <sstream>

#include "model.h"
#include "numbers.h"
#include "raymatch/compare/plot.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/html.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/provenance.h"
#include "raymatch/core/toml_reader.h"
#include "raymatch/fit/fit.h"
#include "raymatch/simulate/physical_image.h"
#include "raymatch/simulate/scene.h"
#include "runner.h"

namespace raymatch::fit {

namespace fs = std::filesystem;
using internal::FromEigen;
using internal::Matrix;
using internal::ToEigen;

SensitivitySpec SensitivitySceneSpec(const std::string& scene, const std::string& calibration) {
  SensitivitySpec spec;
  spec.scene_file = fs::absolute(scene).string();
  spec.scene = ParseTomlFile(spec.scene_file);
  if (!calibration.empty())
    spec.scene.insert_or_assign("calibration", fs::absolute(calibration).string());
  return spec;
}

double DefaultSensitivityStep(const std::string& key, double value) {
  const std::string unit = UnitOf(key);
  if (unit == "um") return 0.2;
  if (unit == "deg") return 0.5;
  if (key.ends_with("index") || key.ends_with("n0")) return 0.002;
  if (key.find("background_") != std::string::npos) return 0.5;
  return std::max(1e-3, 0.01 * std::abs(value));
}

namespace {

/// The keys' values: image keys from the images (defocus) or 0 (backgrounds), the rest from the
/// scene. Throws Error naming the key.
double KeyValue(const SensitivitySpec& spec, const std::string& key,
                const std::vector<double>& defocus) {
  if (!key.starts_with("image")) return SceneValue(spec.scene, key, spec.scene_file);
  const auto image_key = ParseImageKey(key, defocus.size());
  if (!image_key) throw Error("key '" + key + "': " + ImageKeysHelp(defocus.size()));
  return image_key->second == "defocus_um" ? defocus[image_key->first] : 0.0;
}

/// The Schur complement of the last row and column (a nuisance profiled out).
Eigen::MatrixXd ProfileLast(const Eigen::MatrixXd& f) {
  const Eigen::Index p = f.rows() - 1;
  const double ee = f(p, p);
  Eigen::MatrixXd out = f.topLeftCorner(p, p);
  if (ee > 0) out -= f.topRightCorner(p, 1) * f.bottomLeftCorner(1, p) / ee;
  return out;
}

/// Square roots of the inverse's diagonal; empty when the matrix is not positive definite.
std::vector<double> Bounds(const Eigen::MatrixXd& f) {
  const Matrix inv = InverseSpd(FromEigen(f));
  std::vector<double> b;
  for (size_t i = 0; i < inv.size(); ++i) b.push_back(inv[i][i] > 0 ? std::sqrt(inv[i][i]) : NAN);
  return b;
}

/// Derivative images of one ray-stream set: per image, the keys' then the log-exposure's (mu).
struct SetImages {
  std::vector<Image> mu;
  std::vector<std::vector<Image>> d;  // [image][key, then exposure]
};

/// Per image, the information of the chosen sets (cross products of their even and odd halves:
/// unbiased by the derivatives' own noise), keys then log-exposure.
std::vector<Eigen::MatrixXd> Information(const std::vector<SetImages>& sets,
                                         const std::vector<Image>& mu,
                                         const std::vector<size_t>& use, double read_variance) {
  const size_t K = mu.size(), Q = sets[0].d[0].size();
  std::vector<Eigen::MatrixXd> out;
  for (size_t k = 0; k < K; ++k) {
    std::vector<std::vector<Image>> half[2];
    for (int h = 0; h < 2; ++h) half[h].assign(1, std::vector<Image>(Q));
    int count[2] = {0, 0};
    for (size_t s : use) {
      const int h = int(s % 2);
      ++count[h];
      for (size_t i = 0; i < Q; ++i) {
        Image& a = half[h][0][i];
        const Image& b = sets[s].d[k][i];
        if (a.empty()) a = Image(b.width, b.height);
        for (size_t q = 0; q < b.size(); ++q) a.pixels[q] += b.pixels[q];
      }
    }
    for (int h = 0; h < 2; ++h)
      for (Image& a : half[h][0])
        for (float& v : a.pixels) v /= float(count[h]);
    out.push_back(
        ToEigen(FisherInformation({mu[k]}, half[0], half[1], std::vector<double>{read_variance})));
  }
  return out;
}

struct Bound {
  std::vector<double> crb, crb_known;
  Eigen::MatrixXd fisher;
  std::vector<Eigen::MatrixXd> per_image;  // keys x keys, nuisance profiled out when asked
};

Bound BoundsOf(const std::vector<Eigen::MatrixXd>& info, size_t P, bool nuisance) {
  Bound b;
  b.fisher = Eigen::MatrixXd::Zero(Eigen::Index(P), Eigen::Index(P));
  Eigen::MatrixXd known = b.fisher;
  for (const Eigen::MatrixXd& f : info) {
    b.per_image.push_back(nuisance ? ProfileLast(f)
                                   : f.topLeftCorner(Eigen::Index(P), Eigen::Index(P)));
    b.fisher += b.per_image.back();
    known += f.topLeftCorner(Eigen::Index(P), Eigen::Index(P));
  }
  b.crb = Bounds(b.fisher);
  b.crb_known = Bounds(known);
  return b;
}

}  // namespace

std::vector<DesignChoice> RankDesigns(const std::vector<Matrix>& per_image,
                                      const std::vector<double>& defocus_um, int planes,
                                      const std::vector<size_t>& design_keys, size_t* compared) {
  const size_t K = per_image.size();
  std::vector<DesignChoice> all;
  if (planes < 1 || size_t(planes) > K) return all;
  std::vector<size_t> pick(static_cast<size_t>(planes));
  std::iota(pick.begin(), pick.end(), 0);
  for (;;) {
    Eigen::MatrixXd f = ToEigen(per_image[pick[0]]);
    for (size_t j = 1; j < pick.size(); ++j) f += ToEigen(per_image[pick[j]]);
    f /= double(planes);  // one image's photons shared among the planes
    DesignChoice c;
    for (size_t j : pick) c.defocus_um.push_back(defocus_um[j]);
    c.crb = Bounds(f);
    double log_sum = 0;
    bool ok = !c.crb.empty();
    for (size_t i : design_keys) {
      ok = ok && std::isfinite(c.crb[i]) && c.crb[i] > 0;
      if (ok) log_sum += std::log(c.crb[i]);
    }
    c.objective = ok ? std::exp(log_sum / double(design_keys.size())) : INFINITY;
    if (c.crb.empty()) c.crb.assign(per_image[0].size(), NAN);
    all.push_back(std::move(c));
    // Next combination in lexicographic order.
    int j = planes - 1;
    while (j >= 0 && pick[size_t(j)] == K - size_t(planes) + size_t(j)) --j;
    if (j < 0) break;
    ++pick[size_t(j)];
    for (size_t m = size_t(j) + 1; m < pick.size(); ++m) pick[m] = pick[m - 1] + 1;
  }
  if (compared) *compared = all.size();
  std::stable_sort(all.begin(), all.end(), [](const DesignChoice& a, const DesignChoice& b) {
    return a.objective < b.objective;
  });
  return all;
}

namespace {

/// The fit specification whose model and derivative machinery the sensitivity runs on: the
/// scene's images (empty: the expected images are what counts) at the focus positions, one
/// parameter per key spanning its difference step, the exposure known. Fills `r`'s keys and
/// `theta` with the keys' values.
FitSpec SensitivityFitSpec(const SensitivitySpec& spec, const simulate::Scene& scene,
                           const FileLocation& where, SensitivityResult* r,
                           std::vector<double>* theta) {
  FitSpec fs;
  fs.file = spec.scene_file;
  fs.scene_file = spec.scene_file;
  fs.scene = spec.scene;
  fs.seed = spec.seed;
  fs.threads = spec.threads;
  fs.rays.ray_factor = spec.ray_factor;
  fs.rays.fractions = {1.0};
  fs.rays.photons_per_pixel = r->photons_per_pixel;
  fs.rays.fit_exposure = false;  // the exposure's information enters as a parameter below
  // An image model without simulation noise (optics = "mie" or "physical"): every set is the
  // same images, so one is computed and copied, with a tenth of the step (no noise to outrun;
  // the fringes' linear range).
  fs.optics = simulate::ImageOpticsName(scene.trace.optics);
  for (double d : r->defocus_um) {
    FitImage fi;
    fi.defocus_um = d;
    fi.photons = Image(scene.camera.nx, scene.camera.ny);
    fi.read_noise_e = spec.read_noise_e;
    fi.where = where;
    fs.images.push_back(std::move(fi));
  }
  for (size_t i = 0; i < spec.keys.size(); ++i) {
    Parameter q;
    q.key = spec.keys[i];
    for (const Parameter& other : fs.parameters)
      if (other.key == q.key) throw Error(where, "key '" + q.key + "' is given twice");
    try {
      q.start = KeyValue(spec, q.key, r->defocus_um);
    } catch (const Error& e) {
      throw Error(where, e.message());
    }
    q.step = i < spec.steps.size() && spec.steps[i] > 0 ? spec.steps[i]
                                                        : DefaultSensitivityStep(q.key, q.start);
    q.lower = q.start - q.step, q.upper = q.start + q.step;  // the differences' span, inside
    q.unit = UnitOf(q.key);
    fs.parameters.push_back(q);
    theta->push_back(q.start);
    SensitivityKey k;
    k.key = q.key, k.unit = q.unit, k.value = q.start, k.step = q.step;
    r->keys.push_back(k);
  }
  return fs;
}

/// The mean image and derivative maps over all sets.
void MeanOverSets(const std::vector<SetImages>& sets, size_t K, size_t P, SensitivityResult* r) {
  r->mu.assign(K, Image());
  r->dmu.assign(K, std::vector<Image>(P));
  for (size_t k = 0; k < K; ++k) {
    r->mu[k] = Image(sets[0].mu[k].width, sets[0].mu[k].height);
    for (size_t i = 0; i < P; ++i) r->dmu[k][i] = Image(r->mu[k].width, r->mu[k].height);
    for (const SetImages& set : sets) {
      for (size_t q = 0; q < r->mu[k].size(); ++q) {
        r->mu[k].pixels[q] += set.mu[k].pixels[q] / float(sets.size());
        for (size_t i = 0; i < P; ++i)
          r->dmu[k][i].pixels[q] += set.d[k][i].pixels[q] / float(sets.size());
      }
    }
  }
}

/// The best sets of 1 .. design_planes focus positions for the design keys.
void RankDesignPlanes(const SensitivitySpec& spec,
                      const std::vector<Eigen::MatrixXd>& per_image_information, size_t K, size_t P,
                      const FileLocation& where, SensitivityResult* r) {
  if (size_t(spec.design_planes) > K)
    throw Error(where, "design: " + std::to_string(spec.design_planes) +
                           " planes asked for, but only " + std::to_string(K) +
                           " candidate focus positions given");
  std::vector<size_t> dk;
  for (const std::string& key : spec.design_keys) {
    const auto it = std::find(spec.keys.begin(), spec.keys.end(), key);
    if (it == spec.keys.end()) throw Error(where, "design key '" + key + "' is not among the keys");
    dk.push_back(size_t(it - spec.keys.begin()));
  }
  if (dk.empty()) {
    dk.resize(P);
    std::iota(dk.begin(), dk.end(), 0);
  }
  for (size_t i : dk) r->design_keys.push_back(spec.keys[i]);
  std::vector<Matrix> per_image;
  for (const Eigen::MatrixXd& f : per_image_information) per_image.push_back(FromEigen(f));
  for (int n = 1; n <= spec.design_planes; ++n) {
    size_t compared = 0;
    std::vector<DesignChoice> ranked = RankDesigns(per_image, r->defocus_um, n, dk, &compared);
    if (!ranked.empty()) r->design_best.push_back(ranked.front());
    if (n == spec.design_planes) {
      r->design_choices = compared;
      ranked.resize(std::min<size_t>(ranked.size(), 10));
      r->design_top = std::move(ranked);
    }
  }
}

}  // namespace

SensitivityResult RunSensitivity(const SensitivitySpec& spec, bool progress) {
  const auto t0 = std::chrono::steady_clock::now();
  const FileLocation where{spec.scene_file};
  if (spec.keys.empty()) throw Error(where, "no keys: name at least one scene key");
  if (spec.sets < 4 || spec.sets % 2) throw Error(where, "sets: expected an even number >= 4");
  const simulate::Scene scene = simulate::LoadScene(spec.scene, spec.scene_file);
  if (scene.trace.optics == simulate::ImageOptics::kPhysical)
    if (const std::string why = simulate::PhysicalUnsupportedReason(scene); !why.empty())
      throw Error(where, why);
  SensitivityResult r;
  r.defocus_um = spec.defocus_um.empty() ? scene.defocus_um : spec.defocus_um;
  r.photons_per_pixel =
      spec.photons_per_pixel > 0 ? spec.photons_per_pixel : scene.trace.photons_per_pixel;
  if (!(r.photons_per_pixel > 0))
    throw Error(where,
                "no photon count: give --photons-per-pixel (or [trace] photons_per_pixel in the "
                "scene)");

  std::vector<double> theta;
  FitSpec fs = SensitivityFitSpec(spec, scene, where, &r, &theta);
  const double step_scale = fs.exact_images() ? 0.1 : 1.0;
  const size_t P = theta.size(), K = fs.images.size();
  auto say = [&](const std::string& m) {
    if (progress) std::fprintf(stderr, "raymatch sensitivity: %s\n", m.c_str());
  };
  FitModel model(fs, spec.threads, say);
  r.rays_per_image = model.RaysAt(1.0);
  r.object_pixel_um = model.object_pixel_um();

  // Derivative images per ray-stream set: central differences with common random numbers.
  std::vector<SetImages> sets(size_t(spec.sets));
  uint64_t rays = 0;
  for (size_t s = 0; s < sets.size(); ++s) {
    if (fs.exact_images() && s > 0) {
      sets[s] = sets[0];
      continue;
    }
    const uint64_t seed = spec.seed + internal::kDerivativeSetSeedStride * s;
    SetImages& set = sets[s];
    set.mu = model.Expected(theta, 1.0, seed, &rays).photons;
    set.d.assign(K, std::vector<Image>(P + 1));
    for (size_t i = 0; i < P; ++i) {
      std::vector<double> a = theta, b = theta;
      a[i] += 0.5 * step_scale * fs.parameters[i].step;
      b[i] -= 0.5 * step_scale * fs.parameters[i].step;
      const Simulated ma = model.Expected(a, 1.0, seed, &rays);
      const Simulated mb = model.Expected(b, 1.0, seed, &rays);
      for (size_t k = 0; k < K; ++k) {
        Image& d = set.d[k][i];
        d = Image(ma.photons[k].width, ma.photons[k].height);
        for (size_t q = 0; q < d.size(); ++q)
          d.pixels[q] =
              float((double(ma.photons[k].pixels[q]) - mb.photons[k].pixels[q]) / (a[i] - b[i]));
      }
      r.evaluations += 2;
    }
    for (size_t k = 0; k < K; ++k) set.d[k][P] = set.mu[k];  // d mu / d ln(exposure) = mu
    ++r.evaluations;
    if (progress)
      say("ray-stream set " + std::to_string(s + 1) + " of " + std::to_string(sets.size()) +
          " done");
  }
  MeanOverSets(sets, K, P, &r);
  const double rv = spec.read_noise_e * spec.read_noise_e;
  std::vector<size_t> all(sets.size());
  std::iota(all.begin(), all.end(), 0);
  const std::vector<Eigen::MatrixXd> info = Information(sets, r.mu, all, rv);
  const Bound b = BoundsOf(info, P, spec.exposure_nuisance);
  if (b.crb.empty())
    throw Error(where,
                "the information matrix is not positive definite: a key does not change the "
                "images, two keys change them alike, or the derivative images are dominated by "
                "their Monte Carlo noise (then raise --ray-factor or the steps)");
  r.fisher = FromEigen(b.fisher);
  const Matrix cov = InverseSpd(r.fisher);
  r.correlation = cov;
  for (size_t i = 0; i < P; ++i)
    for (size_t j = 0; j < P; ++j)
      r.correlation[i][j] = cov[i][j] / std::sqrt(cov[i][i] * cov[j][j]);
  r.exposure_relative_crb = info[0](Eigen::Index(P), Eigen::Index(P)) > 0
                                ? 1 / std::sqrt(info[0](Eigen::Index(P), Eigen::Index(P)))
                                : NAN;
  // The bound's Monte Carlo error: a delete-one jackknife over the sets (each replicate the
  // cross product of the remaining even and odd sets): S - 1 degrees of freedom.
  const size_t n = sets.size();
  std::vector<std::vector<double>> jack;
  for (size_t leave = 0; leave < n; ++leave) {
    std::vector<size_t> use;
    for (size_t s : all)
      if (s != leave) use.push_back(s);
    jack.push_back(BoundsOf(Information(sets, r.mu, use, rv), P, spec.exposure_nuisance).crb);
  }
  std::vector<std::vector<double>> per_image_bounds;  // each image alone
  for (const Eigen::MatrixXd& f : b.per_image) per_image_bounds.push_back(Bounds(f));
  for (size_t i = 0; i < P; ++i) {
    SensitivityKey& k = r.keys[i];
    k.crb = b.crb[i];
    k.crb_exposure_known = b.crb_known[i];
    double mean = 0, var = 0;
    for (const auto& j : jack) mean += (j.empty() ? NAN : j[i]) / double(n);
    for (const auto& j : jack) var += std::pow((j.empty() ? NAN : j[i]) - mean, 2);
    k.crb_mc_error = std::sqrt(double(n - 1) / double(n) * var);
    for (const std::vector<double>& one : per_image_bounds)
      k.crb_per_image.push_back(one.empty() ? INFINITY : one[i]);
  }
  if (spec.design_planes > 0) RankDesignPlanes(spec, b.per_image, K, P, where, &r);
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return r;
}

namespace {

using internal::J;

std::string Num(double v, int digits = 4) { return internal::Num(v, digits); }

/// "object.drop.center_um[2]" -> "object.drop.center_um_2_" (for file names).
std::string Slug(const std::string& key) {
  std::string s;
  for (char c : key)
    s += std::isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '-' ? c : '_';
  return s;
}

nlohmann::json DesignJson(const DesignChoice& c, const SensitivityResult& r) {
  nlohmann::json crb = nlohmann::json::object();
  for (size_t i = 0; i < r.keys.size(); ++i) crb[r.keys[i].key] = J(c.crb[i]);
  return {{"defocus_um", c.defocus_um}, {"crb", crb}, {"objective", J(c.objective)}};
}

/// The derivative maps: a float TIFF (photons per pixel per unit) and a labelled PNG per key and
/// image, in `dir`; returns their HTML figures.
std::string WriteDerivativeMaps(const SensitivityResult& r, const fs::path& dir) {
  const double px = r.object_pixel_um;
  std::ostringstream maps;
  for (size_t k = 0; k < r.mu.size(); ++k) {
    char plane[32];
    std::snprintf(plane, sizeof plane, "z%+07.2fum", r.defocus_um[k]);
    for (size_t i = 0; i < r.keys.size(); ++i) {
      const SensitivityKey& key = r.keys[i];
      const std::string stem = "dmu_" + Slug(key.key) + "_" + plane;
      const std::string unit = key.unit.empty() ? "unit" : key.unit;
      nlohmann::json meta = {{"quantity", "d mu / d " + key.key},
                             {"unit", "photons per pixel per " + unit},
                             {"defocus_um", r.defocus_um[k]},
                             {"provenance", ProvenanceJson()}};
      WriteFloatImage((dir / (stem + ".tif")).string(), r.dmu[k][i], meta.dump());
      compare::MapPlot p;
      p.image = r.dmu[k][i];
      double m = 0;
      for (float v : p.image.pixels) m = std::max(m, double(std::abs(v)));
      p.lo = -m, p.hi = m > 0 ? m : 1;
      if (!(m > 0)) p.lo = -1;
      p.map = compare::ColourMap::kDiverging;
      p.x_left = -0.5 * px * p.image.width, p.x_right = 0.5 * px * p.image.width;
      p.y_top = 0.5 * px * p.image.height, p.y_bottom = -0.5 * px * p.image.height;
      p.title = "d mu / d " + key.key + " at focus " + Num(r.defocus_um[k]) + " µm";
      p.xlabel = "x at the object (µm)", p.ylabel = "y at the object (µm)";
      p.colour_label = "photons per pixel per " + unit;
      p.max_side_px = 360;
      compare::WriteMap((dir / (stem + ".png")).string(), p);
      maps << "<figure style=\"display:inline-block\">"
           << EmbeddedPng((dir / (stem + ".png")).string(), stem) << "<figcaption>" << stem
           << ".tif</figcaption></figure>\n";
    }
  }
  return maps.str();
}

}  // namespace

std::string WriteSensitivityOutputs(const SensitivitySpec& spec, const SensitivityResult& r,
                                    const std::string& dir_name) {
  const fs::path dir(dir_name);
  EnsureDirectory(dir);
  nlohmann::json keys = nlohmann::json::array();
  for (const SensitivityKey& k : r.keys)
    keys.push_back({{"key", k.key},
                    {"unit", k.unit},
                    {"value", k.value},
                    {"step", k.step},
                    {"crb", J(k.crb)},
                    {"crb_mc_error", J(k.crb_mc_error)},
                    {"crb_mc_error_large", !(k.crb_mc_error <= 0.05 * k.crb)},
                    {"crb_exposure_known", J(k.crb_exposure_known)},
                    {"crb_per_image", [&] {
                       nlohmann::json a = nlohmann::json::array();
                       for (double v : k.crb_per_image) a.push_back(J(v));
                       return a;
                     }()}});
  nlohmann::json j = {
      {"provenance", ProvenanceJson()},
      {"scene_file", spec.scene_file},
      {"defocus_um", r.defocus_um},
      {"photons_per_pixel", r.photons_per_pixel},
      {"ray_factor", spec.ray_factor},
      {"rays_per_image", r.rays_per_image},
      {"sets", spec.sets},
      {"evaluations", r.evaluations},
      {"exposure",
       spec.exposure_nuisance ? "nuisance (each image's exposure unknown, profiled out)" : "known"},
      {"read_noise_e", spec.read_noise_e},
      {"exposure_relative_crb", J(r.exposure_relative_crb)},
      {"keys", keys},
      {"fisher", r.fisher},
      {"correlation", r.correlation},
      {"seconds", r.seconds},
      {"method",
       "Fisher information sum dmu_i dmu_j / (mu + read_noise^2) over the pixels of all images; "
       "derivatives by central differences with common random numbers, the cross product of "
       "independent ray-stream halves (unbiased); crb_mc_error: delete-one jackknife over the "
       "sets"}};
  if (!r.design_best.empty()) {
    nlohmann::json best = nlohmann::json::array(), top = nlohmann::json::array();
    for (const DesignChoice& c : r.design_best) best.push_back(DesignJson(c, r));
    for (const DesignChoice& c : r.design_top) top.push_back(DesignJson(c, r));
    j["design"] = {{"keys", r.design_keys},
                   {"planes", spec.design_planes},
                   {"budget", "one image's photons shared among the chosen planes"},
                   {"objective", "geometric mean of the design keys' Cramer-Rao bounds"},
                   {"choices_compared", r.design_choices},
                   {"best_per_count", best},
                   {"top", top}};
  }
  const std::string maps = WriteDerivativeMaps(r, dir);
  WriteTextFileAtomic(dir / "sensitivity.json", j.dump(2) + "\n");

  std::ostringstream h;
  h << "<!doctype html><html><head><meta charset=\"utf-8\"><title>raymatch sensitivity</title>"
       "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto}"
       "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:3px 8px;"
       "text-align:right}</style></head><body>\n<h1>raymatch sensitivity</h1>\n<p>"
    << HtmlEscape(spec.scene_file) << ": " << r.mu.size() << " image(s) at " << r.photons_per_pixel
    << " photons per flat-field pixel; derivative images from " << spec.sets
    << " ray-stream sets of " << r.rays_per_image << " rays per image (" << r.evaluations
    << " evaluations, " << Num(r.seconds, 3)
    << " s). Exposure: " << (spec.exposure_nuisance ? "a nuisance (unknown)" : "known") << ".</p>\n"
    << "<h2>Cramer-Rao bounds</h2><table><tr><th>key</th><th>value</th><th>bound</th>"
       "<th>its Monte Carlo error</th><th>exposure known</th>";
  for (double d : r.defocus_um) h << "<th>image at " << Num(d) << " µm alone</th>";
  h << "</tr>\n";
  for (const SensitivityKey& k : r.keys) {
    h << "<tr><td style=\"text-align:left\">" << HtmlEscape(k.key) << "</td><td>" << Num(k.value, 6)
      << " " << k.unit << "</td><td><b>" << Num(k.crb) << "</b></td><td>" << Num(k.crb_mc_error, 2)
      << (k.crb_mc_error <= 0.05 * k.crb ? "" : " (large: raise the ray factor or sets)")
      << "</td><td>" << Num(k.crb_exposure_known) << "</td>";
    for (double v : k.crb_per_image) h << "<td>" << Num(v) << "</td>";
    h << "</tr>\n";
  }
  h << "</table>\n<h2>Correlations</h2><table><tr><th></th>";
  for (const SensitivityKey& k : r.keys) h << "<th>" << HtmlEscape(k.key) << "</th>";
  h << "</tr>";
  for (size_t i = 0; i < r.keys.size(); ++i) {
    h << "<tr><th>" << HtmlEscape(r.keys[i].key) << "</th>";
    for (double v : r.correlation[i]) h << "<td>" << Num(v, 3) << "</td>";
    h << "</tr>";
  }
  h << "</table>\n";
  if (!r.design_best.empty()) {
    h << "<h2>Experiment design</h2><p>Focus positions that minimise the geometric mean of the "
         "bounds of "
      << HtmlEscape([&] {
           std::string s;
           for (const auto& k : r.design_keys) s += (s.empty() ? "" : ", ") + k;
           return s;
         }())
      << ", one image's photons shared among the chosen planes (" << r.design_choices
      << " choices of " << spec.design_planes << " compared).</p><table><tr><th>planes (µm)</th>";
    for (const SensitivityKey& k : r.keys) h << "<th>" << HtmlEscape(k.key) << "</th>";
    h << "<th>objective</th></tr>\n";
    auto row = [&](const DesignChoice& c) {
      std::string planes;
      for (double d : c.defocus_um) planes += (planes.empty() ? "" : ", ") + Num(d);
      h << "<tr><td style=\"text-align:left\">" << planes << "</td>";
      for (double v : c.crb) h << "<td>" << Num(v) << "</td>";
      h << "<td>" << Num(c.objective) << "</td></tr>\n";
    };
    h << "<tr><th colspan=\"99\" style=\"text-align:left\">best for each number of "
         "planes</th></tr>";
    for (const DesignChoice& c : r.design_best) row(c);
    h << "<tr><th colspan=\"99\" style=\"text-align:left\">best choices of " << spec.design_planes
      << "</th></tr>";
    for (const DesignChoice& c : r.design_top) row(c);
    h << "</table>\n";
  }
  h << "<h2>Which pixels carry the information</h2><p>d mu / d key per image (photons per pixel "
       "per unit of the key; red: the pixel brightens as the key grows).</p>\n"
    << maps << "<p>Everything: sensitivity.json.</p></body></html>\n";
  const fs::path report = dir / "report.html";
  WriteTextFileAtomic(report, h.str());
  return report.string();
}

}  // namespace raymatch::fit
