#include "sources.h"

#include <algorithm>
#include <list>
#include <mutex>

#include "raymatch/core/error.h"

namespace raymatch::simulate {

constexpr double kDeg = M_PI / 180.0;

Field MakeField(const Scene& s, double auto_radius) {
  Field f;
  f.shape = s.source.field_shape;
  f.radius = s.source.field_radius_um > 0 ? s.source.field_radius_um : auto_radius;
  f.half_w = s.source.field_size_um[0] / 2;
  f.half_h = s.source.field_size_um[1] / 2;
  f.center = s.source.field_center_um;
  if (!s.source.spatial_map.empty()) {
    const Image& m0 = s.source.spatial_map;
    if (!s.source.extend_spatial_map) {
      f.map = Distribution2D(m0);
      return f;
    }
    // A measured map covers about the camera's view; rays reach the view from outside it when
    // defocused or deflected by objects, so its edge values continue out to the automatic
    // field extent (the same cell size, edge cells replicated).
    const double cw = 2 * f.half_w / m0.width, ch = 2 * f.half_h / m0.height;
    const int px = std::max(0, int(std::ceil((auto_radius - f.half_w) / cw)));
    const int py = std::max(0, int(std::ceil((auto_radius - f.half_h) / ch)));
    Image m(m0.width + 2 * px, m0.height + 2 * py);
    for (int y = 0; y < m.height; ++y)
      for (int x = 0; x < m.width; ++x)
        m.at(x, y) =
            m0.at(std::clamp(x - px, 0, m0.width - 1), std::clamp(y - py, 0, m0.height - 1));
    f.half_w += px * cw, f.half_h += py * ch;
    f.map = Distribution2D(m);
  }
  return f;
}

/// The calibrated map continued beyond its NA cut (SourceSpec::edge_half_angle_deg): on a grid
/// 4x finer than the map's and aligned with it, padded out to 15 deg beyond the cut. Inside
/// the reference ring (kEdgeRingPixels map pixels inside the cut) a fine cell takes its map
/// pixel's value (the same distribution as the map); from that ring outwards, across the cut and
/// beyond it, the map's value on the ring at the same azimuth times E / E(ring), E the soft edge
/// about the (tilted) edge axis, averaged over 2x2 points per cell so the image moves smoothly
/// with the edge's parameters. The band between the ring and the cut is modelled, not measured:
/// the cone images resolve angles only to about a pixel over their defocus (0.5 um / 20 um =
/// 1.4 deg on the sample), so the measured map falls off over the last 2 deg before the sharp
/// cut (7 % low at 23-24 deg on the sample, and the drop's index fitted 11 sigma low with the
/// true edge). SourceSpec::edge_part keeps only the measured part (inside the ring) or the
/// modelled one (the two add up to the whole, point by point).
Image ContinuedMap(const SourceSpec& ss, double* extent) {
  const Image& m = ss.angular_map;
  const double ext = ss.angular_extent, s_na = ss.map_na_limit;
  if (m.width != m.height) throw Error("a light field continued beyond the NA needs a square map");
  const int n = m.width, f = 4;
  const double pu = 2 * ext / n, cell = pu / f;  // map pixel, fine cell (direction cosines)
  const double target = std::sin(std::min(85.0, std::asin(s_na) / kDeg + 15) * kDeg);
  const int pad = std::max(0, int(std::ceil((std::min(0.99, target) - ext) / cell)));
  const int nf = f * n + 2 * pad;
  *extent = ext + pad * cell;
  const double edge = ss.edge_half_angle_deg, width = ss.edge_width_deg;
  const double tu = std::sin(ss.edge_tilt_deg[0] * kDeg), tv = std::sin(ss.edge_tilt_deg[1] * kDeg);
  auto E = [&](double u, double v) {  // the soft edge about the axis (tu, tv)
    const double s = std::hypot(u - tu, v - tv);
    if (s >= 1) return 0.0;
    return LightFieldSoftEdge(std::asin(s) / kDeg, edge, width);
  };
  const bool keep_in = ss.edge_part != SourceSpec::EdgePart::kBeyond;
  const bool keep_out = ss.edge_part != SourceSpec::EdgePart::kInside;
  const double inner = s_na - kEdgeRingPixels * pu;  // the reference ring (measured)
  auto map_at = [&](double u, double v) {            // nearest map pixel, 0 outside the map
    const int x = int(std::floor((u + ext) / pu)), y = int(std::floor((ext - v) / pu));
    return (x < 0 || y < 0 || x >= n || y >= n) ? 0.0 : double(m.at(x, y));
  };
  Image out(nf, nf);
  for (int y = 0; y < nf; ++y)
    for (int x = 0; x < nf; ++x) {
      const int mx = x - pad, my = y - pad;  // fine cell -> map pixel (mx / f, my / f)
      const double uc = -*extent + (x + 0.5) * cell, vc = *extent - (y + 0.5) * cell;
      const double sc = std::hypot(uc, vc);
      const bool in_map = mx >= 0 && my >= 0 && mx < f * n && my < f * n;
      const double mv = in_map ? double(m.at(mx / f, my / f)) : 0.0;
      if (sc + 0.75 * cell < inner) {
        out.at(x, y) = keep_in ? float(mv) : 0.0f;  // wholly inside the ring: the measurement
        continue;
      }
      double sum = 0;
      for (int a = 0; a < 2; ++a)
        for (int b = 0; b < 2; ++b) {
          const double u = uc + (a - 0.5) * 0.5 * cell, v = vc + (b - 0.5) * 0.5 * cell;
          const double s = std::hypot(u, v);
          if (s < inner) {
            if (keep_in) sum += mv;
          } else if (keep_out) {
            // The ring's value holds the edge's fall-off at the ring: A(phi) E(ring), so the
            // continuation is ring x E / E(ring), not / E(cut) (which made it brighter by
            // E(ring) / E(cut): 20 % on the sample, and its single-plane index 9 sigma high).
            const double c = std::cos(std::atan2(v, u)), sn = std::sin(std::atan2(v, u));
            const double ring = map_at(inner * c, inner * sn);
            sum += ring * E(u, v) / std::max(E(inner * c, inner * sn), 1e-300);
          }
        }
      out.at(x, y) = float(sum / 4);
    }
  return out;
}

/// The light field's angular table, flattened for packet::Tabulated.
packet::Table2D PacketTable(const Distribution2D& d, double extent) {
  packet::Table2D t;
  t.height = d.height();
  t.width = t.height > 0 ? d.row(0).size() : 0;
  t.extent = extent;
  t.marginal_cdf = d.marginal().cdf();
  t.marginal_guide.assign(d.marginal().guide().begin(), d.marginal().guide().end());
  t.marginal_guide_size = static_cast<int64_t>(t.marginal_guide.size());
  t.row_guide_size = t.height > 0 ? static_cast<int64_t>(d.row(0).guide().size()) : 0;
  for (int y = 0; y < t.height; ++y) {
    t.row_cdf.insert(t.row_cdf.end(), d.row(y).cdf().begin(), d.row(y).cdf().end());
    t.row_guide.insert(t.row_guide.end(), d.row(y).guide().begin(), d.row(y).guide().end());
  }
  return t;
}

namespace {

/// A light field's angular tables: what a source needs from its map and edge alone.
struct AngularTables {
  std::shared_ptr<const Distribution2D> angular;
  std::shared_ptr<const packet::Table2D> table;
  double extent = 0, weight = 0;
};

AngularTables BuildTables(const SourceSpec& ss) {
  AngularTables t;
  t.extent = ss.angular_extent;
  const bool edge = ss.edge_half_angle_deg > 0 && ss.map_na_limit > 0;
  const Image map = edge ? ContinuedMap(ss, &t.extent) : ss.angular_map;
  auto d = std::make_shared<Distribution2D>(map);
  t.table = std::make_shared<packet::Table2D>(PacketTable(*d, t.extent));
  t.angular = std::move(d);
  double sum = 0;
  for (float v : map.pixels) sum += v;
  t.weight = map.width > 0 ? sum * std::pow(2 * t.extent / map.width, 2) : 0;
  return t;
}

/// Everything BuildTables reads, compared exactly.
struct TablesKey {
  std::vector<float> map;
  int width = 0, height = 0;
  double extent = 0, na_limit = 0, edge = 0, width_deg = 0;
  std::array<double, 2> tilt{0, 0};
  SourceSpec::EdgePart part = SourceSpec::EdgePart::kAll;
  explicit TablesKey(const SourceSpec& ss)
      : map(ss.angular_map.pixels),
        width(ss.angular_map.width),
        height(ss.angular_map.height),
        extent(ss.angular_extent),
        na_limit(ss.map_na_limit),
        edge(ss.edge_half_angle_deg),
        width_deg(ss.edge_width_deg),
        tilt(ss.edge_tilt_deg),
        part(ss.edge_part) {
    if (part == SourceSpec::EdgePart::kInside) {  // the measured part: the edge's shape unused
      edge = edge > 0 ? 1 : 0;
      width_deg = 0, tilt = {0, 0};
    }
  }
  bool operator==(const TablesKey&) const = default;
};

/// The tables of the last few light fields built in this process. A fit builds its Simulators
/// per evaluation, most of them with the same map and edge (every parameter but the edge's; the
/// measured part inside the ring never changes), and a continued map costs about as much as
/// tracing a small image; the tables are immutable, so the Simulators share them.
std::shared_ptr<const AngularTables> TablesFor(const SourceSpec& ss) {
  static std::mutex mutex;
  static std::list<std::pair<TablesKey, std::shared_ptr<const AngularTables>>> recent;
  constexpr size_t kKept = 8;  // a fit's inside part and its beyond part at a few edges
  TablesKey key(ss);
  {
    const std::lock_guard<std::mutex> lock(mutex);
    for (auto it = recent.begin(); it != recent.end(); ++it)
      if (it->first == key) {
        recent.splice(recent.begin(), recent, it);
        return recent.front().second;
      }
  }
  auto t = std::make_shared<const AngularTables>(BuildTables(ss));
  const std::lock_guard<std::mutex> lock(mutex);
  recent.emplace_front(std::move(key), t);
  if (recent.size() > kKept) recent.pop_back();
  return t;
}

}  // namespace

SourceVariant MakeSource(const Scene& own, double auto_radius,
                         std::shared_ptr<const packet::Table2D>* angular_table) {
  const SourceSpec& ss = own.source;
  switch (ss.type) {
    case SourceType::kCollimated: {
      const double t = ss.tilt_deg * kDeg, a = ss.azimuth_deg * kDeg;
      return CollimatedSource{
          MakeField(own, auto_radius),
          Vec3(std::sin(t) * std::cos(a), std::sin(t) * std::sin(a), std::cos(t))};
    }
    case SourceType::kCone:
      return ConeSource{MakeField(own, auto_radius), std::sin(ss.half_angle_deg * kDeg)};
    case SourceType::kPoint:
      return PointSource{ss.position_um, std::cos(ss.half_angle_deg * kDeg)};
    case SourceType::kLightField: {
      const std::shared_ptr<const AngularTables> t = TablesFor(ss);
      LightFieldSource lf{MakeField(own, auto_radius), t->angular, t->extent};
      lf.weight = t->weight;
      *angular_table = t->table;
      return lf;
    }
    case SourceType::kRayList: {
      std::vector<float> w;
      for (const auto& r : ss.rays) w.push_back(float(r[4]));
      return RayListSource{own.source.rays.data(), Distribution1D(w.data(), int(w.size()))};
    }
  }
  throw Error(FileLocation{own.file}, "unknown source type");
}

}  // namespace raymatch::simulate
