#include "raymatch/simulate/physical_image.h"

#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <cmath>
#include <complex>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <tuple>
#include <utility>

#include "raymatch/core/error.h"
#include "raymatch/core/progress.h"
#include "raymatch/simulate/ray_field.h"
#include "raymatch/simulate/sampling.h"
#include "raymatch/simulate/tracer.h"
#include "raymatch/simulate/water.h"
#include "stages.h"

namespace raymatch::simulate {

namespace {

using C = std::complex<double>;
constexpr double kDeg = M_PI / 180.0;

/// One illumination plane wave: its direction and its weight (flux per unit density).
struct Direction {
  Vec3 d;
  double weight = 0;
};

C DotC(const CVec3& a, const Vec3& b) { return a[0] * b.x + a[1] * b.y + a[2] * b.z; }

/// The unit vectors e_theta, e_phi of direction u about the optical axis (for u on the axis,
/// those of azimuth 0).
void PolarBasis(const Vec3& u, Vec3* e_th, Vec3* e_ph) {
  const double st = std::hypot(u.x, u.y);
  const double cp = st > 1e-12 ? u.x / st : 1.0, sp = st > 1e-12 ? u.y / st : 0.0;
  *e_th = Vec3(u.z * cp, u.z * sp, -st);
  *e_ph = Vec3(-sp, cp, 0);
}

/// The camera-side field (x, y at the object-conjugate plane) of an object-side plane wave of
/// direction u and field a: its e_theta component turned radial, e_phi kept (Richards and
/// Wolf), the camera's rays being paraxial.
std::array<C, 2> ToCamera(const Vec3& u, const CVec3& a) {
  Vec3 e_th, e_ph;
  PolarBasis(u, &e_th, &e_ph);
  const C at = DotC(a, e_th), ap = DotC(a, e_ph);
  const double st = std::hypot(u.x, u.y);
  const double cp = st > 1e-12 ? u.x / st : 1.0, sp = st > 1e-12 ? u.y / st : 0.0;
  return {at * cp - ap * sp, at * sp + ap * cp};
}

/// The illumination's plane waves, their weights the source's flux per unit density.
///  * Collimated: one, along the source's tilt.
///  * A cone: uniform in direction cosines (u, v) within sin(half angle); nodes in s =
///    sin(theta) with the s ds measure, azimuths equally spaced (offset by half a step on
///    alternate rings).
///  * A light field: the same rings out to its map's reach (LightFieldDensity), each
///    direction weighted by the density averaged over its azimuth sector.
/// The outermost rings that together carry less than kTailPower of the power (a soft edge's
/// far tail) are left out, as the exact model leaves them.
/// Rings are split at the NA, where the direct light stops reaching the camera, and on each
/// side again at the corrector's zone edges (and the light field's NA limit and edge ring),
/// where the light's transmission or density jumps; `polar_nodes` per side, shared out by width,
/// at least one per piece.
std::vector<Direction> IlluminationDirections(const Scene& scene, double s_na,
                                              const CorrectorZones& zones) {
  const SourceSpec& ss = scene.source;
  std::vector<Direction> dirs;
  if (ss.type == SourceType::kCollimated) {
    const double t = ss.tilt_deg * kDeg, a = ss.azimuth_deg * kDeg;
    dirs.push_back({Vec3(std::sin(t) * std::cos(a), std::sin(t) * std::sin(a), std::cos(t)), 1});
    return dirs;
  }
  const bool field = ss.type == SourceType::kLightField;
  AngularDensity density;
  std::vector<double> cuts = zones.s;
  double s_max = std::sin(ss.half_angle_deg * kDeg);
  if (field) {
    density = LightFieldDensity(ss);
    cuts.insert(cuts.end(), density.breaks.begin(), density.breaks.end());
    s_max = density.reach;
  }
  const PhysicalSettings& ps = scene.trace.physical;
  std::vector<double> xs, ws;
  auto side = [&](double lo, double hi) {
    std::vector<double> b{lo, hi};
    for (double e : cuts)
      if (e > lo && e < hi) b.push_back(e);
    std::sort(b.begin(), b.end());
    b.erase(std::unique(b.begin(), b.end()), b.end());
    for (size_t i = 0; i + 1 < b.size(); ++i) {
      const double share = b.size() == 2 ? 1.0 : (b[i + 1] - b[i]) / (hi - lo);
      const int nodes = std::max(1, int(std::ceil(ps.polar_nodes * share - 1e-9)));
      GaussLegendre(nodes, b[i], b[i + 1], &xs, &ws);
    }
  };
  side(0, std::min(s_max, s_na));
  if (s_max > s_na) side(s_na, s_max);
  constexpr int kSector = 16;  // density samples across an azimuth sector
  const int az = ps.azimuths;
  std::vector<std::pair<double, double>> rings;  // (s, power)
  std::vector<double> ring_of;                   // each direction's ring's s
  for (size_t i = 0; i < xs.size(); ++i) {
    rings.emplace_back(xs[i], 0.0);
    for (int j = 0; j < az; ++j) {
      const double phi = 2 * M_PI * (j + 0.5 * (i % 2)) / az, st = xs[i];
      double mean = 1;
      if (field) {
        mean = 0;
        for (int q = 0; q < kSector; ++q) {
          const double p = phi + 2 * M_PI / az * ((q + 0.5) / kSector - 0.5);
          mean += density(st * std::cos(p), st * std::sin(p)) / kSector;
        }
        if (!(mean > 0)) continue;
      }
      const double w = ws[i] * st * 2 * M_PI / az * mean;
      dirs.push_back({Vec3(st * std::cos(phi), st * std::sin(phi), std::sqrt(1 - st * st)), w});
      ring_of.push_back(st);
      rings.back().second += w;
    }
  }
  // The far tail costs no spectra (TailStart, as in the exact model).
  const double s_cut = TailStart(std::move(rings));
  std::vector<Direction> kept;
  for (size_t i = 0; i < dirs.size(); ++i)
    if (ring_of[i] < s_cut) kept.push_back(dirs[i]);
  return kept;
}

}  // namespace

std::string PhysicalUnsupportedReason(const Scene& s) {
  switch (s.source.type) {
    case SourceType::kCone:
    case SourceType::kCollimated:
    case SourceType::kLightField:
      break;
    case SourceType::kPoint:
      return "optics = \"physical\" needs plane-wave illumination; a point source is not one";
    case SourceType::kRayList:
      return "optics = \"physical\" needs a source with an angular distribution, not a ray list";
  }
  return "";
}

nlohmann::json PhysicalSampling::ToJson() const {
  return {{"directions", directions},
          {"fft_grid", grid},
          {"fft_grid_um", grid_um},
          {"window_um", window_um},
          {"pixel_subsamples", pixel_subsamples},
          {"field_rays", field_rays},
          {"wavelengths", wavelengths},
          {"times", times}};
}

namespace {

/// The objects' enclosing sphere: the origin of every spectrum and its radius.
std::pair<Vec3, double> ObjectsSphere(const Simulator& sim) {
  return Simulator::EnclosingSphere(sim.ObjectBounds());
}

Scene AsTraced(Scene s) {
  s.trace.optics = ImageOptics::kRays;
  return s;
}

}  // namespace

double AutomaticPhysicalWindowUm(const Scene& scene, double defocus_um) {
  const auto [origin, extent] = ObjectsSphere(Simulator(AsTraced(scene)));
  const WaveWindow w =
      WaveWindowFor(scene, scene.trace.physical.margin_um, extent, defocus_um - origin.z);
  return 2 * (w.rho_light + w.margin);
}

struct PhysicalImager::Impl {
  Scene scene;
  std::unique_ptr<Simulator> sim;
  std::vector<Direction> dirs;
  double k = 0, lambda_medium = 0, s_na = 0;
  double sensor_sign = -1;
  CorrectorZones zones;        // the pupil's apodisation by angle (none: empty)
  SpatialEnvelope spatial;     // a light field's spatial map (none: empty)
  double spatial_mean = 1;     // its mean over the sensor's pixel centres
  Vec3 origin;                 // the objects' centre: the spectra's origin and exit plane
  double extent = 0;           // radius about it that holds the objects
  double flat = 0, scale = 1;  // flat-field flux; photons per unit of it
  mutable PhysicalSampling last;
  // A spectrum or motion: the scene's monochromatic, still parts (a wavelength at a time of the
  // pulse) with their shares of the power, each scaled to the photon target, so their weighted
  // sum is too. Empty: this imager is one such part itself.
  std::vector<std::pair<double, std::unique_ptr<PhysicalImager>>> parts;
  std::shared_ptr<FieldLayouts> layouts;  // (none: each spectrum lays its rays out itself)

