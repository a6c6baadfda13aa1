#include "packet_driver.h"

#include <algorithm>
#include <iterator>

namespace raymatch::simulate {

/// Whether the packet path takes the scene: the one place that decides it (Effects lists it).
PacketSupport PacketSupportFor(const Simulator::Impl& im) {
  const Field* field = nullptr;
  if (const auto* cone = std::get_if<ConeSource>(&im.source)) {
    field = &cone->field;
  } else if (const auto* col = std::get_if<CollimatedSource>(&im.source)) {
    field = &col->field;
  } else if (const auto* lf = std::get_if<LightFieldSource>(&im.source)) {
    if (!im.angular_table || im.angular_table->height == 0) return {false, "empty_angular_map"};
    field = &lf->field;
  } else {
    return {false,
            std::holds_alternative<PointSource>(im.source) ? "point_source" : "ray_list_source"};
  }
  if (field->shape != FieldShape::kDisc && !field->map.empty()) return {false, "spatial_map"};
  if (im.index.size() > size_t(packet::kMaxBounds)) return {false, "too_many_objects"};
  return {true, ""};
}

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
    ps.table = im.angular_table.get();
  }
  packet::NearParams& near = plan.near;
  near.source_z = im.source_z;
  near.num_bounds = static_cast<int>(im.index.size());
  for (int k = 0; k < near.num_bounds; ++k) {
    // A line farther than this from every bounding sphere cannot meet an object; the margin
    // (1e-6 of the radius + 1 nm) is far above the rounding of either test.
    const Vec3& c = im.geometry.bound_center(k);
    near.bound_c[k][0] = c.x, near.bound_c[k][1] = c.y, near.bound_c[k][2] = c.z;
    near.bound_r2[k] = NearBoundR2(im.geometry, k);
  }
  near.split = sel.split;
  near.split_c[0] = sel.split_center.x, near.split_c[1] = sel.split_center.y;
  near.split_c[2] = sel.split_center.z, near.split_r2 = sel.split_r2;
  // The sphere stage: one homogeneous sphere, refraction, TIR and the unpolarised Fresnel
  // branch (the polarised branch, moving or dispersive spheres and everything else stay on the
  // scalar path).
  if (!im.motion && !im.spectral && scene.objects.size() == 1 &&
      scene.objects[0].shape == ShapeType::kSphere && !scene.objects[0].index_field &&
      !im.geometry.has_meshes() && pr != PartialReflection::kPolarized) {
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

namespace {

/// f(lane, k) for each lane still open (out 0) whose `words` words from `skip` past its cursor
/// (k the first) are in the batch; the others go back to the scalar path from their stream.
template <class F>
void DrawForOpenLanes(packet::Rays& r, size_t n, int skip, int words, F&& f) {
  for (size_t i = 0; i < n; ++i) {
    if (r.out[i] != 0) continue;
    const int64_t k = r.cursor[i] + skip;
    if (k + words - 1 < packet::kWords) {
      f(i, k);
    } else {
      r.out[i] = packet::kScalar;
      r.cursor[i] = -1;
    }
  }
}

}  // namespace

/// The corrector's uniform (Rays::u) for the lanes still open (out 0): the word `skip` past the
/// lane's cursor. A lane whose words ran out goes back to the scalar path from its stream.
void CorrectorDraws(packet::Rays& r, size_t n, int skip) {
  DrawForOpenLanes(r, n, skip, 1, [&](size_t i, int64_t k) { r.u[i] = r.words[k][i] * 0x1p-32; });
}

/// The camera PSF's offsets (Rays::psf_du, psf_dv) for the lanes still open: two words from
/// `skip` past the cursor, through the stage both paths run (stages-inl.h, GaussianPair), so
/// that both put a ray on the same pixel. The words are gathered lane by lane, the offsets made
/// a vector at a time.
void PsfDraws(packet::Rays& r, size_t n, int skip, double sigma) {
  std::fill(std::begin(r.psf_du), std::end(r.psf_du), 0.0);  // whole vectors read past n
  std::fill(std::begin(r.psf_dv), std::end(r.psf_dv), 0.0);
  DrawForOpenLanes(r, n, skip, 2, [&](size_t i, int64_t k) {
    r.psf_du[i] = r.words[k][i] * 0x1p-32;
    r.psf_dv[i] = r.words[k + 1][i] * 0x1p-32;
  });
  packet::GaussianOffsets(sigma, n, &r);
}

/// A batch's outcomes after NearTestAndOptics or OpticsAfterObjects into the image and the fate
/// counters; returns how many of its rays reached the optics.
uint64_t CountBatch(const packet::Rays& r, size_t n, Accum& acc) {
  for (size_t i = 0; i < n; ++i) ++acc.image[static_cast<size_t>(r.slot[i])];
  for (int f = 0; f < kNumFates; ++f) acc.counters.fates[f] += r.counts[f];
  return r.counts[int(Fate::kDetected)] + r.counts[int(Fate::kOutsideNa)] +
         r.counts[int(Fate::kMissedSensor)] + r.counts[int(Fate::kAbsorbedCorrector)];
}

}  // namespace raymatch::simulate
