#pragma once
// The objects stage of the scalar path: a ray through the scene's objects (refraction, total
// internal reflection, Fresnel branches, the object stack, gradient-index media) until it leaves
// them all. The packet path's sphere stage (packet.cpp, Sphere) does the same for one
// homogeneous sphere; at each surface both run one interface event (stages-inl.h).
#include <algorithm>
#include <array>
#include <cmath>
#include <complex>

#include "grin_cells.h"
#include "raymatch/core/rng.h"
#include "raymatch/simulate/interfaces.h"
#include "tracer_impl.h"

namespace raymatch::simulate {

/// Pseudo-random unit vector perpendicular to d (polarisation of a new ray).
inline Vec3 RandomPerpendicular(const Vec3& d, double u) {
  const Vec3 a = std::abs(d.x) < 0.9 ? Vec3(1, 0, 0) : Vec3(0, 1, 0);
  const Vec3 e1 = Normalize(Cross(d, a)), e2 = Cross(d, e1);
  const double phi = 2 * M_PI * u;
  return e1 * std::cos(phi) + e2 * std::sin(phi);
}

enum class GrinOutcome { kHit, kStepCap, kNoSurface };

/// Object obj's centre at the ray's time (moving scenes), else its center_um.
inline Vec3 ObjectCenter(const Simulator::Impl& im, int obj, const ObjectShifts* moved) {
  return moved ? im.center[obj] + moved->of(obj) : im.center[obj];
}

/// A spherically symmetric field (n depends on |p - centre| only: Luneburg, fish-eye) conserves
/// the ray's angular momentum L = (r - c) x T (Bouguer's formula, Born & Wolf sec. 3.2.1) and
/// the eikonal |T| = n. Near a tangent exit a position error e moves the exit by e / alpha
/// along the surface (alpha: the exit angle to it), so each accepted state is projected back
/// onto both invariants (Hairer, Lubich & Wanner, Geometric Numerical Integration, 2006,
/// sec. IV.4): the orbit keeps its exact shape and the exit angle follows from L.
inline bool IsCentralField(const IndexField& f) {
  return f.type == IndexFieldType::kLuneburg || f.type == IndexFieldType::kFishEye;
}

inline void ProjectOnInvariants(const IndexField& f, const Vec3& center, const Vec3& l,
                                GrinPoint* s) {
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

/// A field carried along a curved ray from (x0, t0) to (x1, t1) (t: the unit tangents): in an
/// isotropic gradient-index medium the field turns only as much as it must to stay transverse
/// to the ray, which is parallel transport along it (Rytov's law; Born and Wolf, Principles of
/// Optics, sec. 3.1.3). Over one step it is the double reflection of Wang, Juttler, Zheng and
/// Liu, ACM Trans. Graph. 27, 2 (2008), a fourth-order rotation-minimising frame: reflect in
/// the plane normal to the chord, then in the plane that takes the reflected tangent to t1. Both
/// reflections are real and linear, so they act on a complex field's parts alike and keep its
/// length.
inline void TransportField(std::array<std::complex<double>, 3>& e, const Vec3& x0, const Vec3& x1,
                           const Vec3& t0, const Vec3& t1) {
  auto reflect = [&e](const Vec3& v, double c) {
    const std::complex<double> along = (e[0] * v.x + e[1] * v.y + e[2] * v.z) * (2 / c);
    e[0] -= along * v.x, e[1] -= along * v.y, e[2] -= along * v.z;
  };
  const Vec3 v1 = x1 - x0;
  const double c1 = Dot(v1, v1);
  Vec3 tl = t0;
  if (c1 > 0) {
    reflect(v1, c1);
    tl = t0 - v1 * (2 * Dot(v1, t0) / c1);
  }
  const Vec3 v2 = t1 - tl;
  const double c2 = Dot(v2, v2);
  if (c2 > 1e-30) reflect(v2, c2);
}

/// Follows a curved ray inside gradient-index object `obj` from `o` (direction `d`) to the next
/// surface. Each accepted step's chord is tested against the surfaces; a step whose chord crosses
/// one is shortened (the crossing parameter scales the step) until the crossing chord is shorter
/// than 1e-3 um or 1e-5 of the object size, then the ray leaves at the chord's hit point with
/// the direction T/|T| at the step's end. Across uniform cells of a grid the ray goes straight
/// in one step (exact there), to the surface if it is nearer.
/// `f`: object obj's field as this ray sees it (its own, or a view at the ray's wavelength).
/// With kOpticalPath, `*opl` is increased by the optical path from o to *hp, the integral of
/// n ds (the images' instantiations are the code without it). With the parameter dt = ds / n it
/// is the integral of n^2 dt, whose derivative 2 D.T is known at both ends of every step, so
/// each step adds the corrected trapezoid (Hermite) rule h (f0 + f1) / 2 + h^2 (f0' - f1') / 12
/// (error O(h^5), the order of the Sharma step itself) without another field evaluation;
/// straight steps across uniform cells and the last chord, at most the surface tolerance long,
/// add n times their length. With `field`, that field is carried along the path
/// (TransportField, step by step) from `d` to `*dout`.
template <bool kMesh, bool kOpticalPath = false>
GrinOutcome IntegrateToSurface(const Simulator::Impl& im, const IndexField& f,
                               const GrinSettings& cfg, int obj, const Vec3& o, const Vec3& d,
                               Hit* hit, Vec3* hp, Vec3* dout, TraceCounters& c,
                               const ObjectShifts* shifts = nullptr, double* opl = nullptr,
                               std::array<std::complex<double>, 3>* field = nullptr) {
  const UniformCells* uniform = im.uniform[obj].empty() ? nullptr : &im.uniform[obj];
  const Vec3 center = ObjectCenter(im, obj, shifts);  // the field moves with its object
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
    if (path >= clear) clear = geo.SurfaceClearance(s.r, shifts);
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
          crosses = geo.Intersect<kMesh>(s.r, dir, &h, shifts) && h.t <= free;
        }
        if (crosses) {
          *hit = h;
          *hp = s.r + dir * h.t;
          *dout = dir;
          if constexpr (kOpticalPath) *opl += s.n * h.t;
          return GrinOutcome::kHit;
        }
        if constexpr (kOpticalPath) *opl += s.n * free;
        s = MakeGrinPoint(f, center, s.r + dir * free, s.t);
        moved(free);
        continue;
      }
    }
    GrinPoint s1 = s;
    double used = 0, next = dt;
    [[maybe_unused]] GridCell start_cell;  // the polynomial a cell step's stages used
    if (cell_steps) {
      if constexpr (kOpticalPath) start_cell = f.Cell(s.r - center);
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
        crosses = L > 0 && geo.Intersect<kMesh>(s.r, chord / L, &h, shifts) && h.t <= L;
      }
      if (!crosses) {
        if (central) ProjectOnInvariants(f, center, angular_momentum, &s1);
        if constexpr (kOpticalPath) {
          // A cell step ends just past a face, where the gradient jumps: the end's derivative
          // is the start cell's polynomial's, the field the step integrated.
          Vec3 d1 = s1.d;
          if (cell_steps && shrink == 0) {
            double n1;
            IndexField::EvalInCell(start_cell, s1.r - center, &n1, &d1);
            d1 = d1 * n1;
          }
          const double f0 = s.n * s.n, f1 = s1.n * s1.n;
          const double g0 = 2 * Dot(s.d, s.t), g1 = 2 * Dot(d1, s1.t);  // d(n^2)/dt
          *opl += used * (f0 + f1) / 2 + used * used * (g0 - g1) / 12;
        }
        if (field) TransportField(*field, s.r, s1.r, Normalize(s.t), Normalize(s1.t));
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
        if constexpr (kOpticalPath) *opl += s.n * h.t;
        // In a steep gradient the direction at the step's end may already bend back inward;
        // the crossing chord points outward by construction, so leave along it then.
        if (Dot(*dout, h.normal) <= 0) *dout = chord / L;
        if (field) TransportField(*field, s.r, *hp, Normalize(s.t), *dout);
        return GrinOutcome::kHit;
      }
      // Aim the (shorter) step at the crossing point; it is within the accepted error. Near a
      // tangent exit the straight chord leaves the surface much later than the curved path
      // (both bend alike), so aiming shortened the step by ~0.1 % a try and after 60 tries the
      // ray left at the chord's far end, past its true exit and turned backwards.
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

