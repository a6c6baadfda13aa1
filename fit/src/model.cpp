#include "model.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <tuple>

#include "raymatch/compare/measures.h"
#include "raymatch/simulate/wave_image.h"

namespace raymatch::fit {

namespace {

/// Whether pixel p enters the likelihood under a FitImage::usable mask (empty: every pixel).
inline bool Uses(const Image& mask, size_t p) { return mask.pixels.empty() || mask.pixels[p] > 0; }

/// Signed deviance residual of one pixel: sign(mu - e) sqrt(2 [mu - e + e ln(e/mu)]).
/// Counts below 0 (dark subtraction of read noise) are taken as 0.
inline double DevianceResidual(double e, double mu) {
  mu = std::max(mu, 1e-6);
  e = std::max(e, 0.0);
  const double d = 2 * (mu - e + (e > 0 ? e * std::log(e / mu) : 0.0));
  const double r = std::sqrt(std::max(d, 0.0));
  return mu >= e ? r : -r;
}

/// The Poisson deviance of one (binned) experimental image against its template t over the
/// pixels `use` lets in.
double ImageDeviance(const Image& e, const std::vector<double>& t, const Image& use) {
  double d = 0;
  for (size_t p = 0; p < e.size(); ++p) {
    if (!Uses(use, p)) continue;
    const double r = DevianceResidual(e.pixels[p], t[p]);
    d += r * r;
  }
  return d;
}

/// Expected Poisson deviance 2[mu - e + e ln(e/mu)] of one pixel with known mean mu: summed
/// over the Poisson distribution below 30, 1 + 1/(6 mu) + 1/(6 mu^2) above (the asymptotic
/// series; McCullagh and Nelder, Generalized Linear Models, 2nd ed., section 6.2).
double ExpectedPixelDeviance(double mu) {
  if (mu >= 30) return 1 + 1 / (6 * mu) + 1 / (6 * mu * mu);
  if (mu <= 0) return 0;
  double sum = 0, p = std::exp(-mu);  // P(e = 0)
  const int top = static_cast<int>(mu + 12 * std::sqrt(mu) + 20);
  for (int e = 0; e <= top; ++e) {
    const double d = 2 * (mu - e + (e > 0 ? e * std::log(e / mu) : 0.0));
    sum += p * d;
    p *= mu / (e + 1);
  }
  return sum;
}

}  // namespace

double PoissonDeviance(const Image& e, const Image& mu) {
  double s = 0;
  for (size_t i = 0; i < e.size(); ++i) {
    const double r = DevianceResidual(e.pixels[i], mu.pixels[i]);
    s += r * r;
  }
  return s;
}

FitModel::FitModel(const FitSpec& spec, int threads, std::function<void(const std::string&)> say)
    : spec_(spec), threads_(threads), say_(std::move(say)) {
  const size_t P = spec.parameters.size();
  built_ = simulate::LoadScene(spec.scene, spec.scene_file);
  bool edge_keys = false, psf_key = false;
  double psf_max = 0;
  for (const Parameter& p : spec.parameters) {
    bindings_.push_back(internal::Bind(p.key, built_, spec.images.size()));
    const internal::Binding& b = bindings_.back();
    read_per_evaluation_ = read_per_evaluation_ || (b.InScene() && !b.Typed());
    edge_keys = edge_keys || b.kind == internal::Binding::Kind::kEdge;
    if (b.kind == internal::Binding::Kind::kPsf) {
      psf_key = true;
      psf_max = std::max({psf_max, p.upper, p.start});
    }
    split_allowed_ = split_allowed_ && b.KeepsSplit();
  }
  split_allowed_ = split_allowed_ && spec.rays.reuse_background;
  edge_split_ = split_allowed_ && edge_keys;

  // The parameter box's corners (or, for many parameters, its axis end points): the region the
  // objects can occupy and the largest automatic source field.
  // Keys that neither move objects nor widen the field (the light field's edge beyond the NA,
  // the camera PSF) stay at their start: 2^8 corners of a sphere calibration would be 2^5.
  std::vector<double> start, lower, upper;
  for (const Parameter& p : spec.parameters) {
    start.push_back(p.start);
    lower.push_back(p.lower);
    upper.push_back(p.upper);
  }
  // Typed keys skip the scene file's range checks per evaluation: read the scene at each key's
  // bounds once, so a box that leaves a valid range fails here as it would have at its first
  // evaluation there.
  for (size_t i = 0; i < P; ++i)
    if (bindings_[i].Typed() && !bindings_[i].SpansRegion())
      for (double v : {spec.parameters[i].lower, spec.parameters[i].upper}) {
        std::vector<double> th = start;
        th[i] = v;
        SceneByReading(th);
      }
  std::vector<std::vector<double>> probes{start};
  object_pixel_um_ = simulate::Simulator(SceneAt(start)).object_pixel_um();
  if (split_allowed_ && psf_key) {
    // The PSF on a 4x finer grid: a ray's position within its fine pixel is taken as uniform,
    // an error below a quarter pixel's scale; the margin holds the rays the PSF brings in.
    psf_os_ = 4;
    psf_margin_ = int(std::ceil(5 * psf_max / (object_pixel_um_ / psf_os_))) + 2;
  }
  for (auto& c : Corners(start, lower, upper)) probes.push_back(std::move(c));
  std::vector<std::pair<Vec3, double>> bounds;
  double max_field = 0, wave_window_um = 0;
  for (const auto& th : probes) {
    const simulate::Scene sc = SceneByReading(th);
    if (spec.exact_images())  // one FFT window for every evaluation ([trace.mie] window_um)
      for (double dz : sc.defocus_um)
        wave_window_um = std::max(wave_window_um, spec.optics == "physical"
                                                      ? simulate::AutomaticPhysicalWindowUm(sc, dz)
                                                      : simulate::AutomaticMieWindowUm(sc, dz));
    const simulate::Simulator sim(
        internal::TracedScene(sc, simulate::SourceSpec::EdgePart::kAll, psf_os_, psf_margin_));
    for (const auto& b : sim.ObjectBounds()) bounds.push_back(b);
    max_field = std::max(max_field, sim.field_radius_um());
  }
  simulate::Scene s0 = SceneAt(start);
  if (s0.source.type != simulate::SourceType::kPoint && s0.source.field_radius_um == 0) {
    field_radius_ = max_field;
    s0.source.field_radius_um = field_radius_;  // as SceneAt() applies it from now on
  }
  std::tie(region_center_, region_radius_) = RegionOf(bounds);
  if (!(region_radius_ > 0)) split_allowed_ = false;

  // Photon-matched rays: the experiment's flat-background photons per pixel.
  double ppp = spec.rays.photons_per_pixel;
  const toml::table* trace = spec.scene["trace"].as_table();
  const bool scene_rays = trace && trace->contains("rays");
  if (ppp == 0 && !scene_rays) ppp = s0.trace.photons_per_pixel;
  if (ppp == 0 && !scene_rays) {
    ppp = BorderMedian(spec.images[0].photons);  // as `run` recovers the exposure
    if (!(ppp > 0))
      throw raymatch::Error(FileLocation{spec.file},
                            "the first image's background is not positive: give "
                            "[rays] photons_per_pixel");
    say_("background of the first image: " + std::to_string(ppp) + " photons per pixel");
  }
  photon_matched_rays_ = ppp > 0 ? simulate::Simulator(s0).RaysForPhotonTarget(ppp) : s0.trace.rays;
  if (spec.exact_images()) {
    double per_ray = 0;
    if (!(ppp > 0)) simulate::Simulator(s0).RaysForPhotonTarget(1.0, &per_ray);
    const double photons = ppp > 0 ? ppp : per_ray * double(photon_matched_rays_);
    if (spec.optics == "physical")
      images_ = std::make_unique<internal::PhysicalImageModel>(photons, wave_window_um, threads_);
    else
      images_ = std::make_unique<internal::MieImageModel>(photons, wave_window_um, threads_);
  } else {
    internal::RayImageModel::Setup setup;
    setup.images = spec.images.size();
    setup.threads = threads_;
    setup.region_center = region_center_, setup.region_radius = region_radius_;
    setup.split = split_allowed_, setup.edge_split = edge_split_;
    setup.psf_os = psf_os_, setup.psf_margin = psf_margin_;
    setup.object_pixel_um = object_pixel_um_;
    if (edge_split_) {
      // The part inside the NA's share of the rays at the start.
      using Part = simulate::SourceSpec::EdgePart;
      const double all =
          simulate::Simulator(internal::TracedScene(s0, Part::kAll, psf_os_, psf_margin_))
              .source_weight();
      const double in =
          simulate::Simulator(internal::TracedScene(s0, Part::kInside, psf_os_, psf_margin_))
              .source_weight();
      if (!(all > 0 && in > 0))
        throw raymatch::Error(FileLocation{spec.file}, "light_field_edge keys need a light field");
      setup.inside_share = in / all;
    }
    images_ = std::make_unique<internal::RayImageModel>(setup);
  }
  for (const FitImage& f : spec.images)
    for (float v : f.photons.pixels) data_range_ = std::max(data_range_, double(v));
}

std::vector<std::vector<double>> FitModel::Corners(const std::vector<double>& at,
                                                   const std::vector<double>& lo,
                                                   const std::vector<double>& hi) const {
  // Keys that neither move objects nor widen the field (the light field's edge beyond the NA,
  // the camera PSF) stay at `at`: 2^8 corners of a sphere calibration would be 2^5.
  std::vector<size_t> moving;
  for (size_t i = 0; i < at.size(); ++i)
    if (bindings_[i].SpansRegion()) moving.push_back(i);
  std::vector<std::vector<double>> probes;
  const size_t M = moving.size();
  if (M <= 10) {
    for (uint32_t c = 0; c < (1u << M); ++c) {
      std::vector<double> th = at;
      for (size_t j = 0; j < M; ++j) th[moving[j]] = (c >> j) & 1 ? hi[moving[j]] : lo[moving[j]];
      probes.push_back(th);
    }
  } else {
    for (size_t i : moving)
      for (double v : {lo[i], hi[i]}) {
        std::vector<double> th = at;
        th[i] = v;
        probes.push_back(th);
      }
  }
  return probes;
}

std::pair<Vec3, double> FitModel::RegionOf(const std::vector<std::pair<Vec3, double>>& bounds) {
  if (bounds.empty()) return {Vec3(), 0.0};
  const auto [center, radius] = simulate::Simulator::EnclosingSphere(bounds);
  return {center, 1.02 * radius + 0.5};  // margin: a micrometre-scale safety shell
}

bool FitModel::FocusRegion(const std::vector<double>& theta, double steps) {
  if (!split_allowed_ || images_->exact()) return false;
  std::vector<double> lo = theta, hi = theta;
  for (size_t i = 0; i < theta.size(); ++i) {
    const Parameter& p = spec_.parameters[i];
    lo[i] = std::max(p.lower, theta[i] - steps * p.step);
    hi[i] = std::min(p.upper, theta[i] + steps * p.step);
  }
  std::vector<std::pair<Vec3, double>> bounds;
  for (const auto& th : Corners(theta, lo, hi)) {
    const simulate::Simulator sim(internal::TracedScene(
        SceneAt(th), simulate::SourceSpec::EdgePart::kAll, psf_os_, psf_margin_));
    for (const auto& b : sim.ObjectBounds()) bounds.push_back(b);
  }
  const auto [center, radius] = RegionOf(bounds);
  if (!(radius > 0) || radius >= region_radius_) return false;
  region_center_ = center, region_radius_ = radius;
  images_->SetRegion(center, radius);
  return true;
}

simulate::Scene FitModel::SceneByReading(const std::vector<double>& theta) const {
  toml::table t = spec_.scene;
  for (size_t i = 0; i < theta.size(); ++i)
    if (bindings_[i].InScene())
      SetSceneValue(t, spec_.parameters[i].key, theta[i], spec_.scene_file);
  return Finished(simulate::LoadScene(t, spec_.scene_file), theta);
}

simulate::Scene FitModel::SceneAt(const std::vector<double>& theta) const {
  if (read_per_evaluation_) return SceneByReading(theta);
  simulate::Scene s = built_;
  for (size_t i = 0; i < theta.size(); ++i)
    if (bindings_[i].Typed()) internal::Patch(bindings_[i], theta[i], &s);
  return Finished(std::move(s), theta);
}

simulate::Scene FitModel::Finished(simulate::Scene s, const std::vector<double>& theta) const {
  s.defocus_um = DefocusAt(theta);
  if (field_radius_ > 0) s.source.field_radius_um = field_radius_;
  simulate::ValidateScene(s);
  return s;
}

std::vector<double> FitModel::DefocusAt(const std::vector<double>& theta) const {
  std::vector<double> d;
  for (const FitImage& f : spec_.images) d.push_back(f.defocus_um);
  for (size_t i = 0; i < theta.size(); ++i)
    if (bindings_[i].kind == internal::Binding::Kind::kDefocus) d[bindings_[i].image] = theta[i];
  return d;
}

Image FitModel::BackgroundOf(const std::vector<double>& theta, size_t i, int width,
                             int height) const {
  double level = 0, gx = 0, gy = 0;
  bool any = false;
  for (size_t k = 0; k < theta.size(); ++k) {
    const internal::Binding& b = bindings_[k];
    if (b.kind != internal::Binding::Kind::kBackground || b.image != i) continue;
    any = true;
    (b.background == 0 ? level : b.background == 1 ? gx : gy) = theta[k];
  }
  if (!any) return Image();
  Image b(width, height);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x)
      b.at(x, y) =
          static_cast<float>(level + gx * (x - 0.5 * (width - 1)) + gy * (y - 0.5 * (height - 1)));
  return b;
}

