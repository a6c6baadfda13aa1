// The tracer's stages, written once for the scalar path and the SIMD packet path.
//
// Each stage is a template over a lane type L: the scalar path instantiates it with ScalarLanes
// (stages.h: double and bool, one ray), the packet path with VecLanes below (a Highway vector
// of doubles and its mask). This is Google Highway's -inl.h pattern: packet.cpp includes this
// file once per instruction set (hwy/foreach_target.h), so every target compiles the stages with
// its own vector width; the scalar files include it once (the static target; they instantiate
// the ScalarLanes stages only). The images of the two paths agree because they run the same
// code; keep the operations in their order and never contract a * b + c (every file that
// includes this one is built with -ffp-contract=off).
//
// Stages are written mask-style: every lane runs every operation, and a stage marks a lane's
// fate with Outcome::Mark, which keeps the first fate a lane gets. L::Stop lets the one-lane
// instantiation leave a stage as soon as its ray is settled (as a scalar loop would); vectors
// never stop early.

// Per-target include guard (Highway's pattern: toggled for each target foreach_target.h visits).
#if defined(RAYMATCH_SIMULATE_STAGES_INL_H_) == defined(HWY_TARGET_TOGGLE)
#ifdef RAYMATCH_SIMULATE_STAGES_INL_H_
#undef RAYMATCH_SIMULATE_STAGES_INL_H_
#else
#define RAYMATCH_SIMULATE_STAGES_INL_H_
#endif

#include <hwy/highway.h>

#include <cmath>
#include <cstdint>

#include "stages.h"

