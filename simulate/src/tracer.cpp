#include "raymatch/simulate/tracer.h"

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/global_control.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <mutex>
#include <optional>
#include <thread>
#include <variant>

#include "raymatch/core/cluster.h"
#include "raymatch/core/error.h"
#include "raymatch/core/rng.h"
#include "raymatch/simulate/geometry.h"
#include "raymatch/simulate/interfaces.h"
#include "raymatch/simulate/sampling.h"
#include "packet.h"
#include "stages-inl.h"  // the static target: the stages' one-lane instantiation
#include "stages.h"

namespace raymatch::simulate {

const char* SimdTarget() { return packet::TargetName(); }

namespace st = stages::HWY_NAMESPACE;
using L1 = stages::ScalarLanes;  // one ray: the stages' scalar instantiation

const char* FateName(Fate f) {
  static const char* names[] = {"detected",           "outside_na",      "missed_sensor",
                                "absorbed_corrector", "interaction_cap", "escaped",
                                "lost_inside",        "grin_step_cap"};
  return names[static_cast<int>(f)];
}

namespace {

// All counters as one array (for sums over threads and MPI ranks) and back: the one list of
// the counters.
template <typename C, typename F>
void ForEachCounter(C& c, F&& f) {
  for (auto& v : c.fates) f(v);
  f(c.interface_events), f(c.fresnel_evaluations), f(c.corrector_tests), f(c.mesh_queries);
  f(c.shape_queries), f(c.rays_hitting_objects), f(c.grin_steps), f(c.grin_segments);
  f(c.grin_uniform_steps);
  for (auto& v : c.path_class) f(v);
}

std::vector<uint64_t> PackCounters(const TraceCounters& c) {
  std::vector<uint64_t> out;
  ForEachCounter(c, [&](uint64_t v) { out.push_back(v); });
  return out;
}

TraceCounters UnpackCounters(const uint64_t* p) {
  TraceCounters c;
  ForEachCounter(c, [&](uint64_t& v) { v = *p++; });
  return c;
}

}  // namespace

void TraceCounters::Add(const TraceCounters& o) {
  const std::vector<uint64_t> other = PackCounters(o);
  const uint64_t* p = other.data();
  ForEachCounter(*this, [&](uint64_t& v) { v += *p++; });
}

uint64_t TraceCounters::total_fates() const {
  uint64_t s = 0;
  for (uint64_t f : fates) s += f;
  return s;
}

namespace {

constexpr double kDeg = M_PI / 180.0;

// ---------------------------------------------------------------- sources
// Each source yields a point where the ray crosses z = 0 (absent objects) and a unit direction
// with d.z > 0; the tracer then starts it on the source plane before all objects.

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
/// radius sin(theta_max) (REFERENCE.md section 6: radiance is density per dx dy du dv).
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
  Distribution2D angular;
  double extent;
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
    angular.Sample(u0, u1, &x, &y);
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

using SourceVariant = std::variant<CollimatedSource, ConeSource, PointSource, LightFieldSource, RayListSource>;

}  // namespace

/// Whether the straight line through p along unit d passes within sqrt(r2) of c: the one test
/// that splits a plane's rays into those that can meet the fit's region and the others
/// (SplitRaysBySphere and TraceFarRays must agree ray for ray).
static inline bool LinePassesWithin(const Vec3& p, const Vec3& d, const Vec3& c, double r2) {
  const double cc[3] = {c.x, c.y, c.z};
  return st::LineDistance2<L1>(cc, {p.x, p.y, p.z}, {d.x, d.y, d.z}) <= r2;
}

// Which of a plane's rays to trace: all of [0, n), a list of indices, or all but a sorted list.
struct RaySelection {
  const uint64_t* list = nullptr;
  const uint64_t* skip = nullptr;
  size_t skip_count = 0;
  uint64_t first = 0;         // without a list: the rays [first, first + n)
  bool split = false;         // leave out (and report) rays whose line meets the sphere
  Vec3 split_center;
  double split_r2 = 0;
};

namespace {

// Per-thread accumulation: integer counts, so sums do not depend on the partition.
/// Rays of the packet path that meet the scene's one sphere, waiting for the sphere stage.
struct SphereQueue {
  std::unique_ptr<packet::Rays> rays;  // made on first use
  size_t count = 0;
  /// Lane i of batch r (its id, cursor and source sample) joins; true when the queue is full.
  bool Push(const packet::Rays& r, size_t i) {
    packet::Rays& q = *rays;
    const size_t m = count++;
    q.ids[m] = r.ids[i], q.cursor[m] = r.cursor[i];
    q.px[m] = r.px[i], q.py[m] = r.py[i], q.pz[m] = r.pz[i];
    q.dx[m] = r.dx[i], q.dy[m] = r.dy[i], q.dz[m] = r.dz[i];
    return count == packet::kBatch;
  }
};

struct Accum {
  std::vector<uint32_t> image;  // the nx * ny pixels, then spare elements (not part of it)
  TraceCounters counters;
  std::unique_ptr<packet::Rays> rays;  // the packet path's batch (made on first use)
  SphereQueue sphere_queue;
};

}  // namespace

struct Simulator::Impl {
  Geometry geometry;
  SourceVariant source;
  Optics optics;                  // at defocus 0
  PacketSupport packets;          // whether the packet path takes this scene
  std::vector<double> index;             // per object
  std::vector<const IndexField*> field;  // per object; null = homogeneous
  std::vector<UniformCells> uniform;      // per object; empty unless a grid field
  std::vector<Vec3> center;
  std::vector<double> size;  // characteristic size (for first GRIN steps)
  bool has_grin = false;
  packet::Table2D angular_table;  // the light field's table for the packet path
  double field_radius_um = 0;  // resolved source field radius (automatic or given)
  double medium;
  double source_z;
  explicit Impl(const Scene& s) : geometry(s.objects) {}
};

namespace {

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
        m.at(x, y) = m0.at(std::clamp(x - px, 0, m0.width - 1), std::clamp(y - py, 0, m0.height - 1));
    f.half_w += px * cw, f.half_h += py * ch;
    f.map = Distribution2D(m);
  }
  return f;
}

}  // namespace

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
    // Two thin lenses from f, WD and BFD (REFERENCE.md section 6).
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
  // accepts from an on-axis point (docs/optics.md).
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