/// A physical-optics ray's branch choices and field (Simulator::TraceFieldRay) as
/// TraceObjects carries them.
struct FieldTrace {
  Simulator::FieldRay* ray = nullptr;
  uint32_t reflect_mask = 0;
  double index_after = 1;  // the medium's index after the last event
};

/// The field of a physical-optics ray across one surface: the branch its mask chooses (total
/// internal reflection always reflects), the s and p parts of its complex field times the
/// power-normalised amplitude coefficients (ComplexFresnel). Returns whether it reflects.
inline bool FieldBranch(FieldTrace& ft, bool tir, const Vec3& d, const Vec3& nf, const Vec3& t,
                        double n1, double n2, double cos_i, double cos_t) {
  Simulator::FieldRay& r = *ft.ray;
  const bool asked = (ft.reflect_mask >> r.events) & 1u;
  ++r.events;
  if (tir && !asked) r.evanescent = true;
  const bool reflect = tir || asked;
  Vec3 s_dir = Cross(d, nf);
  const double sl = Length(s_dir);
  // At normal incidence any s direction will do (s and p have the same coefficients there).
  s_dir = sl > 1e-12 ? s_dir / sl : RandomPerpendicular(d, 0.0);
  const Vec3 p_in = Cross(s_dir, d), dn = reflect ? Reflect(d, nf) : t, p_out = Cross(s_dir, dn);
  using C = std::complex<double>;
  const C es = r.field[0] * s_dir.x + r.field[1] * s_dir.y + r.field[2] * s_dir.z;
  const C ep = r.field[0] * p_in.x + r.field[1] * p_in.y + r.field[2] * p_in.z;
  const FresnelAmplitudes fa = ComplexFresnel(n1, n2, cos_i);
  const double power = reflect ? 1.0 : std::sqrt(n2 * cos_t / (n1 * cos_i));
  const C as = (reflect ? fa.rs : fa.ts * power) * es, ap = (reflect ? fa.rp : fa.tp * power) * ep;
  r.field = {as * s_dir.x + ap * p_out.x, as * s_dir.y + ap * p_out.y, as * s_dir.z + ap * p_out.z};
  ft.index_after = reflect ? n1 : n2;
  return reflect;
}

