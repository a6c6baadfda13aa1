// The optics after the objects (stages.h: Optics) from a scene's description.
#include <algorithm>
#include <cmath>
#include <functional>

#include "raymatch/simulate/scene.h"
#include "sources.h"
#include "stages.h"

namespace raymatch::simulate {

std::pair<double, double> SensorToObject(const CameraSpec& cam, double sensor_sign, double col,
                                         double row) {
  const double u = (col - cam.nx / 2.0) * cam.pixel_pitch_um;
  const double v = (cam.ny / 2.0 - row) * cam.pixel_pitch_um;
  return {(u + cam.offset_um[0]) / sensor_sign, (v + cam.offset_um[1]) / sensor_sign};
}

WaveWindow WaveWindowFor(const Scene& s, double margin_um, double radius_um, double dz) {
  const double s_na = AcceptanceSin(s), tan_na = s_na / std::sqrt(1 - s_na * s_na);
  const double margin =
      margin_um > 0 ? margin_um : 8 + 8 * s.wavelength_um / (s_na * s.medium_index);
  return {radius_um + (std::abs(dz) + radius_um) * tan_na, margin};
}

double FlatFieldPhotons(const Scene& s) {
  if (s.trace.photons_per_pixel > 0) return s.trace.photons_per_pixel;
  Scene flat = s;
  flat.objects.clear();
  flat.trace.optics = ImageOptics::kRays;
  double per_ray = 0;
  Simulator(flat).RaysForPhotonTarget(1.0, &per_ray);
  return per_ray * double(s.trace.rays);
}

int PixelSubsamples(int setting, double pixel_object_um, double lambda_medium, double s_na) {
  return setting > 0 ? setting
                     : std::max(1, int(std::ceil(pixel_object_um / (lambda_medium / (8 * s_na)))));
}

Optics MakeOptics(const Scene& s) {
  Optics o;
  const OpticsSpec& sp = s.optics;
  const double f = sp.objective_focal_mm * 1e3;
  // NA = n sin(theta) in the medium the objective looks into (docs/conventions.md).
  const double tan_na = std::tan(std::asin(AcceptanceSin(s)));
  double z;
  if (sp.model == ObjectiveModel::kSingle) {
    o.lenses[0] = {f, f, 0, 1 / f};
    o.num_lenses = 1;
    o.stop_z = 2 * f;
    z = f;
  } else {
    // Two thin lenses from f, WD and BFD: d = f - BFD WD / f, f1 = d / (1 - BFD/f),
    // f2 = d / (1 - WD/f) (so that the pair has focal length f and these two distances).
    const double wd = sp.working_distance_mm * 1e3, bfd = sp.back_focal_mm * 1e3;
    const double d = f - bfd * wd / f;
    const double f1 = d / (1 - bfd / f), f2 = d / (1 - wd / f);
    o.lenses[0] = {wd, f1, 0, 1 / f1};
    o.lenses[1] = {wd + d, f2, 0, 1 / f2};
    o.num_lenses = 2;
    o.stop_z = wd + d + bfd;
    z = wd;
  }
  o.stop_after = o.num_lenses;
  // The stop at the back focal plane is a pure angle filter: height there = f tan(theta).
  // Radius f tan(asin(NA / n)) passes exactly the rays a real (sine-condition) objective of this NA
  // accepts from an on-axis point.
  const double stop_r = f * tan_na;
  o.stop_r2 = stop_r * stop_r;
  const double tube_z = o.stop_z + sp.tube_distance_mm * 1e3;
  o.lenses[o.num_lenses++] = {tube_z, sp.tube_focal_mm * 1e3, 0, 1 / (sp.tube_focal_mm * 1e3)};
  o.sensor_z = tube_z + sp.tube_focal_mm * 1e3 + s.camera.sensor_shift_mm * 1e3;
  o.corrector = sp.corrector.enabled;
  if (sp.corrector.enabled) {
    const double cz = sp.corrector.distance_mm > 0 ? sp.corrector.distance_mm * 1e3 : z;
    o.corrector_z = cz;
    const size_t n = sp.corrector.transmissions.size();
    for (size_t i = 0; i < n; ++i) {
      // Default: equal-width zones out to 2 % beyond the NA edge at the corrector plane.
      const double r = sp.corrector.ring_outer_mm.empty() ? cz * tan_na * 1.02 * double(i + 1) / n
                                                          : sp.corrector.ring_outer_mm[i] * 1e3;
      o.ring_outer2.push_back(r * r);
      o.ring_t.push_back(sp.corrector.transmissions[i]);
    }
  }
  o.pitch = s.camera.pixel_pitch_um;
  o.inv_pitch = 1 / o.pitch;  // products, not divisions, in the inner loop
  o.off_x = s.camera.offset_um[0];
  o.off_y = s.camera.offset_um[1];
  o.sign = s.camera.flip ? -1.0 : 1.0;
  o.psf_sigma_sensor = s.camera.psf_sigma_um * std::abs(Magnification(sp));
  o.nx = s.camera.nx;
  o.ny = s.camera.ny;
  return o;
}

CorrectorZones CorrectorZonesOf(const Scene& scene) {
  const Optics optics = MakeOptics(scene);
  CorrectorZones z;
  if (optics.corrector)
    for (size_t i = 0; i < optics.ring_outer2.size(); ++i) {
      z.s.push_back(std::sin(std::atan(std::sqrt(optics.ring_outer2[i]) / optics.corrector_z)));
      z.t.push_back(optics.ring_t[i]);
    }
  return z;
}

AngularDensity LightFieldDensity(const SourceSpec& ss) {
  AngularDensity d;
  d.extent = ss.angular_extent;
  const bool edge = ss.edge_half_angle_deg > 0 && ss.map_na_limit > 0;
  d.map = std::make_shared<Image>(edge ? ContinuedMap(ss, &d.extent) : ss.angular_map);
  d.pu = 2 * d.extent / d.map->width;
  if (ss.map_na_limit > 0) {
    d.breaks.push_back(ss.map_na_limit);
    d.breaks.push_back(ss.map_na_limit -
                       kEdgeRingPixels * 2 * ss.angular_extent / ss.angular_map.width);
  }
  d.s_max = std::min(0.999, d.extent * std::sqrt(2.0));
  const Image& m = *d.map;
  for (int y = 0; y < m.height; ++y)
    for (int x = 0; x < m.width; ++x)
      if (m.at(x, y) > 0) {
        // The cell's corner farthest from the axis.
        const double u0 = -d.extent + x * d.pu, v0 = d.extent - y * d.pu;
        const double u = std::max(std::abs(u0), std::abs(u0 + d.pu));
        const double v = std::max(std::abs(v0), std::abs(v0 - d.pu));
        d.reach = std::max(d.reach, std::hypot(u, v));
      }
  d.reach = std::min(d.reach, d.s_max);
  return d;
}

double SpatialEnvelope::MeanOverSensor(const CameraSpec& cam, double sensor_sign) const {
  double sum = 0;
  for (int r = 0; r < cam.ny; ++r)
    for (int c = 0; c < cam.nx; ++c) {
      const auto [x, y] = SensorToObject(cam, sensor_sign, c + 0.5, r + 0.5);
      sum += At(x, y);
    }
  return sum / (double(cam.nx) * cam.ny);
}

double TailStart(std::vector<std::pair<double, double>> rings) {
  double total = 0;
  for (const auto& ring : rings) total += ring.second;
  std::sort(rings.begin(), rings.end(), std::greater<>());  // outermost first
  double tail = 0, s_cut = 2;
  for (const auto& [s, power] : rings) {
    if (tail + power > kTailPower * total) break;
    tail += power;
    s_cut = s;
  }
  return s_cut;
}

SpatialEnvelope SpatialEnvelopeOf(const Scene& scene) {
  SpatialEnvelope e;
  const SourceSpec& ss = scene.source;
  if (ss.type == SourceType::kLightField && !ss.spatial_map.empty()) {
    e.map = ss.spatial_map;
    e.w = ss.field_size_um[0], e.h = ss.field_size_um[1];
    e.x0 = ss.field_center_um.x, e.y0 = ss.field_center_um.y;
    e.clamp = ss.extend_spatial_map;
  }
  return e;
}

}  // namespace raymatch::simulate