namespace {

/// Pseudo-random unit vector perpendicular to d (polarisation of a new ray).
Vec3 RandomPerpendicular(const Vec3& d, double u) {
  const Vec3 a = std::abs(d.x) < 0.9 ? Vec3(1, 0, 0) : Vec3(0, 1, 0);
  const Vec3 e1 = Normalize(Cross(d, a)), e2 = Cross(d, e1);
  const double phi = 2 * M_PI * u;
  return e1 * std::cos(phi) + e2 * std::sin(phi);
}

enum class GrinOutcome { kHit, kStepCap, kNoSurface };

/// A spherically symmetric field (n depends on |p - centre| only: Luneburg, fish-eye) conserves
/// the ray's angular momentum L = (r - c) x T (Bouguer's formula, Born & Wolf sec. 3.2.1) and
/// the eikonal |T| = n. Near a tangent exit a position error e moves the exit by e / alpha
/// along the surface (alpha: the exit angle to it), so each accepted state is projected back
/// onto both invariants (Hairer, Lubich & Wanner, Geometric Numerical Integration, 2006,
/// sec. IV.4): the orbit keeps its exact shape and the exit angle follows from L.
bool IsCentralField(const IndexField& f) {
  return f.type == IndexFieldType::kLuneburg || f.type == IndexFieldType::kFishEye;
}

void ProjectOnInvariants(const IndexField& f, const Vec3& center, const Vec3& l, GrinPoint* s) {
  const double l2 = Dot(l, l);
  Vec3 p = s->r - center;
  if (l2 > 0) p = p - l * (Dot(p, l) / l2);  // back into the plane of the orbit
  const double p2 = Dot(p, p);
  if (!(p2 > 0)) return;
  const Vec3 t_perp = Cross(l, p) / p2;  // p x t_perp = l for p normal to l
  const double sign = Dot(s->t, p) >= 0 ? 1.0 : -1.0;
  const GrinPoint q = MakeGrinPoint(f, center, center + p, s->t);  // n and D at the new point
  const double radial2 = q.n * q.n - Dot(t_perp, t_perp);
  *s = q;
  s->t = t_perp + p * (sign * std::sqrt(std::max(0.0, radial2)) / std::sqrt(p2));
}

/// Follows a curved ray inside gradient-index object `obj` from `o` (direction `d`) to the next
/// surface. Each accepted step's chord is tested against the surfaces; a step whose chord crosses
/// one is shortened (the crossing parameter scales the step) until the crossing chord is shorter
/// than 1e-3 um or 1e-5 of the object size, then the ray leaves at the chord's hit point with
/// the direction T/|T| at the step's end. Across uniform cells of a grid the ray goes straight
/// in one step (exact there), to the surface if it is nearer.
template <bool kMesh>
GrinOutcome IntegrateToSurface(const Simulator::Impl& im, const GrinSettings& cfg, int obj,
                               const Vec3& o, const Vec3& d, Hit* hit, Vec3* hp, Vec3* dout,
                               TraceCounters& c) {
  const IndexField& f = *im.field[obj];
  const UniformCells* uniform = im.uniform[obj].empty() ? nullptr : &im.uniform[obj];
  const Vec3& center = im.center[obj];
  const Geometry& geo = im.geometry;
  const double surface_tol = std::min(1e-3, 1e-5 * im.size[obj]);
  GrinPoint s = MakeGrinPoint(f, center, o, d);
  const bool central = IsCentralField(f);
  const Vec3 angular_momentum = Cross(o - center, s.t);
  // The orbit of a central field leaves the sphere it entered at the angle alpha to the surface
  // with cos(pi/2 - alpha) = |L| / (n R). Near a tangent exit (alpha -> 0) the exit point moves by
  // e / alpha for a position error e and the direction by e / (alpha R), so the step tolerance
  // shrinks with alpha^2 below alpha = 0.01 (down to 1e-6 of the setting): rays entering
  // within ~5e-5 R of a Luneburg lens's edge, and only those, take smaller steps.
  GrinSettings local = cfg;
  if (central) {
    const double r0 = Length(o - center);
    const double sin_exit = r0 > 0 ? Length(angular_momentum) / (s.n * r0) : 0.0;
    const double alpha = std::sqrt(std::max(0.0, 1 - std::min(1.0, sin_exit * sin_exit)));
    local.tolerance_um = cfg.tolerance_um * std::clamp(alpha * alpha / 1e-4, 1e-6, 1.0);
  }
  double dt = 0.05 * im.size[obj] / Length(s.t);
  // 3D grids: steps from face to face (the cell of s.r is kept between steps).
  const bool cell_steps = UsesCellSteps(f, cfg);
  GridCellPair cells;
  // Paths shorter than the clearance cannot reach a surface (spheres only; 0 otherwise). `clear`
  // is a lower bound of the clearance at s.r: the distance to a surface changes by at most the
  // length of a chord, so the bound follows the steps and the clearance itself is computed only
  // where a path reaches the bound (the same surface queries as computing it at every step).
  double clear = 0;
  auto clearance = [&](double path) {
    if (path >= clear) clear = geo.SurfaceClearance(s.r);
    return clear;
  };
  auto moved = [&](double chord) { clear -= chord * (1 + 1e-12) + 1e-12; };
  // Whether the cell of s.r (cell steps keep it) has corner values that differ by more than the
  // uniform tolerance along an axis: then its block is not uniform and there is no straight
  // step to look up.
  auto in_varying_cell = [&] {
    const Vec3 p = s.r - center;
    const GridCell& cell = cells.now();
    const double tol = cfg.uniform_tolerance;
    return cell.at.x == p.x && cell.at.y == p.y && cell.at.z == p.z &&
           (std::abs(cell.c[1]) > tol || std::abs(cell.c[2]) > tol || std::abs(cell.c[3]) > tol);
  };
  ++c.grin_segments;
  for (int step = 0; step < cfg.max_steps; ++step) {
    if (uniform && !(cell_steps && in_varying_cell())) {
      // Straight across uniform cells when that beats the next curved step.
      const double free = uniform->FreeLength(s.r - center);
      if (free > dt * s.n) {
        const Vec3 dir = s.t / s.n;
        Hit h;
        ++c.grin_uniform_steps;
        bool crosses = false;
        if (free >= clearance(free)) {
          ++c.shape_queries;
          if constexpr (kMesh) ++c.mesh_queries;
          crosses = geo.Intersect<kMesh>(s.r, dir, &h) && h.t <= free;
        }
        if (crosses) {
          *hit = h;
          *hp = s.r + dir * h.t;
          *dout = dir;
          return GrinOutcome::kHit;
        }
        s = MakeGrinPoint(f, center, s.r + dir * free, s.t);
        moved(free);
        continue;
      }
    }
    GrinPoint s1 = s;
    double used = 0, next = dt;
    if (cell_steps) {
      CellStep(f, center, local, &cells, &s1, &next, &used);
    } else {
      AdaptiveStep(f, center, local, &s1, &next, &used);
    }
    ++c.grin_steps;
    for (int shrink = 0;; ++shrink) {
      const Vec3 chord = s1.r - s.r;
      const double L = Length(chord);
      Hit h;
      bool crosses = false;
      if (L >= clearance(L)) {
        ++c.shape_queries;
        if constexpr (kMesh) ++c.mesh_queries;
        crosses = L > 0 && geo.Intersect<kMesh>(s.r, chord / L, &h) && h.t <= L;
      }
      if (!crosses) {
        if (central) ProjectOnInvariants(f, center, angular_momentum, &s1);
        s = s1;
        dt = next;
        if (central) {
          clear = 0;  // the projection moved the point off the chord
        } else {
          moved(L);
        }
        break;
      }
      if (L <= surface_tol || shrink > 60) {
        *hit = h;
        *hp = s.r + chord * (h.t / L);
        *dout = Normalize(s1.t);
        // In a steep gradient the direction at the step's end may already bend back inward;
        // the crossing chord points outward by construction, so leave along it then.
        if (Dot(*dout, h.normal) <= 0) *dout = chord / L;
        return GrinOutcome::kHit;
      }
      // Aim the (shorter) step at the crossing point; it is within the accepted error. Near a
      // tangent exit the straight chord leaves the surface much later than the curved path
      // (both bend alike), so aiming shortened the step by ~0.1 % a try and after 60 tries the
      // ray left at the chord's far end, past its true exit and turned backwards (issue 15).
      // From the second try on the step is at least halved: a bisection on the path.
      const double aim = std::max(0.05, 0.999 * h.t / L);
      used *= shrink == 0 ? aim : std::min(0.5, aim);
      next = used;
      s1 = SharmaStep(f, center, s, used);
      if (central) ProjectOnInvariants(f, center, angular_momentum, &s1);
    }
  }
  return GrinOutcome::kStepCap;
}

/// Traces a ray through the objects until it leaves them all (or ends). Updates o, d (and the
/// polarisation) to the ray leaving the last surface; returns true with *fate set when the ray
/// ended inside the objects (interaction cap, numerical loss, step cap).
template <PartialReflection kPR, bool kMesh>
bool TraceObjects(const Simulator::Impl& im, const TraceSpec& trace, RayRng& rng, Vec3& o, Vec3& d,
                  Vec3& pol, TraceCounters& c, Fate* fate_out) {
  const Geometry& geo = im.geometry;
  Fate fate = Fate::kDetected;
  bool done = false;
  // Objects the ray is inside, innermost last (nested objects: a bubble in a drop).
  int stack[kMaxNesting];
  int depth = 0;
  auto index_at = [&](int obj, const Vec3& x) {
    if (obj < 0) return im.medium;
    if (im.has_grin && im.field[obj]) return im.field[obj]->Index(x - im.center[obj]);
    return im.index[obj];
  };
  int events = 0, internal_reflections = 0;
  bool classified = false;
  for (;;) {
    Hit h;
    Vec3 hp;
    const int cur = depth ? stack[depth - 1] : -1;
    if (im.has_grin && cur >= 0 && im.field[cur]) {
      const GrinOutcome g = IntegrateToSurface<kMesh>(im, trace.grin, cur, o, d, &h, &hp, &d, c);
      if (g != GrinOutcome::kHit) {
        fate = g == GrinOutcome::kStepCap ? Fate::kGrinStepCap : Fate::kLostInside;
        done = true;
        break;
      }
    } else {
      ++c.shape_queries;
      if constexpr (kMesh) ++c.mesh_queries;
      if (!geo.Intersect<kMesh>(o, d, &h)) break;
      hp = o + d * h.t;
    }
    if (events == 0) ++c.rays_hitting_objects;
    if (++events > trace.max_interactions) {
      fate = Fate::kInteractionCap;
      done = true;
      break;
    }
    ++c.interface_events;
    const bool entering = Dot(d, h.normal) < 0;
    // The medium beyond a surface being left is the innermost enclosing object other than
    // the one left.
    int outer = -1;
    if (!entering)
      for (int k = depth - 1; k >= 0; --k)
        if (stack[k] != h.object) {
          outer = stack[k];
          break;
        }
    const double n1 = entering ? index_at(cur, hp) : index_at(h.object, hp);
    const double n2 = entering ? index_at(h.object, hp) : index_at(outer, hp);
    const Vec3 nf = entering ? h.normal : -h.normal;  // faces the incoming ray
    const double cos_i = -Dot(d, nf);
    Vec3 dt;
    double cos_t = 0;
    bool reflect = !Refract(d, nf, n1 / n2, &dt, &cos_t);  // TIR
    if (!reflect) {
      if constexpr (kPR == PartialReflection::kUnpolarized) {
        ++c.fresnel_evaluations;
        reflect = rng.Uniform() < Fresnel(n1, n2, cos_i, cos_t).R();
      } else if constexpr (kPR == PartialReflection::kPolarized) {
        ++c.fresnel_evaluations;
        // Split the field into s (perpendicular to the plane of incidence) and p parts;
        // reflect with the power-weighted reflectance, then carry the new s/p mixture.
        const FresnelCoefficients fc = Fresnel(n1, n2, cos_i, cos_t);
        Vec3 s_dir = Cross(d, nf);
        const double sl = Length(s_dir);
        s_dir = sl > 1e-12 ? s_dir / sl : RandomPerpendicular(d, 0.0);
        const double es = Dot(pol, s_dir), ep = Dot(pol, Cross(s_dir, d));
        const double R = es * es * fc.Rs + ep * ep * fc.Rp;
        reflect = rng.Uniform() < R;
        const Vec3 dn = reflect ? Reflect(d, nf) : dt;
        const double as = reflect ? fc.rs * es : (1 + fc.rs) * es;            // t_s = 1 + r_s
        const double ap = reflect ? fc.rp * ep : (1 + fc.rp) * ep * n1 / n2;  // t_p
        const Vec3 e = s_dir * as + Cross(s_dir, dn) * ap;
        const double el = Length(e);
        pol = el > 0 ? e / el : RandomPerpendicular(dn, 0.25);
      }
    }
    if (reflect) {
      d = Normalize(Reflect(d, nf));
      o = hp + nf * geo.epsilon(h.object);
      if (!classified) {
        if (entering && events == 1) {
          ++c.path_class[0];
          classified = true;
        } else if (!entering) {
          ++internal_reflections;
        }
      }
    } else {
      d = Normalize(dt);
      o = hp - nf * geo.epsilon(h.object);
      if (entering) {
        if (depth == kMaxNesting) {
          fate = Fate::kLostInside;  // deeper nesting than supported
          done = true;
          break;
        }
        stack[depth++] = h.object;
      } else {
        for (int k = depth - 1; k >= 0; --k)
          if (stack[k] == h.object) {
            for (int m = k; m + 1 < depth; ++m) stack[m] = stack[m + 1];
            --depth;
            break;
          }
      }
      if (!classified && !entering) {
        ++c.path_class[std::min(1 + internal_reflections, kNumPathClasses - 1)];
        classified = true;
      }
    }
  }
  if (!done && depth > 0) {
    fate = Fate::kLostInside;
    done = true;
  }
  *fate_out = fate;
  return done;
}

template <PartialReflection kPR, bool kCorrector, bool kMesh, class Source>
void TraceSampledRay(const Simulator::Impl& im, const TraceSpec& trace, const Optics& op,
                     uint64_t ray, const Vec3& p, Vec3 d, RayRng& rng, const RaySelection& sel,
                     Accum& acc, std::vector<uint64_t>* near_out);

/// One ray of the plane, from its own stream: the scalar path, and the packet path's fallback.
template <PartialReflection kPR, bool kCorrector, bool kMesh, class Source>
void TraceRay(const Simulator::Impl& im, const Source& src, const TraceSpec& trace, const Optics& op,
              uint32_t plane, uint64_t ray, const RaySelection& sel, Accum& acc,
              std::vector<uint64_t>* near_out) {
  TraceCounters& c = acc.counters;
  RayRng rng(trace.seed, plane, ray);
  Vec3 p, d;
  if (!src.Sample(rng, &p, &d)) {
    ++c.fates[int(Fate::kEscaped)];
    return;
  }
  TraceSampledRay<kPR, kCorrector, kMesh, Source>(im, trace, op, ray, p, d, rng, sel, acc,
                                                  near_out);
}

/// TraceRay after the source: the ray leaves p along d; rng stands after the source's words.
template <PartialReflection kPR, bool kCorrector, bool kMesh, class Source>
void TraceSampledRay(const Simulator::Impl& im, const TraceSpec& trace, const Optics& op,
                     uint64_t ray, const Vec3& p, Vec3 d, RayRng& rng, const RaySelection& sel,
                     Accum& acc, std::vector<uint64_t>* near_out) {
  const Geometry& geo = im.geometry;
  const bool has_objects = !geo.empty();
  TraceCounters& c = acc.counters;
  if (sel.split && LinePassesWithin(p, d, sel.split_center, sel.split_r2)) {
    near_out->push_back(ray);  // as SplitRaysBySphere
    return;
  }
  Vec3 o = p;
  // (1 / d.z, a product: the packet path reuses the reciprocal for the slopes below)
  if constexpr (!std::is_same_v<Source, PointSource>) {
    const st::V3<L1> q = st::OnPlane<L1>(im.source_z, {p.x, p.y, p.z}, {d.x, d.y, d.z}, 1 / d.z);
    o = Vec3(q.x, q.y, q.z);
  }
  Vec3 pol;
  if constexpr (kPR == PartialReflection::kPolarized) pol = RandomPerpendicular(d, rng.Uniform());

  Fate fate = Fate::kDetected;
  bool done = false;
  if (has_objects) done = TraceObjects<kPR, kMesh>(im, trace, rng, o, d, pol, c, &fate);
  if (!done && d.z <= 0) {
    fate = Fate::kEscaped;
    done = true;
  }
  if (done) {
    ++c.fates[int(fate)];
    return;
  }
  // The optics stages (stages-inl.h), one lane.
  auto out = st::Outcome<L1>::Open();
  st::Beam<L1> beam = st::Beam<L1>::From({o.x, o.y, o.z}, {d.x, d.y, d.z}, 1 / d.z);
  if constexpr (kCorrector) {
    ++c.corrector_tests;
    st::CorrectorStage<L1>(op, beam, out, [&] { return rng.Uniform(); });
  }
  if (!out.settled) st::LensStage<L1>(op, beam, out);
  if (!out.settled) {
    double u, v;
    st::SensorPoint<L1>(op, beam, u, v);
    if (op.psf_sigma_sensor > 0) {  // Box-Muller: two independent normal offsets
      const double r = op.psf_sigma_sensor * std::sqrt(-2 * std::log(1 - rng.Uniform()));
      const double phi = 2 * M_PI * rng.Uniform();
      u += r * std::cos(phi);
      v += r * std::sin(phi);
    }
    const double pixel = st::SensorPixel<L1>(op, u, v, out);
    if (!out.settled) ++acc.image[static_cast<size_t>(pixel)];
  }
  ++c.fates[int(out.settled ? st::FateOf(out.code) : Fate::kDetected)];
}

/// Calls f(ray) for the rays [begin, end) of the selection, in ascending order of i.
template <class F>
void ForEachSelectedRay(const RaySelection& sel, uint64_t begin, uint64_t end, F&& f) {
  // Rays to leave out (ascending): the first one at or after this range.
  const uint64_t* skip =
      sel.skip ? std::lower_bound(sel.skip, sel.skip + sel.skip_count, sel.first + begin) : nullptr;
  const uint64_t* skip_end = sel.skip ? sel.skip + sel.skip_count : nullptr;
  for (uint64_t i = begin; i < end; ++i) {
    // A subset of the plane's rays keeps each ray's own stream (TraceRays, TracePlaneExcept).
    const uint64_t ray = sel.list ? sel.list[i] : sel.first + i;
    if (skip != skip_end && *skip == ray) {
      ++skip;
      continue;
    }
    f(ray);
  }
}

template <PartialReflection kPR, bool kCorrector, bool kMesh, class Source>
void TraceRange(const Simulator::Impl& im, const Source& src, const TraceSpec& trace,
                const Optics& op, uint32_t plane, uint64_t begin, uint64_t end,
                const RaySelection& sel, Accum& acc, std::vector<uint64_t>* near_out) {
  ForEachSelectedRay(sel, begin, end, [&](uint64_t ray) {
    TraceRay<kPR, kCorrector, kMesh>(im, src, trace, op, plane, ray, sel, acc, near_out);
  });
}

// ---------------------------------------------------------------- SIMD packets
// The packet path (packet.h) traces the rays that meet no object, which are most of an image's,
// several at a time; it hands every other ray to TraceRay. Images are the same bit for bit.

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

/// The sources the packet stages sample (which Source types get a packet instantiation).
template <class Source>
constexpr bool kPacketSource = std::is_same_v<Source, ConeSource> ||
                               std::is_same_v<Source, CollimatedSource> ||
                               std::is_same_v<Source, LightFieldSource>;

/// Whether the packet path takes the scene: the one place that decides it (Effects lists it).
PacketSupport PacketSupportFor(const Simulator::Impl& im) {
  const Field* field = nullptr;
  if (const auto* cone = std::get_if<ConeSource>(&im.source)) {
    field = &cone->field;
  } else if (const auto* col = std::get_if<CollimatedSource>(&im.source)) {
    field = &col->field;
  } else if (const auto* lf = std::get_if<LightFieldSource>(&im.source)) {
    if (im.angular_table.height == 0) return {false, "empty_angular_map"};
    field = &lf->field;
  } else {
    return {false, std::holds_alternative<PointSource>(im.source) ? "point_source"
                                                                  : "ray_list_source"};
  }
  if (field->shape != FieldShape::kDisc && !field->map.empty()) return {false, "spatial_map"};
  if (im.optics.psf_sigma_sensor > 0) return {false, "camera_psf"};
  if (im.index.size() > size_t(packet::kMaxBounds)) return {false, "too_many_objects"};
  return {true, ""};
}

struct PacketPlan {
  packet::SourceParams source;
  packet::NearParams near;
  /// Rays that meet the scene's one homogeneous sphere go through the sphere stage too.
  std::optional<packet::SphereParams> sphere;
};

/// The packet stages' parameters for a scene the packet path takes (PacketSupportFor).
PacketPlan MakePacketPlan(const Simulator::Impl& im, const Scene& scene, PartialReflection pr,
                          const RaySelection& sel) {
  PacketPlan plan;
  packet::SourceParams& ps = plan.source;
  auto set_field = [&](const Field& f) {
    ps.disc_field = f.shape == FieldShape::kDisc;
    ps.radius = f.radius, ps.half_w = f.half_w, ps.half_h = f.half_h;
    ps.center[0] = f.center.x, ps.center[1] = f.center.y, ps.center[2] = f.center.z;
  };
  if (const auto* cone = std::get_if<ConeSource>(&im.source)) {
    set_field(cone->field);
    ps.direction = packet::SourceParams::kCone, ps.sin_max = cone->sin_max;
  } else if (const auto* col = std::get_if<CollimatedSource>(&im.source)) {
    set_field(col->field);
    ps.direction = packet::SourceParams::kCollimated;
    ps.dir[0] = col->dir.x, ps.dir[1] = col->dir.y, ps.dir[2] = col->dir.z;
  } else if (const auto* lf = std::get_if<LightFieldSource>(&im.source)) {
    set_field(lf->field);
    ps.direction = packet::SourceParams::kTabulated;
    ps.table = &im.angular_table;
  }
  packet::NearParams& near = plan.near;
  near.source_z = im.source_z;
  near.num_bounds = static_cast<int>(im.index.size());
  for (int k = 0; k < near.num_bounds; ++k) {
    // A line farther than this from every bounding sphere cannot meet an object; the margin
    // (1e-6 of the radius + 1 nm) is far above the rounding of either test.
    const Vec3& c = im.geometry.bound_center(k);
    const double r = im.geometry.bound_radius(k) * (1 + 1e-6) + 1e-3;
    near.bound_c[k][0] = c.x, near.bound_c[k][1] = c.y, near.bound_c[k][2] = c.z;
    near.bound_r2[k] = r * r;
  }
  near.split = sel.split;
  near.split_c[0] = sel.split_center.x, near.split_c[1] = sel.split_center.y;
  near.split_c[2] = sel.split_center.z, near.split_r2 = sel.split_r2;
  // The sphere stage: one homogeneous sphere, refraction, TIR and the unpolarised Fresnel
  // branch (the polarised branch and everything else stay on the scalar path).
  if (scene.objects.size() == 1 && scene.objects[0].shape == ShapeType::kSphere &&
      !scene.objects[0].index_field && !im.geometry.has_meshes() &&
      pr != PartialReflection::kPolarized) {
    const ObjectSpec& o = scene.objects[0];
    packet::SphereParams sp;
    sp.center[0] = o.center_um.x, sp.center[1] = o.center_um.y, sp.center[2] = o.center_um.z;
    sp.radius2 = o.radius_um * o.radius_um;  // as Geometry's SphereShape
    sp.index = im.index[0], sp.medium = im.medium, sp.epsilon = im.geometry.epsilon(0);
    sp.source_z = im.source_z;
    sp.max_interactions = scene.trace.max_interactions;
    sp.fresnel = pr == PartialReflection::kUnpolarized;
    plan.sphere = sp;
  }
  return plan;
}

/// The corrector's uniform (Rays::u) for the lanes still open (out 0): the word `skip` past the
/// lane's cursor. A lane whose words ran out goes back to the scalar path from its stream.
void CorrectorDraws(packet::Rays& r, size_t n, int skip) {
  for (size_t i = 0; i < n; ++i) {
    if (r.out[i] != 0) continue;
    const int64_t k = r.cursor[i] + skip;
    if (k < packet::kWords) {
      r.u[i] = r.words[k][i] * 0x1p-32;
    } else {
      r.out[i] = packet::kScalar;
      r.cursor[i] = -1;
    }
  }
}

/// A batch's outcomes after Background or Onward into the image and the fate counters; returns
/// how many of its rays reached the optics.
uint64_t CountBatch(const packet::Rays& r, size_t n, Accum& acc) {
  for (size_t i = 0; i < n; ++i) ++acc.image[static_cast<size_t>(r.slot[i])];
  for (int f = 0; f < kNumFates; ++f) acc.counters.fates[f] += r.counts[f];
  return r.counts[int(Fate::kDetected)] + r.counts[int(Fate::kOutsideNa)] +
         r.counts[int(Fate::kMissedSensor)] + r.counts[int(Fate::kAbsorbedCorrector)];
}

/// The queued rays that meet the sphere, through the sphere stage and on through the optics;
/// those that run out of random words are traced again on the scalar path.
template <PartialReflection kPR, bool kCorrector, bool kMesh, class Source>
void TraceSphereQueue(const Simulator::Impl& im, const Source& src, const TraceSpec& trace,
                      const Optics& op, uint32_t plane, const RaySelection& sel, Accum& acc,
                      std::vector<uint64_t>* near_out, const PacketPlan& plan) {
  packet::Rays& q = *acc.sphere_queue.rays;
  const size_t m = acc.sphere_queue.count;
  acc.sphere_queue.count = 0;
  // All their words (the batch made the third Philox block only where the source needed it).
  packet::PhiloxWords(trace.seed, plane, q.ids, m, &q);
  packet::Sphere(*plan.sphere, m, &q);
  if constexpr (kCorrector) CorrectorDraws(q, m, 0);  // the corrector's draw follows the sphere's
  packet::Onward(op, m, &q);
  const uint64_t optics = CountBatch(q, m, acc);
  TraceCounters& c = acc.counters;
  for (size_t i = 0; i < m; ++i) {
    if (q.out[i] == packet::kScalar) continue;  // counted when traced again below
    c.shape_queries += static_cast<uint64_t>(q.queries[i]);
    c.interface_events += static_cast<uint64_t>(q.interface_events[i]);
    c.fresnel_evaluations += static_cast<uint64_t>(q.fresnel[i]);
    c.rays_hitting_objects += q.events[i] > 0;
    if (q.path_class[i] >= 0) ++c.path_class[static_cast<size_t>(q.path_class[i])];
  }
  if constexpr (kCorrector) c.corrector_tests += optics;
  for (size_t k = 0; k < q.num_rare; ++k)
    TraceRay<kPR, kCorrector, kMesh>(im, src, trace, op, plane,
                                     q.ids[static_cast<size_t>(q.rare[k])], sel, acc, near_out);
}

/// One batch of packet::kBatch rays (at most; their indices in acc.rays->ids): the source, the
/// near test and the optics in packets, then each ray the packets handed back, in ray order.
template <PartialReflection kPR, bool kCorrector, bool kMesh, class Source>
void TraceBatch(const Simulator::Impl& im, const Source& src, const TraceSpec& trace,
                const Optics& op, uint32_t plane, const RaySelection& sel, Accum& acc,
                std::vector<uint64_t>* near_out, const PacketPlan& plan, size_t n) {
  packet::Rays& r = *acc.rays;
  // Words drawn after the source by a ray that meets nothing: polarisation, corrector.
  constexpr int kPolWords = kPR == PartialReflection::kPolarized ? 1 : 0;
  constexpr int kExtraWords = kPolWords + (kCorrector ? 1 : 0);
  packet::SampleSource(plan.source, trace.seed, plane, r.ids, n, kExtraWords, &r);
  if constexpr (std::is_same_v<Source, LightFieldSource>) packet::Tabulated(*plan.source.table, n, &r);
  // The corrector's draw follows the source's (and the polarisation's) words.
  if constexpr (kCorrector) CorrectorDraws(r, n, kPolWords);
  packet::Background(plan.near, op, n, &r);
  const uint64_t optics = CountBatch(r, n, acc);
  TraceCounters& c = acc.counters;
  const uint64_t queries = im.geometry.empty() ? 0 : 1;  // the one query that found nothing
  c.shape_queries += queries * optics;  // rays that met nothing: one query each
  if constexpr (kMesh) c.mesh_queries += optics;
  if constexpr (kCorrector) c.corrector_tests += optics;
  for (size_t k = 0; k < r.num_rare; ++k) {  // in ray order: the near list stays ascending
    const size_t i = static_cast<size_t>(r.rare[k]);
    const uint64_t ray = r.ids[i];
    if (r.out[i] == packet::kNear) {
      near_out->push_back(ray);
    } else if (r.cursor[i] < 0) {  // the batch's words ran out: all again from the stream
      TraceRay<kPR, kCorrector, kMesh>(im, src, trace, op, plane, ray, sel, acc, near_out);
    } else if (plan.sphere) {  // near the sphere: queued for the sphere stage
      if (acc.sphere_queue.Push(r, i))
        TraceSphereQueue<kPR, kCorrector, kMesh>(im, src, trace, op, plane, sel, acc, near_out,
                                                 plan);
    } else {  // near an object: on from the packet's source sample and the stream's cursor
      RayRng rng(trace.seed, plane, ray);
      rng.SkipTo(static_cast<uint64_t>(r.cursor[i]));
      TraceSampledRay<kPR, kCorrector, kMesh, Source>(im, trace, op, ray,
                                                      Vec3(r.px[i], r.py[i], r.pz[i]),
                                                      Vec3(r.dx[i], r.dy[i], r.dz[i]), rng, sel,
                                                      acc, near_out);
    }
  }
}

/// TraceRange in batches of packet::kBatch rays: the same rays, counts and counters.
template <PartialReflection kPR, bool kCorrector, bool kMesh, class Source>
void TraceRangePackets(const Simulator::Impl& im, const Source& src, const TraceSpec& trace,
                       const Optics& op, uint32_t plane, uint64_t begin, uint64_t end,
                       const RaySelection& sel, Accum& acc, std::vector<uint64_t>* near_out,
                       const PacketPlan& plan) {
  if (!acc.rays) acc.rays = std::make_unique<packet::Rays>();  // value-initialised
  if (plan.sphere && !acc.sphere_queue.rays)
    acc.sphere_queue.rays = std::make_unique<packet::Rays>();
  size_t n = 0;
  ForEachSelectedRay(sel, begin, end, [&](uint64_t ray) {
    acc.rays->ids[n++] = ray;
    if (n == packet::kBatch) {
      TraceBatch<kPR, kCorrector, kMesh>(im, src, trace, op, plane, sel, acc, near_out, plan, n);
      n = 0;
    }
  });
  if (n > 0) TraceBatch<kPR, kCorrector, kMesh>(im, src, trace, op, plane, sel, acc, near_out, plan, n);
  if (acc.sphere_queue.count > 0)
    TraceSphereQueue<kPR, kCorrector, kMesh>(im, src, trace, op, plane, sel, acc, near_out, plan);
}

class Progress {
 public:
  Progress(bool enabled, std::string label, uint64_t total)
      : enabled_(enabled), label_(std::move(label)), total_(total) {
    if (enabled_) thread_ = std::thread([this] { Loop(); });
  }
  ~Progress() {
    if (!enabled_) return;
    {
      std::lock_guard<std::mutex> lk(m_);
      stop_ = true;
    }
    cv_.notify_all();
    thread_.join();
    std::fprintf(stderr, "\r\033[K");
  }
  void Add(uint64_t n) { done_.fetch_add(n, std::memory_order_relaxed); }

