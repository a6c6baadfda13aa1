#pragma once
// Surfaces of the scene's objects and the nearest-hit query used by the tracer.
//
// Analytic shapes (sphere, ellipsoid, box) are intersected in closed form in double precision.
// Triangle meshes go through an Embree 3 BVH, which is built only when the scene has meshes.
// Normals returned are unit length and point out of the object.
#include <deque>
#include <memory>
#include <vector>

#include "raymatch/core/vec.h"
#include "raymatch/simulate/scene.h"

namespace raymatch::simulate {

struct Hit {
  double t = 0;  ///< distance along the (unit) direction
  Vec3 normal;   ///< outward unit normal
  int object = -1;
};

struct SphereShape {
  Vec3 center;
  double radius, radius2;
  int object;
};
/// Ellipsoid or box in its own frame: local = rot_t * (p - center).
struct FramedShape {
  Vec3 center;
  Mat3 rot, rot_t;
  Vec3 half;  ///< semi-axes (ellipsoid) or half-sizes (box)
  Vec3 inv_half;
  int object;
};

struct MeshInfo {
  size_t triangles = 0;
  double signed_volume_um3 = 0;
  bool flipped = false;  ///< winding was inward and has been reversed
  size_t degenerate_removed = 0;
};

/// Where each object is at a ray's emission time (motion during the exposure): object k is
/// displaced by shift[k] from its center_um; meshes move by Embree's linear motion blur, whose
/// time mesh_time in [0, 1] spans the pulse's offsets [-max, +max] (Geometry's max_offset_us).
struct ObjectShifts {
  const Vec3* shift = nullptr;  ///< per object, micrometres
  float mesh_time = 0.5f;
  Vec3 of(int object) const { return shift[object]; }
};

class Geometry {
 public:
  /// `max_offset_us`: the largest |t - centre| of the pulse (ExposureSpec::max_offset_us); a
  /// moving object (ObjectSpec::velocity_um_per_us) is bounded over its whole path, and a moving
  /// mesh gets two Embree time steps at -max and +max.
  explicit Geometry(const std::vector<ObjectSpec>& objects, double max_offset_us = 0);
  ~Geometry();
  Geometry(const Geometry&) = delete;
  Geometry& operator=(const Geometry&) = delete;

  /// Nearest hit with t > 0 along unit direction `d`; false when none.
  /// kMesh: include the Embree query (false when the scene has no meshes). `moved`: where the
  /// objects are at this ray's time (null: at their centres).
  template <bool kMesh>
  bool Intersect(const Vec3& o, const Vec3& d, Hit* hit, const ObjectShifts* moved = nullptr) const;

  bool has_meshes() const { return scene_ != nullptr; }
  bool empty() const {
    return spheres_.empty() && ellipsoids_.empty() && boxes_.empty() && !scene_;
  }
  /// Offset used to leave a surface of object i without re-hitting it (micrometres).
  double epsilon(int object) const { return eps_[object]; }
  const std::vector<MeshInfo>& meshes() const { return mesh_info_; }
  /// Largest distance of any object point from the origin (for automatic field sizes).
  double extent_um() const { return extent_um_; }
  /// A lower bound of the distance from `p` to every object surface: exact when all objects
  /// are spheres, 0 (no bound) otherwise. A path shorter than it cannot cross a surface.
  double SurfaceClearance(const Vec3& p, const ObjectShifts* moved = nullptr) const {
    if (!ellipsoids_.empty() || !boxes_.empty() || scene_) return 0;
    double d = 1e300;
    for (const auto& s : spheres_) {
      const Vec3 c = moved ? s.center + moved->of(s.object) : s.center;
      d = std::min(d, std::abs(Length(p - c) - s.radius));
    }
    return d;
  }
  double min_z_um() const { return min_z_um_; }
  /// A bounding sphere of object i (centre and radius, micrometres).
  const Vec3& bound_center(int object) const { return bound_center_[object]; }
  double bound_radius(int object) const { return bound_radius_[object]; }

 private:
  bool IntersectMesh(const Vec3& o, const Vec3& d, Hit* hit, float time) const;