uint64_t FitModel::RaysAt(double fraction) const {
  return std::max<uint64_t>(
      1, std::llround(double(photon_matched_rays_) * spec_.rays.ray_factor * fraction));
}

double FitModel::ScaleAt(double fraction) const {
  return double(photon_matched_rays_) / double(RaysAt(fraction));
}

Simulated FitModel::Expected(const std::vector<double>& theta, double fraction, uint64_t seed,
                             uint64_t* rays_traced) {
  internal::Draw draw;
  draw.rays = RaysAt(fraction);
  draw.photons_per_ray = ScaleAt(fraction);
  draw.seed = seed;
  if (built_.objects.size() == 1) {  // the scene is a function of theta
    draw.across_key = theta;
    for (size_t i = 0; i < theta.size(); ++i)
      if (bindings_[i].MovesAcross()) draw.across_key[i] = 0;
  }
  draw.inside_key = draw.beyond_key = theta;
  for (size_t i = 0; i < theta.size(); ++i) {
    using Kind = internal::Binding::Kind;
    const Kind k = bindings_[i].kind;
    if (k == Kind::kBackground || (k == Kind::kPsf && psf_os_ > 1))  // not traced
      draw.inside_key[i] = draw.beyond_key[i] = 0;
    if (k == Kind::kEdge && edge_split_) draw.inside_key[i] = 0;  // the other population's
  }
  internal::ModelImages m = images_->Images(SceneAt(theta), draw, rays_traced);
  Simulated out;
  out.finite_ray_correction = !images_->exact() && spec_.rays.finite_ray_correction;
  for (size_t i = 0; i < m.counts.size(); ++i)
    AddExposureAndBackground(theta, i, std::move(m.counts[i]), m.photons_per_count, &out);
  return out;
}