 private:
  void Loop() {
    const auto t0 = std::chrono::steady_clock::now();
    std::unique_lock<std::mutex> lk(m_);
    // Runs shorter than ~2 s print nothing.
    if (cv_.wait_for(lk, std::chrono::seconds(2), [this] { return stop_; })) return;
    while (!stop_) {
      const double f = double(done_.load()) / double(std::max<uint64_t>(total_, 1));
      const double el =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      const int w = 30, filled = static_cast<int>(f * w);
      std::fprintf(stderr, "\r%s [%.*s%*s] %5.1f%%  %.0f s elapsed, ~%.0f s left", label_.c_str(),
                   filled, "##############################", w - filled, "", 100 * f, el,
                   f > 0 ? el * (1 - f) / f : 0.0);
      std::fflush(stderr);
      cv_.wait_for(lk, std::chrono::milliseconds(500), [this] { return stop_; });
    }
  }
  bool enabled_;
  std::string label_;
  uint64_t total_;
  std::atomic<uint64_t> done_{0};
  std::thread thread_;
  std::mutex m_;
  std::condition_variable cv_;
  bool stop_ = false;
};

}  // namespace

Simulator::Simulator(const Scene& scene) : scene_(scene), impl_(std::make_unique<Impl>(scene)) {
  Impl& im = *impl_;
  im.medium = scene.medium_index;
  for (const ObjectSpec& o : scene.objects) {
    im.index.push_back(o.index);
    im.field.push_back(o.index_field.get());
    im.uniform.push_back(o.index_field ? UniformCells(*o.index_field, scene.trace.grin.uniform_tolerance)
                                       : UniformCells());
    im.center.push_back(o.center_um);
    im.size.push_back(o.shape == ShapeType::kSphere ? o.radius_um : Length(o.semi_axes_um));
    im.has_grin = im.has_grin || o.index_field != nullptr;
  }
  im.optics = MakeOptics(scene);
  // Source plane: before every object (and never after z = 0, where fields are defined).
  const double min_z = im.geometry.empty() ? 0.0 : im.geometry.min_z_um();
  im.source_z = std::min(0.0, min_z - 1.0 - 1e-3 * std::abs(min_z));
  // Automatic field radius: the sensor's view at the object plane, widened by the angular
  // spread over the largest defocus and object depth, plus 5 %.
  const double m = std::abs(Magnification(scene.optics));
  const double view =
      0.5 * std::hypot(scene.camera.nx, scene.camera.ny) * scene.camera.pixel_pitch_um / m +
      std::hypot(scene.camera.offset_um[0], scene.camera.offset_um[1]) / m;
  double max_dz = 0;
  for (double dz : scene.defocus_um) max_dz = std::max(max_dz, std::abs(dz));
  const double tan_max = std::tan(std::min(scene.source.half_angle_deg, 80.0) * kDeg) +
                         std::tan(std::asin(AcceptanceSin(scene)));
  const double auto_r_objects = 1.05 * (view + (max_dz + im.geometry.extent_um()) * tan_max) + 1.0;
  const SourceSpec& ss = scene.source;
  im.field_radius_um = ss.field_radius_um > 0 ? ss.field_radius_um : auto_r_objects;
  // A given radius also bounds how far a measured spatial map is continued, so a fit that fixes
  // it gets the same rays whatever the objects' extent.
  const double auto_r = im.field_radius_um;
  switch (ss.type) {
    case SourceType::kCollimated: {
      const double t = ss.tilt_deg * kDeg, a = ss.azimuth_deg * kDeg;
      im.source =
          CollimatedSource{MakeField(scene, auto_r),
                           Vec3(std::sin(t) * std::cos(a), std::sin(t) * std::sin(a), std::cos(t))};
      break;
    }
    case SourceType::kCone:
      im.source = ConeSource{MakeField(scene, auto_r), std::sin(ss.half_angle_deg * kDeg)};
      break;
    case SourceType::kPoint:
      im.source = PointSource{ss.position_um, std::cos(ss.half_angle_deg * kDeg)};
      break;
    case SourceType::kLightField: {
      LightFieldSource lf{MakeField(scene, auto_r), Distribution2D(ss.angular_map),
                          ss.angular_extent};
      im.angular_table = PacketTable(lf);
      im.source = std::move(lf);
      break;
    }
    case SourceType::kRayList: {
      std::vector<float> w;
      for (const auto& r : ss.rays) w.push_back(float(r[4]));
      im.source = RayListSource{scene_.source.rays.data(), Distribution1D(w.data(), int(w.size()))};
      break;
    }
  }
  im.packets = PacketSupportFor(im);
  if (ss.type == SourceType::kPoint) {
    for (const ObjectSpec& o : scene.objects)
      if (o.shape == ShapeType::kSphere && Length(ss.position_um - o.center_um) < o.radius_um)
        throw Error(o.where, "the point source lies inside object '" + o.name + "'");
  }
}

