#pragma once
// The light sources of the tracer (simulate/src/tracer.cpp dispatches over SourceVariant): each
// yields a point where the ray crosses z = 0 (absent objects) and a unit direction with d.z > 0;
// the tracer then starts it on the source plane before all objects.
#include <array>
#include <cmath>
#include <memory>
#include <variant>

#include "packet.h"
#include "raymatch/core/rng.h"
#include "raymatch/core/vec.h"
#include "raymatch/simulate/sampling.h"
#include "raymatch/simulate/scene.h"
#include "stages-inl.h"  // the static target: the stages' one-lane instantiation

namespace raymatch::simulate {

namespace st = stages::HWY_NAMESPACE;
using L1 = stages::ScalarLanes;  // one ray: the stages' scalar instantiation

/// SampleUnitDisc through the shared stage: tries from the ray's stream until one lies inside.
inline void UnitDisc(RayRng& rng, double* a, double* b) {
  for (;;) {
    // Two statements: the words are drawn in this order (argument order is unspecified).
    const double ca = double(rng.NextU32()) - 0x1p31;  // the centred word, exact
    const double cb = double(rng.NextU32()) - 0x1p31;
    if (st::DiscTry<L1>(ca, cb, *a, *b)) return;
  }
}

struct Field {
  FieldShape shape;
  double radius, half_w, half_h;
  Vec3 center;
  Distribution2D map;  // optional spatial map over the rectangle
  Vec3 Sample(RayRng& rng) const {
    if (shape == FieldShape::kDisc) {
      double a, b;
      UnitDisc(rng, &a, &b);
      const double c[3] = {center.x, center.y, center.z};
      const st::V3<L1> p = st::DiscFieldPoint<L1>(c, radius, a, b);
      return Vec3(p.x, p.y, p.z);
    }
    const double u0 = rng.Uniform(), u1 = rng.Uniform();
    if (!map.empty()) {
      double x, y;
      map.Sample(u0, u1, &x, &y);
      return center + Vec3((2 * x - 1) * half_w, (1 - 2 * y) * half_h, 0);  // row 0 = +y
    }
    return center + Vec3((2 * u0 - 1) * half_w, (2 * u1 - 1) * half_h, 0);
  }
};

struct CollimatedSource {
  Field field;
  Vec3 dir;
  bool Sample(RayRng& rng, Vec3* p, Vec3* d) const {
    *p = field.Sample(rng);
    *d = dir;
    return true;
  }
};

/// Uniform radiance inside a cone: uniform density in direction cosines (u, v) over a disc of
/// radius sin(theta_max) (radiance is ray density per dx dy du dv).
struct ConeSource {
  Field field;
  double sin_max;
  bool Sample(RayRng& rng, Vec3* p, Vec3* d) const {
    *p = field.Sample(rng);
    double a, b;
    UnitDisc(rng, &a, &b);
    const st::V3<L1> dir = st::ConeDirection<L1>(a, b, sin_max);  // u^2 + v^2 < sin_max^2 < 1
    *d = Vec3(dir.x, dir.y, dir.z);
    return true;
  }
};

/// Isotropic point emitter (uniform per solid angle) into a cone about +z.
struct PointSource {
  Vec3 position;
  double cos_max;
  bool Sample(RayRng& rng, Vec3* p, Vec3* d) const {
    const double cz = 1 - rng.Uniform() * (1 - cos_max);
    const double sz = std::sqrt(std::max(0.0, 1 - cz * cz));
    const double phi = 2 * M_PI * rng.Uniform();
    *p = position;
    *d = Vec3(sz * std::cos(phi), sz * std::sin(phi), cz);
    return true;
  }
};

/// Tabulated angular radiance over direction cosines (the calibration's light field).
struct LightFieldSource {
  Field field;
  /// The angular table, shared by the Simulators that trace the same light field and edge
  /// (MakeSource).
  std::shared_ptr<const Distribution2D> angular;
  double extent;
  /// The map's radiance integrated over direction cosines (sum x cell area): the populations
  /// of one continued light field (SourceSpec::edge_part) get rays in proportion to it.
  double weight = 0;
  bool Sample(RayRng& rng, Vec3* p, Vec3* d) const {
    *p = field.Sample(rng);
    // Two statements: the order in which a call's arguments are evaluated is unspecified, and
    // the words must be drawn in the same order by every compiler (and by the packet path).
    const double u0 = rng.Uniform();
    const double u1 = rng.Uniform();
    return Direction(u0, u1, d);
  }
  /// The direction for the uniforms (u0, u1); false for a map cell beyond the unit circle.
  bool Direction(double u0, double u1, Vec3* d) const {
    double x, y;
    angular->Sample(u0, u1, &x, &y);
    st::V3<L1> dir;
    if (st::TabulatedDirection<L1>(x, y, extent, dir)) return false;  // no physical direction
    *d = Vec3(dir.x, dir.y, dir.z);
    return true;
  }
};

/// Weighted ray list at the object plane (e.g. imported from a Zemax source file): ray i with
/// probability proportional to its weight.
struct RayListSource {
  const std::array<double, 5>* rays;  // the Simulator's own scene's list (not copied)
  Distribution1D weights;
  bool Sample(RayRng& rng, Vec3* p, Vec3* d) const {
    int i = 0;
    weights.Sample(rng.Uniform(), &i);
    const auto& r = rays[i];
    *p = Vec3(r[0], r[1], 0);
    *d = Vec3(r[2], r[3], std::sqrt(1 - r[2] * r[2] - r[3] * r[3]));  // u^2 + v^2 < 1 (reader)
    return true;
  }
};

using SourceVariant =
    std::variant<CollimatedSource, ConeSource, PointSource, LightFieldSource, RayListSource>;

/// The source field for a scene (auto_radius: the automatic disc radius, also how far a
/// measured spatial map is continued).
Field MakeField(const Scene& s, double auto_radius);
/// A calibrated light field cut at its NA, continued beyond it under the soft edge
/// (SourceSpec::edge_*; only the part SourceSpec::edge_part names), on a grid 4x finer than the
/// map's: the angular map the source samples; `*extent` receives its half-width (direction
/// cosines).
Image ContinuedMap(const SourceSpec& ss, double* extent);

/// The scene's source; `angular_table` receives a light field's table for the packet path.
/// `own` must outlive the source (a ray list is not copied).
SourceVariant MakeSource(const Scene& own, double auto_radius,
                         std::shared_ptr<const packet::Table2D>* angular_table);

}  // namespace raymatch::simulate