void FitModel::AddExposureAndBackground(const std::vector<double>& theta, size_t i, Image counts,
                                        double scale, Simulated* out) const {
  // The image's additive background (image[i].background_* keys): photons per pixel, a
  // level and slopes per pixel about the image centre, added to the expected image after the
  // exposure. The exposure profile matches the totals of the rest, which the joint optimum
  // of a Poisson model with a free level and scale satisfies exactly.
  const Image bg_image = BackgroundOf(theta, i, counts.width, counts.height);
  const Image& usable = spec_.images[i].usable;
  double bg_sum = 0;
  for (size_t p = 0; p < bg_image.size(); ++p)
    if (Uses(usable, p)) bg_sum += bg_image.pixels[p];
  double s = scale;
  if (spec_.rays.fit_exposure) {
    // The exposure is a nuisance parameter: its maximum-likelihood value for Poisson counts
    // is sum(e) / sum(mu) in closed form (profiled out at every evaluation). A fixed exposure
    // would turn any error in the photon count (the experiment's, or the 0.4 % of the
    // photon-target pilot) into a shift of z, radius and index, which change how much light
    // leaves the aperture.
    double se = 0, sm = 0;
    for (size_t p = 0; p < counts.size(); ++p)
      if (Uses(usable, p))
        se += std::max(0.0f, spec_.images[i].photons.pixels[p]), sm += counts.pixels[p];
    if (sm > 0 && se - bg_sum > 0) s = (se - bg_sum) / sm;
  }
  for (float& v : counts.pixels) v = static_cast<float>(v * s);
  if (!bg_image.pixels.empty())
    for (size_t p = 0; p < counts.size(); ++p)
      counts.pixels[p] = std::max(0.0f, counts.pixels[p] + bg_image.pixels[p]);
  out->photons.push_back(std::move(counts));
  // An exact model's image has no counting noise: no photons per ray.
  out->photons_per_ray.push_back(images_->exact() ? 0.0 : s);
}