Simulator::~Simulator() = default;

double Simulator::source_plane_z_um() const { return impl_->source_z; }
double Simulator::object_pixel_um() const {
  return scene_.camera.pixel_pitch_um / std::abs(Magnification(scene_.optics));
}
bool Simulator::has_mesh_bvh() const { return impl_->geometry.has_meshes(); }

std::vector<std::string> Simulator::Effects() const {
  static const char* src[] = {"source:collimated", "source:cone", "source:point",
                              "source:lightfield", "source:ray_list"};  // SourceType order
  std::vector<std::string> e{src[static_cast<int>(scene_.source.type)]};
  if (!impl_->geometry.empty()) {
    e.push_back("refraction");
    e.push_back("total_internal_reflection");
    if (scene_.trace.partial_reflection == PartialReflection::kUnpolarized)
      e.push_back("partial_reflection:unpolarized");
    if (scene_.trace.partial_reflection == PartialReflection::kPolarized)
      e.push_back("partial_reflection:polarized");
  }
  if (impl_->has_grin) e.push_back("gradient_index:sharma_embedded");
  if (std::any_of(impl_->field.begin(), impl_->field.end(), [&](const IndexField* f) {
        return f && UsesCellSteps(*f, scene_.trace.grin);
      }))
    e.push_back("gradient_index:cell_steps");
  if (impl_->geometry.has_meshes()) e.push_back("mesh_bvh:embree");
  if (scene_.optics.corrector.enabled) e.push_back("angular_corrector");
  e.push_back(scene_.optics.model == ObjectiveModel::kSingle ? "objective:single_ideal_lens"
                                                             : "objective:two_ideal_lenses");
  e.push_back("tube_lens");
  if (scene_.camera.psf_sigma_um > 0) e.push_back("camera_psf:gaussian");
  e.push_back(impl_->packets.ok ? std::string("simd_packets")
                                : std::string("scalar_only:") + impl_->packets.reason);
  return e;
}

