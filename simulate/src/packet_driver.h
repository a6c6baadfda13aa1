#pragma once
// The packet path's driver: a chunk's rays in batches through the packet stages (packet.h), the
// sphere stage's queue, and the rays the stages hand back to the scalar path (trace_ray.h).
#include <optional>
#include <type_traits>
#include <vector>

#include "packet.h"
#include "trace_ray.h"
#include "tracer_impl.h"

namespace raymatch::simulate {

/// The sources the packet stages sample (which Source types get a packet instantiation).
template <class Source>
constexpr bool kPacketSource =
    std::is_same_v<Source, ConeSource> || std::is_same_v<Source, CollimatedSource> ||
    std::is_same_v<Source, LightFieldSource>;

/// Whether the packet path takes the scene: the one place that decides it (Effects lists it).
PacketSupport PacketSupportFor(const Simulator::Impl& im);

struct PacketPlan {
  packet::SourceParams source;
  packet::NearParams near;
  /// Rays that meet the scene's one homogeneous sphere go through the sphere stage too.
  std::optional<packet::SphereParams> sphere;
};

/// The packet stages' parameters for a scene the packet path takes (PacketSupportFor).
PacketPlan MakePacketPlan(const Simulator::Impl& im, const Scene& scene, PartialReflection pr,
                          const RaySelection& sel);

/// The corrector's uniform (Rays::u) for the lanes still open (out 0): the word `skip` past the
/// lane's cursor. A lane whose words ran out goes back to the scalar path from its stream.
void CorrectorDraws(packet::Rays& r, size_t n, int skip);

/// The camera PSF's offsets for the lanes still open: the two words `skip` past the lane's
/// cursor (TraceRay draws them after the corrector's). Out of words: back to the scalar path.
void PsfDraws(packet::Rays& r, size_t n, int skip, double sigma);

/// A batch's outcomes after NearTestAndOptics or OpticsAfterObjects into the image and the fate
/// counters; returns how many of its rays reached the optics.
uint64_t CountBatch(const packet::Rays& r, size_t n, Accum& acc);

/// The queued rays that meet the sphere, through the sphere stage and on through the optics;
/// those that run out of random words are traced again on the scalar path.
template <class Cfg, class Source>
void TraceSphereQueue(const Simulator::Impl& im, const Source& src, const TraceSpec& trace,
                      const Optics& op, uint32_t plane, const RaySelection& sel, Accum& acc,
                      std::vector<uint64_t>* near_out, const PacketPlan& plan) {
  packet::Rays& q = *acc.sphere_queue.rays;
  const size_t m = acc.sphere_queue.count;
  acc.sphere_queue.count = 0;
  // All their words (the batch made the third Philox block only where the source needed it).
  packet::PhiloxWords(trace.seed, plane, q.ids, m, &q);
  packet::Sphere(*plan.sphere, m, &q);
  if constexpr (Cfg::kCorrector)
    CorrectorDraws(q, m, 0);  // the corrector's draw follows the sphere's
  if (op.psf_sigma_sensor > 0) PsfDraws(q, m, Cfg::kCorrector ? 1 : 0, op.psf_sigma_sensor);
  packet::OpticsAfterObjects(op, m, &q);
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
  if constexpr (Cfg::kCorrector) c.corrector_tests += optics;
  for (size_t k = 0; k < q.num_handed_back; ++k)
    TraceRay<Cfg>(im, src, trace, op, plane, q.ids[static_cast<size_t>(q.handed_back[k])], sel, acc,
                  near_out);
}

/// One batch of packet::kBatch rays (at most; their indices in acc.rays->ids): the source, the
/// near test and the optics in packets, then each ray the packets handed back, in ray order.
template <class Cfg, class Source>
void TraceBatch(const Simulator::Impl& im, const Source& src, const TraceSpec& trace,
                const Optics& op, uint32_t plane, const RaySelection& sel, Accum& acc,
                std::vector<uint64_t>* near_out, const PacketPlan& plan, size_t n) {
  packet::Rays& r = *acc.rays;
  // Words drawn after the source by a ray that meets nothing: polarisation, corrector.
  constexpr int kPolWords = Cfg::kPR == PartialReflection::kPolarized ? 1 : 0;
  constexpr int kExtraWords = kPolWords + (Cfg::kCorrector ? 1 : 0);
  const bool psf = op.psf_sigma_sensor > 0;  // two more words: the PSF's offset
  packet::SampleSource(plan.source, trace.seed, plane, r.ids, n, kExtraWords + (psf ? 2 : 0), &r);
  if constexpr (std::is_same_v<Source, LightFieldSource>)
    packet::Tabulated(*plan.source.table, n, &r);
  // The corrector's draw follows the source's (and the polarisation's) words.
  if constexpr (Cfg::kCorrector) CorrectorDraws(r, n, kPolWords);
  if (psf) PsfDraws(r, n, kExtraWords, op.psf_sigma_sensor);
  packet::NearTestAndOptics(plan.near, op, n, &r);
  const uint64_t optics = CountBatch(r, n, acc);
  TraceCounters& c = acc.counters;
  const uint64_t queries = im.geometry.empty() ? 0 : 1;  // the one query that found nothing
  c.shape_queries += queries * optics;                   // rays that met nothing: one query each
  if constexpr (Cfg::kMesh) c.mesh_queries += optics;
  if constexpr (Cfg::kCorrector) c.corrector_tests += optics;
  for (size_t k = 0; k < r.num_handed_back; ++k) {  // in ray order: the near list stays ascending
    const size_t i = static_cast<size_t>(r.handed_back[k]);
    const uint64_t ray = r.ids[i];
    if (r.out[i] == packet::kNear) {
      near_out->push_back(ray);
    } else if (r.cursor[i] < 0) {  // the batch's words ran out: all again from the stream
      TraceRay<Cfg>(im, src, trace, op, plane, ray, sel, acc, near_out);
    } else if (plan.sphere) {  // near the sphere: queued for the sphere stage
      if (acc.sphere_queue.Push(r, i))
        TraceSphereQueue<Cfg>(im, src, trace, op, plane, sel, acc, near_out, plan);
    } else {  // near an object: on from the packet's source sample and the stream's cursor
      RayRng rng(trace.seed, plane, ray);
      rng.SkipTo(static_cast<uint64_t>(r.cursor[i]));
      TraceSampledRay<Cfg, Source>(im, trace, op, ray, Vec3(r.px[i], r.py[i], r.pz[i]),
                                   Vec3(r.dx[i], r.dy[i], r.dz[i]), rng, sel, acc, near_out);
    }
  }
}

/// TraceRange in batches of packet::kBatch rays: the same rays, counts and counters.
template <class Cfg, class Source>
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
      TraceBatch<Cfg>(im, src, trace, op, plane, sel, acc, near_out, plan, n);
      n = 0;
    }
  });
  if (n > 0) TraceBatch<Cfg>(im, src, trace, op, plane, sel, acc, near_out, plan, n);
  if (acc.sphere_queue.count > 0)
    TraceSphereQueue<Cfg>(im, src, trace, op, plane, sel, acc, near_out, plan);
}

}  // namespace raymatch::simulate
