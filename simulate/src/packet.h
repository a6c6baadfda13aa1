#pragma once
// SIMD packet stages of the tracer (packet.cpp, Google Highway with run-time dispatch).
//
// A batch of up to kBatch rays is traced stage by stage in structure-of-arrays form: the first
// kWords words of every ray's Philox stream, the source sample, and for rays whose straight line
// passes no object, the whole way through the corrector and the ideal lenses to a pixel. The
// physical stages (disc samples, source directions, the near test, the optics) are the scalar
// path's own, instantiated for vectors (stages-inl.h); the sphere stage follows the scalar
// TraceObjects operation by operation. All of it in IEEE double without fused multiply-adds (the
// files are built with -ffp-contract=off), so a ray traced here lands in the same pixel with the
// same fate as on the scalar path, bit for bit. Where the scene is one homogeneous sphere, the
// rays that meet it go through the sphere stage (Sphere); other rays that meet an object go on
// from their packet source sample on the scalar path; rays that need more random words than the
// batch holds are traced again from their own stream.
#include <cstddef>
#include <cstdint>
#include <vector>

#include "stages.h"

namespace raymatch::simulate::packet {

inline constexpr size_t kBatch = 256;  ///< rays per batch: a multiple of every vector length
inline constexpr int kWords = 12;      ///< random words per ray made up front (3 Philox blocks)
inline constexpr int kMaxBounds = 8;   ///< objects the near test takes; more: scalar path

/// The light field's angular table (a Distribution2D, sampling.h) laid out for the packet
/// stage: the marginal over rows and every row's conditional, each a cdf (n + 1 values) and a
/// guide table, the rows' back to back. Built once per Simulator.
struct Table2D {
  int width = 0, height = 0;
  int64_t row_guide_size = 0, marginal_guide_size = 0;
  std::vector<double> marginal_cdf, row_cdf;       // height + 1; height x (width + 1)
  std::vector<int64_t> marginal_guide, row_guide;  // marginal_guide_size; height x row_guide_size
  double extent = 0;                               // direction cosines span [-extent, extent]
};

/// A source the packet stage samples: a field (disc or rectangle without a map) and a direction
/// (cone, collimated, or drawn by the caller from two uniforms: the tabulated light field).
struct SourceParams {
  enum Direction { kCone, kCollimated, kTabulated };
  bool disc_field = true;
  double radius = 0, half_w = 0, half_h = 0;
  double center[3] = {0, 0, 0};
  Direction direction = kCone;
  const Table2D* table = nullptr;  ///< kTabulated: the angular table
  double sin_max = 0;
  double dir[3] = {0, 0, 1};
};

/// The near test before the optics: rays whose straight line passes within an object's
/// bounding sphere (with a margin) leave the packet for the scalar path or the sphere stage.
struct NearParams {
  double source_z = 0;
  int num_bounds = 0;  ///< object bounding spheres (centre, squared radius with a margin)
  double bound_c[kMaxBounds][3] = {};
  double bound_r2[kMaxBounds] = {};
  bool split = false;  ///< TraceFarRays: report rays whose line passes within the sphere
  double split_c[3] = {0, 0, 0};
  double split_r2 = 0;
};

/// Image elements the packet path needs beyond the nx * ny pixels (Rays::slot).
inline constexpr size_t kSpareSlots = 8;

/// One batch, structure of arrays (about 60 KiB; one per worker thread).
struct Rays {
  uint32_t words[kWords][kBatch];
  int64_t cursor[kBatch];  ///< next unused word of the ray's stream; -1: the words ran out
  double px[kBatch], py[kBatch], pz[kBatch];  ///< source sample on its plane
  double dx[kBatch], dy[kBatch], dz[kBatch];  ///< unit direction
  double u[kBatch], v[kBatch];  ///< tabulated direction's uniforms; u: then the corrector draw
  double psf_du[kBatch], psf_dv[kBatch];  ///< the camera PSF's offset at the sensor (PsfDraws)
  double out[kBatch];  ///< pixel index, FateCode(fate), kScalar or kNear (stages.h)
  // The optics' summary of out[0, n): the image element each lane adds one to (its pixel, or
  // for every other outcome a spare element past the image, npix + lane % 8, so that the adds
  // never wait on each other), the lanes for the scalar path or the near list (kScalar, kNear)
  // in lane order, and how many lanes got each fate (counts[int(fate)]).
  int64_t slot[kBatch];
  int64_t handed_back[kBatch];
  size_t num_handed_back = 0;
  uint64_t counts[kNumFates] = {};
  // The sphere stage's work per lane (TraceCounters' meanings), and the rays' indices.
  int64_t queries[kBatch], interface_events[kBatch], fresnel[kBatch], path_class[kBatch];
  int64_t events[kBatch];  ///< > 0: the ray met the sphere
  uint64_t ids[kBatch];
};

/// One homogeneous sphere in a medium: the scene the sphere stage traces.
struct SphereParams {
  double center[3] = {0, 0, 0};
  double radius2 = 0, index = 1, medium = 1, epsilon = 0, source_z = 0;
  int max_interactions = 100;
  bool fresnel = false;  ///< unpolarised partial reflection (else refraction and TIR only)
};

/// Rays::words for the rays' streams (RayRng(seed, stream, rays[i]): words 0 .. kWords-1).
void PhiloxWords(uint64_t seed, uint32_t stream, const uint64_t* rays, size_t n, Rays* r);
/// Source samples from the rays' streams: p, d (not for kTabulated), cursor; u, v for
/// kTabulated. Makes the words it reads (a Philox block at a time, as needed), and those up to
/// cursor + extra_words - 1 that the caller reads next.
void SampleSource(const SourceParams& s, uint64_t seed, uint32_t stream, const uint64_t* rays,
                  size_t n, int extra_words, Rays* r);
/// LightFieldSource::Direction for the lanes with out 0: d from the uniforms (u, v) through the
/// table (Distribution2D::Sample), or out = FateCode(escaped) for a direction beyond the unit
/// circle.
void Tabulated(const Table2D& t, size_t n, Rays* r);
/// Rays::out and its summary from p, d (and u: the corrector's uniform); lanes whose out is
/// already negative on entry keep it (the caller marks rejected or out-of-words rays).
void NearTestAndOptics(const NearParams& near, const Optics& o, size_t n, Rays* r);
/// Rays from their source samples (p, d, cursor) through one homogeneous sphere until they
/// leave it: Rays::out 0 (p, d: where and how it left; cursor after its draws), the code of
/// escaped, interaction_cap or lost_inside, or kScalar (out of words); the per-lane work counters.
void Sphere(const SphereParams& s, size_t n, Rays* r);
/// The optics for rays that left the objects at p along d (no source plane, no near tests).
void OpticsAfterObjects(const Optics& o, size_t n, Rays* r);
/// The uniforms (u1, u2) in psf_du, psf_dv of the first n rays, replaced by two independent
/// normal offsets of standard deviation sigma (stages-inl.h, GaussianPair).
void GaussianOffsets(double sigma, size_t n, Rays* r);
/// The instruction set chosen at run time, e.g. "AVX3" (Highway's target name).
const char* TargetName();

}  // namespace raymatch::simulate::packet
