// The exact wave image of a sphere (wave_image.h states the model; docs/wave-optics.md derives
// it). Frames: the world frame of docs/conventions.md, light along +z; each illumination node
// is computed for a wave tilted in the x-z plane and a sphere on the axis, then rotated and
// shifted to the scene's sphere by the azimuthal harmonics.
#include "raymatch/simulate/wave_image.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <complex>
#include <functional>
#include <map>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "raymatch/core/error.h"
#include "raymatch/core/rng.h"
#include "raymatch/simulate/mie.h"
#include "raymatch/simulate/sampling.h"
#include "raymatch/simulate/tracer.h"
#include "sources.h"
#include "stages.h"

namespace raymatch::simulate {

namespace {

constexpr double kDeg = M_PI / 180.0;

/// Keys' cubic convolution weights (a = -1/2) for offset t in [0, 1).
inline void KeysWeights(double t, double w[4]) {
  const double t2 = t * t, t3 = t2 * t;
  w[0] = -0.5 * t3 + t2 - 0.5 * t;
  w[1] = 1.5 * t3 - 2.5 * t2 + 1;
  w[2] = -1.5 * t3 + 2 * t2 + 0.5 * t;
  w[3] = 0.5 * t3 - 0.5 * t2;
}

/// One illumination node: a polar angle of the incident wave with its quadrature weight and the
/// source's azimuthal moments there.
struct Node {
  double s = 0, cos = 1;       // sin and cos of the polar angle
  double omega = 0;            // quadrature weight x Jacobian (s ds), or 1 for a single direction
  std::vector<double> wc, ws;  // integral of w(s, phi) cos(m phi), sin(m phi) d phi
};

/// The sphere whose outer surface scatters (the larger of a coated sphere's two) and the core
/// inside it (null for a homogeneous sphere); MieUnsupportedReason says when a scene has them.
struct MieSpheres {
  const ObjectSpec* shell = nullptr;
  const ObjectSpec* core = nullptr;
};

MieSpheres SpheresOf(const Scene& s) {
  if (s.objects.size() == 1) return {&s.objects[0], nullptr};
  const bool first_outer = s.objects[0].radius_um >= s.objects[1].radius_um;
  return {&s.objects[first_outer ? 0 : 1], &s.objects[first_outer ? 1 : 0]};
}
}  // namespace

std::string MieUnsupportedReason(const Scene& s) {
  if (s.objects.empty() || s.objects.size() > 2)
    return "optics = \"mie\" needs one sphere (or two concentric ones: a coated sphere); the "
           "scene has " +
           std::to_string(s.objects.size()) + " objects";
  for (const ObjectSpec& o : s.objects) {
    if (o.shape != ShapeType::kSphere)
      return "optics = \"mie\" needs a sphere; object '" + o.name + "' is not one";
    if (o.index_field)
      return "optics = \"mie\" needs a homogeneous sphere; '" + o.name + "' has an index field";
  }
  if (const MieSpheres sp = SpheresOf(s); sp.core) {
    // Concentric to well below a wavelength's thousandth: the series assumes one centre.
    const double off = Length(sp.core->center_um - sp.shell->center_um);
    if (off > 1e-9 * sp.shell->radius_um)
      return "optics = \"mie\" takes two spheres as a coated sphere only when they are "
             "concentric: '" +
             sp.core->name + "' is " + std::to_string(off) + " um from the centre of '" +
             sp.shell->name + "' (a fit key that moves one of them moves it off)";
    if (!(sp.core->radius_um < sp.shell->radius_um))
      return "optics = \"mie\": the core '" + sp.core->name +
             "' of a coated sphere must be "
             "smaller than its shell '" +
             sp.shell->name + "'";
    if (Length(sp.core->velocity_um_per_us - sp.shell->velocity_um_per_us) > 0)
      return "optics = \"mie\": a coated sphere's core '" + sp.core->name + "' and shell '" +
             sp.shell->name + "' must move together (the same velocity_um_per_us)";
  }
  switch (s.source.type) {
    case SourceType::kCone:
    case SourceType::kLightField:
      break;
    case SourceType::kCollimated:
      if (s.source.tilt_deg != 0)
        return "optics = \"mie\" takes a collimated source along the axis only (tilt_deg = 0)";
      break;
    case SourceType::kPoint:
      return "optics = \"mie\" needs plane-wave illumination; a point source is not one";
    case SourceType::kRayList:
      return "optics = \"mie\" needs a source with an angular distribution, not a ray list";
  }
  return "";
}

nlohmann::json MieSampling::ToJson() const {
  return {{"directions", directions},
          {"azimuthal_harmonics", harmonics},
          {"fft_grid", grid},
          {"fft_grid_um", grid_um},
          {"window_um", window_um},
          {"pixel_subsamples", pixel_subsamples},
          {"mie_terms", terms},
          {"wavelengths", wavelengths},
          {"size_parameter", size_parameter},
          {"core_size_parameter", core_size_parameter}};
}

/// What the render reads besides the harmonics: the sphere's place, the pupil, the sensor's map
/// and the illumination's spatial envelope. A spectrum's wavelengths share it.
struct RenderGeometry {
  double lambda_medium = 0;
  double s_na = 0;    // sin of the objective's acceptance angle in the medium
  double radius = 0;  // sphere radius
  Vec3 center;
  int harmonics = 0;
  // Corrector: zone outer edges in sin(theta) and intensity transmissions (empty: none).
  std::vector<double> zone_s, zone_t;
  double magnification = 1;
  double sensor_sign = -1;  // sign x M: sensor coordinate per object coordinate
  // Spatial envelope (light field's spatial map; empty: uniform).
  SpatialEnvelope spatial;
  double spatial_mean = 1;
};

struct MieImager::Impl : RenderGeometry {
  Scene scene;
  MieSettings set;
  double k = 0;  // wavenumber in the medium (rad / um)
  MieCoefficients mie;
  MieTable table;
  std::vector<Node> nodes;
  // The pupil as zones in sin(theta): outer edges (the last is the NA) and amplitudes sqrt(T).
  std::vector<double> pupil_edges, pupil_amp;
  double flat = 0;   // flat-field flux (source units)
  double scale = 1;  // photons per pixel per flat-field unit
  mutable MieSampling last;
  // A spectrum: one monochromatic imager per wavelength node, with its share of the power
  // (each normalised to the photon target, so the weighted sum is too); their nodes'
  // harmonics are summed on one radial grid and rendered once.
  std::vector<std::pair<double, std::unique_ptr<MieImager>>> wavelengths;
  int interleave = 1;  // classes of illumination nodes with their own wavelengths
  int all_nodes = 0;   // illumination nodes before a class kept its own

