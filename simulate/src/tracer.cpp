#include "raymatch/simulate/tracer.h"

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/global_control.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <iterator>
#include <optional>
#include <thread>
#include <variant>

#include "objects.h"
#include "packet_driver.h"
#include "raymatch/core/cluster.h"
#include "raymatch/core/error.h"
#include "raymatch/core/progress.h"
#include "raymatch/core/rng.h"
#include "trace_ray.h"
#include "tracer_impl.h"

namespace raymatch::simulate {

const char* SimdTarget() { return packet::TargetName(); }

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
  f(c.grin_uniform_steps), f(c.motion_draws), f(c.wavelength_draws);
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

constexpr double kDeg = M_PI / 180.0;

Simulator::Simulator(const Scene& scene) : scene_(scene), impl_(std::make_unique<Impl>(scene)) {
  Impl& im = *impl_;
  im.medium = scene.medium_index;
  for (const ObjectSpec& o : scene.objects) {
    im.index.push_back(o.index);
    im.field.push_back(o.index_field.get());
    im.uniform.push_back(o.index_field
                             ? UniformCells(*o.index_field, scene.trace.grin.uniform_tolerance)
                             : UniformCells());
    im.center.push_back(o.center_um);
    im.size.push_back(o.shape == ShapeType::kSphere ? o.radius_um : Length(o.semi_axes_um));
    im.has_grin = im.has_grin || o.index_field != nullptr;
  }
  im.motion = scene.has_motion();
  for (const ObjectSpec& o : scene.objects) im.velocity.push_back(o.velocity_um_per_us);
  im.exposure = scene.exposure;
  im.spectral = scene.is_spectral();
  im.spectrum = scene.source.spectrum;
  for (const ObjectSpec& o : scene.objects) {
    im.dispersion.push_back(o.dispersion);
    // A water density field under a spectrum: its index at each wavelength of the spectrum's
    // range as an affine map of the one its grid holds.
    const bool water_field = im.spectral && o.index_field && o.index_field->water;
    im.water_map.push_back(
        water_field ? WaterMapTable(
                          o.index_field->water->density_kg_m3, o.index_field->water->temperature_K,
                          o.index_field->water->wavelength_um, scene.source.spectrum.Sample(0),
                          scene.source.spectrum.Sample(std::nextafter(1.0, 0.0)))
                    : WaterMapTable());
    im.spectral_fields = im.spectral_fields || water_field;
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
  im.source = MakeSource(scene_, auto_r, &im.angular_table);
  im.packets = PacketSupportFor(im);
  if (ss.type == SourceType::kPoint) {
    for (const ObjectSpec& o : scene.objects)
      if (o.shape == ShapeType::kSphere && Length(ss.position_um - o.center_um) < o.radius_um)
        throw Error(o.where, "the point source lies inside object '" + o.name + "'");
  }
}

Simulator::~Simulator() = default;

double Simulator::source_plane_z_um() const { return impl_->source_z; }

double Simulator::source_weight() const {
  const auto* lf = std::get_if<LightFieldSource>(&impl_->source);
  return lf ? lf->weight : 0;
}
const WaterMapTable* Simulator::WaterMapOf(int object) const {
  const WaterMapTable& t = impl_->water_map.at(size_t(object));
  return t.empty() ? nullptr : &t;
}

double Simulator::object_pixel_um() const {
  return scene_.camera.pixel_pitch_um / std::abs(Magnification(scene_.optics));
}
bool Simulator::has_mesh_bvh() const { return impl_->geometry.has_meshes(); }

std::vector<std::string> Simulator::Effects() const {
  static const char* src[] = {"source:collimated", "source:cone", "source:point",
                              "source:lightfield", "source:ray_list"};  // SourceType order
  std::vector<std::string> e{src[static_cast<int>(scene_.source.type)]};
  if (scene_.source.type == SourceType::kLightField && scene_.source.edge_half_angle_deg > 0 &&
      scene_.source.map_na_limit > 0)
    e.push_back("light_field_edge:tanh");
  if (!impl_->geometry.empty()) {
    e.push_back("refraction");
    e.push_back("total_internal_reflection");
    if (scene_.trace.partial_reflection == PartialReflection::kUnpolarized)
      e.push_back("partial_reflection:unpolarized");
    if (scene_.trace.partial_reflection == PartialReflection::kPolarized)
      e.push_back("partial_reflection:polarized");
  }
  if (impl_->has_grin) e.push_back("gradient_index:sharma_embedded");
  if (std::any_of(impl_->field.begin(), impl_->field.end(),
                  [&](const IndexField* f) { return f && UsesCellSteps(*f, scene_.trace.grin); }))
    e.push_back("gradient_index:cell_steps");
  if (impl_->geometry.has_meshes()) e.push_back("mesh_bvh:embree");
  if (scene_.optics.corrector.enabled) e.push_back("angular_corrector");
  e.push_back(scene_.optics.model == ObjectiveModel::kSingle ? "objective:single_ideal_lens"
                                                             : "objective:two_ideal_lenses");
  e.push_back("tube_lens");
  if (scene_.camera.psf_sigma_um > 0) e.push_back("camera_psf:gaussian");
  if (impl_->spectral) {
    e.push_back(std::string("spectrum:") + SpectrumTypeName(scene_.source.spectrum.type));
  }
  if (impl_->motion || impl_->spectral)  // the packet path's sphere stage is for static spheres
    e.push_back(std::string("scalar_near_objects:") + (impl_->motion ? "motion" : "spectrum"));
  if (impl_->motion) {
    e.push_back(std::string("motion:") + PulseName(scene_.exposure.shape));
  }
  e.push_back(impl_->packets.ok ? std::string("simd_packets")
                                : std::string("scalar_only:") + impl_->packets.reason);
  return e;
}

PlaneResult Simulator::TracePlane(double defocus_um, uint32_t plane_index, uint64_t rays,
                                  const RunControl& control) const {
  return Trace(defocus_um, plane_index, RaySelection::Range(0, rays), control);
}

PlaneResult Simulator::TracePlaneExcept(double defocus_um, uint32_t plane_index, uint64_t rays,
                                        const std::vector<uint64_t>& excluded,
                                        const RunControl& control) const {
  return TraceRangeExcept(defocus_um, plane_index, 0, rays, excluded, control);
}

PlaneResult Simulator::TraceRays(double defocus_um, uint32_t plane_index,
                                 std::span<const uint64_t> ray_indices,
                                 const RunControl& control) const {
  return Trace(defocus_um, plane_index, RaySelection::Of(ray_indices), control);
}

PlaneResult Simulator::TraceRangeExcept(double defocus_um, uint32_t plane_index, uint64_t first,
                                        uint64_t last, std::span<const uint64_t> excluded,
                                        const RunControl& control) const {
  RAYMATCH_CHECK(first <= last);
  return Trace(defocus_um, plane_index, RaySelection::Range(first, last).Except(excluded), control);
}

PlaneResult Simulator::TraceFarRays(double defocus_um, uint32_t plane_index, uint64_t first,
                                    uint64_t last, const Vec3& center_um, double radius_um,
                                    std::vector<uint64_t>* near, const RunControl& control) const {
  RAYMATCH_CHECK(first <= last);
  return Trace(defocus_um, plane_index,
               RaySelection::Range(first, last).SplitBy(center_um, radius_um), control, near);
}

namespace {

// SplitRaysBySphere with the squared radius.
void SplitRays(const Simulator::Impl& im, uint64_t seed, uint32_t plane_index, uint64_t first,
               uint64_t last, const Vec3& center_um, double r2, std::vector<uint64_t>* near,
               std::vector<uint64_t>* far) {
  constexpr uint64_t kChunk = 65536;
  const uint64_t chunks = (last - first + kChunk - 1) / kChunk;
  // Per-chunk lists joined in chunk order: the result does not depend on the thread count.
  std::vector<std::vector<uint64_t>> near_c(chunks), far_c(chunks);
  tbb::parallel_for(uint64_t(0), chunks, [&](uint64_t ci) {
    const uint64_t b = first + ci * kChunk, e = std::min(last, b + kChunk);
    std::visit(
        [&](const auto& src) {
          for (uint64_t ray = b; ray < e; ++ray) {
            RayRng rng(seed, plane_index, ray);
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

}  // namespace

PlaneResult Simulator::Trace(double defocus_um, uint32_t plane_index, const RaySelection& sel,
                             const RunControl& control, std::vector<uint64_t>* near) const {
  RAYMATCH_CHECK(!sel.skip || std::is_sorted(sel.skip, sel.skip + sel.skip_count));
  RAYMATCH_CHECK(!sel.split || (near != nullptr && !sel.list));
  if (sel.split && GetCluster().size > 1) {
    // MPI ranks trace different chunks, but every rank needs the whole near list: split first
    // (every rank samples the whole range), then trace the rest across the ranks.
    std::vector<uint64_t> part;
    SplitRays(*impl_, scene_.trace.seed, plane_index, sel.first, sel.first + sel.count,
              sel.split_center, sel.split_r2, &part, nullptr);
    const std::span<const uint64_t> skip(sel.skip, sel.skip ? sel.skip_count : 0);
    std::vector<uint64_t> split_off, left_out;  // the near rays not skipped; both lists
    std::set_difference(part.begin(), part.end(), skip.begin(), skip.end(),
                        std::back_inserter(split_off));
    std::set_union(part.begin(), part.end(), skip.begin(), skip.end(),
                   std::back_inserter(left_out));
    RaySelection rest = sel;
    rest.split = false;
    PlaneResult r = Trace(defocus_um, plane_index, rest.Except(left_out), control);
    near->insert(near->end(), split_off.begin(), split_off.end());
    return r;
  }
  const uint64_t rays = sel.count;
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
  const bool draws = im.motion || im.spectral;  // rays near objects draw a time or wavelength
  constexpr uint64_t kChunk = 8192;
  const uint64_t chunks = (rays + kChunk - 1) / kChunk;
  const uint64_t my_chunks = chunks > rank ? (chunks - rank + ranks - 1) / ranks : 0;
  Progress progress(
      control.progress && cluster.is_root(),
      ranks > 1 ? control.label + " (" + std::to_string(ranks) + " ranks)" : control.label,
      std::min(rays, my_chunks * kChunk));

  const Optics op = im.optics.Shifted(defocus_um);  // this plane's optics, for both paths
  const std::optional<PacketPlan> plan = control.simd && im.packets.ok
                                             ? std::optional(MakePacketPlan(im, scene_, pr, sel))
                                             : std::nullopt;
  // Split mode: each chunk's near rays in their own list, joined in chunk order below.
  std::vector<std::vector<uint64_t>> near_by_chunk(sel.split ? chunks : 0);
  auto run_chunk = [&](uint64_t ci) {
    const uint64_t b = ci * kChunk, e = std::min(rays, b + kChunk);
    Accum& acc = accums.local();
    std::vector<uint64_t>* near_out = sel.split ? &near_by_chunk[ci] : nullptr;
    const TraceSpec& ts = scene_.trace;
    // The inner loop chosen from the scene's effects (TraceConfig) and its source.
    std::visit(
        [&](const auto& src) {
          using Source = std::decay_t<decltype(src)>;
          WithTraceConfig(pr, corr, mesh, draws, [&]<class Cfg>() {
            if constexpr (kPacketSource<Source>) {
              if (plan) {
                TraceRangePackets<Cfg>(im, src, ts, op, plane_index, b, e, sel, acc, near_out,
                                       *plan);
                return;
              }
            }
            TraceRange<Cfg>(im, src, ts, op, plane_index, b, e, sel, acc, near_out);
          });
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
  const bool mesh = impl_->geometry.has_meshes();
  WithTraceConfig(scene_.trace.partial_reflection, false, mesh, false, [&]<class Cfg>() {
    out.ended = TraceObjects<Cfg::kPR, Cfg::kMesh, true>(*impl_, scene_.trace, rng, out.origin,
                                                         out.direction, pol, out.counters,
                                                         &out.fate, {}, &out.optical_path_um);
  });
  return out;
}

Simulator::FieldRay Simulator::TraceFieldRay(const Vec3& origin, const Vec3& direction,
                                             const std::array<std::complex<double>, 3>& field,
                                             uint32_t reflect_mask, int max_events) const {
  RAYMATCH_CHECK(max_events >= 0 && max_events <= FieldRay::kMaxEvents);
  FieldRay r;
  r.origin = origin;
  r.direction = Normalize(direction);
  r.field = field;
  r.segments[0] = {origin, r.direction, 0.0, scene_.medium_index, false};
  r.n_segments = 1;
  TraceSpec trace = scene_.trace;
  trace.max_interactions = max_events;
  FieldTrace ft{&r, reflect_mask, scene_.medium_index};
  RayRng rng(scene_.trace.seed, 0, 0);  // not drawn from: the mask chooses every branch
  Vec3 pol(0, 0, 0);
  TraceCounters counters;
  const bool mesh = impl_->geometry.has_meshes();
  WithTraceConfig(PartialReflection::kOff, false, mesh, false, [&]<class Cfg>() {
    r.ended = TraceObjects<Cfg::kPR, Cfg::kMesh, true, true>(*impl_, trace, rng, r.origin,
                                                             r.direction, pol, counters, &r.fate,
                                                             {}, &r.optical_path_um, &ft);
  });
  return r;
}

uint64_t Simulator::RaysForPhotonTarget(double photons_per_pixel, double* hppr) const {
  // Pilot: the same source and optics without objects (a flat field), fixed seed and stream.
  Scene flat = scene_;
  flat.objects.clear();
  // The same source field as the real scene: its automatic size depends on the objects.
  if (flat.source.field_shape == FieldShape::kDisc)
    flat.source.field_radius_um = impl_->field_radius_um;
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
  SplitRays(*impl_, scene_.trace.seed, plane_index, first, last, center_um, radius_um * radius_um,
            near, far);
}

double Simulator::field_radius_um() const { return impl_->field_radius_um; }

std::pair<Vec3, double> Simulator::EnclosingSphere(
    const std::vector<std::pair<Vec3, double>>& spheres) {
  if (spheres.empty()) return {Vec3(), 0.0};
  Vec3 lo = spheres[0].first, hi = lo;
  for (const auto& [c, r] : spheres) {
    lo = Vec3(std::min(lo.x, c.x - r), std::min(lo.y, c.y - r), std::min(lo.z, c.z - r));
    hi = Vec3(std::max(hi.x, c.x + r), std::max(hi.y, c.y + r), std::max(hi.z, c.z + r));
  }
  const Vec3 centre = (lo + hi) * 0.5;
  double radius = 0;
  for (const auto& [c, r] : spheres) radius = std::max(radius, Length(c - centre) + r);
  return {centre, radius};
}

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