Image BinImage(const Image& a, int b) {
  if (b <= 1) return a;
  Image o(std::max(1, a.width / b), std::max(1, a.height / b));
  for (int y = 0; y < o.height * b && y < a.height; ++y)
    for (int x = 0; x < o.width * b && x < a.width; ++x) o.at(x / b, y / b) += a.at(x, y);
  return o;
}

int FitModel::BinAt(size_t level) const {
  if (level < spec_.rays.binning.size()) return spec_.rays.binning[level];
  // The SSIM family is multi-scale or windowed already (the paper's MS-SSIM held its optimum
  // down to 1/1024 of the rays unbinned); binning serves the per-pixel Poisson deviance and MSE.
  if (spec_.error != ErrorFunction::kPoisson && spec_.error != ErrorFunction::kMse) return 1;
  if (spec_.exact_images()) return 1;  // no simulation noise to bin away
  const double k = spec_.rays.ray_factor * spec_.rays.fractions[level];
  int b = 1;
  while (b * b * k < 1 - 1e-9) ++b;
  return b;
}

const std::vector<Image>& FitModel::Experiment(int bin) const {
  std::lock_guard<std::mutex> lk(binned_mutex_);
  auto& v = binned_experiment_[bin];
  if (v.empty())
    for (size_t i = 0; i < spec_.images.size(); ++i) {
      v.push_back(BinImage(spec_.images[i].photons, bin));
      const double shift = ReadShift(i, bin);  // e + r^2: the shifted-Poisson count
      if (shift > 0)
        for (float& x : v.back().pixels) x = std::max(0.0f, x + static_cast<float>(shift));
    }
  return v;
}

std::string Fmt(double v, int prec) {
  std::ostringstream os;
  os.precision(prec);
  os << v;
  return os.str();
}

/// The template of image i of `sim`, given its binned counts: each count plus one ray
/// (TemplateMean), plus the image's read-noise shift (ReadShift), the mean every Poisson
/// measure below compares the (equally shifted) experiment with.
std::vector<double> FitModel::TemplateOf(const Image& binned, const Simulated& sim, size_t i,
                                         int bin) const {
  std::vector<double> t(binned.size());
  const double shift = ReadShift(i, bin);
  for (size_t p = 0; p < binned.size(); ++p)
    t[p] =
        TemplateMean(binned.pixels[p], sim.photons_per_ray[i], sim.finite_ray_correction) + shift;
  return t;
}

const std::vector<Image>& FitModel::Usable(int bin) const {
  std::lock_guard<std::mutex> lk(binned_mutex_);
  auto& v = binned_usable_[bin];
  if (v.empty())
    for (const FitImage& f : spec_.images) {
      if (f.usable.pixels.empty()) {
        v.push_back(Image());
        continue;
      }
      Image b = BinImage(f.usable, bin);  // a binned pixel is usable when all of its pixels are
      for (float& x : b.pixels) x = x >= float(bin * bin) - 0.5f ? 1.0f : 0.0f;
      v.push_back(std::move(b));
    }
  return v;
}

double FitModel::ReadShift(size_t i, int bin) const {
  if (spec_.error != ErrorFunction::kPoisson) return 0;
  const double r = spec_.images[i].read_noise_e;
  return r * r * bin * bin;  // a binned pixel sums bin^2 independent read-outs
}