PlaneResult Simulator::TracePlane(double defocus_um, uint32_t plane_index, uint64_t rays,
                                  const RunControl& control) const {
  return Trace(defocus_um, plane_index, rays, {}, control);
}

PlaneResult Simulator::TracePlaneExcept(double defocus_um, uint32_t plane_index, uint64_t rays,
                                        const std::vector<uint64_t>& excluded,
                                        const RunControl& control) const {
  return TraceRangeExcept(defocus_um, plane_index, 0, rays, excluded, control);
}

PlaneResult Simulator::TraceRays(double defocus_um, uint32_t plane_index,
                                 std::span<const uint64_t> ray_indices,
                                 const RunControl& control) const {
  RaySelection sel;
  sel.list = ray_indices.data();
  return Trace(defocus_um, plane_index, ray_indices.size(), sel, control);
}

PlaneResult Simulator::TraceRangeExcept(double defocus_um, uint32_t plane_index, uint64_t first,
                                        uint64_t last, std::span<const uint64_t> excluded,
                                        const RunControl& control) const {
  RAYMATCH_CHECK(first <= last && std::is_sorted(excluded.begin(), excluded.end()));
  RaySelection sel;
  sel.skip = excluded.data(), sel.skip_count = excluded.size(), sel.first = first;
  return Trace(defocus_um, plane_index, last - first, sel, control);
}