  /// The parts of a spectrum and of motion (`parts`), and this imager's sampling from them.
  void BuildParts();

  /// The intensity change of one direction on the window's grid (n x n, spacing h, corner x0,
  /// y0), the mean of two orthogonal polarisations, added with `weight` to `dev`.
  void AddDirection(const Direction& dir, double dz, int n, double h, double x0, double y0,
                    double weight, FieldLayout* layout, std::vector<double>* dev,
                    uint64_t* rays) const;
  /// The same for polarisation `pol` with its scattered spectrum `sp` on grid `g`.
  void AddPolarisation(const Direction& dir, const CVec3& pol, const RaySpectrum& sp,
                       const SpectrumGrid& g, double dz, int n, double h, double x0, double y0,
                       double weight, std::vector<double>* dev) const;
};

PhysicalImager::PhysicalImager(const Scene& scene) : impl_(std::make_unique<Impl>()) {
  const std::string why = PhysicalUnsupportedReason(scene);
  if (!why.empty()) throw Error(FileLocation{scene.file}, why);
  Impl& im = *impl_;
  im.scene = scene;
  if (scene.source.spectrum.type != SpectrumType::kNone || scene.has_motion()) {
    im.BuildParts();
    return;
  }
  im.sim = std::make_unique<Simulator>(AsTraced(scene));
  im.lambda_medium = scene.wavelength_um / scene.medium_index;
  im.k = 2 * M_PI / im.lambda_medium;
  im.s_na = AcceptanceSin(scene);
  im.sensor_sign = MakeOptics(scene).sign * Magnification(scene.optics);
  // The objects' bounding sphere: the origin of every spectrum (its exit plane through it).
  std::tie(im.origin, im.extent) = ObjectsSphere(*im.sim);
  im.zones = CorrectorZonesOf(scene);
  im.dirs = IlluminationDirections(scene, im.s_na, im.zones);
  // The direct light that passes the NA and the corrector is the flat field (unit flux
  // density per weight).
  for (const Direction& d : im.dirs) {
    const double st = std::hypot(d.d.x, d.d.y);
    if (st <= im.s_na) im.flat += d.weight * im.zones.At(st);
  }
  if (!(im.flat > 0))
    throw Error(FileLocation{scene.file},
                "optics = \"physical\": no direct light passes the objective (a dark field): the "
                "photon scale is defined by the flat field");
  // A light field's spatial map is an envelope of the image; its mean over the sensor's pixel
  // centres keeps the flat field's mean at the photon target.
  im.spatial = SpatialEnvelopeOf(scene);
  if (!im.spatial.empty()) {
    im.spatial_mean = im.spatial.MeanOverSensor(scene.camera, im.sensor_sign);
    if (!(im.spatial_mean > 0))
      throw Error(FileLocation{scene.file},
                  "optics = \"physical\": the light field's spatial map is zero over the whole "
                  "sensor");
  }
  im.scale = FlatFieldPhotons(scene) / (im.flat * im.spatial_mean);
  im.last.directions = int(im.dirs.size());
}

void PhysicalImager::Impl::BuildParts() {
  // Incoherent over wavelengths: lines as given; a Gaussian or tabulated spectrum at the
  // midpoints of `spectrum_nodes` equal-power quantiles (the ray model draws from the same
  // distribution), each with the objects' indices at its wavelength (their dispersion laws; a
  // water density field's grid mapped to it, WaterIndexMap, in a copy). Motion: the pulse's
  // `motion_nodes` equal-power quantiles (midpoints) as times, every object where it is then.
  const SpectrumSpec& sp = scene.source.spectrum;
  const PhysicalSettings& ps = scene.trace.physical;
  std::vector<std::pair<double, double>> lambdas;  // wavelength, share
  if (sp.type == SpectrumType::kLines) {
    for (size_t k = 0; k < sp.wavelengths_um.size(); ++k)
      lambdas.emplace_back(sp.wavelengths_um[k], sp.weights[k]);
  } else if (sp.type != SpectrumType::kNone) {
    for (int k = 0; k < ps.spectrum_nodes; ++k)
      lambdas.emplace_back(sp.Sample((k + 0.5) / ps.spectrum_nodes), 1.0 / ps.spectrum_nodes);
  } else {
    lambdas.emplace_back(scene.wavelength_um, 1.0);
  }
  const int times = scene.has_motion() ? ps.motion_nodes : 1;
  for (const auto& [lambda, share] : lambdas)
    for (int t = 0; t < times; ++t) {
      Scene one = scene;
      one.source.spectrum = SpectrumSpec{};
      one.wavelength_um = lambda;
      const double at = scene.has_motion() ? scene.exposure.Offset((t + 0.5) / times) : 0.0;
      for (ObjectSpec& o : one.objects) {
        if (o.dispersion.law != DispersionLaw::kNone) o.index = o.dispersion.IndexAt(lambda);
        if (o.index_field && o.index_field->water &&
            lambda != o.index_field->water->wavelength_um) {
          const IndexField::WaterStates& w = *o.index_field->water;
          const AffineIndexMap m =
              WaterIndexMap(w.density_kg_m3, w.temperature_K, w.wavelength_um, lambda);
          auto at_lambda = std::make_shared<IndexField>(*o.index_field);
          for (double& v : at_lambda->values) v = m.offset + m.scale * v;
          at_lambda->min_n = m.offset + m.scale * at_lambda->min_n;
          at_lambda->max_n = m.offset + m.scale * at_lambda->max_n;
          auto states = std::make_shared<IndexField::WaterStates>(w);
          states->wavelength_um = lambda;
          at_lambda->water = states;
          o.index_field = at_lambda;
        }
        o.center_um = o.center_um + o.velocity_um_per_us * at;
        o.velocity_um_per_us = Vec3();
      }
      one.exposure = ExposureSpec{};
      parts.emplace_back(share / times, std::make_unique<PhysicalImager>(one));
    }
  last = parts[0].second->sampling();  // every part has the same directions
  last.wavelengths = int(lambdas.size());
  last.times = times;
}

PhysicalImager::~PhysicalImager() = default;

void PhysicalImager::KeepLayouts(std::shared_ptr<FieldLayouts> layouts) {
  Impl& im = *impl_;
  RAYMATCH_CHECK(layouts);
  if (!im.parts.empty()) {
    if (layouts->parts.size() != im.parts.size()) layouts->parts.assign(im.parts.size(), nullptr);
    for (size_t i = 0; i < im.parts.size(); ++i) {
      if (!layouts->parts[i]) layouts->parts[i] = std::make_shared<FieldLayouts>();
      im.parts[i].second->KeepLayouts(layouts->parts[i]);
    }
    return;  // (the parts lay out their own directions)
  }
  if (layouts->directions.size() != im.dirs.size())
    layouts->directions.assign(im.dirs.size(), FieldLayout{});
  im.layouts = std::move(layouts);
}

const Scene& PhysicalImager::scene() const { return impl_->scene; }
PhysicalSampling PhysicalImager::sampling() const { return impl_->last; }

std::vector<std::string> PhysicalImager::Effects() const {
  const Scene& s = impl_->scene;
  // A spectrum's or motion's parts image the rest alike.
  if (!impl_->parts.empty()) {
    std::vector<std::string> e = impl_->parts[0].second->Effects();
    if (s.source.spectrum.type != SpectrumType::kNone) e.push_back("spectrum");
    if (s.has_motion()) e.push_back("motion");
    return e;
  }
  std::vector<std::string> e{"optics:physical"};
  e.push_back(s.source.type == SourceType::kCone         ? "source:cone"
              : s.source.type == SourceType::kLightField ? "source:light_field"
                                                         : "source:collimated");
  if (!impl_->spatial.empty()) e.push_back("spatial_map");
  if (!s.objects.empty()) e.push_back("fresnel_branches");
  if (!impl_->zones.s.empty()) e.push_back("corrector");
  if (s.camera.psf_sigma_um > 0) e.push_back("psf");
  return e;
}

void PhysicalImager::Impl::AddDirection(const Direction& dir, double dz, int n, double h, double x0,
                                        double y0, double weight, FieldLayout* layout,
                                        std::vector<double>* dev, uint64_t* rays) const {
  const double L = n * h, dk = 2 * M_PI / L;
  const int j_hi = int(std::floor(k * s_na / dk));
  SpectrumGrid g;
  g.nx = g.ny = 2 * j_hi + 1;
  g.kx0 = g.ky0 = -j_hi * dk;
  g.dk = dk;
  g.k_max = k * s_na;
  const PhysicalSettings& ps = scene.trace.physical;
  RaySpectrumSettings rs;
  rs.ray_spacing_um = ps.ray_spacing_um;
  rs.refine_levels = ps.refine_levels;
  rs.max_cell_steps = ps.max_cell_steps;
  rs.max_events = ps.max_events;
  // Two orthogonal polarisations transverse to the direction, each of unit flux density through
  // the z-plane (|E0|^2 cos(theta_in) = 1); one outline for both.
  Vec3 e_th, e_ph;
  PolarBasis(dir.d, &e_th, &e_ph);
  const double e_scale = 1 / std::sqrt(dir.d.z);
  const std::vector<CVec3> pols{{e_th.x, e_th.y, e_th.z}, {e_ph.x, e_ph.y, e_ph.z}};
  std::vector<CVec3> e0s;
  for (const CVec3& p : pols) e0s.push_back({p[0] * e_scale, p[1] * e_scale, p[2] * e_scale});
  const std::vector<RaySpectrum> sp = RayAngularSpectra(*sim, dir.d, e0s, origin, g, rs, layout);
  for (size_t q = 0; q < pols.size(); ++q) {
    *rays += sp[q].rays;
    AddPolarisation(dir, pols[q], sp[q], g, dz, n, h, x0, y0, 0.5 * weight, dev);
  }
}

void PhysicalImager::Impl::AddPolarisation(const Direction& dir, const CVec3& pol,
                                           const RaySpectrum& sp, const SpectrumGrid& g, double dz,
                                           int n, double h, double x0, double y0, double weight,
                                           std::vector<double>* dev) const {
  const double dk = g.dk;
  const int j_hi = (g.nx - 1) / 2;
  // The camera's field as plane waves: sqrt(cos theta) (aplanatic) times the corrector's
  // amplitude sqrt(T), the defocus phase, the window's corner phase (fields are relative to the
  // origin), on the FFT's bins; one transform per component.
  const double cx = x0 - origin.x, cy = y0 - origin.y;
  std::array<cv::Mat, 2> m;
  for (cv::Mat& a : m) a = cv::Mat(n, n, CV_64FC2, cv::Scalar::all(0));
  const double kz_in = k * dir.d.z;
  for (int j = 0; j < g.ny; ++j)
    for (int i = 0; i < g.nx; ++i) {
      const double kx = g.kx0 + i * dk, ky = g.ky0 + j * dk, kt2 = kx * kx + ky * ky;
      if (kt2 > g.k_max * g.k_max) continue;
      const CVec3& a = sp.a[size_t(j) * g.nx + i];
      const double kz = std::sqrt(k * k - kt2), ct = kz / k;
      const Vec3 u(kx / k, ky / k, ct);
      const double amp = std::sqrt(ct * zones.At(std::sqrt(kt2) / k));
      if (amp == 0) continue;
      const C f = dk * dk * amp * std::exp(C(0, (kz - kz_in) * dz + kx * cx + ky * cy));
      const std::array<C, 2> e = ToCamera(u, a);
      const int bi = ((i - j_hi) % n + n) % n, bj = ((j - j_hi) % n + n) % n;
      for (int c = 0; c < 2; ++c) {
        const C v = f * e[c];
        m[c].at<cv::Vec2d>(bj, bi) += cv::Vec2d(v.real(), v.imag());
      }
    }
  for (cv::Mat& a : m) cv::dft(a, a, cv::DFT_INVERSE);  // sums, no 1 / N
  // The direct wave (inside the NA): amplitude sqrt(cos theta_in) |E0| = 1 on the camera,
  // times the corrector's sqrt(T).
  const double s_in = std::hypot(dir.d.x, dir.d.y);
  const bool direct = s_in <= s_na;
  std::array<C, 2> b0 = ToCamera(dir.d, pol);
  for (C& b : b0) b *= std::sqrt(zones.At(s_in));
  // Its phase is separable: a factor per column times one per row (2n exponentials, not n^2).
  std::vector<C> col_phase(static_cast<size_t>(n)), row_phase(static_cast<size_t>(n));
  for (int p = 0; p < n; ++p) {
    col_phase[size_t(p)] = std::exp(C(0, k * dir.d.x * (cx + p * h)));
    row_phase[size_t(p)] = std::exp(C(0, k * dir.d.y * (cy + p * h)));
  }
  tbb::parallel_for(0, n, [&](int q) {  // each grid point on its own: any thread count
    for (int p = 0; p < n; ++p) {
      const cv::Vec2d ex = m[0].at<cv::Vec2d>(q, p), ey = m[1].at<cv::Vec2d>(q, p);
      const C sx(ex[0], ex[1]), sy(ey[0], ey[1]);
      double d = std::norm(sx) + std::norm(sy);
      if (direct) {
        const C ph = col_phase[size_t(p)] * row_phase[size_t(q)];
        d += 2 * (std::conj(b0[0] * ph) * sx + std::conj(b0[1] * ph) * sy).real();
      }
      (*dev)[size_t(q) * n + p] += weight * d;
    }
  });
}

Image PhysicalImager::Expected(double defocus_um, int threads, bool progress,
                               const std::string& label) const {
  const Impl& im = *impl_;
  const Scene& s = im.scene;
  const CameraSpec& cam = s.camera;
  if (!im.parts.empty()) {
    // The parts one after another, each summed in a fixed order: the same for any threads.
    std::vector<double> sum(size_t(cam.nx) * cam.ny, 0.0);
    Progress bar(progress, label.empty() ? "physical optics" : label, im.parts.size());
    uint64_t rays = 0;
    for (const auto& [share, part] : im.parts) {
      const Image one = part->Expected(defocus_um, threads);
      for (size_t i = 0; i < sum.size(); ++i) sum[i] += share * one.pixels[i];
      rays += part->sampling().field_rays;
      bar.Add(1);
    }
    Image img(cam.nx, cam.ny);
    for (size_t i = 0; i < sum.size(); ++i) img.pixels[i] = float(sum[i]);
    const PhysicalSampling first = im.parts[0].second->sampling();
    im.last.grid = first.grid, im.last.grid_um = first.grid_um, im.last.window_um = first.window_um;
    im.last.pixel_subsamples = first.pixel_subsamples;
    im.last.field_rays = rays;
    return img;
  }
  // The window: the objects' light on the focal plane (their extent, spread by the NA over
  // the defocus) and a margin for the pupil's diffraction tails, periodic.
  const PhysicalSettings& ps = s.trace.physical;
  const double dz = defocus_um - im.origin.z;
  const WaveWindow win = WaveWindowFor(s, ps.margin_um, im.extent, dz);
  const double half = ps.window_um > 0 ? ps.window_um / 2 : win.rho_light + win.margin;
  const double h_max = im.lambda_medium / (4 * im.s_na) / ps.oversample;
  const int n = cv::getOptimalDFTSize(int(std::ceil(2 * half / h_max)));
  const double h = 2 * half / n;
  const double x0 = im.origin.x - half, y0 = im.origin.y - half;
  std::vector<double> dev(size_t(n) * n, 0.0);
  uint64_t rays = 0;
  if (!s.objects.empty()) {
    tbb::task_arena arena(threads > 0 ? threads : tbb::task_arena::automatic);
    // Directions one after another (each spectrum runs in parallel itself), in a fixed order:
    // the same sums for any thread count.
    Progress bar(progress, label.empty() ? "physical optics" : label, im.dirs.size());
    arena.execute([&] {
      for (size_t i = 0; i < im.dirs.size(); ++i) {
        const Direction& d = im.dirs[i];
        FieldLayout* layout = im.layouts ? &im.layouts->directions[i] : nullptr;
        im.AddDirection(d, dz, n, h, x0, y0, d.weight, layout, &dev, &rays);
        bar.Add(1);
      }
    });
  }
  // The camera's PSF (a Gaussian of psf_sigma_um at the object plane) blurs the intensity; the
  // flat field is unchanged by it.
  if (s.camera.psf_sigma_um > 0) {
    cv::Mat m(n, n, CV_64F, dev.data());
    cv::GaussianBlur(m, m, cv::Size(0, 0), s.camera.psf_sigma_um / h, s.camera.psf_sigma_um / h,
                     cv::BORDER_REPLICATE);
  }
  // Pixels integrated on K x K sub-samples, the grid read bilinearly (zero change outside).
  const double pix_obj = cam.pixel_pitch_um / std::abs(Magnification(s.optics));
  const int kss = PixelSubsamples(ps.pixel_subsamples, pix_obj, im.lambda_medium, im.s_na);
  auto at = [&](double x, double y) {
    const double fx = (x - x0) / h, fy = (y - y0) / h;
    const int ix = int(std::floor(fx)), iy = int(std::floor(fy));
    if (ix < 0 || iy < 0 || ix + 1 >= n || iy + 1 >= n) return 0.0;
    const double tx = fx - ix, ty = fy - iy;
    const double* r0 = &dev[size_t(iy) * n + ix];
    const double* r1 = r0 + n;
    return (1 - ty) * ((1 - tx) * r0[0] + tx * r0[1]) + ty * ((1 - tx) * r1[0] + tx * r1[1]);
  };
  Image img(cam.nx, cam.ny);
  tbb::parallel_for(0, cam.ny, [&](int r) {
    for (int c = 0; c < cam.nx; ++c) {
      double sum = 0;
      for (int b = 0; b < kss; ++b)
        for (int a = 0; a < kss; ++a) {
          const auto [x, y] =
              SensorToObject(cam, im.sensor_sign, c + (a + 0.5) / kss, r + (b + 0.5) / kss);
          sum += at(x, y);
        }
      const auto [xc, yc] = SensorToObject(cam, im.sensor_sign, c + 0.5, r + 0.5);
      const double val = im.scale * im.spatial.At(xc, yc) * (im.flat + sum / (kss * kss));
      RAYMATCH_CHECK(std::isfinite(val));  // (std::max below would hide a NaN as 0)
      img.at(c, r) = float(std::max(0.0, val));
    }
  });
  im.last.grid = n;
  im.last.grid_um = h;
  im.last.window_um = 2 * half;
  im.last.pixel_subsamples = kss;
  im.last.field_rays = rays;
  return img;
}

}  // namespace raymatch::simulate