double FitModel::Error(const Simulated& sim, int bin) const {
  const std::vector<Image>& use = Usable(bin);  // pixels left out: saturated, clipped
  const std::vector<Image>& exp = Experiment(bin);
  std::vector<Image> mu;
  for (const Image& m : sim.photons) mu.push_back(BinImage(m, bin));
  double s = 0;
  size_t npix = 0;
  for (size_t i = 0; i < mu.size(); ++i) {
    const Image& e = exp[i];
    switch (spec_.error) {
      case ErrorFunction::kPoisson:
        s += ImageDeviance(e, TemplateOf(mu[i], sim, i, bin), use[i]);
        break;
      case ErrorFunction::kMse:
        for (size_t p = 0; p < e.size(); ++p)
          s += (double(mu[i].pixels[p]) - e.pixels[p]) * (double(mu[i].pixels[p]) - e.pixels[p]);
        npix += e.size();
        break;
      case ErrorFunction::kSsim: {
        compare::SsimOptions o;
        o.data_range = data_range_ * bin * bin;
        s += 1 - compare::Ssim(e, mu[i], o).ssim;
        break;
      }
      case ErrorFunction::kMsSsim: {
        compare::MsSsimOptions o;
        o.data_range = data_range_ * bin * bin;
        s += 1 - compare::MsSsim(e, mu[i], o).ms_ssim;
        break;
      }
      case ErrorFunction::kCwSsim: {
        compare::CwSsimOptions o;
        o.data_range = data_range_ * bin * bin;
        s += 1 - compare::CwSsim(e, mu[i], o).cw_ssim;
        break;
      }
    }
  }
  if (spec_.error == ErrorFunction::kMse) return s / double(std::max<size_t>(npix, 1));
  if (spec_.error != ErrorFunction::kPoisson) return s / double(mu.size());
  return s;
}

size_t FitModel::num_residuals(int bin) const {
  size_t n = 0;
  for (const Image& e : Experiment(bin)) n += e.size();
  return n;
}

void FitModel::DevianceResiduals(const Simulated& sim, int bin, double* out) const {
  const std::vector<Image>& use = Usable(bin);  // pixels left out: saturated, clipped
  const std::vector<Image>& exp = Experiment(bin);
  for (size_t i = 0; i < sim.photons.size(); ++i) {
    const Image& e = exp[i];
    const std::vector<double> t = TemplateOf(BinImage(sim.photons[i], bin), sim, i, bin);
    for (size_t p = 0; p < e.size(); ++p)
      *out++ = Uses(use[i], p) ? DevianceResidual(e.pixels[p], t[p]) : 0.0;
  }
}

std::vector<double> FitModel::Project(
    const std::vector<std::vector<Image>>& dmu, int bin,
    const std::function<std::vector<double>(size_t)>& residual) const {
  const std::vector<Image>& use = Usable(bin);
  const size_t P = dmu.empty() ? 0 : dmu[0].size();
  std::vector<double> score(P, 0.0);
  for (size_t i = 0; i < dmu.size(); ++i) {
    const std::vector<double> f = residual(i);
    std::vector<Image> g;
    for (size_t j = 0; j < P; ++j) g.push_back(BinImage(dmu[i][j], bin));
    for (size_t p = 0; p < f.size(); ++p) {
      if (!Uses(use[i], p)) continue;
      for (size_t a = 0; a < P; ++a) score[a] += double(g[a].pixels[p]) * f[p];
    }
  }
  return score;
}

std::vector<double> FitModel::Score(const Simulated& sim,
                                    const std::vector<std::vector<Image>>& dmu,
                                    const std::vector<Image>& reference, int bin) const {
  const std::vector<Image>& exp = Experiment(bin);
  return Project(dmu, bin, [&](size_t i) {
    const Image& e = exp[i];
    const Image m = BinImage(sim.photons[i], bin), v = BinImage(reference.at(i), bin);
    const double shift = ReadShift(i, bin);  // (in e and in the weights; cancels in e - m)
    std::vector<double> f(e.size());
    for (size_t p = 0; p < e.size(); ++p)
      f[p] = (std::max(double(e.pixels[p]), 0.0) - (double(m.pixels[p]) + shift)) /
             (std::max(double(v.pixels[p]), kReferenceFloor) + shift);
    return f;
  });
}

std::vector<double> FitModel::PoissonScore(const Simulated& sim,
                                           const std::vector<std::vector<Image>>& dmu,
                                           int bin) const {
  const std::vector<Image>& exp = Experiment(bin);
  return Project(dmu, bin, [&](size_t i) {
    const Image& e = exp[i];
    std::vector<double> f = TemplateOf(BinImage(sim.photons[i], bin), sim, i, bin);
    for (size_t p = 0; p < e.size(); ++p)
      f[p] = std::max(double(e.pixels[p]), 0.0) / std::max(f[p], 1e-6) - 1;
    return f;
  });
}

