// SIMD packet stages of the tracer (packet.h). Google Highway compiles this file once per
// instruction set (SSSE3/SSE4, AVX2, AVX-512, ...) and picks the best the CPU has at run time,
// so one binary runs everywhere and uses all the vector width there is.
//
// Bit-identity with the scalar tracer rests on three rules: the same operations in the same
// order (the physical stages are the scalar path's own, stages-inl.h, instantiated here for
// vectors; the rest names the scalar line it mirrors), IEEE double arithmetic with
// correctly rounded division and square root in both paths, and no contraction of a * b + c
// into a fused multiply-add (CMake builds this file with -ffp-contract=off; Highway's MulAdd is
// never used). test_simulate's Packet.* tests compare images, counters and near lists with the
// scalar path's on every instruction set this CPU has (they cannot see a difference of one
// rounding, which moves a ray across a pixel edge almost never: the build flag guards that).
#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "packet.cpp"
#include "packet.h"

#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>

#include "stages-inl.h"

HWY_BEFORE_NAMESPACE();
namespace raymatch::simulate::packet {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;
namespace st = stages::HWY_NAMESPACE;
using L = st::VecLanes;  // the stages' lane type here

using DF = hn::ScalableTag<double>;
using DU = hn::RebindToUnsigned<DF>;  // u64 lanes, as many as the doubles
using DI = hn::RebindToSigned<DF>;
using DU32 = hn::Rebind<uint32_t, DF>;  // u32 storage of the words, same lane count

// The 64-bit product of two u64 lanes holding 32-bit values.
HWY_INLINE hn::Vec<DU> Mul32(hn::Vec<DU> a, hn::Vec<DU> b) {
#if HWY_TARGET == HWY_SCALAR
  return hn::Mul(a, b);  // one lane: plain 64-bit multiplication
#else
  const hn::Repartition<uint32_t, DU> d32;  // the same bits as twice as many u32 lanes
  return hn::MulEven(hn::BitCast(d32, a), hn::BitCast(d32, b));
#endif
}

// Philox4x32-10 (Salmon et al., SC'11; Random123's philox4x32 with its constants) for the rays
// i .. i + lanes: block `block` of each ray's stream, i.e. its words 4 block .. 4 block + 3. The
// four counters sit in u64 lanes that hold 32-bit values.
HWY_INLINE void PhiloxBlock(uint64_t seed, uint32_t stream, const uint64_t* rays, size_t i,
                            int block, Rays* r) {
  const DU du;
  const DU32 dw;
  constexpr uint32_t kM0 = 0xD2511F53u, kM1 = 0xCD9E8D57u;
  constexpr uint32_t kW0 = 0x9E3779B9u, kW1 = 0xBB67AE85u;
  const auto lo_mask = hn::Set(du, 0xFFFFFFFFull);
  const auto m0 = hn::Set(du, kM0), m1 = hn::Set(du, kM1);
  const auto index = hn::LoadU(du, rays + i);
  auto c0 = hn::And(index, lo_mask), c1 = hn::ShiftRight<32>(index);
  auto c2 = hn::Set(du, stream), c3 = hn::Set(du, uint64_t(block));
  uint32_t k0 = static_cast<uint32_t>(seed), k1 = static_cast<uint32_t>(seed >> 32);
  for (int round = 0; round < 10; ++round) {
    const auto p0 = Mul32(c0, m0), p1 = Mul32(c2, m1);
    const auto n0 = hn::Xor(hn::Xor(hn::ShiftRight<32>(p1), c1), hn::Set(du, k0));
    const auto n2 = hn::Xor(hn::Xor(hn::ShiftRight<32>(p0), c3), hn::Set(du, k1));
    c1 = hn::And(p1, lo_mask);
    c3 = hn::And(p0, lo_mask);
    c0 = n0, c2 = n2;
    k0 += kW0, k1 += kW1;  // the key schedule (32-bit wrap-around)
  }
  uint32_t* w = r->words[4 * block];
  hn::StoreU(hn::TruncateTo(dw, c0), dw, w + i);
  hn::StoreU(hn::TruncateTo(dw, c1), dw, w + kBatch + i);
  hn::StoreU(hn::TruncateTo(dw, c2), dw, w + 2 * kBatch + i);
  hn::StoreU(hn::TruncateTo(dw, c3), dw, w + 3 * kBatch + i);
}

void PhiloxWordsImpl(uint64_t seed, uint32_t stream, const uint64_t* rays, size_t n, Rays* r) {
  for (size_t i = 0; i < n; i += hn::Lanes(DU()))
    for (int block = 0; block < kWords / 4; ++block) PhiloxBlock(seed, stream, rays, i, block, r);
}

// One vector of rays' words: the blocks made so far, and the rest made when a stage reaches
// them (most rays need only the first two of the three blocks).
struct Words {
  Rays* r;
  size_t i;
  uint64_t seed;
  uint32_t stream;
  const uint64_t* rays;
  int blocks = 0;
  void Need(int word) {
    for (; blocks * 4 <= word && blocks < kWords / 4; ++blocks)
      PhiloxBlock(seed, stream, rays, i, blocks, r);
  }
};

// The 32-bit words at p minus 2^31, as doubles (exact): the word goes to double through int32,
// which every x86 target converts natively: double(w) = double(int32(w ^ 2^31)) + 2^31.
HWY_INLINE hn::Vec<DF> Centred(const uint32_t* p) {
  const hn::Rebind<int32_t, DF> di32;
  const auto w = hn::LoadU(DU32(), p);
  return hn::PromoteTo(DF(), hn::BitCast(di32, hn::Xor(w, hn::Set(DU32(), 0x80000000u))));
}

// RayRng::Uniform: the word times 2^-32 (exact).
HWY_INLINE hn::Vec<DF> Uniform(const uint32_t* p) {
  const DF df;
  return hn::Mul(hn::Add(Centred(p), hn::Set(df, 2147483648.0)), hn::Set(df, 0x1p-32));
}
HWY_INLINE hn::Vec<DF> Uniform(Words& words, int word) {
  words.Need(word);
  return Uniform(words.r->words[word] + words.i);
}

// 2 rng.Uniform() - 1 for the word: every step of it is exact (a 32-bit integer scaled by
// powers of two, then 1 subtracted from a multiple of 2^-31 in [0, 2)), so it equals
// (word - 2^31) * 2^-31, which is what is computed here.
HWY_INLINE hn::Vec<DF> Symmetric(Words& words, int word) {
  words.Need(word);
  return hn::Mul(Centred(words.r->words[word] + words.i), hn::Set(DF(), 0x1p-31));
}

// The pair of words at j as SampleUnitDisc forms it: (2u - 1, 2u' - 1), and whether it lies in
// the unit disc (a * a + b * b < 1; the loop there rejects >= 1).
HWY_INLINE hn::Mask<DF> DiscPair(Words& w, int j, hn::Vec<DF>& a, hn::Vec<DF>& b) {
  w.Need(j + 1);
  return st::DiscTry<L>(Centred(w.r->words[j] + w.i), Centred(w.r->words[j + 1] + w.i), a, b);
}

// SampleUnitDisc from each lane's cursor on (even: every draw before it came in pairs). A lane
// whose words run out gets cursor -1.
HWY_INLINE void UnitDisc(Words& w, hn::Vec<DI>& cursor, hn::Vec<DF>& a_out, hn::Vec<DF>& b_out) {
  const DF df;
  const DI di;
  auto done = hn::RebindMask(df, hn::Lt(cursor, hn::Zero(di)));  // out of words already
  for (int j = 0; j + 1 < kWords; j += 2) {
    const auto active = hn::AndNot(done, hn::RebindMask(df, hn::Eq(cursor, hn::Set(di, j))));
    if (hn::AllFalse(df, active)) continue;
    hn::Vec<DF> a, b;
    const auto take = hn::And(active, DiscPair(w, j, a, b));
    a_out = hn::IfThenElse(take, a, a_out);
    b_out = hn::IfThenElse(take, b, b_out);
    done = hn::Or(done, take);
    cursor = hn::IfThenElse(hn::RebindMask(di, active), hn::Add(cursor, hn::Set(di, 2)), cursor);
  }
  cursor = hn::IfThenElse(hn::RebindMask(di, done), cursor, hn::Set(di, -1));
}

// Two discs drawn one after the other from word 0 (a disc field, then a cone's direction) in
// one pass over the pairs: the first inside pair is the field's, the next one the direction's.
HWY_INLINE void TwoDiscs(Words& w, hn::Vec<DI>& cursor, hn::Vec<DF>& fa, hn::Vec<DF>& fb,
                         hn::Vec<DF>& da, hn::Vec<DF>& db) {
  const DF df;
  const DI di;
  auto field_done = hn::Lt(hn::Zero(df), hn::Zero(df)), dir_done = field_done;  // all false
  auto end = hn::Set(di, -1);
  for (int j = 0; j + 1 < kWords; j += 2) {
    hn::Vec<DF> a, b;
    const auto inside = DiscPair(w, j, a, b);
    const auto take_dir = hn::AndNot(dir_done, hn::And(field_done, inside));
    const auto take_field = hn::AndNot(field_done, inside);
    fa = hn::IfThenElse(take_field, a, fa);
    fb = hn::IfThenElse(take_field, b, fb);
    da = hn::IfThenElse(take_dir, a, da);
    db = hn::IfThenElse(take_dir, b, db);
    end = hn::IfThenElse(hn::RebindMask(di, take_dir), hn::Set(di, j + 2), end);
    field_done = hn::Or(field_done, take_field);
    dir_done = hn::Or(dir_done, take_dir);
    if (hn::AllTrue(df, dir_done)) break;
  }
  cursor = end;
}

void SampleSourceImpl(const SourceParams& s, uint64_t seed, uint32_t stream, const uint64_t* rays,
                      size_t n, int extra_words, Rays* r) {
  const DF df;
  const DI di;
  const size_t N = hn::Lanes(df);
  // The first two blocks for the whole batch up front (independent vectors keep the multiplier
  // busy); the third only for vectors that reach it.
  for (size_t i = 0; i < n; i += N)
    for (int block = 0; block < 2; ++block) PhiloxBlock(seed, stream, rays, i, block, r);
  for (size_t i = 0; i < n; i += N) {
    Words w{r, i, seed, stream, rays, 2};
    auto cursor = hn::Zero(di);
    hn::Vec<DF> px, py;
    auto da = hn::Zero(df), db = hn::Zero(df);  // the cone's disc, when drawn with the field's
    const bool two_discs = s.disc_field && s.direction == SourceParams::kCone;
    if (s.disc_field) {  // Field::Sample, disc: center + (x radius, y radius, 0)
      auto a = hn::Zero(df), b = hn::Zero(df);
      if (two_discs)
        TwoDiscs(w, cursor, a, b, da, db);
      else
        UnitDisc(w, cursor, a, b);
      const st::V3<L> p = st::DiscFieldPoint<L>(s.center, s.radius, a, b);
      px = p.x, py = p.y;
    } else {  // rectangle: center + ((2 u0 - 1) half_w, (2 u1 - 1) half_h, 0)
      px = hn::Add(hn::Set(df, s.center[0]), hn::Mul(Symmetric(w, 0), hn::Set(df, s.half_w)));
      py = hn::Add(hn::Set(df, s.center[1]), hn::Mul(Symmetric(w, 1), hn::Set(df, s.half_h)));
      cursor = hn::Set(di, 2);
    }
    hn::StoreU(px, df, r->px + i);
    hn::StoreU(py, df, r->py + i);
    hn::StoreU(hn::Set(df, s.center[2] + 0.0), df, r->pz + i);
    switch (s.direction) {
      case SourceParams::kCone: {  // ConeSource::Sample
        if (!two_discs) UnitDisc(w, cursor, da, db);
        const st::V3<L> d = st::ConeDirection<L>(da, db, s.sin_max);
        hn::StoreU(d.x, df, r->dx + i);
        hn::StoreU(d.y, df, r->dy + i);
        hn::StoreU(d.z, df, r->dz + i);
        break;
      }
      case SourceParams::kCollimated:
        hn::StoreU(hn::Set(df, s.dir[0]), df, r->dx + i);
        hn::StoreU(hn::Set(df, s.dir[1]), df, r->dy + i);
        hn::StoreU(hn::Set(df, s.dir[2]), df, r->dz + i);
        break;
      case SourceParams::kTabulated: {  // the caller maps (u, v) through the angular table
        // Lanes out of words keep cursor -1; the others need two more words.
        const auto ok =
            hn::AndNot(hn::Lt(cursor, hn::Zero(di)), hn::Lt(cursor, hn::Set(di, kWords - 1)));
        auto u = hn::Zero(df), v = hn::Zero(df);
        for (int j = 0; j + 1 < kWords; j += 2) {  // the cursor is even here
          const auto at = hn::RebindMask(df, hn::Eq(cursor, hn::Set(di, j)));
          if (hn::AllFalse(df, at)) continue;  // (and the third block stays unmade if unused)
          u = hn::IfThenElse(at, Uniform(w, j), u);
          v = hn::IfThenElse(at, Uniform(w, j + 1), v);
        }
        hn::StoreU(u, df, r->u + i);
        hn::StoreU(v, df, r->v + i);
        cursor = hn::IfThenElse(ok, hn::Add(cursor, hn::Set(di, 2)), hn::Set(di, -1));
        break;
      }
    }
    // The words the caller reads after the source (polarisation, corrector) must exist too.
    if (extra_words > 0)
      w.Need(static_cast<int>(hn::GetLane(hn::MaxOfLanes(di, cursor))) + extra_words - 1);
    hn::StoreU(cursor, di, r->cursor + i);
    hn::StoreU(
        hn::IfThenElseZero(hn::RebindMask(df, hn::Lt(cursor, hn::Zero(di))), hn::Set(df, kScalar)),
        df, r->out + i);
  }
}

void TabulatedImpl(const Table2D& t, size_t n, Rays* r) {
  const DF df;
  const DI di;
  const size_t N = hn::Lanes(df);
  const auto zero = hn::Zero(df);
  for (size_t i = 0; i < n; i += N) {
    auto out = hn::LoadU(df, r->out + i);
    const auto open = hn::Eq(out, zero);
    if (hn::AllFalse(df, open)) continue;
    // Distribution2D::Sample(u0, u1): y from the marginal with u1, then x in that row with u0
    hn::Vec<DI> row, col;
    const auto y =
        st::Sample1D<L>(t.marginal_cdf.data(), hn::Zero(di), t.marginal_guide.data(), hn::Zero(di),
                        t.height, t.marginal_guide_size, hn::LoadU(df, r->v + i), &row);
    // The row's offsets, multiplied in double (exact for these sizes; not every target
    // multiplies 64-bit integers).
    const auto row_d = hn::ConvertTo(df, row);
    const auto cdf_at = hn::ConvertTo(di, hn::Mul(row_d, hn::Set(df, double(t.width + 1))));
    const auto guide_at = hn::ConvertTo(di, hn::Mul(row_d, hn::Set(df, double(t.row_guide_size))));
    const auto x = st::Sample1D<L>(t.row_cdf.data(), cdf_at, t.row_guide.data(), guide_at, t.width,
                                   t.row_guide_size, hn::LoadU(df, r->u + i), &col);
    // Beyond the unit circle: escaped
    st::V3<L> d;
    const auto beyond = hn::And(open, st::TabulatedDirection<L>(x, y, t.extent, d));
    out = hn::IfThenElse(beyond, hn::Set(df, FateCode(Fate::kEscaped)), out);
    hn::StoreU(out, df, r->out + i);
    hn::StoreU(d.x, df, r->dx + i);
    hn::StoreU(d.y, df, r->dy + i);
    hn::StoreU(d.z, df, r->dz + i);
  }
}

void GaussianOffsetsImpl(double sigma, size_t n, Rays* r) {
  const DF df;
  const size_t N = hn::Lanes(df);
  for (size_t i = 0; i < n; i += N) {  // kBatch is a multiple of N: whole vectors stay inside
    hn::Vec<DF> du, dv;
    st::GaussianPair<L>(hn::LoadU(df, r->psf_du + i), hn::LoadU(df, r->psf_dv + i), sigma, du, dv);
    hn::StoreU(du, df, r->psf_du + i);
    hn::StoreU(dv, df, r->psf_dv + i);
  }
}

// Stores the lanes' outcomes and adds the lanes below n to the batch's summary (Rays).
HWY_INLINE void Summarise(const Optics& o, hn::Vec<DF> out, size_t i, size_t n, Rays* r) {
  const DF df;
  const DI di;
  hn::StoreU(out, df, r->out + i);
  const auto valid = hn::FirstN(df, n - i);  // the last vector may reach past the batch
  const auto detected = hn::Ge(out, hn::Zero(df));
  // Pixel indices are integers below 2^31: exact in double and in int64.
  const auto spare =
      hn::Add(hn::Set(df, o.nx * o.ny),
              hn::ConvertTo(df, hn::And(hn::Iota(di, 0), hn::Set(di, kSpareSlots - 1))));
  hn::StoreU(hn::ConvertTo(di, hn::IfThenElse(detected, out, spare)), di, r->slot + i);
  r->counts[int(Fate::kDetected)] += hn::CountTrue(df, hn::And(valid, detected));
  for (Fate f : kPacketFates)
    r->counts[int(f)] += hn::CountTrue(df, hn::And(valid, hn::Eq(out, hn::Set(df, FateCode(f)))));
  const auto back =
      hn::And(valid, hn::Or(hn::Eq(out, hn::Set(df, kScalar)), hn::Eq(out, hn::Set(df, kNear))));
  if (!hn::AllFalse(df, back)) {
    uint8_t bits[8] = {};
    hn::StoreMaskBits(df, back, bits);
    for (size_t k = 0; k < hn::Lanes(df); ++k)
      if ((bits[k / 8] >> (k % 8)) & 1)
        r->handed_back[r->num_handed_back++] = static_cast<int64_t>(i + k);
  }
}

// The near test (before the optics only), then the optics stages (stages-inl.h) to a pixel.
void OpticsImpl(const NearParams& near, const Optics& o, size_t n, bool from_objects, Rays* r) {
  const DF df;
  const size_t N = hn::Lanes(df);
  const auto zero = hn::Zero(df);
  r->num_handed_back = 0;
  for (uint64_t& c : r->counts) c = 0;
  for (size_t i = 0; i < n; i += N) {
    const st::V3<L> p{hn::LoadU(df, r->px + i), hn::LoadU(df, r->py + i), hn::LoadU(df, r->pz + i)};
    const st::V3<L> d{hn::LoadU(df, r->dx + i), hn::LoadU(df, r->dy + i), hn::LoadU(df, r->dz + i)};
    const auto code = hn::LoadU(df, r->out + i);
    st::Outcome<L> out{hn::Lt(code, zero), code};  // settled: lanes whose outcome is known
    if (!from_objects) {
      if (near.split)
        out.MarkCode(hn::Le(st::LineDistance2<L>(near.split_c, p, d), hn::Set(df, near.split_r2)),
                     kNear);
      for (int k = 0; k < near.num_bounds; ++k)
        out.MarkCode(
            hn::Le(st::LineDistance2<L>(near.bound_c[k], p, d), hn::Set(df, near.bound_r2[k])),
            kScalar);
      out.MarkCode(hn::Le(d.z, zero), kScalar);  // the scalar path calls these escaped; let it
    }
    if (hn::AllTrue(df, out.settled)) {
      Summarise(o, out.code, i, n, r);
      continue;
    }
    // After the objects, p is already where the ray left them.
    const auto inv_dz = hn::Div(hn::Set(df, 1.0), d.z);
    auto b = st::Beam<L>::From(from_objects ? p : st::OnPlane<L>(near.source_z, p, d, inv_dz), d,
                               inv_dz);
    auto corrector_uniform = [&] { return hn::LoadU(df, r->u + i); };
    if (o.corrector)
      st::OpticalTrain<L, true>(o, b, out, corrector_uniform);
    else
      st::OpticalTrain<L, false>(o, b, out, corrector_uniform);
    hn::Vec<DF> u, v;
    st::SensorPoint<L>(o, b, u, v);
    if (o.psf_sigma_sensor > 0) {  // TraceRay: u += r cos(phi), v += r sin(phi)
      u = hn::Add(u, hn::LoadU(df, r->psf_du + i));
      v = hn::Add(v, hn::LoadU(df, r->psf_dv + i));
    }
    const auto pixel = st::SensorPixel<L>(o, u, v, out);
    Summarise(o, hn::IfThenElse(out.settled, out.code, pixel), i, n, r);
  }
}

// rng.Uniform() from each lane's next word (its cursor < kWords) where `m`, else 0.
HWY_INLINE hn::Vec<DF> UniformAtCursor(const Rays& r, size_t i, hn::Vec<DI> cursor,
                                       hn::Mask<DF> m) {
  const DF df;
  auto u = hn::Zero(df);
  for (int j = 0; j < kWords; ++j) {
    const auto at = hn::And(m, hn::RebindMask(df, hn::Eq(cursor, hn::Set(DI(), j))));
    if (hn::AllFalse(df, at)) continue;
    u = hn::IfThenElse(at, Uniform(r.words[j] + i), u);
  }
  return u;
}

// IntersectSphere(o, d, c, r2) per lane, from f = o - c: the distance *t along d to the
// sphere's first crossing ahead of o; false where the ray misses it or it lies behind.
HWY_INLINE hn::Mask<DF> SphereAhead(hn::Vec<DF> fx, hn::Vec<DF> fy, hn::Vec<DF> fz, hn::Vec<DF> dx,
                                    hn::Vec<DF> dy, hn::Vec<DF> dz, hn::Vec<DF> r2,
                                    hn::Vec<DF>* t) {
  const DF df;
  const auto zero = hn::Zero(df);
  const auto b = hn::Neg(st::Dot<L>({fx, fy, fz}, {dx, dy, dz}));
  const auto qx = hn::Add(fx, hn::Mul(dx, b)), qy = hn::Add(fy, hn::Mul(dy, b)),
             qz = hn::Add(fz, hn::Mul(dz, b));
  const auto disc = hn::Sub(r2, st::Dot<L>({qx, qy, qz}, {qx, qy, qz}));
  const auto c0 = hn::Sub(st::Dot<L>({fx, fy, fz}, {fx, fy, fz}), r2);
  const auto away = hn::Or(hn::Lt(disc, zero), hn::And(hn::Gt(c0, zero), hn::Lt(b, zero)));
  const auto root = hn::Sqrt(hn::IfThenElseZero(hn::Not(away), disc));
  const auto q = hn::Add(b, hn::CopySign(root, b));
  auto t0 = hn::IfThenElse(hn::Ne(q, zero), hn::Div(c0, q), zero), t1 = q;
  const auto swap = hn::Gt(t0, t1);
  const auto lo = hn::IfThenElse(swap, t1, t0), hi = hn::IfThenElse(swap, t0, t1);
  t0 = lo, t1 = hi;
  *t = hn::IfThenElse(hn::Gt(t0, zero), t0, t1);
  return hn::AndNot(away, hn::Or(hn::Gt(t0, zero), hn::Gt(t1, zero)));
}

// TraceObjects for one homogeneous sphere, several rays at a time (packet.h, Sphere): the sphere
// test (IntersectSphere), its normal, and the interface event both paths run
// (stages-inl.h, InterfaceEvent); the object stack is a depth (it can only hold this sphere).
void SphereImpl(const SphereParams& sp, size_t n, Rays* r) {
  const DF df;
  const DI di;
  const size_t N = hn::Lanes(df);
  const auto zero = hn::Zero(df), one = hn::Set(df, 1.0);
  const auto cx = hn::Set(df, sp.center[0]), cy = hn::Set(df, sp.center[1]),
             cz = hn::Set(df, sp.center[2]), r2 = hn::Set(df, sp.radius2);
  const auto n_obj = hn::Set(df, sp.index), n_med = hn::Set(df, sp.medium);
  const auto eps = hn::Set(df, sp.epsilon);
  for (size_t i = 0; i < n; i += N) {
    const auto px = hn::LoadU(df, r->px + i), py = hn::LoadU(df, r->py + i),
               pz = hn::LoadU(df, r->pz + i);
    st::V3<L> d{hn::LoadU(df, r->dx + i), hn::LoadU(df, r->dy + i), hn::LoadU(df, r->dz + i)};
    st::V3<L> o = st::OnPlane<L>(sp.source_z, {px, py, pz}, d, hn::Div(one, d.z));
    auto cursor = hn::LoadU(di, r->cursor + i);
    auto out = st::Outcome<L>::Open();
    auto active = hn::FirstN(df, n - i);
    auto path = st::ObjectPath<L>::Start();
    auto queries = hn::Zero(di), fresnel = hn::Zero(di);
    auto count = [&](hn::Vec<DI>& v, hn::Mask<DF> m) {
      v = hn::IfThenElse(hn::RebindMask(di, m), hn::Add(v, hn::Set(di, 1)), v);
    };
    // The unpolarised Fresnel draw from each lane's next word; a lane out of words goes to the
    // scalar path.
    auto draw = [&](hn::Mask<DF> tir, const st::FacedSurface<L>& face, hn::Vec<DF> n1,
                    hn::Vec<DF> n2, hn::Vec<DF> cos_t, const st::V3<L>&, hn::Mask<DF>& live,
                    st::Outcome<L>& ends) {
      if (!sp.fresnel) return tir;
      const auto drawn = hn::AndNot(tir, live);
      count(fresnel, drawn);
      const auto out_of_words =
          hn::And(drawn, hn::RebindMask(df, hn::Gt(cursor, hn::Set(di, kWords - 1))));
      ends.MarkCode(out_of_words, kScalar);
      live = hn::AndNot(out_of_words, live);
      const auto drawing = hn::AndNot(out_of_words, drawn);
      const auto u = UniformAtCursor(*r, i, cursor, drawing);
      count(cursor, drawing);
      const auto R = st::FresnelReflectance<L>(n1, n2, face.cos_i, cos_t);
      return hn::Or(tir, hn::And(drawing, hn::Lt(u, R)));
    };
    while (!hn::AllFalse(df, active)) {
      count(queries, active);  // ++c.shape_queries
      hn::Vec<DF> t;
      const auto hit =
          SphereAhead(hn::Sub(o.x, cx), hn::Sub(o.y, cy), hn::Sub(o.z, cz), d.x, d.y, d.z, r2, &t);
      active = hn::And(active, hit);  // the others left the sphere for good
      if (hn::AllFalse(df, active)) break;
      // hp = o + d * t; normal = Normalize(hp - c)
      const st::V3<L> hp{hn::Add(o.x, hn::Mul(d.x, t)), hn::Add(o.y, hn::Mul(d.y, t)),
                         hn::Add(o.z, hn::Mul(d.z, t))};
      const st::V3<L> v{hn::Sub(hp.x, cx), hn::Sub(hp.y, cy), hn::Sub(hp.z, cz)};
      const auto len = hn::Sqrt(st::Dot<L>(v, v));
      const st::V3<L> normal{hn::Div(v.x, len), hn::Div(v.y, len), hn::Div(v.z, len)};
      const auto inside = hn::RebindMask(df, hn::Gt(path.depth, hn::Zero(di)));
      // The media on either side: entering from the medium (or from inside the sphere itself,
      // which the stack cannot hold twice), leaving into the medium.
      auto indices = [&](const st::FacedSurface<L>& face, hn::Vec<DF>& n1, hn::Vec<DF>& n2) {
        n1 = hn::IfThenElse(face.entering, hn::IfThenElse(inside, n_obj, n_med), n_obj);
        n2 = hn::IfThenElse(face.entering, n_obj, n_med);
      };
      st::InterfaceEvent<L>(sp.max_interactions, hp, normal, eps, inside, d, o, active, path, out,
                            indices, draw);
    }
    // Left the sphere: still inside by the stack -> lost; travelling away from the objective
    // (d.z <= 0) -> escaped; the rest go on to the optics from where they left.
    out.Mark(hn::RebindMask(df, hn::Gt(path.depth, hn::Zero(di))), Fate::kLostInside);
    out.Mark(hn::Le(d.z, zero), Fate::kEscaped);
    hn::StoreU(out.code, df, r->out + i);
    hn::StoreU(o.x, df, r->px + i), hn::StoreU(o.y, df, r->py + i), hn::StoreU(o.z, df, r->pz + i);
    hn::StoreU(d.x, df, r->dx + i), hn::StoreU(d.y, df, r->dy + i), hn::StoreU(d.z, df, r->dz + i);
    hn::StoreU(cursor, di, r->cursor + i);
    hn::StoreU(queries, di, r->queries + i);
    hn::StoreU(path.interface_events, di, r->interface_events + i);
    hn::StoreU(fresnel, di, r->fresnel + i);
    hn::StoreU(path.path_class, di, r->path_class + i);
    hn::StoreU(path.events, di, r->events + i);
  }
}

}  // namespace HWY_NAMESPACE
}  // namespace raymatch::simulate::packet
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace raymatch::simulate::packet {

HWY_EXPORT(PhiloxWordsImpl);
HWY_EXPORT(SampleSourceImpl);
HWY_EXPORT(OpticsImpl);
HWY_EXPORT(SphereImpl);
HWY_EXPORT(TabulatedImpl);
HWY_EXPORT(GaussianOffsetsImpl);

void PhiloxWords(uint64_t seed, uint32_t stream, const uint64_t* rays, size_t n, Rays* r) {
  HWY_DYNAMIC_DISPATCH(PhiloxWordsImpl)(seed, stream, rays, n, r);
}
void SampleSource(const SourceParams& s, uint64_t seed, uint32_t stream, const uint64_t* rays,
                  size_t n, int extra_words, Rays* r) {
  HWY_DYNAMIC_DISPATCH(SampleSourceImpl)(s, seed, stream, rays, n, extra_words, r);
}
void NearTestAndOptics(const NearParams& near, const Optics& o, size_t n, Rays* r) {
  HWY_DYNAMIC_DISPATCH(OpticsImpl)(near, o, n, false, r);
}
void OpticsAfterObjects(const Optics& o, size_t n, Rays* r) {
  HWY_DYNAMIC_DISPATCH(OpticsImpl)(NearParams{}, o, n, true, r);
}
void Sphere(const SphereParams& s, size_t n, Rays* r) { HWY_DYNAMIC_DISPATCH(SphereImpl)(s, n, r); }
void Tabulated(const Table2D& t, size_t n, Rays* r) {
  HWY_DYNAMIC_DISPATCH(TabulatedImpl)(t, n, r);
}
void GaussianOffsets(double sigma, size_t n, Rays* r) {
  HWY_DYNAMIC_DISPATCH(GaussianOffsetsImpl)(sigma, n, r);
}
const char* TargetName() {
  // The target HWY_DYNAMIC_DISPATCH uses: the best one both compiled and supported.
  const int64_t chosen = hwy::SupportedTargets() & HWY_TARGETS;
  return hwy::TargetName(chosen & -chosen);  // lowest bit = best target
}

}  // namespace raymatch::simulate::packet
#endif