PlaneResult Simulator::TraceFarRays(double defocus_um, uint32_t plane_index, uint64_t first,
                                    uint64_t last, const Vec3& center_um, double radius_um,
                                    std::vector<uint64_t>* near, const RunControl& control) const {
  RAYMATCH_CHECK(first <= last && near != nullptr);
  if (GetCluster().size > 1) {
    // MPI ranks trace different chunks, but every rank needs the whole near list: split first
    // (every rank samples the whole range), then trace the rest across the ranks.
    std::vector<uint64_t> part;
    SplitRaysBySphere(plane_index, first, last, center_um, radius_um, &part, nullptr);
    PlaneResult r = TraceRangeExcept(defocus_um, plane_index, first, last, part, control);
    near->insert(near->end(), part.begin(), part.end());
    return r;
  }
  RaySelection sel;
  sel.first = first, sel.split = true, sel.split_center = center_um;
  sel.split_r2 = radius_um * radius_um;
  return Trace(defocus_um, plane_index, last - first, sel, control, near);
}

PlaneResult Simulator::Trace(double defocus_um, uint32_t plane_index, uint64_t rays,
                             const RaySelection& sel, const RunControl& control,
                             std::vector<uint64_t>* near) const {
  const Impl& im = *impl_;
  int threads = control.threads > 0 ? control.threads : scene_.trace.threads;
  if (threads <= 0) threads = static_cast<int>(std::thread::hardware_concurrency());
  threads = std::max(1, threads);
  const size_t npix = size_t(scene_.camera.nx) * scene_.camera.ny;
  tbb::enumerable_thread_specific<Accum> accums([npix] {
    Accum a;
    a.image.assign(npix + packet::kSpareSlots, 0);  // + the packet path's spare elements
    return a;
  });
  const auto t0 = std::chrono::steady_clock::now();
  // MPI ranks (core/cluster.h) take every size-th chunk; integer counts summed over the ranks
  // give the image of one process bit for bit. Rank 0's progress stands for the whole job.
  const Cluster& cluster = GetCluster();
  const uint64_t rank = uint64_t(cluster.rank), ranks = uint64_t(std::max(1, cluster.size));
  const PartialReflection pr =
      im.geometry.empty() ? PartialReflection::kOff : scene_.trace.partial_reflection;
  const bool corr = scene_.optics.corrector.enabled;
  const bool mesh = im.geometry.has_meshes();
  constexpr uint64_t kChunk = 8192;
  const uint64_t chunks = (rays + kChunk - 1) / kChunk;
  const uint64_t my_chunks = chunks > rank ? (chunks - rank + ranks - 1) / ranks : 0;
  Progress progress(control.progress && cluster.is_root(),
                    ranks > 1 ? control.label + " (" + std::to_string(ranks) + " ranks)" : control.label,
                    std::min(rays, my_chunks * kChunk));

  const Optics op = im.optics.Shifted(defocus_um);  // this plane's optics, for both paths
  const std::optional<PacketPlan> plan =
      control.simd && im.packets.ok ? std::optional(MakePacketPlan(im, scene_, pr, sel))
                                    : std::nullopt;
  // Split mode: each chunk's near rays in their own list, joined in chunk order below.
  std::vector<std::vector<uint64_t>> near_by_chunk(sel.split ? chunks : 0);
  auto run_chunk = [&](uint64_t ci) {
    const uint64_t b = ci * kChunk, e = std::min(rays, b + kChunk);
    Accum& acc = accums.local();
    std::vector<uint64_t>* near_out = sel.split ? &near_by_chunk[ci] : nullptr;
    const TraceSpec& ts = scene_.trace;
    // Choose the inner loop once per chunk from the scene's effects.
    std::visit(
        [&](const auto& src) {
          using Source = std::decay_t<decltype(src)>;
          auto range = [&]<PartialReflection P, bool C, bool M>() {
            if constexpr (kPacketSource<Source>) {
              if (plan) {
                TraceRangePackets<P, C, M>(im, src, ts, op, plane_index, b, e, sel, acc,
                                           near_out, *plan);
                return;
              }
            }
            TraceRange<P, C, M>(im, src, ts, op, plane_index, b, e, sel, acc, near_out);
          };
          auto dispatch = [&]<PartialReflection P>() {
            if (corr && mesh)
              range.template operator()<P, true, true>();
            else if (corr)
              range.template operator()<P, true, false>();
            else if (mesh)
              range.template operator()<P, false, true>();
            else
              range.template operator()<P, false, false>();
          };
          switch (pr) {
            case PartialReflection::kOff:
              dispatch.template operator()<PartialReflection::kOff>();
              break;
            case PartialReflection::kUnpolarized:
              dispatch.template operator()<PartialReflection::kUnpolarized>();
              break;
            case PartialReflection::kPolarized:
              dispatch.template operator()<PartialReflection::kPolarized>();
              break;
          }
        },
        im.source);
    progress.Add(e - b);
  };

  // Allow exactly `threads` workers even beyond the core count (determinism tests use that).
  tbb::global_control limit(tbb::global_control::max_allowed_parallelism, threads);
  tbb::task_arena arena(threads);
  arena.execute([&] {
    tbb::parallel_for(tbb::blocked_range<uint64_t>(0, my_chunks, 1),
                      [&](const tbb::blocked_range<uint64_t>& r) {
                        for (uint64_t k = r.begin(); k != r.end(); ++k) run_chunk(rank + k * ranks);
                      });
  });

  PlaneResult res;
  res.defocus_um = defocus_um;
  res.rays = rays;
  if (sel.skip)  // the listed rays in [first, first + rays) were left out
    res.rays -= std::lower_bound(sel.skip, sel.skip + sel.skip_count, sel.first + rays) -
                std::lower_bound(sel.skip, sel.skip + sel.skip_count, sel.first);
  if (sel.split) {
    RAYMATCH_CHECK(near != nullptr && ranks == 1);
    for (const auto& v : near_by_chunk) {
      near->insert(near->end(), v.begin(), v.end());
      res.rays -= v.size();
    }
  }
  res.threads = threads;
  res.ranks = static_cast<int>(ranks);
  res.simd = plan.has_value();
  std::vector<uint64_t> sum(npix, 0);
  for (const Accum& a : accums) {
    for (size_t i = 0; i < npix; ++i) sum[i] += a.image[i];
    res.counters.Add(a.counters);
  }
  if (ranks > 1 && cluster.sum) {
    std::vector<uint64_t> packed = PackCounters(res.counters);
    const size_t nc = packed.size();
    packed.insert(packed.end(), sum.begin(), sum.end());
    cluster.sum(packed.data(), packed.size());
    res.counters = UnpackCounters(packed.data());
    std::copy(packed.begin() + long(nc), packed.end(), sum.begin());
  }
  res.counts = Image(scene_.camera.nx, scene_.camera.ny);
  for (size_t i = 0; i < npix; ++i) res.counts.pixels[i] = static_cast<float>(sum[i]);
  res.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  RAYMATCH_CHECK(res.counters.total_fates() == res.rays);  // every ray accounted for
  return res;
}

