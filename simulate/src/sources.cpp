#include "sources.h"

#include <algorithm>

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

/// The light field's angular table, flattened for packet::Tabulated.
packet::Table2D PacketTable(const LightFieldSource& lf) {
  packet::Table2D t;
  const Distribution2D& d = lf.angular;
  t.height = d.height();
  t.width = t.height > 0 ? d.row(0).size() : 0;
  t.extent = lf.extent;
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

SourceVariant MakeSource(const Scene& own, double auto_radius, packet::Table2D* angular_table) {
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
      LightFieldSource lf{MakeField(own, auto_radius), Distribution2D(ss.angular_map),
                          ss.angular_extent};
      *angular_table = PacketTable(lf);
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