std::vector<std::vector<double>> FitModel::CrossInformation(
    const std::vector<std::vector<Image>>& a, const std::vector<std::vector<Image>>& b,
    const std::vector<Image>& reference, int bin) const {
  const std::vector<Image>& use = Usable(bin);
  const size_t na = a.empty() ? 0 : a[0].size(), nb = b.empty() ? 0 : b[0].size();
  std::vector<std::vector<double>> m(na, std::vector<double>(nb, 0.0));
  for (size_t i = 0; i < a.size(); ++i) {
    const double shift = ReadShift(i, bin);
    const Image v = BinImage(reference.at(i), bin);
    std::vector<Image> ga, gb;
    for (size_t j = 0; j < na; ++j) ga.push_back(BinImage(a[i][j], bin));
    for (size_t j = 0; j < nb; ++j) gb.push_back(BinImage(b.at(i).at(j), bin));
    for (size_t p = 0; p < v.size(); ++p) {
      if (!Uses(use[i], p)) continue;
      const double weight = 1 / (std::max(double(v.pixels[p]), kReferenceFloor) + shift);
      for (size_t r = 0; r < na; ++r)
        for (size_t c = 0; c < nb; ++c)
          m[r][c] += double(ga[r].pixels[p]) * gb[c].pixels[p] * weight;
    }
  }
  return m;
}

std::pair<double, double> FitModel::ExpectedDeviance(const std::vector<std::vector<double>>& ts,
                                                     const Simulated& sim, int bin,
                                                     size_t parameters) const {
  const std::vector<Image>& use = Usable(bin);  // pixels left out: saturated, clipped
  // A pixel's deviance for a correct model: the Poisson part of the experiment (exact for low
  // counts) times 1 + w for the template's own Poisson noise (w photons per ray: variance
  // mu (1 + 1/k) about the mean); each fitted parameter removes about one such unit.
  double mean = 0, var = 0, units = 0, pixels = 0;
  for (size_t i = 0; i < ts.size(); ++i) {
    const double w = sim.photons_per_ray[i];
    const double shift = ReadShift(i, bin);
    for (size_t p = 0; p < ts[i].size(); ++p) {
      if (!Uses(use[i], p)) continue;
      const double t = ts[i][p];
      // The template's own noise is that of its photons, not of the read-noise shift.
      const double u = 1 + w * std::max(0.0, t - shift) / std::max(t, 1e-12);
      const double g = ExpectedPixelDeviance(t) * u;
      mean += g, var += 2 * g * g, units += u, pixels += 1;
    }
  }
  if (pixels > 0)
    mean -= double(parameters) * units / pixels,
        var *= std::max(0.0, 1 - double(parameters) / pixels);
  return {mean, std::sqrt(var)};
}

std::vector<std::vector<double>> FitModel::Templates(const Simulated& sim, int bin) const {
  std::vector<std::vector<double>> ts;
  for (size_t i = 0; i < sim.photons.size(); ++i)
    ts.push_back(TemplateOf(BinImage(sim.photons[i], bin), sim, i, bin));
  return ts;
}

std::vector<double> FitModel::TemplateStep(const Simulated& sim, int bin,
                                           const std::vector<std::vector<Image>>& dmu_a,
                                           const std::vector<std::vector<Image>>& dmu_b) const {
  return GaussNewtonStep(sim, bin, dmu_a, dmu_b, Templates(sim, bin));
}

double FitModel::TemplatesDeviance(const std::vector<std::vector<double>>& ts, int bin) const {
  const std::vector<Image>& use = Usable(bin);
  const std::vector<Image>& exp = Experiment(bin);
  double d = 0;
  for (size_t i = 0; i < ts.size(); ++i) d += ImageDeviance(exp[i], ts[i], use[i]);
  return d;
}