Simulator::ObjectExit Simulator::TraceThroughObjects(const Vec3& origin, const Vec3& direction,
                                                     uint64_t ray_index) const {
  ObjectExit out;
  out.origin = origin;
  out.direction = Normalize(direction);
  RayRng rng(scene_.trace.seed, 0, ray_index);
  Vec3 pol = RandomPerpendicular(out.direction, rng.Uniform());
  auto run = [&]<PartialReflection P>() {
    out.ended = impl_->geometry.has_meshes()
                    ? TraceObjects<P, true>(*impl_, scene_.trace, rng, out.origin, out.direction,
                                            pol, out.counters, &out.fate)
                    : TraceObjects<P, false>(*impl_, scene_.trace, rng, out.origin, out.direction,
                                             pol, out.counters, &out.fate);
  };
  switch (scene_.trace.partial_reflection) {
    case PartialReflection::kOff:
      run.template operator()<PartialReflection::kOff>();
      break;
    case PartialReflection::kUnpolarized:
      run.template operator()<PartialReflection::kUnpolarized>();
      break;
    case PartialReflection::kPolarized:
      run.template operator()<PartialReflection::kPolarized>();
      break;
  }
  return out;
}

uint64_t Simulator::RaysForPhotonTarget(double photons_per_pixel, double* hppr) const {
  // Pilot: the same source and optics without objects (a flat field), fixed seed and stream.
  Scene flat = scene_;
  flat.objects.clear();
  // The same source field as the real scene: its automatic size depends on the objects.
  if (flat.source.field_shape == FieldShape::kDisc) flat.source.field_radius_um = impl_->field_radius_um;
  flat.trace.seed = 0x5eed;
  Simulator pilot(flat);
  constexpr uint64_t kPilotRays = 400000;
  const PlaneResult r = pilot.TracePlane(0.0, 0xFFFFFFFFu, kPilotRays);
  const double per_ray_per_pixel =
      double(r.counters.fates[int(Fate::kDetected)]) / (double(kPilotRays) * r.counts.size());
  if (hppr) *hppr = per_ray_per_pixel;
  if (!(per_ray_per_pixel > 0))
    throw Error(FileLocation{scene_.file},
                "no light reaches the sensor in the flat field: check source field, NA and camera");
  return static_cast<uint64_t>(std::ceil(photons_per_pixel / per_ray_per_pixel));
}