  /// A spectrum's sampling: the first wavelength's, with every class's directions.
  MieSampling SpectrumSampling() const {
    MieSampling m = wavelengths[0].second->sampling();
    for (int j = 1; j < interleave; ++j)
      m.directions += wavelengths[j].second->sampling().directions;
    m.wavelengths = int(wavelengths.size());
    return m;
  }

  double Transmission(double s) const {
    if (s > s_na) return 0;
    if (zone_s.empty()) return 1;
    for (size_t i = 0; i < zone_s.size(); ++i)
      if (s <= zone_s[i]) return zone_t[i];
    return 0;
  }

  /// The object-plane point of the sensor position (col, row) in pixels.
  std::pair<double, double> ObjectPoint(double col, double row) const {
    return SensorToObject(scene.camera, sensor_sign, col, row);
  }

  double SpatialAt(double x, double y) const { return spatial.At(x, y); }

  /// The image's azimuthal harmonics about the sphere for one axial offset `dz` of the focal
  /// plane from its centre: the illumination nodes' intensity changes, summed with their
  /// weights, on the radial grid rho = q drho. They do not depend on the sphere's lateral
  /// position, so they are kept per dz (MoveAcross renders them at another).
  struct Pattern {
    int n = 0;     // FFT grid
    double h = 0;  // its spacing
    double drho = 0;
    int n_rho = 0;
    std::vector<std::vector<double>> cm, sm;  // cos and sin harmonics, [m][q]
  };
  mutable std::map<double, Pattern> patterns;
  /// The harmonics at `dz`: this wavelength's nodes on its own grid or, for a spectrum, every
  /// wavelength's nodes with their shares of the photons on one radial grid (rendered once).
  const Pattern& PatternAt(double dz, tbb::task_arena& arena) const;
  /// A monochromatic imager's FFT grid at `dz` and its own radial grid.
  struct Grid {
    int n = 0;
    double h = 0, drho = 0;
    int n_rho = 0;
  };
  Grid GridAt(double dz) const;
  /// Adds the harmonics of the illumination nodes of `parts` (monochromatic imagers, each with
  /// its factor) at `dz` on the radial grid (drho, n_rho) to `pat`, in a fixed order (the same
  /// sums for any thread count).
  static void SumNodes(const std::vector<std::pair<const Impl*, double>>& parts, double dz,
                       double drho, int n_rho, int harmonics, tbb::task_arena& arena, Pattern* pat);
  void BuildSource();
  void BuildNodes(const std::vector<double>& breaks, double s_max,
                  const std::function<double(double, double)>& density);
  // The intensity change of node j's wave on the grid, as azimuthal harmonics d_m(rho).
  void NodeHarmonics(const Node& nd, double dz, int n, double h, double drho, int n_rho,
                     std::vector<std::vector<double>>* d) const;
};

void MieImager::Impl::BuildNodes(const std::vector<double>& breaks_in, double s_max,
                                 const std::function<double(double, double)>& density) {
  std::vector<double> breaks{0, s_max};
  for (double b : breaks_in)
    if (b > 0 && b < s_max) breaks.push_back(b);
  std::sort(breaks.begin(), breaks.end());
  breaks.erase(std::unique(breaks.begin(), breaks.end(),
                           [](double a, double b) { return std::abs(a - b) < 1e-12; }),
               breaks.end());
  const int n_phi = 720;
  for (size_t p = 0; p + 1 < breaks.size(); ++p) {
    const double a = breaks[p], b = breaks[p + 1];
    const int panels = std::max(1, int(std::ceil((b - a) / set.panel_width - 1e-9)));
    for (int q = 0; q < panels; ++q) {
      std::vector<double> xs, ws;
      GaussLegendre(set.nodes_per_panel, a + (b - a) * q / panels, a + (b - a) * (q + 1) / panels,
                    &xs, &ws);
      for (size_t i = 0; i < xs.size(); ++i) {
        Node nd;
        nd.s = xs[i];
        nd.cos = std::sqrt(1 - nd.s * nd.s);
        nd.omega = ws[i] * nd.s;
        nd.wc.assign(harmonics + 1, 0.0);
        nd.ws.assign(harmonics + 1, 0.0);
        for (int l = 0; l < n_phi; ++l) {
          const double phi = 2 * M_PI * (l + 0.5) / n_phi;
          const double w = density(nd.s * std::cos(phi), nd.s * std::sin(phi));
          if (w == 0) continue;
          for (int m = 0; m <= harmonics; ++m) {
            nd.wc[m] += w * std::cos(m * phi);
            nd.ws[m] += w * std::sin(m * phi);
          }
        }
        for (int m = 0; m <= harmonics; ++m)
          nd.wc[m] *= 2 * M_PI / n_phi, nd.ws[m] *= 2 * M_PI / n_phi;
        if (nd.wc[0] > 0) nodes.push_back(std::move(nd));
      }
    }
  }
  // A soft edge's far tail costs no fields (TailStart).
  std::vector<std::pair<double, double>> rings;  // (s, power)
  for (const Node& nd : nodes) rings.emplace_back(nd.s, nd.omega * nd.wc[0]);
  const double s_cut = TailStart(std::move(rings));
  std::erase_if(nodes, [s_cut](const Node& nd) { return nd.s >= s_cut; });
}

void MieImager::Impl::BuildSource() {
  const SourceSpec& ss = scene.source;
  std::vector<double> breaks{s_na};
  breaks.insert(breaks.end(), zone_s.begin(), zone_s.end());
  switch (ss.type) {
    case SourceType::kCollimated: {  // along the axis (MieUnsupportedReason)
      harmonics = 0;
      Node nd;
      nd.s = 0, nd.cos = 1, nd.omega = 1;
      nd.wc = {1.0};
      nd.ws = {0.0};
      nodes.push_back(nd);
      break;
    }
    case SourceType::kCone: {
      harmonics = 0;
      const double sm = std::sin(ss.half_angle_deg * kDeg);
      BuildNodes(breaks, sm, [](double, double) { return 1.0; });
      break;
    }
    case SourceType::kLightField: {
      harmonics = set.harmonics;
      const AngularDensity density = LightFieldDensity(ss);
      breaks.insert(breaks.end(), density.breaks.begin(), density.breaks.end());
      BuildNodes(breaks, density.s_max, density);
      break;
    }
    default:
      throw Error(FileLocation{scene.file}, MieUnsupportedReason(scene));
  }
  if (nodes.empty())
    throw Error(FileLocation{scene.file}, "optics = \"mie\": the source emits no light");
}

MieImager::MieImager(const Scene& scene) : MieImager(scene, 1, 0) {}

MieImager::MieImager(const Scene& scene, int stride, int offset) : impl_(std::make_unique<Impl>()) {
  const std::string why = MieUnsupportedReason(scene);
  if (!why.empty()) throw Error(FileLocation{scene.file}, why);
  Impl& im = *impl_;
  im.scene = scene;
  im.set = scene.trace.mie;
  const SpectrumSpec& sp = scene.source.spectrum;
  if (sp.type != SpectrumType::kNone) {
    // Incoherent over wavelengths: lines as given; a Gaussian or tabulated spectrum at the
    // midpoints of K equal-power quantiles (the ray model draws from the same distribution),
    // each node with the sphere's index at its wavelength.
    // Interleaved (spectrum_interleave S > 1): the illumination nodes split into S classes by
    // index modulo S, class j at the quantiles (k S + j + 1/2) / (K S): each direction sees K
    // stratified wavelengths, shifted from class to class, so that together they sample K S
    // (a monochromatic image's sharp resonances weigh 1 / (K S), not 1 / K).
    struct Node {
      double wavelength, share;
      int cls;
    };
    // No more classes than illumination nodes: with fewer, the first class says how many
    // there are and the spectrum is built again.
    auto build = [&](int S) {
      std::vector<Node> nodes;
      if (sp.type == SpectrumType::kLines) {
        for (size_t k = 0; k < sp.wavelengths_um.size(); ++k)
          nodes.push_back({sp.wavelengths_um[k], sp.weights[k], 0});
      } else {
        const int K = im.set.spectrum_nodes;
        for (int k = 0; k < K; ++k)
          for (int j = 0; j < S; ++j)
            nodes.push_back({sp.Sample((k * S + j + 0.5) / (K * S)), 1.0 / K, j});
      }
      im.wavelengths.clear();
      im.wavelengths.resize(nodes.size());
      auto make = [&](size_t k) {
        Scene one = scene;
        one.source.spectrum = SpectrumSpec{};
        one.wavelength_um = nodes[k].wavelength;
        for (ObjectSpec& o : one.objects)
          if (o.dispersion.law != DispersionLaw::kNone)
            o.index = o.dispersion.IndexAt(nodes[k].wavelength);
        im.wavelengths[k] = {nodes[k].share, std::make_unique<MieImager>(one, S, nodes[k].cls)};
      };
      make(0);
      if (S > 1 && im.wavelengths[0].second->impl_->all_nodes < S)
        return im.wavelengths[0].second->impl_->all_nodes;
      tbb::parallel_for(size_t(1), nodes.size(), make);  // independent imagers
      return S;
    };
    int S = sp.type == SpectrumType::kLines ? 1 : im.set.spectrum_interleave;
    if (const int fewer = build(S); fewer < S) build(S = fewer);
    im.interleave = S;
    // Rendered once from the wavelengths' summed harmonics (PatternAt), already in photons:
    // what the render reads is the wavelengths' common geometry, the flat field their sum.
    static_cast<RenderGeometry&>(im) = *im.wavelengths[0].second->impl_;
    im.scale = 1;
    im.flat = 0;
    for (const auto& [share, one] : im.wavelengths) {
      const Impl& c = *one->impl_;
      im.lambda_medium = std::min(im.lambda_medium, c.lambda_medium);  // pixel sub-samples
      im.flat += share * c.scale * c.flat;
    }
    im.last = im.SpectrumSampling();
    return;
  }
  const MieSpheres spheres = SpheresOf(scene);
  const ObjectSpec& o = *spheres.shell;
  im.radius = o.radius_um;
  im.center = o.center_um;
  im.lambda_medium = scene.wavelength_um / scene.medium_index;
  im.k = 2 * M_PI / im.lambda_medium;
  im.s_na = AcceptanceSin(scene);
  auto relative = [&](const ObjectSpec& a) {
    return Complex(a.index / scene.medium_index, a.absorption_index / scene.medium_index);
  };
  const ObjectSpec* core = spheres.core;
  im.mie = core ? ComputeCoatedMie(relative(*core), im.k * core->radius_um, relative(o),
                                   im.k * im.radius)
                : ComputeMie(relative(o), im.k * im.radius);
  const OpticsSpec& op = scene.optics;
  const CorrectorZones zones = CorrectorZonesOf(scene);
  im.zone_s = zones.s, im.zone_t = zones.t;
  for (size_t i = 0; i < im.zone_s.size() && im.zone_s[i] < im.s_na; ++i) {
    im.pupil_edges.push_back(im.zone_s[i]);
    im.pupil_amp.push_back(std::sqrt(im.zone_t[i]));
  }
  im.pupil_edges.push_back(im.s_na);
  im.pupil_amp.push_back(std::sqrt(im.Transmission(im.s_na)));
  im.BuildSource();
  // The photon scale is the flat field of all nodes; a class of an interleaved spectrum keeps
  // its own nodes (and their direct light) only.
  double flat_all = 0;
  for (const Node& nd : im.nodes) flat_all += nd.omega * nd.wc[0] * im.Transmission(nd.s);
  im.all_nodes = int(im.nodes.size());
  if (stride > 1) {
    std::vector<Node> mine;
    for (size_t i = size_t(offset); i < im.nodes.size(); i += size_t(stride))
      mine.push_back(std::move(im.nodes[i]));
    im.nodes = std::move(mine);
  }
  // The largest scattering angle: the steepest wave to the farthest accepted direction.
  double s_max = 0;
  for (const Node& nd : im.nodes) s_max = std::max(s_max, nd.s);
  im.table = MieTable(im.mie, std::asin(std::min(1.0, s_max)) + std::asin(im.s_na) + 0.01);
  for (const Node& nd : im.nodes) im.flat += nd.omega * nd.wc[0] * im.Transmission(nd.s);
  if (!(flat_all > 0))
    throw Error(FileLocation{scene.file},
                "optics = \"mie\": no direct light passes the objective (a dark field): the "
                "photon scale is defined by the flat field");
  im.magnification = Magnification(op);
  im.sensor_sign = MakeOptics(scene).sign * im.magnification;
  im.spatial = SpatialEnvelopeOf(scene);
  // Photons: the flat field's mean over the sensor is photons_per_pixel (as in the ray model's
  // photon target); with a ray count instead, the ray model's flat field of that many rays.
  im.spatial_mean = im.spatial.MeanOverSensor(scene.camera, im.sensor_sign);
  const double photons = FlatFieldPhotons(scene);
  if (!(im.spatial_mean > 0))
    throw Error(FileLocation{scene.file},
                "optics = \"mie\": the light field's spatial map is "
                "zero over the whole sensor");
  im.scale = photons / (flat_all * im.spatial_mean);
  im.last.directions = int(im.nodes.size());
  im.last.harmonics = im.harmonics;
  im.last.terms = im.mie.terms();
  im.last.size_parameter = im.mie.x;
  im.last.core_size_parameter = im.mie.x_core;
  im.last.background = im.flat;
}

MieImager::~MieImager() = default;
const Scene& MieImager::scene() const { return impl_->scene; }
MieSampling MieImager::sampling() const { return impl_->last; }

std::vector<std::string> MieImager::Effects() const {
  const Scene& s = impl_->scene;
  std::vector<std::string> e{"optics:mie"};
  e.push_back(s.source.type == SourceType::kCone         ? "source:cone"
              : s.source.type == SourceType::kCollimated ? "source:collimated"
                                                         : "source:light_field");
  if (!impl_->spatial.empty()) e.push_back("spatial_map");
  if (!impl_->zone_s.empty()) e.push_back("corrector");
  if (s.camera.psf_sigma_um > 0) e.push_back("psf");
  if (!impl_->wavelengths.empty()) e.push_back("spectrum");
  if (s.has_motion()) e.push_back("motion");
  if (s.objects.size() == 2) e.push_back("coated");
  for (const ObjectSpec& o : s.objects)
    if (o.absorption_index > 0) {
      e.push_back("absorption");
      break;
    }
  return e;
}

namespace {
/// The azimuthal harmonics d_m(rho) about the sphere (grid point 0) of the intensity change
/// dev[x * n + y] (0 <= y, even in y) on an n x n grid of spacing h, at n_rho radii drho apart,
/// m = 0 .. mh. The pattern is even in psi (the incidence plane is a mirror plane), so
/// d_m = (2 - delta_m0) / N sum_l D(psi_l) cos(m psi_l) over N points of the circle, from the
/// half circle with trapezoid end weights; N follows the intensity's highest spatial frequency,
/// band.
void AzimuthalHarmonics(const std::vector<double>& dev, int n, double h, double drho, int n_rho,
                        int mh, double band, std::vector<std::vector<double>>* d) {
  d->assign(mh + 1, std::vector<double>(n_rho, 0.0));
  auto sample = [&](double x, double y) {
    const double gx = x / h, gy = y / h;
    const double fx = std::floor(gx), fy = std::floor(gy);
    double wx[4], wy[4];
    KeysWeights(gx - fx, wx);
    KeysWeights(gy - fy, wy);
    // The taps lie within the grid points NodeHarmonics transformed (|x| <= need < n / 2): one
    // wrap at most; y >= 0 (the half circle), taps below 0 mirrored.
    auto wrap = [n](int i) { return i < 0 ? i + n : (i >= n ? i - n : i); };
    const int ix = int(fx) - 1, iy = int(fy) - 1;
    const int yb[4] = {std::abs(iy), std::abs(iy + 1), iy + 2, iy + 3};
    double sum = 0;
    for (int a = 0; a < 4; ++a) {
      const double* xp = &dev[size_t(wrap(ix + a)) * n];
      sum +=
          wx[a] * (wy[0] * xp[yb[0]] + wy[1] * xp[yb[1]] + wy[2] * xp[yb[2]] + wy[3] * xp[yb[3]]);
    }
    return sum;
  };
  for (int q = 0; q < n_rho; ++q) {
    const double rho = q * drho;
    const int nf = 2 * int(std::ceil((band * rho + mh + 16) / 2));
    const int half = nf / 2;
    std::vector<double> acc(mh + 1, 0.0);
    // cos and sin of psi_l by rotation (rounding grows as l eps), cos(m psi) by Chebyshev's
    // recurrence cos(m psi) = 2 cos(psi) cos((m - 1) psi) - cos((m - 2) psi).
    const double c1 = std::cos(2 * M_PI / nf), s1 = std::sin(2 * M_PI / nf);
    double cl = 1, sl = 0;
    for (int l = 0; l <= half; ++l) {
      const double w = (l == 0 || l == half) ? 1.0 : 2.0;
      const double v = w * sample(rho * cl, rho * sl);
      acc[0] += v;
      double cm2 = 1, cm1 = cl;
      for (int m = 1; m <= mh; ++m) {
        acc[m] += v * cm1;
        const double next = 2 * cl * cm1 - cm2;
        cm2 = cm1, cm1 = next;
      }
      const double cn = cl * c1 - sl * s1;
      sl = sl * c1 + cl * s1, cl = cn;
    }
    for (int m = 0; m <= mh; ++m) (*d)[m][q] = acc[m] * (m == 0 ? 1.0 : 2.0) / nf;
  }
}

}  // namespace

void MieImager::Impl::NodeHarmonics(const Node& nd, double dz, int n, double h, double drho,
                                    int n_rho, std::vector<std::vector<double>>* d) const {
  const double L = n * h, dk = 2 * M_PI / L;
  const Vec3 kin(nd.s, 0, nd.cos);
  const double kz_in = k * nd.cos;
  const Vec3 p1(0, 1, 0), p2(nd.cos, 0, -nd.s);  // TE and TM polarisations of the wave
  const double kna = k * s_na, kna_out = kna + dk;
  const int i_lo = int(std::ceil((-kna_out - k * nd.s) / dk));
  const int i_hi = int(std::floor((kna_out - k * nd.s) / dk));
  const int j_hi = int(std::floor(kna_out / dk));
  // The sphere on the axis and a wave in the x-z plane are symmetric under y -> -y, so of each
  // polarisation's field at the camera one component is even in y and the other odd (TE: Ey
  // even, Ex odd; TM: Ex even, Ey odd). One transform of their sum gives both: the even part
  // is (G(y) + G(-y)) / 2, the odd part (G(y) - G(-y)) / 2. The modes fill only the rows
  // |ky| <= kna_out, so the transform along x runs on those rows alone (row j_hi + j holds
  // ky = j dk), and the one along y on the transposed result.
  const int rows = 2 * j_hi + 1;
  // Buffers kept per thread: allocating them per node costs more in page faults than the
  // transforms.
  thread_local struct {
    std::array<cv::Mat, 2> g, t;
    cv::Mat gt;
    std::vector<double> dev;
  } work;
  std::array<cv::Mat, 2>& g = work.g;  // per polarisation: the modes of Ex + Ey
  for (cv::Mat& a : g) {
    a.create(rows, n, CV_64FC2);
    a.setTo(cv::Scalar::all(0));
  }
  const double norm = -2 * M_PI / (k * k * L * L);
  for (int j = -j_hi; j <= j_hi; ++j) {
    const double ky = dk * j;
    for (int i = i_lo; i <= i_hi; ++i) {
      const double kx = k * nd.s + dk * i, kt2 = kx * kx + ky * ky;
      if (kt2 > kna_out * kna_out) continue;
      const double kt = std::sqrt(kt2);
      // The pupil's amplitude, averaged over the mode's Fourier cell: the cell's share of each
      // zone (a linear ramp across the edge, over the cell's width along the radius), so the
      // discrete pupil's edges move smoothly with the window instead of as a staircase.
      const double ramp = dk * (kt > 0 ? (std::abs(kx) + std::abs(ky)) / kt : 1.0);
      auto inside = [&](double edge_k) { return std::clamp((edge_k - kt) / ramp + 0.5, 0.0, 1.0); };
      double amp = 0, below = 0;
      for (size_t z = 0; z < pupil_edges.size(); ++z) {
        const double in = inside(pupil_edges[z] * k);
        amp += (in - below) * pupil_amp[z];
        below = in;
      }
      if (amp <= 0) continue;
      const double st = std::min(kt / k, 1.0), ct = std::sqrt(std::max(0.0, 1 - st * st));
      const Vec3 ks(kx / k, ky / k, ct);
      const double cos_scat = std::clamp(Dot(ks, kin), -1.0, 1.0);
      const MieAmplitudes sa = table.At(std::acos(cos_scat));
      Vec3 e_perp = Cross(kin, ks);
      const double cn = Length(e_perp);
      e_perp = cn > 1e-12 ? e_perp / cn : Vec3(0, 1, 0);
      const Vec3 e_par_i = Cross(e_perp, kin), e_par_s = Cross(e_perp, ks);
      const Complex f =
          norm / ct * amp * std::sqrt(ct) * std::exp(Complex(0, (k * ct - kz_in) * dz));
      const double cp = kt2 > 0 ? kx / kt : 1.0, sp = kt2 > 0 ? ky / kt : 0.0;  // of its azimuth
      const Vec3 e_th(ct * cp, ct * sp, -st), e_ph(-sp, cp, 0);
      const int col = ((i % n) + n) % n;
      for (int p = 0; p < 2; ++p) {
        const Vec3& pol = p == 0 ? p1 : p2;
        const Complex a_par = sa.s2 * Dot(pol, e_par_i), a_perp = sa.s1 * Dot(pol, e_perp);
        // E_s = a_par e_par_s + a_perp e_perp, resolved on e_theta, e_phi of the direction.
        const Complex a_th = a_par * Dot(e_par_s, e_th) + a_perp * Dot(e_perp, e_th);
        const Complex a_ph = a_par * Dot(e_par_s, e_ph) + a_perp * Dot(e_perp, e_ph);
        const Complex e = f * (a_th * (cp + sp) + a_ph * (cp - sp));  // Ex + Ey
        g[p].at<cv::Vec2d>(j + j_hi, col) += cv::Vec2d(e.real(), e.imag());
      }
    }
  }
  // t[p](x, y): the field sum at grid point (x, y), x the row (the transposed layout).
  // The polar resampling below reads grid points with |x|, |y| <= `need` only.
  const int need = std::min(n / 2 - 1, int(std::ceil((n_rho - 1) * drho / h)) + 3);
  std::array<cv::Mat, 2>& t = work.t;
  cv::Mat& gt = work.gt;
  for (int p = 0; p < 2; ++p) {
    cv::dft(g[p], g[p], cv::DFT_INVERSE | cv::DFT_ROWS);  // along x; sums, no 1/N
    cv::transpose(g[p], gt);                              // n x rows: x, then ky from -j_hi
    t[p].create(n, n, CV_64FC2);
    for (int c = 0; c < n; ++c) {
      if (c > need && c < n - need) continue;
      const cv::Vec2d* src = gt.ptr<cv::Vec2d>(c);
      cv::Vec2d* dst = t[p].ptr<cv::Vec2d>(c);
      std::copy(src + j_hi, src + rows, dst);  // ky >= 0 at 0 .. j_hi
      std::fill(dst + j_hi + 1, dst + n - j_hi, cv::Vec2d(0, 0));
      std::copy(src, src + j_hi, dst + n - j_hi);  // ky < 0 wrapped to the end
    }
    // Along y, for the x rows that are read.
    cv::Mat lo = t[p].rowRange(0, need + 1), hi = t[p].rowRange(n - need, n);
    cv::dft(lo, lo, cv::DFT_INVERSE | cv::DFT_ROWS);
    cv::dft(hi, hi, cv::DFT_INVERSE | cv::DFT_ROWS);
  }
  // The direct wave: amplitude sqrt(T cos) on the polarisation's image direction.
  const double a0 = std::sqrt(Transmission(nd.s) * nd.cos);
  // dev[x * n + y]: the intensity change at grid point (x, y), for 0 <= y <= need (it is even
  // in y).
  std::vector<double>& dev = work.dev;
  dev.resize(size_t(n) * n);
  for (int c = 0; c < n; ++c) {
    if (c > need && c < n - need) continue;
    const cv::Vec2d *g1 = t[0].ptr<cv::Vec2d>(c), *g2 = t[1].ptr<cv::Vec2d>(c);
    for (int r = 0; r <= need; ++r) {
      const int rm = r == 0 ? 0 : n - r;  // -y
      // |E|^2 + |O|^2 = (|G(y)|^2 + |G(-y)|^2) / 2; the even part's real part is
      // Re(G(y) + G(-y)) / 2. TE: direct (0, a0) on the even Ey; TM: direct (a0, 0) on the even
      // Ex. |a0 + U|^2 - a0^2 = 2 a0 Re U + |U|^2.
      auto one = [&](const cv::Vec2d* gp) {
        const cv::Vec2d &a = gp[r], &b = gp[rm];
        return 0.5 * (a[0] * a[0] + a[1] * a[1] + b[0] * b[0] + b[1] * b[1]) + a0 * (a[0] + b[0]);
      };
      dev[size_t(c) * n + r] = 0.5 * (one(g1) + one(g2));
    }
  }
  AzimuthalHarmonics(dev, n, h, drho, n_rho, harmonics, 2 * kna, d);
}

namespace {
/// The window for a sphere of `radius_um` whose centre lies `dz` before the focal plane.
WaveWindow WindowFor(const Scene& s, double radius_um, double dz) {
  return WaveWindowFor(s, s.trace.mie.margin_um, radius_um, dz);
}
}  // namespace

double AutomaticMieWindowUm(const Scene& scene, double defocus_um) {
  if (scene.objects.empty()) throw std::invalid_argument("AutomaticMieWindowUm: no sphere");
  const ObjectSpec& o = *SpheresOf(scene).shell;
  const WaveWindow w = WindowFor(scene, o.radius_um, defocus_um - o.center_um.z);
  return 2 * (w.rho_light + w.margin);
}

MieImager::Impl::Grid MieImager::Impl::GridAt(double dz) const {
  const WaveWindow win = WindowFor(scene, radius, dz);
  const double margin = win.margin;
  Grid g;
  g.h = lambda_medium / (4 * s_na) / set.oversample;
  g.n = cv::getOptimalDFTSize(int(std::ceil(2 * (win.rho_light + margin) / g.h)));
  double rho_max = win.rho_light + margin / 2;
  if (set.window_um > 0) {  // a fixed window: the same grid for every radius and defocus
    g.n = cv::getOptimalDFTSize(int(std::ceil(set.window_um / g.h)));
    g.h = set.window_um / g.n;
    rho_max = set.window_um / 2 - margin / 2;
  }
  g.drho = g.h / 2;
  g.n_rho = int(std::ceil(rho_max / g.drho)) + 3;
  return g;
}

void MieImager::Impl::SumNodes(const std::vector<std::pair<const Impl*, double>>& parts, double dz,
                               double drho, int n_rho, int harmonics, tbb::task_arena& arena,
                               Pattern* pat) {
  struct Task {
    const Impl* im;
    const Node* node;
    Grid grid;
    double factor;
  };
  std::vector<Task> tasks;
  for (const auto& [im, factor] : parts) {
    const Grid g = im->GridAt(dz);
    for (const Node& nd : im->nodes) tasks.push_back({im, &nd, g, factor});
  }
  const int mh = harmonics;
  pat->cm.assign(mh + 1, std::vector<double>(n_rho, 0.0));
  pat->sm = pat->cm;
  // In blocks of a fixed size (the memory of the per-node harmonics stays bounded for a
  // spectrum of many wavelengths), each summed in task order.
  constexpr size_t kBlock = 128;
  std::vector<std::vector<std::vector<double>>> per(std::min(kBlock, tasks.size()));
  for (size_t b0 = 0; b0 < tasks.size(); b0 += kBlock) {
    const size_t nb = std::min(kBlock, tasks.size() - b0);
    arena.execute([&] {
      tbb::parallel_for(size_t(0), nb, [&](size_t j) {
        const Task& t = tasks[b0 + j];
        t.im->NodeHarmonics(*t.node, dz, t.grid.n, t.grid.h, drho, n_rho, &per[j]);
      });
    });
    for (size_t j = 0; j < nb; ++j) {
      const Task& t = tasks[b0 + j];
      // Unit flux through the z-plane: amplitude^2 = 1 / cos.
      const double w = t.factor * t.node->omega / t.node->cos;
      for (int m = 0; m <= mh; ++m)
        for (int q = 0; q < n_rho; ++q) {
          pat->cm[m][q] += w * t.node->wc[m] * per[j][m][q];
          if (m > 0) pat->sm[m][q] += w * t.node->ws[m] * per[j][m][q];
        }
    }
  }
}

const MieImager::Impl::Pattern& MieImager::Impl::PatternAt(double dz,
                                                           tbb::task_arena& arena) const {
  if (auto it = patterns.find(dz); it != patterns.end()) return it->second;
  Pattern pat;  // stored once complete, so a failed computation leaves no entry behind
  if (wavelengths.empty()) {
    const Grid g = GridAt(dz);
    SumNodes({{this, 1.0}}, dz, g.drho, g.n_rho, harmonics, arena, &pat);
    pat.n = g.n, pat.h = g.h, pat.drho = g.drho, pat.n_rho = g.n_rho;
  } else {
    // A spectrum: each wavelength's harmonics in photons (its share x its photon scale) on one
    // radial grid, the finest of the wavelengths' reaching as far as the farthest.
    std::vector<std::pair<const Impl*, double>> parts;
    double drho = 0, reach = 0;
    for (const auto& [share, one] : wavelengths) {
      const Impl& c = *one->impl_;
      parts.emplace_back(&c, share * c.scale);
      const Grid g = c.GridAt(dz);
      drho = drho > 0 ? std::min(drho, g.drho) : g.drho;
      reach = std::max(reach, (g.n_rho - 3) * g.drho);
    }
    const int n_rho = int(std::ceil(reach / drho)) + 3;
    SumNodes(parts, dz, drho, n_rho, harmonics, arena, &pat);
    const Grid g0 = parts[0].first->GridAt(dz);  // the first wavelength's, for the record
    pat.n = g0.n, pat.h = g0.h, pat.drho = drho, pat.n_rho = n_rho;
  }
  if (patterns.size() >= 64) patterns.clear();  // bounded memory
  return patterns.emplace(dz, std::move(pat)).first->second;
}

void MieImager::MoveAcross(double x_um, double y_um) {
  Impl& im = *impl_;
  im.center.x = x_um, im.center.y = y_um;
  for (ObjectSpec& o : im.scene.objects) o.center_um.x = x_um, o.center_um.y = y_um;
  for (auto& [w, one] : im.wavelengths) one->MoveAcross(x_um, y_um);
}

Image MieImager::Expected(double defocus_um, int threads) const {
  const Impl& im = *impl_;
  if (!im.wavelengths.empty()) im.last = im.SpectrumSampling();
  const Scene& s = im.scene;
  const MieSettings& set = im.set;
  // Motion: the pulse's equal-power quantiles (midpoints) as times, the sphere where it is at
  // each; positions that share an axial offset share the harmonics (a lateral move only
  // shifts the image), so lateral motion costs renders, not fields.
  struct Group {
    double z;
    std::vector<std::pair<double, double>> xy;
  };
  std::vector<Group> groups;
  const Vec3 vel = s.objects[0].velocity_um_per_us;
  const int times = s.has_motion() ? set.motion_nodes : 1;
  for (int k = 0; k < times; ++k) {
    const double t = s.has_motion() ? s.exposure.Offset((k + 0.5) / times) : 0.0;
    const Vec3 c = im.center + vel * t;
    if (groups.empty() || groups.back().z != c.z) groups.push_back({c.z, {}});
    groups.back().xy.emplace_back(c.x, c.y);
  }
  // Render: pixels integrated on K x K sub-samples; the PSF convolves the fine image.
  const CameraSpec& cam = s.camera;
  const double pix_obj = cam.pixel_pitch_um / std::abs(im.magnification);
  const int kss = PixelSubsamples(set.pixel_subsamples, pix_obj, im.lambda_medium, im.s_na);
  const double fine = pix_obj / kss;
  const double psf = cam.psf_sigma_um;
  const int pad = psf > 0 ? int(std::ceil(4 * psf / fine)) : 0;
  const int fw = cam.nx * kss + 2 * pad, fh = cam.ny * kss + 2 * pad;
  cv::Mat dev(fh, fw, CV_64F, cv::Scalar(0));
  tbb::task_arena arena(threads > 0 ? threads : tbb::task_arena::automatic);
  int n = 0;
  double h = 0;
  for (const Group& g : groups) {
    const double dz = defocus_um - g.z;
    const Impl::Pattern& pat = im.PatternAt(dz, arena);
    n = pat.n, h = pat.h;
    const double drho = pat.drho;
    const int n_rho = pat.n_rho;
    const int mh = im.harmonics;
    const std::vector<std::vector<double>>&cm = pat.cm, &sm = pat.sm;
    auto deviation = [&](double dx, double dy) {
      const double rho = std::hypot(dx, dy);
      const double gr = rho / drho;
      if (gr >= n_rho - 3) return 0.0;
      const int q = int(gr);
      double w[4];
      KeysWeights(gr - q, w);
      auto at = [&](const std::vector<double>& f) {
        // f is even in rho about 0 (a smooth function of x, y): f(-drho) = f(drho).
        return w[0] * f[std::abs(q - 1)] + w[1] * f[q] + w[2] * f[q + 1] + w[3] * f[q + 2];
      };
      double v = at(cm[0]);
      if (mh > 0) {
        const double psi = std::atan2(dy, dx);
        for (int m = 1; m <= mh; ++m)
          v += at(cm[m]) * std::cos(m * psi) + at(sm[m]) * std::sin(m * psi);
      }
      return v;
    };
    const double share = 1.0 / times;
    arena.execute([&] {
      tbb::parallel_for(0, fh, [&](int r) {
        double* row = dev.ptr<double>(r);
        for (int c = 0; c < fw; ++c) {
          const auto [x, y] = im.ObjectPoint((c - pad + 0.5) / kss, (r - pad + 0.5) / kss);
          for (const auto& [cx, cy] : g.xy) row[c] += share * deviation(x - cx, y - cy);
        }
      });
    });
  }
  if (psf > 0)
    cv::GaussianBlur(dev, dev, cv::Size(0, 0), psf / fine, psf / fine, cv::BORDER_REPLICATE);
  Image out(cam.nx, cam.ny);
  for (int r = 0; r < cam.ny; ++r)
    for (int c = 0; c < cam.nx; ++c) {
      double sum = 0;
      for (int b = 0; b < kss; ++b) {
        const double* row = dev.ptr<double>(pad + r * kss + b);
        for (int a = 0; a < kss; ++a) sum += row[pad + c * kss + a];
      }
      const auto [x, y] = im.ObjectPoint(c + 0.5, r + 0.5);
      const double env = im.SpatialAt(x, y);
      const double val = im.scale * env * (im.flat + sum / (kss * kss));
      out.at(c, r) = float(std::isfinite(val) ? std::max(0.0, val) : 0.0);
    }
  im.last.grid = n;
  im.last.grid_um = h;
  im.last.window_um = n * h;
  im.last.pixel_subsamples = kss;
  return out;
}

namespace {
/// Poisson variate from uniforms: inversion below mean 10, Hormann's PTRS above (W. Hormann,
/// "The transformed rejection method for generating Poisson random variables", Insurance:
/// Mathematics and Economics 12, 39 (1993)).
double PoissonDraw(double mu, RayRng& rng) {
  if (!(mu > 0)) return 0;
  if (mu < 10) {
    double p = std::exp(-mu), sum = p;
    const double u = rng.Uniform();
    int k = 0;
    while (u > sum && k < 1000) {
      ++k;
      p *= mu / k;
      sum += p;
    }
    return k;
  }
  const double smu = std::sqrt(mu), b = 0.931 + 2.53 * smu, a = -0.059 + 0.02483 * b;
  const double inv_alpha = 1.1239 + 1.1328 / (b - 3.4), vr = 0.9277 - 3.6224 / (b - 2);
  const double log_mu = std::log(mu);
  for (;;) {
    const double u = rng.Uniform() - 0.5, v = rng.Uniform();
    const double us = 0.5 - std::abs(u);
    const double k = std::floor((2 * a / us + b) * u + mu + 0.43);
    if (us >= 0.07 && v <= vr) return k;
    if (k < 0 || (us < 0.013 && v > us)) continue;
    if (std::log(v) + std::log(inv_alpha) - std::log(a / (us * us) + b) <=
        -mu + k * log_mu - std::lgamma(k + 1))
      return k;
  }
}
}  // namespace

Image PoissonSample(const Image& expected, uint64_t seed, uint32_t plane) {
  Image out(expected.width, expected.height);
  tbb::parallel_for(size_t(0), expected.size(), [&](size_t i) {
    RayRng rng(seed, plane, i);
    out.pixels[i] = float(PoissonDraw(expected.pixels[i], rng));
  });
  return out;
}

}  // namespace raymatch::simulate