std::vector<double> FitModel::GaussNewtonStep(const Simulated& sim, int bin,
                                              const std::vector<std::vector<Image>>& dmu_a,
                                              const std::vector<std::vector<Image>>& dmu_b,
                                              const std::vector<std::vector<double>>& ts,
                                              std::vector<std::vector<Image>>* mean_dmu) const {
  const size_t P = dmu_a.empty() ? 0 : dmu_a[0].size();
  if (P == 0 || dmu_a.size() != ts.size() || dmu_b.size() != ts.size()) return {};
  const std::vector<Image>& use = Usable(bin);
  const std::vector<Image>& exp = Experiment(bin);
  // The weighted least-squares normal equations of the Pearson residuals (the weights of the
  // tests below) in the parameters' derivative images. Noisy derivative images would add
  // their noise's variance to the normal matrix and shorten the step (errors in the
  // regressors); the cross products of two independent halves are free of it.
  Eigen::MatrixXd n = Eigen::MatrixXd::Zero(Eigen::Index(P), Eigen::Index(P));
  Eigen::VectorXd b = Eigen::VectorXd::Zero(Eigen::Index(P));
  std::vector<std::vector<Image>> ga(ts.size()), gb(ts.size()), g(ts.size());
  for (size_t i = 0; i < ts.size(); ++i) {
    if (dmu_a[i].size() != P || dmu_b[i].size() != P) return {};
    for (size_t j = 0; j < P; ++j) {
      ga[i].push_back(BinImage(dmu_a[i][j], bin));
      gb[i].push_back(BinImage(dmu_b[i][j], bin));
      g[i].push_back(ga[i][j]);
      for (size_t q = 0; q < g[i][j].size(); ++q)
        g[i][j].pixels[q] = 0.5f * (ga[i][j].pixels[q] + gb[i][j].pixels[q]);
    }
    const double w = sim.photons_per_ray[i], shift = ReadShift(i, bin);
    const double ray = sim.finite_ray_correction ? w : 0;  // the residuals of Goodness
    const Image& e = exp[i];
    for (size_t p = 0; p < e.size(); ++p) {
      if (!Uses(use[i], p)) continue;
      const double t = ts[i][p];
      const double v = t + w * std::max(0.0, t - shift);
      const double r = std::max(0.0, double(e.pixels[p])) - (t - ray);
      for (size_t j = 0; j < P; ++j) {
        b(Eigen::Index(j)) += g[i][j].pixels[p] * r / v;
        for (size_t k = 0; k < P; ++k)
          n(Eigen::Index(j), Eigen::Index(k)) += 0.5 *
                                                 (double(ga[i][j].pixels[p]) * gb[i][k].pixels[p] +
                                                  double(gb[i][j].pixels[p]) * ga[i][k].pixels[p]) /
                                                 v;
      }
    }
  }
  // Solved on the unit-free (correlation) scale; directions the images do not determine (a
  // parameter that leaves them unchanged, eigenvalues below 1e-10 of the largest; the cross
  // products' noise can make one negative) are left out.
  Eigen::VectorXd s = n.diagonal().cwiseSqrt();
  for (Eigen::Index j = 0; j < s.size(); ++j)
    if (!(s(j) > 0)) s(j) = std::numeric_limits<double>::infinity();
  const Eigen::MatrixXd c = s.cwiseInverse().asDiagonal() * n * s.cwiseInverse().asDiagonal();
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> es(c);
  if (es.info() != Eigen::Success) return {};
  const Eigen::VectorXd lambda = es.eigenvalues();
  const double top = lambda.maxCoeff();
  if (!(top > 0)) return {};
  Eigen::VectorXd inv = Eigen::VectorXd::Zero(lambda.size());
  for (Eigen::Index j = 0; j < lambda.size(); ++j)
    if (lambda(j) > 1e-10 * top) inv(j) = 1 / lambda(j);
  const Eigen::VectorXd bs = s.cwiseInverse().asDiagonal() * b;
  Eigen::VectorXd step = s.cwiseInverse().asDiagonal() * (es.eigenvectors() * inv.asDiagonal() *
                                                          es.eigenvectors().transpose() * bs);
  if (mean_dmu) *mean_dmu = std::move(g);
  return std::vector<double>(step.data(), step.data() + step.size());
}

std::vector<double> FitModel::StepToTheTemplatesBest(const Simulated& sim, int bin,
                                                     const std::vector<std::vector<Image>>& dmu_a,
                                                     const std::vector<std::vector<Image>>& dmu_b,
                                                     std::vector<std::vector<double>>* ts) const {
  std::vector<std::vector<Image>> g;
  const std::vector<double> full = GaussNewtonStep(sim, bin, dmu_a, dmu_b, *ts, &g);
  const size_t P = full.size();
  if (P == 0) return {};
  // The step is linear: taken whole, or halved while that lowers the deviance more (a step
  // that does not lower it is not taken), and no pixel's photons fall below half of the
  // estimate's.
  auto moved = [&](double f) {
    std::vector<std::vector<double>> m = *ts;
    for (size_t i = 0; i < m.size(); ++i) {
      const double shift = ReadShift(i, bin);
      for (size_t p = 0; p < m[i].size(); ++p) {
        double t = m[i][p];
        for (size_t j = 0; j < P; ++j) t += f * g[i][j].pixels[p] * full[j];
        m[i][p] = std::max(t, shift + 0.5 * (m[i][p] - shift));
      }
    }
    return m;
  };
  double best = TemplatesDeviance(*ts, bin), taken = 0;
  std::vector<std::vector<double>> best_ts;
  for (double f = 1; f > 0.1; f *= 0.5) {
    std::vector<std::vector<double>> m = moved(f);
    const double d = TemplatesDeviance(m, bin);
    if (!(d < best)) {
      if (taken > 0) break;
      continue;
    }
    best = d, taken = f, best_ts = std::move(m);
  }
  std::vector<double> step(P, 0.0);
  if (taken == 0) return step;
  *ts = std::move(best_ts);
  for (size_t j = 0; j < P; ++j) step[j] = taken * full[j];
  return step;
}