HWY_BEFORE_NAMESPACE();
namespace raymatch::simulate::stages {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

/// The packet path's lanes: as many doubles as this target's vectors hold.
struct VecLanes {
  using D = hn::ScalableTag<double>;
  using DI = hn::RebindToSigned<D>;
  using V = hn::Vec<D>;
  using M = hn::Mask<D>;
  using I = hn::Vec<DI>;
  using MI = hn::Mask<DI>;
  static constexpr bool kOneLane = false;
  static HWY_INLINE V Set(double x) { return hn::Set(D(), x); }
  static HWY_INLINE V Add(V a, V b) { return hn::Add(a, b); }
  static HWY_INLINE V Sub(V a, V b) { return hn::Sub(a, b); }
  static HWY_INLINE V Mul(V a, V b) { return hn::Mul(a, b); }
  static HWY_INLINE V Div(V a, V b) { return hn::Div(a, b); }
  static HWY_INLINE V Neg(V a) { return hn::Neg(a); }
  static HWY_INLINE V Sqrt(V a) { return hn::Sqrt(a); }
  static HWY_INLINE V Floor(V a) { return hn::Floor(a); }
  static HWY_INLINE M Lt(V a, V b) { return hn::Lt(a, b); }
  static HWY_INLINE M Le(V a, V b) { return hn::Le(a, b); }
  static HWY_INLINE M Gt(V a, V b) { return hn::Gt(a, b); }
  static HWY_INLINE M Ge(V a, V b) { return hn::Ge(a, b); }
  static HWY_INLINE M Eq(V a, V b) { return hn::Eq(a, b); }
  static HWY_INLINE V Select(M m, V a, V b) { return hn::IfThenElse(m, a, b); }
  static HWY_INLINE M And(M a, M b) { return hn::And(a, b); }
  static HWY_INLINE M Or(M a, M b) { return hn::Or(a, b); }
  static HWY_INLINE M AndNot(M not_a, M b) { return hn::AndNot(not_a, b); }
  static HWY_INLINE M Not(M a) { return hn::Not(a); }
  static HWY_INLINE M False() { return hn::Lt(hn::Zero(D()), hn::Zero(D())); }
  static HWY_INLINE M True() { return hn::Eq(hn::Zero(D()), hn::Zero(D())); }
  static HWY_INLINE bool None(M m) { return hn::AllFalse(D(), m); }
  static HWY_INLINE bool Stop(M) { return false; }
  static HWY_INLINE I ISet(int64_t x) { return hn::Set(DI(), x); }
  static HWY_INLINE I IAdd(I a, I b) { return hn::Add(a, b); }
  static HWY_INLINE I ISub(I a, I b) { return hn::Sub(a, b); }
  static HWY_INLINE MI ILt(I a, I b) { return hn::Lt(a, b); }
  static HWY_INLINE MI IGt(I a, I b) { return hn::Gt(a, b); }
  static HWY_INLINE MI IEq(I a, I b) { return hn::Eq(a, b); }
  static HWY_INLINE I ISelect(MI m, I a, I b) { return hn::IfThenElse(m, a, b); }
  static HWY_INLINE MI IAnd(MI a, MI b) { return hn::And(a, b); }
  static HWY_INLINE MI ToIMask(M m) { return hn::RebindMask(DI(), m); }
  static HWY_INLINE M ToMask(MI m) { return hn::RebindMask(D(), m); }
  static HWY_INLINE bool INone(MI m) { return hn::AllFalse(DI(), m); }
  static HWY_INLINE I ToInt(V x) { return hn::ConvertTo(DI(), x); }
  static HWY_INLINE V ToDouble(I x) { return hn::ConvertTo(D(), x); }
  static HWY_INLINE V Gather(const double* p, I i) { return hn::GatherIndex(D(), p, i); }
  static HWY_INLINE I GatherI(const int64_t* p, I i) { return hn::GatherIndex(DI(), p, i); }
};

template <class L>
struct V3 {
  typename L::V x, y, z;
};

/// a.x b.x + a.y b.y + a.z b.z (Vec3's Dot, in its order).
template <class L>
HWY_INLINE typename L::V Dot(const V3<L>& a, const V3<L>& b) {
  return L::Add(L::Add(L::Mul(a.x, b.x), L::Mul(a.y, b.y)), L::Mul(a.z, b.z));
}

// ---------------------------------------------------------------- outcomes

/// Each lane's fate, kept by the first stage that marks it: the one way a stage ends a ray.
/// `code` holds packet::FateCode(fate) (or a packet-only code: kScalar, kNear).
template <class L>
struct Outcome {
  typename L::M settled;
  typename L::V code;
  /// Every lane open (no default member initialisers: they would be compiled outside the
  /// target's attributes).
  static HWY_INLINE Outcome Open() { return {L::False(), L::Set(0.0)}; }
  HWY_INLINE void Mark(typename L::M m, Fate f) { MarkCode(m, packet::FateCode(f)); }
  HWY_INLINE void MarkCode(typename L::M m, double c) {
    const typename L::M now = L::AndNot(settled, m);
    code = L::Select(now, L::Set(c), code);
    settled = L::Or(settled, now);
  }
};

/// The fate of a settled one-lane outcome (packet::FateCode inverted).
inline Fate FateOf(double code) { return static_cast<Fate>(static_cast<int>(-code)); }

// ---------------------------------------------------------------- sources

/// One try of SampleUnitDisc from two centred words (word - 2^31, an exact double): a = 2u - 1
/// and b = 2u' - 1 for u = word 2^-32 (every step exact, so equal to centred 2^-31), and whether
/// (a, b) lies inside the unit disc (a a + b b < 1; a try at or beyond it is rejected).
template <class L>
HWY_INLINE typename L::M DiscTry(typename L::V centred_a, typename L::V centred_b, typename L::V& a,
                                 typename L::V& b) {
  a = L::Mul(centred_a, L::Set(0x1p-31));
  b = L::Mul(centred_b, L::Set(0x1p-31));
  return L::Lt(L::Add(L::Mul(a, a), L::Mul(b, b)), L::Set(1.0));
}

/// The disc field's point for the unit-disc sample (a, b): center + (a radius, b radius, 0).
template <class L>
HWY_INLINE V3<L> DiscFieldPoint(const double center[3], double radius, typename L::V a,
                                typename L::V b) {
  return {L::Add(L::Set(center[0]), L::Mul(a, L::Set(radius))),
          L::Add(L::Set(center[1]), L::Mul(b, L::Set(radius))), L::Set(center[2] + 0.0)};
}

/// The cone source's direction for the unit-disc sample (a, b): uniform in direction cosines
/// u = a sin_max, v = b sin_max, and w = sqrt(1 - u u - v v).
template <class L>
HWY_INLINE V3<L> ConeDirection(typename L::V a, typename L::V b, double sin_max) {
  const typename L::V u = L::Mul(a, L::Set(sin_max)), v = L::Mul(b, L::Set(sin_max));
  return {u, v, L::Sqrt(L::Sub(L::Sub(L::Set(1.0), L::Mul(u, u)), L::Mul(v, v)))};
}

/// The light field's direction for its table's sample (x, y) in [0, 1)^2: u = (2 x - 1) extent,
/// v = (1 - 2 y) extent. Returns the lanes beyond the unit circle (no direction; d.z = 1 there).
template <class L>
HWY_INLINE typename L::M TabulatedDirection(typename L::V x, typename L::V y, double extent,
                                            V3<L>& d) {
  const typename L::V one = L::Set(1.0), two = L::Set(2.0), e = L::Set(extent);
  const typename L::V u = L::Mul(L::Sub(L::Mul(two, x), one), e);
  const typename L::V v = L::Mul(L::Sub(one, L::Mul(two, y)), e);
  const typename L::V w2 = L::Sub(L::Sub(one, L::Mul(u, u)), L::Mul(v, v));
  const typename L::M beyond = L::Le(w2, L::Set(0.0));
  d = {u, v, L::Sqrt(L::Select(beyond, one, w2))};
  return beyond;
}

/// Where the straight ray from p along d crosses plane z0: p + d ((z0 - p.z) inv_dz), with
/// inv_dz = 1 / d.z (the source plane before the objects).
template <class L>
HWY_INLINE V3<L> OnPlane(double z0, const V3<L>& p, const V3<L>& d, typename L::V inv_dz) {
  const typename L::V s = L::Mul(L::Sub(L::Set(z0), p.z), inv_dz);
  return {L::Add(p.x, L::Mul(d.x, s)), L::Add(p.y, L::Mul(d.y, s)), L::Add(p.z, L::Mul(d.z, s))};
}

/// Distribution1D::Sample: u in [0, 1) to x in [0, 1) over the piecewise-constant density with
/// n bins whose cdf (n + 1 values) starts at cdf + cdf_at and whose guide table (g entries, a
/// power of two; entry k: the largest i with cdf[i] <= k / g) at guide + guide_at; *bin gets
/// the bin. From the guide's entry for u's bucket forward to the largest i with cdf[i] <= u,
/// then back out of empty bins, then linear within the bin.
template <class L, class G>
HWY_INLINE typename L::V Sample1D(const double* cdf, typename L::I cdf_at, const G* guide,
                                  typename L::I guide_at, int n, int64_t g, typename L::V u,
                                  typename L::I* bin) {
  using V = typename L::V;
  using I = typename L::I;
  const V zero = L::Set(0.0), one = L::Set(1.0);
  const I one_i = L::ISet(1), n_i = L::ISet(n);
  // k = u > 0 ? min(int(u g), g - 1) : 0   (u g is exact: g is a power of two)
  I k = L::ToInt(L::Mul(u, L::Set(double(g))));
  k = L::ISelect(L::IGt(k, L::ISet(g - 1)), L::ISet(g - 1), k);
  k = L::ISelect(L::ToIMask(L::Gt(u, zero)), k, L::ISet(0));
  I i = L::GatherI(guide, L::IAdd(guide_at, k));
  for (;;) {  // while (i + 1 <= n && cdf[i + 1] <= u) ++i
    const auto room = L::ILt(i, n_i);
    const V next = L::Gather(cdf, L::IAdd(cdf_at, L::ISelect(room, L::IAdd(i, one_i), i)));
    const auto step = L::IAnd(room, L::ToIMask(L::Le(next, u)));
    if (L::INone(step)) break;
    i = L::ISelect(step, L::IAdd(i, one_i), i);
  }
  // i = clamp(i, 0, n - 1); while (i > 0 && cdf[i + 1] - cdf[i] <= 0) --i: no empty bin
  i = L::ISelect(L::ILt(i, L::ISet(0)), L::ISet(0), i);
  i = L::ISelect(L::IGt(i, L::ISet(n - 1)), L::ISet(n - 1), i);
  V lo, hi;
  for (;;) {
    lo = L::Gather(cdf, L::IAdd(cdf_at, i));
    hi = L::Gather(cdf, L::IAdd(cdf_at, L::IAdd(i, one_i)));
    const auto back = L::IAnd(L::IGt(i, L::ISet(0)), L::ToIMask(L::Le(L::Sub(hi, lo), zero)));
    if (L::INone(back)) break;
    i = L::ISelect(back, L::ISub(i, one_i), i);
  }
  // du = width > 0 ? (u - cdf[i]) / width : 0.5; x = min((i + clamp(du, 0, 1)) / n, 1 - 2^-53)
  const V width = L::Sub(hi, lo);
  const V du = L::Select(L::Gt(width, zero), L::Div(L::Sub(u, lo), width), L::Set(0.5));
  const V clamped = L::Select(L::Lt(du, zero), zero, L::Select(L::Lt(one, du), one, du));
  const V x = L::Div(L::Add(L::ToDouble(i), clamped), L::Set(double(n)));
  const V below_one = L::Set(0x1.fffffffffffffp-1);  // std::nextafter(1.0, 0.0)
  *bin = i;
  return L::Select(L::Lt(below_one, x), below_one, x);
}

// ---------------------------------------------------------------- objects

/// Squared distance from centre c to the straight line through p along unit d: Dot(w, w) - t t
/// with w = c - p, t = Dot(w, d). The near test of both paths (and of the fit's split).
template <class L>
HWY_INLINE typename L::V LineDistance2(const double c[3], const V3<L>& p, const V3<L>& d) {
  const V3<L> w{L::Sub(L::Set(c[0]), p.x), L::Sub(L::Set(c[1]), p.y), L::Sub(L::Set(c[2]), p.z)};
  const typename L::V t = Dot(w, d);
  return L::Sub(Dot(w, w), L::Mul(t, t));
}

/// Snell refraction of unit d at unit normal nf facing the incoming ray, eta = n1 / n2 and
/// cos_i = -Dot(d, nf): sin2_t = eta^2 max(0, 1 - cos_i^2); t = d eta + nf (eta cos_i - cos_t).
/// Returns the lanes with total internal reflection (sin2_t >= 1; t is not a direction there).
template <class L>
HWY_INLINE typename L::M Refract(const V3<L>& d, const V3<L>& nf, typename L::V eta,
                                 typename L::V cos_i, V3<L>& t, typename L::V& cos_t) {
  const typename L::V zero = L::Set(0.0), one = L::Set(1.0);
  const typename L::V c2 = L::Sub(one, L::Mul(cos_i, cos_i));
  const typename L::V sin2_t = L::Mul(L::Mul(eta, eta), L::Select(L::Lt(zero, c2), c2, zero));
  const typename L::M tir = L::Ge(sin2_t, one);
  cos_t = L::Sqrt(L::Select(tir, zero, L::Sub(one, sin2_t)));
  const typename L::V k = L::Sub(L::Mul(eta, cos_i), cos_t);
  t = {L::Add(L::Mul(d.x, eta), L::Mul(nf.x, k)), L::Add(L::Mul(d.y, eta), L::Mul(nf.y, k)),
       L::Add(L::Mul(d.z, eta), L::Mul(nf.z, k))};
  return tir;
}

/// The unpolarised Fresnel reflectance (rs^2 + rp^2) / 2 from n1 into n2 (Born & Wolf signs):
/// rs = (n1 cos_i - n2 cos_t) / (n1 cos_i + n2 cos_t), rp = (n2 cos_i - n1 cos_t) / (...).
template <class L>
HWY_INLINE typename L::V FresnelReflectance(typename L::V n1, typename L::V n2, typename L::V cos_i,
                                            typename L::V cos_t) {
  const typename L::V a1 = L::Mul(n1, cos_i), a2 = L::Mul(n2, cos_t);
  const typename L::V rs = L::Div(L::Sub(a1, a2), L::Add(a1, a2));
  const typename L::V b1 = L::Mul(n2, cos_i), b2 = L::Mul(n1, cos_t);
  const typename L::V rp = L::Div(L::Sub(b1, b2), L::Add(b1, b2));
  return L::Mul(L::Set(0.5), L::Add(L::Mul(rs, rs), L::Mul(rp, rp)));
}

/// A ray's state among the objects, per lane: its interface events, how many objects it is inside
/// (the scalar path keeps their indices beside the count), and the path class of its first
/// departure from the first object hit (TraceCounters::path_class; -1 until it is known) with the
/// internal reflections counted until then.
template <class L>
struct ObjectPath {
  typename L::I events, interface_events, depth, internal, path_class;
  typename L::M classified;
  static HWY_INLINE ObjectPath Start() {
    const typename L::I zero = L::ISet(0);
    return {zero, zero, zero, zero, L::ISet(-1), L::False()};
  }
};

/// The surface an interface event meets, as the incoming ray sees it: whether it enters the
/// object (Dot(d, n) < 0), the normal facing the ray (nf = n entering, -n leaving), and
/// cos_i = -Dot(d, nf).
template <class L>
struct FacedSurface {
  typename L::M entering;
  V3<L> nf;
  typename L::V cos_i;
};

/// What an interface event did to each lane's object stack: pushed the surface's object
/// (transmitted into it) or popped it (transmitted out of it).
template <class L>
struct StackMoves {
  typename L::M push, pop;
};

/// One interface event of the objects stage, for both paths: the lanes `active` reach the
/// surface point hp along unit d, where the surface has the unit normal n (pointing out of its
/// object); `inside`: the surface's object is on the lane's stack. In order:
///  1. ++events; a lane beyond max_interactions ends (interaction cap);
///  2. the surface faced (FacedSurface);
///  3. indices(face, n1, n2): the indices before and beyond the surface;
///  4. Refract from n1 into n2: total internal reflection reflects;
///  5. reflect = draw(tir, face, n1, n2, cos_t, t, active, out): the partial-reflection branch
///     (the scalar path's random stream, the packet path's words; a draw may end lanes);
///  6. the ray leaves: d = Normalize(reflect ? Reflect(d, nf) : t) from o = hp + nf eps
///     (reflected) or hp - nf eps (transmitted), eps the surface's offset;
///  7. transmitted into the object pushes it (a lane already kMaxNesting deep ends: lost inside),
///     transmitted out of it pops it;
///  8. the path class of the first departure: reflected at the first entry, class 0; reflected
///     from inside, one more internal reflection; leaving, class 1 + internal reflections (the
///     last class holds the rest).
/// `active` loses the lanes that end here; `out` gets their fates.
template <class L, class Indices, class Draw>
HWY_INLINE StackMoves<L> InterfaceEvent(int max_interactions, const V3<L>& hp, const V3<L>& n,
                                        typename L::V eps, typename L::M inside, V3<L>& d, V3<L>& o,
                                        typename L::M& active, ObjectPath<L>& path, Outcome<L>& out,
                                        Indices&& indices, Draw&& draw) {
  using V = typename L::V;
  using M = typename L::M;
  const typename L::I one_i = L::ISet(1);
  const typename L::MI counted = L::ToIMask(active);
  path.events = L::ISelect(counted, L::IAdd(path.events, one_i), path.events);
  const M capped = L::And(active, L::ToMask(L::IGt(path.events, L::ISet(max_interactions))));
  out.Mark(capped, Fate::kInteractionCap);
  active = L::AndNot(capped, active);
  if (L::None(active)) return {L::False(), L::False()};
  const typename L::MI on = L::ToIMask(active);
  path.interface_events =
      L::ISelect(on, L::IAdd(path.interface_events, one_i), path.interface_events);
  FacedSurface<L> face;
  const V zero = L::Set(0.0);
  face.entering = L::Lt(Dot(d, n), zero);
  face.nf = {L::Select(face.entering, n.x, L::Neg(n.x)), L::Select(face.entering, n.y, L::Neg(n.y)),
             L::Select(face.entering, n.z, L::Neg(n.z))};
  face.cos_i = L::Neg(Dot(d, face.nf));
  V n1, n2;
  indices(face, n1, n2);
  V3<L> t;
  V cos_t;
  const M tir = Refract<L>(d, face.nf, L::Div(n1, n2), face.cos_i, t, cos_t);
  const M reflect = draw(tir, face, n1, n2, cos_t, t, active, out);
  // The ray leaves (Reflect and Normalize of interfaces.h and vec.h, in their order).
  const V two_dn = L::Mul(L::Set(2.0), Dot(d, face.nf));
  const V3<L> r{L::Sub(d.x, L::Mul(face.nf.x, two_dn)), L::Sub(d.y, L::Mul(face.nf.y, two_dn)),
                L::Sub(d.z, L::Mul(face.nf.z, two_dn))};
  const V3<L> e{L::Select(reflect, r.x, t.x), L::Select(reflect, r.y, t.y),
                L::Select(reflect, r.z, t.z)};
  const V len = L::Sqrt(Dot(e, e));
  const V3<L> a{L::Mul(face.nf.x, eps), L::Mul(face.nf.y, eps), L::Mul(face.nf.z, eps)};
  d = {L::Select(active, L::Div(e.x, len), d.x), L::Select(active, L::Div(e.y, len), d.y),
       L::Select(active, L::Div(e.z, len), d.z)};
  o = {L::Select(active, L::Select(reflect, L::Add(hp.x, a.x), L::Sub(hp.x, a.x)), o.x),
       L::Select(active, L::Select(reflect, L::Add(hp.y, a.y), L::Sub(hp.y, a.y)), o.y),
       L::Select(active, L::Select(reflect, L::Add(hp.z, a.z), L::Sub(hp.z, a.z)), o.z)};
  // The object stack.
  const M transmit = L::AndNot(reflect, active);
  const M push = L::And(transmit, face.entering);
  const M deepest = L::And(push, L::ToMask(L::IEq(path.depth, L::ISet(kMaxNesting))));
  out.Mark(deepest, Fate::kLostInside);
  active = L::AndNot(deepest, active);
  const StackMoves<L> moves{L::And(push, active),
                            L::And(L::AndNot(face.entering, transmit), inside)};
  path.depth = L::ISelect(L::ToIMask(moves.push), L::IAdd(path.depth, one_i), path.depth);
  path.depth = L::ISelect(L::ToIMask(moves.pop), L::ISub(path.depth, one_i), path.depth);
  // The path class of the first departure.
  const M open = L::AndNot(path.classified, active);
  const M first_reflection =
      L::And(L::And(open, reflect), L::And(face.entering, L::ToMask(L::IEq(path.events, one_i))));
  path.path_class = L::ISelect(L::ToIMask(first_reflection), L::ISet(0), path.path_class);
  const M internal = L::AndNot(first_reflection, L::AndNot(face.entering, L::And(open, reflect)));
  path.internal = L::ISelect(L::ToIMask(internal), L::IAdd(path.internal, one_i), path.internal);
  const M leaves = L::AndNot(face.entering, L::AndNot(reflect, open));
  const typename L::I cls = L::IAdd(path.internal, one_i), last = L::ISet(kNumPathClasses - 1);
  path.path_class =
      L::ISelect(L::ToIMask(leaves), L::ISelect(L::IGt(cls, last), last, cls), path.path_class);
  path.classified = L::Or(path.classified, L::Or(first_reflection, leaves));
  return moves;
}

// ---------------------------------------------------------------- optics

/// A ray between the objects and the sensor, paraxial optics on exact slopes (tangent law): at
/// (x, y) on plane z with slopes sx = d.x / d.z, sy = d.y / d.z.
template <class L>
struct Beam {
  typename L::V x, y, z, sx, sy;
  /// The ray leaving p along d (d.z > 0; inv_dz = 1 / d.z).
  static HWY_INLINE Beam From(const V3<L>& p, const V3<L>& d, typename L::V inv_dz) {
    return {p.x, p.y, p.z, L::Mul(d.x, inv_dz), L::Mul(d.y, inv_dz)};
  }
  /// On to plane zp: x += sx (zp - z), y likewise.
  HWY_INLINE void Go(double zp) {
    const typename L::V dz = L::Sub(L::Set(zp), z);
    x = L::Add(x, L::Mul(sx, dz));
    y = L::Add(y, L::Mul(sy, dz));
    z = L::Set(zp);
  }
  HWY_INLINE typename L::V R2() const { return L::Add(L::Mul(x, x), L::Mul(y, y)); }
};

/// The corrector: the lane's zone (the first whose outer radius it lies within; beyond the last:
/// outside the NA) and its transmission draw (`uniform()`, made only where a ray needs it on one
/// lane: the scalar path draws from its stream there).
template <class L, class Uniform>
HWY_INLINE void CorrectorStage(const Optics& o, Beam<L>& b, Outcome<L>& out, Uniform&& uniform) {
  b.Go(o.corrector_z);
  const typename L::V r2 = b.R2();
  const int rings = static_cast<int>(o.ring_outer2.size());
  typename L::M beyond = L::True();  // beyond every zone so far
  typename L::V t = L::Set(rings > 0 ? o.ring_t[0] : 0.0);
  for (int k = 0; k < rings; ++k) {
    beyond = L::And(beyond, L::Gt(r2, L::Set(o.ring_outer2[k])));
    if (k + 1 < rings) t = L::Select(beyond, L::Set(o.ring_t[k + 1]), t);
    if (L::Stop(L::Not(beyond))) break;  // one lane: its zone is found
  }
  out.Mark(beyond, Fate::kOutsideNa);
  if (L::Stop(out.settled)) return;
  out.Mark(L::Ge(uniform(), t), Fate::kAbsorbedCorrector);  // rng.Uniform() >= the zone's t
}

/// The ideal lenses with the aperture stop before lens stop_after, each with its rim.
template <class L>
HWY_INLINE void LensStage(const Optics& o, Beam<L>& b, Outcome<L>& out) {
  for (int l = 0; l < o.num_lenses; ++l) {
    if (l == o.stop_after) {
      b.Go(o.stop_z);
      out.Mark(L::Gt(b.R2(), L::Set(o.stop_r2)), Fate::kOutsideNa);
      if (L::Stop(out.settled)) return;
    }
    const Lens& lens = o.lenses[l];
    b.Go(lens.z);
    if (lens.rim > 0) {
      out.Mark(L::Gt(b.R2(), L::Set(lens.rim * lens.rim)), Fate::kOutsideNa);
      if (L::Stop(out.settled)) return;
    }
    b.sx = L::Sub(b.sx, L::Mul(b.x, L::Set(lens.power)));  // sx -= x / f
    b.sy = L::Sub(b.sy, L::Mul(b.y, L::Set(lens.power)));
  }
}

/// The optical train from the objects to the sensor plane, in order: each element is a stage
/// above. A new element is one stage function and one line here (its parameters in Optics, and
/// a Fate if it removes rays for a new reason); both paths then trace it.
template <class L, bool kCorrector, class Uniform>
HWY_INLINE void OpticalTrain(const Optics& o, Beam<L>& b, Outcome<L>& out,
                             Uniform&& corrector_uniform) {
  if constexpr (kCorrector) {
    CorrectorStage<L>(o, b, out, corrector_uniform);
    if (L::Stop(out.settled)) return;
  }
  LensStage<L>(o, b, out);
  if (L::Stop(out.settled)) return;
  b.Go(o.sensor_z);
}

/// Where the beam meets the sensor, in the stored image's frame: u = sign x - off_x, likewise v.
template <class L>
HWY_INLINE void SensorPoint(const Optics& o, const Beam<L>& b, typename L::V& u, typename L::V& v) {
  u = L::Sub(L::Mul(L::Set(o.sign), b.x), L::Set(o.off_x));
  v = L::Sub(L::Mul(L::Set(o.sign), b.y), L::Set(o.off_y));
}

/// Two independent normal offsets of standard deviation sigma from two uniforms u1, u2 in
/// [0, 1) (multiples of 2^-32), by the Box-Muller transform (Box & Muller 1958):
/// r = sigma sqrt(-2 ln(1 - u1)), phi = 2 pi u2, (du, dv) = r (cos phi, sin phi). ln, cos and sin
/// are evaluated here from exact scalings and series, so that one lane and a vector give the
/// same bits (a library's vector and scalar functions do not agree to the last bit):
///  - ln x for x = 1 - u1 in [2^-32, 1]: x = 2^e y by exact power-of-two scalings with y in
///    [1/sqrt 2, sqrt 2), ln y = 2 atanh(s) with s = (y - 1) / (y + 1), |s| <= 0.1716, summed to
///    s^23 (the next term is below 2^-53 of the sum);
///  - cos and sin of 2 pi u2 by quadrants: q = floor(4 u2 + 1/2) and t = 4 u2 - q (both exact),
///    theta = t pi / 2 in [-pi/4, pi/4], Taylor series to theta^17 and theta^18 (the next terms are
///    below 2^-53), then the quadrant's exact swap and signs.
/// Accurate to a few units in the last place, as the library functions are.
template <class L>
HWY_INLINE void GaussianPair(typename L::V u1, typename L::V u2, double sigma, typename L::V& du,
                             typename L::V& dv) {
  using V = typename L::V;
  const V one = L::Set(1.0), zero = L::Set(0.0);
  // ln(1 - u1)
  V y = L::Sub(one, u1);  // exact: u1 is a multiple of 2^-32 below 1
  V e = zero;
  constexpr double kSteps[5][3] = {// k, 2^-k, 2^k
                                   {16, 0x1p-16, 0x1p16},
                                   {8, 0x1p-8, 0x1p8},
                                   {4, 0x1p-4, 0x1p4},
                                   {2, 0x1p-2, 0x1p2},
                                   {1, 0x1p-1, 0x1p1}};
  for (const auto& k : kSteps) {  // before step k, y >= 2^-2k; after it, y >= 2^-k
    const auto small = L::Lt(y, L::Set(k[1]));
    y = L::Select(small, L::Mul(y, L::Set(k[2])), y);
    e = L::Select(small, L::Sub(e, L::Set(k[0])), e);
  }
  const auto low = L::Lt(y, L::Set(0.70710678118654752440));  // y in [1/2, 1] -> [1/sqrt 2, sqrt 2)
  y = L::Select(low, L::Add(y, y), y);
  e = L::Select(low, L::Sub(e, one), e);
  const V s = L::Div(L::Sub(y, one), L::Add(y, one));
  const V s2 = L::Mul(s, s);
  V series = L::Set(1.0 / 23);
  for (int k = 21; k >= 1; k -= 2) series = L::Add(L::Set(1.0 / k), L::Mul(s2, series));
  const V ln_x = L::Add(L::Mul(e, L::Set(0.69314718055994530942)), L::Mul(L::Add(s, s), series));
  const V r = L::Mul(L::Set(sigma), L::Sqrt(L::Mul(L::Set(-2.0), ln_x)));
  // cos and sin of 2 pi u2
  const V four_u = L::Mul(u2, L::Set(4.0));
  const V q = L::Floor(L::Add(four_u, L::Set(0.5)));
  const V theta = L::Mul(L::Sub(four_u, q), L::Set(1.57079632679489661923));
  const V t2 = L::Mul(theta, theta);
  V c = L::Set(1.0), sn = L::Set(1.0);  // Horner from the highest term: 1 - t2/(n(n-1)) (...)
  for (int n = 18; n >= 2; n -= 2)
    c = L::Sub(one, L::Mul(L::Mul(t2, L::Set(1.0 / (n * (n - 1)))), c));
  for (int n = 17; n >= 3; n -= 2)
    sn = L::Sub(one, L::Mul(L::Mul(t2, L::Set(1.0 / (n * (n - 1)))), sn));
  sn = L::Mul(theta, sn);
  // Quadrant q mod 4: (cos, sin) of q pi/2 + theta
  const auto q1 = L::Eq(q, one), q2 = L::Eq(q, L::Set(2.0)), q3 = L::Eq(q, L::Set(3.0));
  const auto swap = L::Or(q1, q3);
  const V cx = L::Select(swap, sn, c), sx = L::Select(swap, c, sn);
  const V cos_phi = L::Select(L::Or(q1, q2), L::Sub(zero, cx), cx);
  const V sin_phi = L::Select(L::Or(q2, q3), L::Sub(zero, sx), sx);
  du = L::Mul(r, cos_phi);
  dv = L::Mul(r, sin_phi);
}

/// The pixel the sensor point (u, v) falls in, row nx + col with col = floor(u / pitch + nx / 2),
/// row = floor(ny / 2 - v / pitch); beside the sensor: missed_sensor.
template <class L>
HWY_INLINE typename L::V SensorPixel(const Optics& o, typename L::V u, typename L::V v,
                                     Outcome<L>& out) {
  const typename L::V inv_pitch = L::Set(o.inv_pitch), zero = L::Set(0.0);
  const typename L::V nx = L::Set(o.nx), ny = L::Set(o.ny);
  const typename L::V col = L::Floor(L::Add(L::Mul(u, inv_pitch), L::Set(0.5 * o.nx)));
  const typename L::V row = L::Floor(L::Sub(L::Set(0.5 * o.ny), L::Mul(v, inv_pitch)));
  const typename L::M inside =
      L::And(L::And(L::Ge(col, zero), L::Lt(col, nx)), L::And(L::Ge(row, zero), L::Lt(row, ny)));
  out.Mark(L::Not(inside), Fate::kMissedSensor);
  return L::Add(L::Mul(row, nx), col);
}

}  // namespace HWY_NAMESPACE
}  // namespace raymatch::simulate::stages
HWY_AFTER_NAMESPACE();

#endif  // per-target include guard
