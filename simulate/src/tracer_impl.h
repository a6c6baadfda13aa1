#pragma once
// What the tracer's files share (tracer.cpp, trace_ray.h, objects.h, packet_driver.*): the
// Simulator's state, the tracing templates' configuration, and the per-thread accumulators.
#include <memory>
#include <vector>

#include "packet.h"
#include "raymatch/simulate/geometry.h"
#include "raymatch/simulate/index_field.h"
#include "raymatch/simulate/tracer.h"
#include "raymatch/simulate/water.h"
#include "sources.h"
#include "stages.h"

namespace raymatch::simulate {

/// The squared radius of object k's bounding sphere as the near tests use it (the packet path's
/// and the scalar path's motion test): the margin (1e-6 of the radius + 1 nm) is far above the
/// rounding of either test.
inline double NearBoundR2(const Geometry& g, int k) {
  const double r = g.bound_radius(k) * (1 + 1e-6) + 1e-3;
  return r * r;
}

/// Whether the straight line through p along unit d passes within sqrt(r2) of c: the one test
/// that splits a plane's rays into those that can meet the fit's region and the others
/// (SplitRaysBySphere and TraceFarRays must agree ray for ray).
inline bool LinePassesWithin(const Vec3& p, const Vec3& d, const Vec3& c, double r2) {
  const double cc[3] = {c.x, c.y, c.z};
  return st::LineDistance2<L1>(cc, {p.x, p.y, p.z}, {d.x, d.y, d.z}) <= r2;
}

/// The inner loop's compile-time switches, chosen once per image from what the scene declares:
/// the partial-reflection branch, the corrector stage, the Embree mesh query and the per-ray
/// draws (motion, spectrum). Every tracing template takes one (WithTraceConfig makes it).
template <PartialReflection kPartialReflection, bool kHasCorrector, bool kHasMesh, bool kHasDraws>
struct TraceConfig {
  static constexpr PartialReflection kPR = kPartialReflection;
  static constexpr bool kCorrector = kHasCorrector;
  static constexpr bool kMesh = kHasMesh;
  static constexpr bool kDraws = kHasDraws;
};

/// f.template operator()<Cfg>() with Cfg the TraceConfig of these switches: the one dispatch
/// from run-time effects to compiled inner loops.
template <class F>
void WithTraceConfig(PartialReflection pr, bool corrector, bool mesh, bool draws, F&& f) {
  auto with_draws = [&]<PartialReflection P, bool C, bool M>() {
    if (draws)
      f.template operator()<TraceConfig<P, C, M, true>>();
    else
      f.template operator()<TraceConfig<P, C, M, false>>();
  };
  auto with_mesh = [&]<PartialReflection P, bool C>() {
    if (mesh)
      with_draws.template operator()<P, C, true>();
    else
      with_draws.template operator()<P, C, false>();
  };
  auto with_corrector = [&]<PartialReflection P>() {
    if (corrector)
      with_mesh.template operator()<P, true>();
    else
      with_mesh.template operator()<P, false>();
  };
  switch (pr) {
    case PartialReflection::kOff:
      with_corrector.template operator()<PartialReflection::kOff>();
      break;
    case PartialReflection::kUnpolarized:
      with_corrector.template operator()<PartialReflection::kUnpolarized>();
      break;
    case PartialReflection::kPolarized:
      with_corrector.template operator()<PartialReflection::kPolarized>();
      break;
  }
}

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

// Per-thread accumulation: integer counts, so sums do not depend on the partition.
struct Accum {
  std::vector<uint32_t> image;  // the nx * ny pixels, then spare elements (not part of it)
  TraceCounters counters;
  std::unique_ptr<packet::Rays> rays;  // the packet path's batch (made on first use)
  SphereQueue sphere_queue;
  std::vector<double> ray_index;  // spectral scenes: each object's index at the ray's wavelength
  std::vector<Vec3> ray_shift;    // moving scenes: each object's displacement at the ray's time
  // Spectral scenes with water density fields: this thread's views of them (AffineView) and
  // each object's field as the ray sees it (a view, or the object's own field).
  std::vector<IndexField> field_views;
  std::vector<const IndexField*> ray_field;
};

/// What one ray sees of the objects when it drew a time or a wavelength (TraceSampledRay): each
/// object's index and index field at its wavelength, each object's displacement at its time.
struct RayObjects {
  const double* index = nullptr;             ///< null: the objects' own indices
  const IndexField* const* field = nullptr;  ///< null: the objects' own fields
  const ObjectShifts* moved = nullptr;       ///< null: every object at its centre
};

struct Simulator::Impl {
  Geometry geometry;
  SourceVariant source;
  Optics optics;                         // at defocus 0
  PacketSupport packets;                 // whether the packet path takes this scene
  std::vector<double> index;             // per object
  std::vector<const IndexField*> field;  // per object; null = homogeneous
  std::vector<UniformCells> uniform;     // per object; empty unless a grid field
  std::vector<Vec3> center;
  std::vector<double> size;  // characteristic size (for first GRIN steps)
  bool has_grin = false;
  std::shared_ptr<const packet::Table2D> angular_table;  // a light field's, for the packet path
  double field_radius_um = 0;  // resolved source field radius (automatic or given)
  double medium;
  double source_z;
  /// Motion during the exposure (Scene::has_motion): each object's velocity and the pulse.
  bool motion = false;
  std::vector<Vec3> velocity;  // per object, um/us
  ExposureSpec exposure;
  /// The spectrum (Scene::is_spectral): each object's index law for the ray's wavelength.
  bool spectral = false;
  SpectrumSpec spectrum;
  std::vector<Dispersion> dispersion;    // per object; law kNone: its constant index
  std::vector<WaterMapTable> water_map;  // per object: its water density field at other
                                         // wavelengths (empty: none, or not spectral)
  bool spectral_fields = false;          // some object's field follows the wavelength
  explicit Impl(const Scene& s) : geometry(s.objects, s.exposure.max_offset_us()) {}
  /// Whether the line through p along d can meet an object (the packet path's near test, lane
  /// for lane: a ray it calls far meets nothing, whenever it was emitted).
  bool NearAnObject(const Vec3& p, const Vec3& d) const {
    for (int k = 0; k < int(index.size()); ++k)
      if (LinePassesWithin(p, d, geometry.bound_center(k), NearBoundR2(geometry, k))) return true;
    return false;
  }
};

}  // namespace raymatch::simulate
