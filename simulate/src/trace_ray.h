#pragma once
// The scalar path: one ray at a time from its own random stream through the source, the
// objects and the optics (the stages of stages-inl.h on one lane); also the packet path's
// fallback for the rays its stages hand back.
#include <algorithm>
#include <cmath>
#include <type_traits>
#include <vector>

#include "objects.h"
#include "raymatch/core/rng.h"
#include "tracer_impl.h"

namespace raymatch::simulate {

template <class Cfg, class Source>
void TraceSampledRay(const Simulator::Impl& im, const TraceSpec& trace, const Optics& op,
                     uint64_t ray, const Vec3& p, Vec3 d, RayRng& rng, const RaySelection& sel,
                     Accum& acc, std::vector<uint64_t>* near_out);

/// One ray of the plane, from its own stream: the scalar path, and the packet path's fallback.
template <class Cfg, class Source>
void TraceRay(const Simulator::Impl& im, const Source& src, const TraceSpec& trace,
              const Optics& op, uint32_t plane, uint64_t ray, const RaySelection& sel, Accum& acc,
              std::vector<uint64_t>* near_out) {
  TraceCounters& c = acc.counters;
  RayRng rng(trace.seed, plane, ray);
  Vec3 p, d;
  if (!src.Sample(rng, &p, &d)) {
    ++c.fates[int(Fate::kEscaped)];
    return;
  }
  TraceSampledRay<Cfg, Source>(im, trace, op, ray, p, d, rng, sel, acc, near_out);
}

/// TraceRay after the source: the ray leaves p along d; rng stands after the source's words.
template <class Cfg, class Source>
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
  // Motion: a ray that can meet the objects draws its emission time and meets each object
  // where it is then (displaced by v_k t; a mesh through Embree's motion blur at that time).
  // The spectrum likewise: such a ray draws its wavelength (after its time), which sets the
  // index of every dispersive object for it.
  // Cfg::kDraws: the scene moves or disperses (Scene::has_motion, is_spectral); static
  // monochromatic scenes compile none of this.
  bool near = false;
  if constexpr (Cfg::kDraws) near = im.NearAnObject(p, d);
  ObjectShifts shifts;
  const ObjectShifts* moved = nullptr;
  if (near && im.motion) {
    const double t = im.exposure.Offset(rng.Uniform());
    const double max = im.exposure.max_offset_us();
    acc.ray_shift.resize(im.velocity.size());
    for (size_t k = 0; k < im.velocity.size(); ++k) acc.ray_shift[k] = im.velocity[k] * t;
    shifts.shift = acc.ray_shift.data();
    shifts.mesh_time = float(std::clamp((t + max) / (2 * max), 0.0, 1.0));
    moved = &shifts;
    ++c.motion_draws;
  }
  RayObjects seen;
  seen.moved = moved;
  if (near && im.spectral) {
    const double lambda = im.spectrum.Sample(rng.Uniform());
    acc.ray_index.resize(im.index.size());
    for (size_t k = 0; k < im.index.size(); ++k)
      acc.ray_index[k] = im.dispersion[k].law == DispersionLaw::kNone
                             ? im.index[k]
                             : im.dispersion[k].IndexAt(lambda);
    seen.index = acc.ray_index.data();
    if (im.spectral_fields) {
      if (acc.ray_field.empty()) {  // this thread's views of the water fields, made once
        acc.field_views.reserve(im.field.size());
        for (size_t k = 0; k < im.field.size(); ++k) {
          const bool mapped = !im.water_map[k].empty();
          acc.field_views.push_back(mapped ? im.field[k]->AffineView() : IndexField());
          acc.ray_field.push_back(mapped ? &acc.field_views[k] : im.field[k]);
        }
      }
      for (size_t k = 0; k < im.field.size(); ++k)
        if (!im.water_map[k].empty()) {
          const AffineIndexMap m = im.water_map[k].At(lambda);
          acc.field_views[k].SetMap(m.offset, m.scale);
        }
      seen.field = acc.ray_field.data();
    }
    ++c.wavelength_draws;
  }
  Vec3 o = p;
  // (1 / d.z, a product: the packet path reuses the reciprocal for the slopes below)
  if constexpr (!std::is_same_v<Source, PointSource>) {
    const st::V3<L1> q = st::OnPlane<L1>(im.source_z, {p.x, p.y, p.z}, {d.x, d.y, d.z}, 1 / d.z);
    o = Vec3(q.x, q.y, q.z);
  }
  Vec3 pol;
  if constexpr (Cfg::kPR == PartialReflection::kPolarized)
    pol = RandomPerpendicular(d, rng.Uniform());

  Fate fate = Fate::kDetected;
  bool done = false;
  if (has_objects) {
    done = TraceObjects<Cfg::kPR, Cfg::kMesh>(im, trace, rng, o, d, pol, c, &fate, seen);
  }
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
  if constexpr (Cfg::kCorrector) ++c.corrector_tests;
  st::OpticalTrain<L1, Cfg::kCorrector>(op, beam, out, [&] { return rng.Uniform(); });
  if (!out.settled) {
    double u, v;
    st::SensorPoint<L1>(op, beam, u, v);
    if (op.psf_sigma_sensor > 0) {  // two independent normal offsets (stages-inl.h)
      const double u1 = rng.Uniform();
      const double u2 = rng.Uniform();
      double du, dv;
      st::GaussianPair<L1>(u1, u2, op.psf_sigma_sensor, du, dv);
      u += du;
      v += dv;
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

template <class Cfg, class Source>
void TraceRange(const Simulator::Impl& im, const Source& src, const TraceSpec& trace,
                const Optics& op, uint32_t plane, uint64_t begin, uint64_t end,
                const RaySelection& sel, Accum& acc, std::vector<uint64_t>* near_out) {
  ForEachSelectedRay(sel, begin, end, [&](uint64_t ray) {
    TraceRay<Cfg>(im, src, trace, op, plane, ray, sel, acc, near_out);
  });
}

}  // namespace raymatch::simulate