void Simulator::SplitRaysBySphere(uint32_t plane_index, uint64_t first, uint64_t last,
                                  const Vec3& center_um, double radius_um,
                                  std::vector<uint64_t>* near, std::vector<uint64_t>* far) const {
  const Impl& im = *impl_;
  const double r2 = radius_um * radius_um;
  constexpr uint64_t kChunk = 65536;
  const uint64_t chunks = (last - first + kChunk - 1) / kChunk;
  // Per-chunk lists joined in chunk order: the result does not depend on the thread count.
  std::vector<std::vector<uint64_t>> near_c(chunks), far_c(chunks);
  tbb::parallel_for(uint64_t(0), chunks, [&](uint64_t ci) {
    const uint64_t b = first + ci * kChunk, e = std::min(last, b + kChunk);
    std::visit(
        [&](const auto& src) {
          for (uint64_t ray = b; ray < e; ++ray) {
            RayRng rng(scene_.trace.seed, plane_index, ray);
            Vec3 p, d;
            // A ray the source rejects ends at once (escaped) in either list.
            const bool ok = src.Sample(rng, &p, &d);
            (ok && LinePassesWithin(p, d, center_um, r2) ? near_c[ci] : far_c[ci]).push_back(ray);
          }
        },
        im.source);
  });
  for (uint64_t ci = 0; ci < chunks; ++ci) {
    if (near) near->insert(near->end(), near_c[ci].begin(), near_c[ci].end());
    if (far) far->insert(far->end(), far_c[ci].begin(), far_c[ci].end());
  }
}

double Simulator::field_radius_um() const { return impl_->field_radius_um; }

std::vector<std::pair<Vec3, double>> Simulator::ObjectBounds() const {
  std::vector<std::pair<Vec3, double>> b;
  for (size_t i = 0; i < scene_.objects.size(); ++i)
    b.push_back({impl_->geometry.bound_center(int(i)), impl_->geometry.bound_radius(int(i))});
  return b;
}

uint64_t Simulator::RaysPerImage() const {
  return scene_.trace.rays > 0 ? scene_.trace.rays
                               : RaysForPhotonTarget(scene_.trace.photons_per_pixel);
}

}  // namespace raymatch::simulate