/// Traces a ray through the objects until it leaves them all (or ends). Updates o, d (and the
/// polarisation) to the ray leaving the last surface; returns true with *fate set when the ray
/// ended inside the objects (interaction cap, numerical loss, step cap). `seen`: the objects'
/// indices, fields and positions at this ray's wavelength and time (RayObjects). Each surface
/// met is the interface event the packet path's sphere stage runs too (stages-inl.h,
/// InterfaceEvent), on one lane. With kOpticalPath, `*opl` receives the optical path, the
/// integral of n ds, from o as given to o as returned (the last surface's hit point plus its
/// offset).
/// With kField (which needs kOpticalPath), `*ft` chooses each branch and carries the ray's field
/// (FieldBranch), and its ray records the path's segments.
template <PartialReflection kPR, bool kMesh, bool kOpticalPath = false, bool kField = false>
bool TraceObjects(const Simulator::Impl& im, const TraceSpec& trace, RayRng& rng, Vec3& o, Vec3& d,
                  Vec3& pol, TraceCounters& c, Fate* fate_out, const RayObjects& seen = {},
                  double* opl = nullptr, FieldTrace* ft = nullptr) {
  static_assert(!kField || kOpticalPath, "a field ray records its optical path");
  const Geometry& geo = im.geometry;
  // Objects the ray is inside, innermost last (nested objects: a bubble in a drop); their count
  // is path.depth.
  int stack[kMaxNesting];
  const double* const index = seen.index ? seen.index : im.index.data();
  const IndexField* const* const field = seen.field ? seen.field : im.field.data();
  const ObjectShifts* const moved = seen.moved;
  auto index_at = [&](int obj, const Vec3& x) {
    if (obj < 0) return im.medium;
    if (im.has_grin && field[obj]) return field[obj]->Index(x - ObjectCenter(im, obj, moved));
    return index[obj];
  };
  st::ObjectPath<L1> path = st::ObjectPath<L1>::Start();
  st::Outcome<L1> out = st::Outcome<L1>::Open();
  auto v3 = [](const Vec3& v) { return st::V3<L1>{v.x, v.y, v.z}; };
  if constexpr (kOpticalPath) *opl = 0;
  [[maybe_unused]] Vec3 from = o;  // where the path's current segment began (the last hit)
  for (;;) {
    Hit h;
    Vec3 hp;
    const int depth = static_cast<int>(path.depth);
    const int cur = depth ? stack[depth - 1] : -1;
    if (im.has_grin && cur >= 0 && field[cur]) {
      // (The offset from the last hit point, within the surface's epsilon, at the index there.)
      if constexpr (kOpticalPath) *opl += index_at(cur, o) * Length(o - from);
      std::array<std::complex<double>, 3>* carried = nullptr;
      if constexpr (kField) carried = &ft->ray->field;
      const GrinOutcome g = IntegrateToSurface<kMesh, kOpticalPath>(
          im, *field[cur], trace.grin, cur, o, d, &h, &hp, &d, c, moved, opl, carried);
      if (g != GrinOutcome::kHit) {
        out.Mark(true, g == GrinOutcome::kStepCap ? Fate::kGrinStepCap : Fate::kLostInside);
        break;
      }
    } else {
      ++c.shape_queries;
      if constexpr (kMesh) ++c.mesh_queries;
      if (!geo.Intersect<kMesh>(o, d, &h, moved)) {
        if constexpr (kOpticalPath) *opl += index_at(cur, o) * Length(o - from);
        break;
      }
      hp = o + d * h.t;
      if constexpr (kOpticalPath) *opl += index_at(cur, hp) * Length(hp - from);
    }
    if constexpr (kOpticalPath) from = hp;
    if (path.events == 0) ++c.rays_hitting_objects;
    int on_stack = -1;  // where the surface's object is on the stack
    for (int k = depth - 1; k >= 0; --k)
      if (stack[k] == h.object) {
        on_stack = k;
        break;
      }
    // The medium beyond a surface being left is the innermost enclosing object other than
    // the one left.
    auto indices = [&](const st::FacedSurface<L1>& face, double& n1, double& n2) {
      if (face.entering) {
        n1 = index_at(cur, hp), n2 = index_at(h.object, hp);
        return;
      }
      int outer = -1;
      for (int k = depth - 1; k >= 0; --k)
        if (stack[k] != h.object) {
          outer = stack[k];
          break;
        }
      n1 = index_at(h.object, hp), n2 = index_at(outer, hp);
    };
    auto draw = [&](bool tir, const st::FacedSurface<L1>& face, double n1, double n2, double cos_t,
                    const st::V3<L1>& t, bool&, st::Outcome<L1>&) {
      if constexpr (kField) {
        return FieldBranch(*ft, tir, d, Vec3(face.nf.x, face.nf.y, face.nf.z), Vec3(t.x, t.y, t.z),
                           n1, n2, face.cos_i, cos_t);
      }
      if (tir) return true;
      if constexpr (kPR == PartialReflection::kUnpolarized) {
        ++c.fresnel_evaluations;
        return rng.Uniform() < st::FresnelReflectance<L1>(n1, n2, face.cos_i, cos_t);
      } else if constexpr (kPR == PartialReflection::kPolarized) {
        ++c.fresnel_evaluations;
        // Split the field into s (perpendicular to the plane of incidence) and p parts;
        // reflect with the power-weighted reflectance, then carry the new s/p mixture.
        const Vec3 nf(face.nf.x, face.nf.y, face.nf.z), dt(t.x, t.y, t.z);
        const FresnelCoefficients fc = Fresnel(n1, n2, face.cos_i, cos_t);
        Vec3 s_dir = Cross(d, nf);
        const double sl = Length(s_dir);
        s_dir = sl > 1e-12 ? s_dir / sl : RandomPerpendicular(d, 0.0);
        const double es = Dot(pol, s_dir), ep = Dot(pol, Cross(s_dir, d));
        const double R = es * es * fc.Rs + ep * ep * fc.Rp;
        const bool reflect = rng.Uniform() < R;
        const Vec3 dn = reflect ? Reflect(d, nf) : dt;
        const double as = reflect ? fc.rs * es : (1 + fc.rs) * es;            // t_s = 1 + r_s
        const double ap = reflect ? fc.rp * ep : (1 + fc.rp) * ep * n1 / n2;  // t_p
        const Vec3 e = s_dir * as + Cross(s_dir, dn) * ap;
        const double el = Length(e);
        pol = el > 0 ? e / el : RandomPerpendicular(dn, 0.25);
        return reflect;
      } else {
        return false;
      }
    };
    st::V3<L1> dl = v3(d), ol = v3(o);
    bool active = true;
    const st::StackMoves<L1> moves =
        st::InterfaceEvent<L1>(trace.max_interactions, v3(hp), v3(h.normal), geo.epsilon(h.object),
                               on_stack >= 0, dl, ol, active, path, out, indices, draw);
    d = Vec3(dl.x, dl.y, dl.z), o = Vec3(ol.x, ol.y, ol.z);
    if (!active) break;
    if (moves.push) stack[depth] = h.object;
    if (moves.pop)
      for (int m = on_stack; m + 1 < depth; ++m) stack[m] = stack[m + 1];
    if constexpr (kField) {
      Simulator::FieldRay& r = *ft->ray;
      const int now = static_cast<int>(path.depth);
      const int inner = now ? stack[now - 1] : -1;
      if (r.n_segments < int(r.segments.size()))
        r.segments[r.n_segments++] = {
            hp,      d, *opl, ft->index_after, im.has_grin && inner >= 0 && field[inner] != nullptr,
            h.normal};
    }
  }
  c.interface_events += uint64_t(path.interface_events);
  if (path.path_class >= 0) ++c.path_class[path.path_class];
  out.Mark(path.depth > 0, Fate::kLostInside);
  *fate_out = out.settled ? st::FateOf(out.code) : Fate::kDetected;
  return out.settled;
}

}  // namespace raymatch::simulate