  std::vector<SphereShape> spheres_;
  std::vector<FramedShape> ellipsoids_, boxes_;
  std::vector<double> eps_;
  std::vector<int> mesh_object_;              // geomID -> object
  std::vector<std::vector<float>> vertices_;  // per mesh, xyz
  std::vector<std::vector<unsigned>> indices_;
  std::deque<std::vector<float>> moving_vertices_;  // moving meshes: at -max and +max
  std::vector<MeshInfo> mesh_info_;
  void* device_ = nullptr;  // RTCDevice
  void* scene_ = nullptr;   // RTCScene
  double extent_um_ = 0, min_z_um_ = 0;
  std::vector<Vec3> bound_center_;
  std::vector<double> bound_radius_;
};

// ---- inline analytic intersections (hot path) ----

/// Smallest root t > tmin of |o + t d - c|^2 = r^2 for unit d, using the numerically stable
/// form of Hearn & Baker / Haines et al. (Ray Tracing Gems ch. 7): the discriminant is computed
/// from the perpendicular distance, so grazing rays far from the sphere keep full precision.
inline bool IntersectSphere(const Vec3& o, const Vec3& d, const Vec3& c, double r2, double* t) {
  const Vec3 f = o - c;
  const double b = -Dot(f, d);
  const Vec3 perp = f + d * b;  // f minus its projection on d
  const double disc = r2 - Dot(perp, perp);
  const double c0 = Dot(f, f) - r2;
  // Outside the sphere and moving away (t0 t1 = c0 > 0, t0 + t1 = 2 b < 0): both roots are
  // negative, as the lines below would find; a ray that has just left a sphere asks this.
  if (disc < 0 || (c0 > 0 && b < 0)) return false;
  const double q = b + std::copysign(std::sqrt(disc), b);
  double t0 = q != 0 ? c0 / q : 0, t1 = q;
  if (t0 > t1) std::swap(t0, t1);
  if (t0 > 0) {
    *t = t0;
    return true;
  }
  if (t1 > 0) {
    *t = t1;
    return true;
  }
  return false;
}

template <bool kMesh>
bool Geometry::Intersect(const Vec3& o, const Vec3& d, Hit* hit, const ObjectShifts* moved) const {
  bool found = false;
  double best = 1e300;
  // A moving object is met in its own frame: the ray's origin shifted by -its displacement
  // (a translation: t and the normal are the same in both frames).
  auto frame = [&](int object) { return moved ? o - moved->of(object) : o; };
  for (const SphereShape& s : spheres_) {
    double t;
    const Vec3 os = frame(s.object);
    if (IntersectSphere(os, d, s.center, s.radius2, &t) && t < best) {
      best = t;
      hit->object = s.object;
      // Normalise rather than divide by the radius: a hit point off the surface by rounding
      // would give |n| != 1, and reflections would then change |d| and compound the error.
      hit->normal = Normalize((os + d * t) - s.center);
      found = true;
    }
  }
  for (const FramedShape& e : ellipsoids_) {
    // Map to the unit sphere: p' = inv_half * rot_t (p - c). Distances scale, so solve with a
    // non-unit direction and convert t back.
    const Vec3 ol = Mul(e.rot_t * (frame(e.object) - e.center), e.inv_half);
    const Vec3 dl = Mul(e.rot_t * d, e.inv_half);
    const double len = Length(dl);
    double tl;
    if (IntersectSphere(ol, dl / len, Vec3{}, 1.0, &tl)) {
      const double t = tl / len;
      if (t < best) {
        best = t;
        hit->object = e.object;
        const Vec3 pl = ol + dl * t;
        hit->normal = Normalize(e.rot * Mul(pl, e.inv_half));  // gradient of |p'|^2
        found = true;
      }
    }
  }
  for (const FramedShape& b : boxes_) {
    const Vec3 ol = b.rot_t * (frame(b.object) - b.center);
    const Vec3 dl = b.rot_t * d;
    double tn = -1e300, tf = 1e300;
    int axis_n = 0, axis_f = 0;
    bool miss = false;
    for (int a = 0; a < 3 && !miss; ++a) {
      const double oa = ol[a], da = dl[a], h = b.half[a];
      if (da == 0) {
        miss = std::abs(oa) > h;
        continue;
      }
      double t1 = (-h - oa) / da, t2 = (h - oa) / da;
      if (t1 > t2) std::swap(t1, t2);
      if (t1 > tn) tn = t1, axis_n = a;
      if (t2 < tf) tf = t2, axis_f = a;
    }
    if (miss || tn > tf || tf <= 0) continue;
    const bool outside = tn > 0;
    const double t = outside ? tn : tf;
    if (t < best) {
      best = t;
      const int a = outside ? axis_n : axis_f;
      Vec3 nl{};
      const double pa = (ol + dl * t)[a];
      (a == 0 ? nl.x : a == 1 ? nl.y : nl.z) = pa > 0 ? 1.0 : -1.0;
      hit->object = b.object;
      hit->normal = b.rot * nl;
      found = true;
    }
  }
  if constexpr (kMesh) {
    Hit mh;
    if (IntersectMesh(o, d, &mh, moved ? moved->mesh_time : 0.f) && mh.t < best) {
      *hit = mh;
      best = mh.t;
      found = true;
    }
  }
  if (found) hit->t = best;
  return found;
}

}  // namespace raymatch::simulate