GoodnessOfFit FitModel::Goodness(const Simulated& sim, int bin, size_t parameters,
                                 const std::vector<std::vector<Image>>& dmu_a,
                                 const std::vector<std::vector<Image>>& dmu_b) const {
  const std::vector<Image>& use = Usable(bin);  // pixels left out: saturated, clipped
  const std::vector<Image>& exp = Experiment(bin);
  GoodnessOfFit g;
  std::vector<std::vector<double>> ts = Templates(sim, bin);
  g.estimate_deviance = TemplatesDeviance(ts, bin);
  g.step = StepToTheTemplatesBest(sim, bin, dmu_a, dmu_b.empty() ? dmu_a : dmu_b, &ts);
  g.deviance = g.step.empty() ? g.estimate_deviance : TemplatesDeviance(ts, bin);
  std::tie(g.expected, g.sd) = ExpectedDeviance(ts, sim, bin, parameters);
  g.z = g.sd > 0 ? (g.deviance - g.expected) / g.sd : 0;
  g.reduced = g.expected > 0 ? g.deviance / g.expected : 1;
  double cross = 0, norm = 0;
  size_t pairs = 0;
  for (size_t i = 0; i < sim.photons.size(); ++i) {
    const Image& e = exp[i];
    const std::vector<double>& t = ts[i];
    const double w = sim.photons_per_ray[i], shift = ReadShift(i, bin);
    // Pearson residuals e - m over the variance of e - m, mu + read noise + w mu (0 where a
    // pixel is left out); m is the template's plain count (with the read-noise shift), whose
    // mean is mu. The template's extra ray (TemplateMean), right for the likelihood's E[e/T],
    // would put -w into every residual and -w B^2 into a block's sum: in dark blocks a large
    // part of its standard deviation. The variance is taken at the template (never 0).
    const double ray = sim.finite_ray_correction ? w : 0;
    Image r(e.width, e.height);
    auto variance = [&](double tp) { return tp + w * std::max(0.0, tp - shift); };
    for (size_t p = 0; p < e.size(); ++p)
      if (Uses(use[i], p)) {
        r.pixels[p] = static_cast<float>((std::max(0.0f, e.pixels[p]) - (t[p] - ray)) /
                                         std::sqrt(variance(t[p])));
        ++g.pixels;
      }
    for (int y = 0; y < r.height; ++y)
      for (int x = 0; x < r.width; ++x) {
        const double a = r.at(x, y);
        norm += a * a;
        if (x + 1 < r.width) cross += a * r.at(x + 1, y), ++pairs;
        if (y + 1 < r.height) cross += a * r.at(x, y + 1), ++pairs;
      }
    // Blocks: sum of (e - m) over the block / sqrt(sum of its variance); whole blocks only.
    const int B = g.block_px;
    for (int by = 0; by + B <= e.height; by += B)
      for (int bx = 0; bx + B <= e.width; bx += B) {
        double d = 0, v = 0;
        for (int y = by; y < by + B; ++y)
          for (int x = bx; x < bx + B; ++x) {
            const size_t q = size_t(y) * size_t(e.width) + size_t(x);
            if (!Uses(use[i], q)) continue;
            d += std::max(0.0f, e.at(x, y)) - (t[q] - ray), v += variance(t[q]);
          }
        if (v > 0) g.block_chi2 += d * d / v, ++g.blocks;
      }
  }
  const double n = double(std::max<size_t>(pairs, 1));
  g.neighbour_correlation = norm > 0 ? cross / norm * double(g.pixels) / n : 0;
  g.neighbour_z = g.neighbour_correlation * std::sqrt(n);
  if (g.blocks > 0) {
    g.block_reduced = g.block_chi2 / double(g.blocks);
    // As a normal deviate (Wilson and Hilferty, Proc. Natl. Acad. Sci. 17, 684 (1931)): the
    // chi-square of a few dozen blocks is skewed, and (chi^2 - n) / sqrt(2n) > 3 would be 0.4 %
    // of a correct model's fits at n = 56, not the 0.135 % its threshold says.
    const double a = 2.0 / (9.0 * double(g.blocks));
    g.block_z = (std::cbrt(g.block_reduced) - (1 - a)) / std::sqrt(a);
  }
  std::vector<std::string> why;
  if (g.z > 3)
    why.push_back("deviance " + Fmt(g.deviance, 6) + " for " + Fmt(g.expected, 6) + " +- " +
                  Fmt(g.sd, 3) + " expected (" + Fmt(g.z, 3) + " standard deviations)");
  if (g.block_z > 3)
    why.push_back("residuals structured on " + std::to_string(g.block_px * bin) +
                  "-pixel blocks (chi-square " + Fmt(g.block_chi2, 5) + " for " +
                  std::to_string(g.blocks) + " blocks, " + Fmt(g.block_z, 3) +
                  " standard deviations)");
  // The correlation must also matter: the simulator's own images carry a vertical neighbour
  // correlation of about 0.01 (measured between two seeds at equal parameters), 2-3.6 standard
  // deviations over 9000 pixels, which changes the variance of any sum by a few per cent. From
  // kNeighbourCorrelation on, structure the model lacks (a PSF left out: 0.1 and more) is meant.
  constexpr double kNeighbourCorrelation = 0.05;
  if (g.neighbour_z > 3 && g.neighbour_correlation > kNeighbourCorrelation)
    why.push_back("neighbouring residuals correlated (" + Fmt(g.neighbour_correlation, 3) + ", " +
                  Fmt(g.neighbour_z, 3) + " standard deviations)");
  g.mismatch = !why.empty();
  if (g.mismatch) {
    g.sigma_inflation = std::sqrt(std::max({1.0, g.reduced, g.block_reduced}));
    g.verdict = "model mismatch: ";
    for (size_t i = 0; i < why.size(); ++i) g.verdict += (i ? "; " : "") + why[i];
    g.verdict += "; the model does not describe the image within its noise, sigmas inflated by " +
                 Fmt(g.sigma_inflation, 3) + " (values may be biased beyond that)";
  } else {
    g.verdict = "consistent with the noise (deviance " + Fmt(g.deviance, 6) + " for " +
                Fmt(g.expected, 6) + " +- " + Fmt(g.sd, 3) + " expected)";
  }
  return g;
}

}  // namespace raymatch::fit
