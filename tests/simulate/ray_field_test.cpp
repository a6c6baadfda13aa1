// Physical optics from rays: field rays (Simulator::TraceFieldRay) and the angular spectrum of a
// plane wave behind an object (ray_field.h) against known answers.
#include "raymatch/simulate/ray_field.h"

#include <gtest/gtest.h>
#include <tbb/global_control.h>

#include <cmath>
#include <cstdio>

#include "raymatch/simulate/interfaces.h"
#include "raymatch/simulate/mie.h"
#include "test_scenes.h"

namespace raymatch::simulate {
namespace {

using testing::MicroscopeScene;
using testing::SphereObject;
using C = std::complex<double>;

Scene SphereIn(double radius, double n, double medium) {
  Scene s = MicroscopeScene();
  s.medium_index = medium;
  s.objects = {SphereObject(radius, n)};
  return s;
}

// A slab of parabolic gradient index, n^2 = nm^2 (1 - g^2 (x^2 + y^2)), in a medium of its axis'
// index nm: a gradient-index rod lens that is a phase object (its faces reflect below 1e-4
// where g rho < 0.2). `turn_deg` turns the box about z (the field is symmetric about it).
Scene LensSlab(double half_width, double thickness, double g_per_um, double nm,
               double turn_deg = 0) {
  Scene s = MicroscopeScene();
  s.medium_index = nm;
  ObjectSpec o = testing::BoxObject({half_width, half_width, thickness / 2}, nm);
  o.rotation_deg = {0, 0, turn_deg};
  auto f = std::make_shared<IndexField>();
  f->type = IndexFieldType::kParabolic;
  f->n0 = nm;
  f->g_per_um = g_per_um;
  o.index_field = f;
  s.objects = {o};
  return s;
}

double Norm2(const CVec3& e) { return std::norm(e[0]) + std::norm(e[1]) + std::norm(e[2]); }

C DotC(const CVec3& e, const Vec3& v) { return e[0] * v.x + e[1] * v.y + e[2] * v.z; }

// A field ray's branches partition its power: at each surface the power-normalised Fresnel
// coefficients satisfy |r|^2 + |t|^2 n2 cos t / (n1 cos i) = 1 (Born and Wolf, sec. 1.5.3), so
// over every reflect/refract sequence of up to 8 events (the rays still inside after 8 keep
// theirs) the |field|^2 sum to 1, for any polarisation. Each branch is counted once: a mask's
// bits beyond the ray's events choose nothing, and a transmission asked for beyond the critical
// angle (evanescent) is the reflection's twin. A sphere above the medium's index and a bubble
// below it (total internal reflection at its first surface beyond h = R / 1.333).
TEST(FieldRay, BranchesShareThePowerThatEntered) {
  const CVec3 pols[3] = {CVec3{1.0, 0.0, 0.0}, CVec3{0.0, 1.0, 0.0},
                         CVec3{C(0.6, 0), C(0, 0.8), 0.0}};
  for (double n : {1.40, 1.0}) {
    const Simulator sim(SphereIn(10, n, 1.333));
    for (double h : {0.0, 3.0, 7.0, 8.0, 9.5, 9.9})
      for (const CVec3& e0 : pols) {
        double total = 0;
        int branches = 0;
        for (uint32_t mask = 0; mask < 256; ++mask) {
          const Simulator::FieldRay r = sim.TraceFieldRay({h, 0.3, -30}, {0, 0, 1}, e0, mask, 8);
          if (r.evanescent || (r.events < 32 && (mask >> r.events) != 0)) continue;
          ASSERT_TRUE(!r.ended || r.fate == Fate::kInteractionCap);
          ++branches;
          total += Norm2(r.field);
          if (!r.ended) EXPECT_LT(std::abs(DotC(r.field, r.direction)), 1e-12) << "transverse";
        }
        const bool tir = n < 1.333 && std::hypot(h, 0.3) > 10 / 1.333;
        EXPECT_GT(branches, tir ? 0 : 2) << "n " << n << " h " << h;
        EXPECT_NEAR(total, 1.0, 1e-12) << "n " << n << " h " << h;
      }
  }
}

// In a gradient-index medium the field turns only as much as it must to stay transverse to the
// ray (Rytov's law, Born and Wolf sec. 3.1.3), so along a helical ray it comes back turned
// about the ray by the solid angle its tangent sweeps, 2 pi (1 - cos theta) a turn (Tomita and
// Chiao, Phys. Rev. Lett. 57, 937 (1986); counter-clockwise for a tangent that circles the
// axis counter-clockwise). In the parabolic medium n^2 = n0^2 (1 - g^2 rho^2) the ray with
// transverse optical momentum n0 g rho at radius rho is the helix of that radius (the ray
// equation d^2 r / dt^2 = grad(n^2) / 2, t = integral ds / n, is a harmonic oscillator of
// frequency n0 g across the axis), with tan theta = g rho / sqrt(1 - 2 g^2 rho^2) and one turn
// per 2 pi sqrt(1 - 2 g^2 rho^2) / g along z. Its two faces pass the s field with
// t_s^2 n2 cos t / (n1 cos i) each (ComplexFresnel). The integrator (1e-5 um a step) leaves
// the ray's direction and the rotation within 1e-6 of the helix's; the bound is 1e-5 rad, 3e-4
// of a turn's rotation. Fails when the field is not carried along the curved path (rotation 0;
// the power then also falls by the field's part along the exit direction).
TEST(FieldRay, HelicalRayTurnsTheFieldByTheSolidAngleItsTangentSweeps) {
  const double nm = 1.333, g = 0.05, rho = 2;
  const double vz = std::sqrt(1 - 2 * g * g * rho * rho), turn = 2 * M_PI * vz / g;
  const double theta = std::atan(g * rho / vz);
  const Vec3 d = Normalize(Vec3(0, g * rho, std::sqrt(1 - g * g * rho * rho)));  // outside
  const Vec3 e1 = Normalize(Cross(d, Vec3(0, 0, 1))), e2 = Cross(d, e1);         // s, p
  const double n_in = nm * std::sqrt(1 - g * g * rho * rho);
  const FresnelAmplitudes fa = ComplexFresnel(nm, n_in, d.z);
  const double cos_t = std::sqrt(1 - std::pow(nm / n_in, 2) * (1 - d.z * d.z));
  const double ts2 = std::norm(fa.ts) * n_in * cos_t / (nm * d.z);
  for (int turns : {1, 2}) {
    const Simulator sim(LensSlab(5, turns * turn, g, nm));
    // Started 5 um in front of the face so as to enter it at (rho, 0).
    const Vec3 start = Vec3(rho, 0, -0.5 * turns * turn) - d * (5 / d.z);
    const Simulator::FieldRay r = sim.TraceFieldRay(start, d, {e1.x, e1.y, e1.z}, 0, 2);
    ASSERT_FALSE(r.ended);
    ASSERT_EQ(r.events, 2);
    EXPECT_LT(Length(r.direction - d), 1e-5);
    const double rotation = std::atan2(DotC(r.field, e2).real(), DotC(r.field, e1).real());
    const double expected = 2 * M_PI * (1 - std::cos(theta)) * turns;
    std::printf("%d turns: rotation %.6f rad, expected %.6f; |E|^2 %.8f, expected %.8f\n", turns,
                rotation, expected, Norm2(r.field), ts2 * ts2);
    EXPECT_NEAR(rotation, expected, 1e-5);
    EXPECT_NEAR(Norm2(r.field), ts2 * ts2, 1e-6);
    EXPECT_LT(std::abs(DotC(r.field, r.direction)), 1e-9);
  }
}

// Beyond the critical angle a bubble (n 1 in water) reflects all the light with Fresnel's
// phases (Born and Wolf, eq. 1.5.58: ComplexFresnel), different for s and p: the field ray
// carries r_s and r_p with their phases, along the mirror direction, whichever branch was
// asked for (a transmission asked for is marked evanescent). Its optical path is the medium's
// index times the two straight legs.
TEST(FieldRay, TotalReflectionCarriesFresnelsPhases) {
  const double R = 10, nm = 1.333, h = 9.0;
  const Simulator sim(SphereIn(R, 1.0, nm));
  const double cos_i = std::sqrt(1 - (h / R) * (h / R));
  const FresnelAmplitudes fa = ComplexFresnel(nm, 1.0, cos_i);
  ASSERT_TRUE(fa.total);
  ASSERT_GT(std::abs(std::arg(fa.rs) - std::arg(fa.rp)), 0.3);  // the phases differ
  const Vec3 hit(h, 0, -R * cos_i), normal = hit / R, d(0, 0, 1);
  const Vec3 out = d - normal * (2 * Dot(d, normal));
  // s is y (the incidence plane is x-z); p in and out are s x d and s x d_out (any common sign
  // of s cancels).
  const Vec3 s_dir(0, 1, 0), p_in = Cross(s_dir, d), p_out = Cross(s_dir, out);
  for (uint32_t mask : {0u, 1u}) {
    const Simulator::FieldRay rs = sim.TraceFieldRay({h, 0, -30}, d, {0.0, 1.0, 0.0}, mask, 4);
    const Simulator::FieldRay rp = sim.TraceFieldRay({h, 0, -30}, d, {1.0, 0.0, 0.0}, mask, 4);
    for (const auto* r : {&rs, &rp}) {
      ASSERT_FALSE(r->ended);
      EXPECT_EQ(r->events, 1);
      EXPECT_EQ(r->evanescent, mask == 0u);
      EXPECT_LT(Length(r->direction - out), 1e-12);
      const double legs = (hit.z + 30) + Dot(r->origin - hit, out);
      EXPECT_NEAR(r->optical_path_um, nm * legs, 1e-7);
    }
    EXPECT_LT(std::abs(rs.field[1] - fa.rs), 1e-12) << rs.field[1] << " against " << fa.rs;
    EXPECT_LT(std::abs(rs.field[0]) + std::abs(rs.field[2]), 1e-12);
    const C ep = fa.rp * Dot(Vec3(1, 0, 0), p_in);
    for (int c = 0; c < 3; ++c)
      EXPECT_LT(std::abs(rp.field[c] - ep * (c == 0   ? p_out.x
                                             : c == 1 ? p_out.y
                                                      : p_out.z)),
                1e-12)
          << c;
  }
}

// The refracted branch (mask 0) of a field ray is the tracer's own ray: the same exit point,
// direction and optical path as TraceThroughObjects (partial reflection off), through a
// homogeneous sphere and a Luneburg lens (a gradient-index field, whose path is curved); its
// recorded segments start at the surfaces with the media's indices and the optical path so far.
TEST(FieldRay, RefractedBranchIsTheTracersRay) {
  const double R = 10;
  for (int grin = 0; grin < 2; ++grin) {
    Scene s = grin ? MicroscopeScene() : SphereIn(R, 1.40, 1.333);
    if (grin) s.medium_index = 1.0, s.objects = {testing::LuneburgSphere(R)};
    const Simulator sim(s);
    for (double h : {0.0, 2.0, 5.0, 8.0, 9.9}) {
      const Vec3 start(h, 0.3, -3 * R), d(0, 0, 1);
      const auto e = sim.TraceThroughObjects(start, d);
      const Simulator::FieldRay r = sim.TraceFieldRay(start, d, {1.0, 0.0, 0.0}, 0, 4);
      ASSERT_FALSE(e.ended || r.ended) << h;
      EXPECT_EQ(r.events, 2);
      EXPECT_LT(Length(r.origin - e.origin), 1e-12) << h;
      EXPECT_LT(Length(r.direction - e.direction), 1e-12) << h;
      EXPECT_NEAR(r.optical_path_um, e.optical_path_um, 1e-12 * e.optical_path_um) << h;
      ASSERT_EQ(r.n_segments, 3);
      const auto& in = r.segments[1];
      EXPECT_NEAR(Length(in.point), R, 1e-6);
      EXPECT_EQ(in.curved, grin == 1);
      EXPECT_NEAR(in.index, grin ? 1.0 : 1.40, 1e-9);
      EXPECT_NEAR(in.optical_path_um, s.medium_index * (in.point.z - start.z), 1e-9);
      EXPECT_NEAR(r.segments[2].index, s.medium_index, 0);
    }
  }
}

/// A square spectrum grid about k_t = 0 out to k NA / n_medium, dk = 2 pi / (8 radius).
SpectrumGrid GridFor(const Scene& s, double radius) {
  const double k = 2 * M_PI * s.medium_index / s.wavelength_um;
  SpectrumGrid g;
  g.dk = 2 * M_PI / (8 * radius);
  g.k_max = k * s.optics.na / s.medium_index;
  g.nx = g.ny = 2 * int(g.k_max / g.dk) + 3;
  g.kx0 = g.ky0 = -g.dk * (g.nx / 2);
  return g;
}

// An opaque object (no branches, max_events 0) leaves Kirchhoff's shadow: minus the incident
// wave over its silhouette, whose transform for a sphere seen along a wave tilted by t in x-z
// is the ellipse of semi-axes R / cos t and R on the z-plane through its centre:
// A = -(E0 transverse) / (2 pi)^2 x 2 pi a b J1(Q) / Q, Q = |(a q_x, b q_y)|, q = k_t - k_in,t
// (Goodman, Introduction to Fourier Optics, sec. 4.4.2). The outline is found by bisection to
// well below 1e-4 of the radius.
TEST(RayField, OpaqueSilhouetteDiffractsAsItsEllipse) {
  const double R = 5;
  const Scene s = SphereIn(R, 1.40, 1.333);
  const Simulator sim(s);
  const double k = 2 * M_PI * s.medium_index / s.wavelength_um;
  const SpectrumGrid g = GridFor(s, R);
  RaySpectrumSettings set;
  set.max_events = 0;
  for (double tilt_deg : {0.0, 12.0}) {
    const double t = tilt_deg * M_PI / 180;
    const Vec3 din(std::sin(t), 0, std::cos(t));
    const CVec3 e0 = {std::cos(t), 0.0, -std::sin(t)};
    const RaySpectrum rs = RayAngularSpectrum(sim, din, e0, {0, 0, 0}, g, set);
    const double a = R / std::cos(t), b = R;
    EXPECT_NEAR(rs.shadow_area_um2, M_PI * a * b, 1e-4 * M_PI * a * b);
    double worst = 0;
    const double peak = 2 * M_PI * a * b / 2 / (4 * M_PI * M_PI);
    for (int j = 0; j < g.ny; ++j)
      for (int i = 0; i < g.nx; ++i) {
        const double kx = g.kx0 + i * g.dk, ky = g.ky0 + j * g.dk;
        if (kx * kx + ky * ky > g.k_max * g.k_max) continue;
        const double qx = kx - k * din.x, qy = ky, Q = std::hypot(a * qx, b * qy);
        const double airy = Q < 1e-9 ? 0.5 : std::cyl_bessel_j(1, Q) / Q;
        const Vec3 u(kx / k, ky / k, std::sqrt(1 - (kx * kx + ky * ky) / (k * k)));
        const C along = DotC(e0, u);
        const C f = -2 * M_PI * a * b * airy / (4 * M_PI * M_PI);
        const CVec3& got = rs.a[size_t(j) * g.nx + i];
        const double uu[3] = {u.x, u.y, u.z};
        for (int c = 0; c < 3; ++c)
          worst = std::max(worst, std::abs(got[c] - f * (e0[c] - along * uu[c])));
      }
    EXPECT_LT(worst, 1e-4 * peak) << "tilt " << tilt_deg;
    EXPECT_EQ(rs.branches, 0);
  }
}

// The shadow's outline closes around a polygon too: a square turned about the axis, whose
// corners poke through the lattice's edges between nodes outside it, has its area to within
// the corner tips the finest outline cells cut off (4 x half a cell, 0.004 um^2) and the
// bisection's precision. Fails (0.2 um^2 a corner at 17 deg) when the cells next to the
// outline are not marched at the finest level: the outline has gaps where a fine cell meets a
// coarse one.
TEST(RayField, TurnedSquaresShadowIsItsArea) {
  const double a = 15;
  for (double turn : {0.0, 5.0, 17.0, 30.0, 45.0}) {
    Scene s = MicroscopeScene();
    s.medium_index = 1.333;
    ObjectSpec o = testing::BoxObject({a, a, 10}, 1.40);
    o.rotation_deg = {0, 0, turn};
    s.objects = {o};
    const Simulator sim(s);
    SpectrumGrid g;
    g.dk = 2 * M_PI / 48, g.k_max = 1, g.nx = g.ny = 5, g.kx0 = g.ky0 = -2 * g.dk;
    RaySpectrumSettings set;
    set.max_events = 0;
    const RaySpectrum rs = RayAngularSpectrum(sim, {0, 0, 1}, {1.0, 0.0, 0.0}, {0, 0, 0}, g, set);
    EXPECT_NEAR(rs.shadow_area_um2, 4 * a * a, 0.005) << turn << " deg";
  }
}

/// The exact scattered spectrum of an axial wave polarised along x on `g`: the far field
/// E_s = exp(ikr) / (-ikr) [S2 E_par e_par + S1 E_perp e_perp] (Bohren and Huffman, ch. 4) has
/// the angular-spectrum density A = -E_s-amplitude / (2 pi k^2 cos theta) (wave_image.h).
std::vector<CVec3> MieSpectrum(const Scene& s, const SpectrumGrid& g) {
  const double k = 2 * M_PI * s.medium_index / s.wavelength_um;
  const ObjectSpec& o = s.objects[0];
  const MieCoefficients mc = ComputeMie(o.index / s.medium_index, k * o.radius_um);
  std::vector<CVec3> a(size_t(g.nx) * g.ny);
  const Vec3 kin(0, 0, 1), pol(1, 0, 0);
  for (int j = 0; j < g.ny; ++j)
    for (int i = 0; i < g.nx; ++i) {
      const double kx = g.kx0 + i * g.dk, ky = g.ky0 + j * g.dk, kt2 = kx * kx + ky * ky;
      if (kt2 > g.k_max * g.k_max) continue;
      const double ct = std::sqrt(1 - kt2 / (k * k));
      const Vec3 ks(kx / k, ky / k, ct);
      const MieAmplitudes sa = Amplitudes(mc, std::acos(std::clamp(ct, -1.0, 1.0)));
      Vec3 e_perp = Cross(kin, ks);
      const double cn = Length(e_perp);
      e_perp = cn > 1e-12 ? e_perp / cn : Vec3(0, 1, 0);
      const Vec3 e_par_i = Cross(e_perp, kin), e_par_s = Cross(e_perp, ks);
      const Complex ap = sa.s2 * Dot(pol, e_par_i), an = sa.s1 * Dot(pol, e_perp);
      const Complex f = -1.0 / (2 * M_PI * k * k * ct);
      CVec3& v = a[size_t(j) * g.nx + i];
      v = {f * (ap * e_par_s.x + an * e_perp.x), f * (ap * e_par_s.y + an * e_perp.y),
           f * (ap * e_par_s.z + an * e_perp.z)};
    }
  return a;
}

/// The relative rms difference of `a` from `ref` (`absolute`: the rms difference) over the grid
/// nodes with scattering angle in [lo_deg, hi_deg).
double RelRms(const std::vector<CVec3>& a, const std::vector<CVec3>& ref, const SpectrumGrid& g,
              double k, double lo_deg, double hi_deg, bool absolute = false) {
  double num = 0, den = 0, nodes = 0;
  for (int j = 0; j < g.ny; ++j)
    for (int i = 0; i < g.nx; ++i) {
      const double kx = g.kx0 + i * g.dk, ky = g.ky0 + j * g.dk, kt = std::hypot(kx, ky);
      if (kt > g.k_max) continue;
      const double th = std::asin(kt / k) * 180 / M_PI;
      if (th < lo_deg || th >= hi_deg) continue;
      const size_t p = size_t(j) * g.nx + i;
      for (int c = 0; c < 3; ++c)
        num += std::norm(a[p][c] - ref[p][c]), den += std::norm(ref[p][c]);
      ++nodes;
    }
  return std::sqrt(num / (absolute ? nodes : den));
}

/// The rms of |a| over the grid nodes with scattering angle in [lo_deg, hi_deg).
double Rms(const std::vector<CVec3>& a, const SpectrumGrid& g, double k, double lo_deg,
           double hi_deg) {
  return RelRms(a, std::vector<CVec3>(a.size()), g, k, lo_deg, hi_deg, true);
}

// A non-absorbing sphere sends forward the power that met it (its silhouette's area times
// |E0|^2) less what its first surface reflects back and what its higher branches send back
// or keep (at most the first surface's reflected power again: each inner reflection takes a
// fraction R of what reaches it, R the same inside and out by Stokes' relations). The lattice
// resolves the branches' edges to its finest step: its cells there are off by at most the
// outline's length times that step, either way. Above, in and below the medium's index (1.20:
// total reflection beyond 64 degrees). It fails when the rays beyond the taper are not counted
// (4 % of the 1.40 sphere's power).
TEST(RayField, ForwardPowerIsWhatMetTheObjectLessWhatReflectsBack) {
  const double R = 5, nm = 1.333;
  for (double n : {1.40, 1.333, 1.20}) {
    const Scene s = SphereIn(R, n, nm);
    const Simulator sim(s);
    const RaySpectrum rs =
        RayAngularSpectrum(sim, {0, 0, 1}, {1.0, 0.0, 0.0}, {0, 0, 0}, GridFor(s, R));
    double back = 0, reflected = 0;
    const int rings = 20000;
    for (int q = 0; q < rings; ++q) {
      const double h = R * (q + 0.5) / rings, ci = std::sqrt(1 - h * h / (R * R));
      const double dA = 2 * M_PI * h * R / rings, r = FresnelReflectance(nm, n, ci);
      reflected += r * dA;
      if (ci > std::sqrt(0.5)) back += r * dA;
    }
    const RaySpectrumSettings set;
    const double h_finest = s.wavelength_um / nm / double(1 << set.refine_levels);
    const double missing = rs.shadow_area_um2 - back - rs.branch_power;
    std::printf("n %.3f: forward %.5f, missing %.5f of the shadow (rim %.5f, reflected %.5f)\n", n,
                rs.branch_power / rs.shadow_area_um2, missing / rs.shadow_area_um2,
                2 * M_PI * R * h_finest / rs.shadow_area_um2, reflected / rs.shadow_area_um2);
    EXPECT_NEAR(rs.shadow_area_um2, M_PI * R * R, 1e-4 * M_PI * R * R);
    const double rim = 2 * M_PI * R * h_finest;
    EXPECT_GE(missing, -rim) << n;
    EXPECT_LE(missing, rim + (reflected - back)) << n;
  }
}

// A sphere of the medium's index changes nothing: its straight-through branch is the incident
// wave over the silhouette, which cancels the shadow. What is left is the exit plane's sampling
// of the sheet's edge, each node taking the share of its cell the sheet covers: over the
// objective's band, relative to the shadow's own spectrum, 0.12 % in the forward 4 degrees and
// 1.9 % at 16-19 degrees where the shadow's spectrum is weak (R 5 and 10 alike). Sampled at the
// nodes alone (a staircase) it was 0.3 % and 9 % at 14-18 degrees, and fails.
TEST(RayField, MatchedSphereScattersNothing) {
  const double nm = 1.333;
  for (double R : {5.0, 10.0}) {
    const Scene s = SphereIn(R, nm, nm);
    const Simulator sim(s);
    const double k = 2 * M_PI * nm / s.wavelength_um;
    const SpectrumGrid g = GridFor(s, R);
    const RaySpectrum rs = RayAngularSpectrum(sim, {0, 0, 1}, {1.0, 0.0, 0.0}, {0, 0, 0}, g);
    RaySpectrumSettings opaque;
    opaque.max_events = 0;
    const std::vector<CVec3> shadow =
        RayAngularSpectrum(sim, {0, 0, 1}, {1.0, 0.0, 0.0}, {0, 0, 0}, g, opaque).a;
    const double bounds[5] = {0.003, 0.012, 0.02, 0.03, 0.04};
    for (int r = 0; r < 5; ++r) {
      const double lo = 4.0 * r, hi = r == 4 ? 19.0 : lo + 4;
      const double ratio = Rms(rs.a, g, k, lo, hi) / Rms(shadow, g, k, lo, hi);
      EXPECT_LT(ratio, bounds[r]) << "R " << R << ", " << lo << "-" << hi << " deg";
    }
  }
}

// Against the exact sphere (Mie theory, mie.h): a 1.40 sphere in water (size parameters 91
// and 181), x polarised, on the objective's band (NA 0.42, 18.4 degrees). Physical optics
// (Kirchhoff's shadow plus geometrical optics' branches) is an asymptotic model: it agrees to
// 2-3 % in the forward lobe, and less well further out where the rim's grazing rays and their
// surface waves (Nussenzveig, Diffraction Effects in Semiclassical Scattering, ch. 9), which
// rays do not carry, matter more. The bounds are the measured errors (docs/physical-optics.md)
// with a margin.
TEST(RayField, SphereAgreesWithMieInTheForwardLobe) {
  const double nm = 1.333;
  const double edges[6] = {0, 3, 6, 10, 14, 19};
  const double bounds[5] = {0.04, 0.09, 0.16, 0.3, 0.5};
  for (double R : {5.0, 10.0}) {
    const Scene s = SphereIn(R, 1.40, nm);
    const Simulator sim(s);
    const double k = 2 * M_PI * nm / s.wavelength_um;
    const SpectrumGrid g = GridFor(s, R);
    const RaySpectrum rs = RayAngularSpectrum(sim, {0, 0, 1}, {1.0, 0.0, 0.0}, {0, 0, 0}, g);
    const std::vector<CVec3> mie = MieSpectrum(s, g);
    std::printf("R %g um: %d branches, %llu rays, %llu triangles\n", R, rs.branches,
                static_cast<unsigned long long>(rs.rays),
                static_cast<unsigned long long>(rs.triangles));
    for (int r = 0; r < 5; ++r) {
      const double e = RelRms(rs.a, mie, g, k, edges[r], edges[r + 1]);
      std::printf("  %4.1f-%4.1f deg: rms difference %.4f of Mie's\n", edges[r], edges[r + 1], e);
      EXPECT_LT(e, bounds[r]) << "R " << R << ", " << edges[r] << "-" << edges[r + 1] << " deg";
    }
  }
}

// A 1.40 sphere (R 5) focuses its straight-through light at about 10 R behind its centre
// (paraxially m R / (2 (m - 1)), m = 1.40 / 1.333); on an exit plane 12 R behind it every tube
// of that branch has passed two focal lines (a point focus), each worth -pi/2 (Born and Wolf,
// sec. 8.8.4). Counted, the spectrum from that plane is within 21-47 % of the one from the
// centre plane (0-9 degrees); not counted, 76-235 % off. (The remaining difference is real to
// the model: the geometrical sheet is cut at its edge where it is sampled, and that edge
// diffracts differently from there; the centre plane is the one that agrees with Mie.)
TEST(RayField, ExitPlanePastTheFocusCountsItsFocalLines) {
  const double R = 5, nm = 1.333;
  const Scene s = SphereIn(R, 1.40, nm);
  const Simulator sim(s);
  const double k = 2 * M_PI * nm / s.wavelength_um;
  SpectrumGrid g = GridFor(s, R);
  const double dk = g.dk / 2;  // a window of 16 R: the light spreads from the focus
  g.nx = g.ny = 2 * int(g.k_max / dk) + 3;
  g.dk = dk, g.kx0 = g.ky0 = -dk * (g.nx / 2);
  const RaySpectrum near = RayAngularSpectrum(sim, {0, 0, 1}, {1.0, 0.0, 0.0}, {0, 0, 0}, g);
  RaySpectrumSettings far_set;
  far_set.exit_plane_um = 12 * R;
  const RaySpectrum far =
      RayAngularSpectrum(sim, {0, 0, 1}, {1.0, 0.0, 0.0}, {0, 0, 0}, g, far_set);
  const std::vector<CVec3> mie = MieSpectrum(s, g);
  const double bounds[3] = {0.3, 0.6, 0.35};
  for (int r = 0; r < 3; ++r) {
    const double lo = 3.0 * r, d = RelRms(far.a, near.a, g, k, lo, lo + 3);
    std::printf("%4.1f-%4.1f deg: far plane from near %.4f, from Mie %.4f (near %.4f)\n", lo,
                lo + 3, d, RelRms(far.a, mie, g, k, lo, lo + 3),
                RelRms(near.a, mie, g, k, lo, lo + 3));
    EXPECT_LT(d, bounds[r]) << lo << " deg";
  }
}

/// The field on the axis at z (um past the origin) of the wave E0 exp(i k z) plus `rs`'s
/// scattered spectrum: E0 exp(i k z) + sum of A exp(i k_z z) dk^2 (x component).
C OnAxis(const RaySpectrum& rs, const SpectrumGrid& g, double k, const CVec3& e0, double z) {
  C u = e0[0] * std::exp(C(0, k * z));
  for (int j = 0; j < g.ny; ++j)
    for (int i = 0; i < g.nx; ++i) {
      const double kx = g.kx0 + i * g.dk, ky = g.ky0 + j * g.dk, kt2 = kx * kx + ky * ky;
      if (kt2 > g.k_max * g.k_max) continue;
      u += rs.a[size_t(j) * g.nx + i][0] * std::exp(C(0, std::sqrt(k * k - kt2) * z)) * g.dk * g.dk;
    }
  return u;
}

/// The lens of the two tests below (a 30 um square, 110.7 um long, g 0.01 / um, in water) on a
/// 48 um window out to 0.45 k, with its rays' crossing of the axis: rho0 the entry radius.
struct SlabLens {
  double a = 15, t = 110.7, g = 0.01, nm = 1.333;
  /// Where the exact ray entering at rho0 crosses the axis past the slab (from its centre):
  /// x = rho0 cos(n0 g tau), z = n(rho0) tau inside (tau = integral ds / n), leaving with the
  /// transverse optical momentum rho0 n0 g sin(n0 g tau_exit), kept across the face.
  double Crossing(double rho0) const {
    const double n = nm * std::sqrt(1 - g * g * rho0 * rho0), tau = t / n;
    const double x = rho0 * std::cos(nm * g * tau), p = rho0 * nm * g * std::sin(nm * g * tau);
    return t / 2 + x / std::tan(std::asin(p / nm));
  }
  SpectrumGrid Grid(double k) const {
    SpectrumGrid gr;
    gr.dk = 2 * M_PI / 48;
    gr.k_max = 0.45 * k;
    gr.nx = gr.ny = 2 * int(gr.k_max / gr.dk) + 3;
    gr.kx0 = gr.ky0 = -gr.dk * (gr.nx / 2);
    return gr;
  }
};

// A thin-lens check: the gradient-index slab (SlabLens) brings the plane wave to a focus at
// the paraxial back focal length cot(g t) / g past its face (the paraxial ray x0 cos(g z)
// leaves with the slope -x0 g sin(g t), kept across the face where the indices match),
// 50.1 um, with spherical aberration: the corner rays (rho0 = a sqrt 2) cross the axis 4 um
// sooner. The wave's on-axis intensity peaks between the two (for primary spherical aberration
// midway, Born and Wolf sec. 9.4.2), and there, for a pupil this far from the diffraction
// limit's depth, it is the focus of a uniform converging wave: power P = (2a)^2 |E0|^2 into the
// solid angle Omega = (2a cos(g t) / BFL)^2 of the exit face seen from the focus, I = P Omega /
// lambda^2 (Fresnel's integral at the focus; Goodman, Introduction to Fourier Optics, sec.
// 5.2), up to its paraxial approximation (sin^2 of 0.19 rad, 3 %). The field's phase sets where
// the focus is (a wrong optical path through the gradient or a phase sign moves or removes it),
// the tubes' amplitudes how bright.
TEST(RayField, GradientIndexSlabFocusesAsARodLens) {
  const SlabLens L;
  const Scene s = LensSlab(L.a, L.t, L.g, L.nm);
  const Simulator sim(s);
  const double k = 2 * M_PI * L.nm / s.wavelength_um, lambda = s.wavelength_um / L.nm;
  const SpectrumGrid g = L.Grid(k);
  const CVec3 e0 = {1.0, 0.0, 0.0};
  const RaySpectrum rs = RayAngularSpectrum(sim, {0, 0, 1}, e0, {0, 0, 0}, g);
  const double paraxial = L.t / 2 + 1 / (L.g * std::tan(L.g * L.t));
  const double corner = L.Crossing(L.a * std::sqrt(2.0));
  double z_peak = 0, i_peak = 0;
  const double dz = 0.25;
  std::vector<double> in;
  for (double z = 95; z <= 112; z += dz) in.push_back(std::norm(OnAxis(rs, g, k, e0, z)));
  const size_t m = size_t(std::max_element(in.begin(), in.end()) - in.begin());
  ASSERT_TRUE(m > 0 && m + 1 < in.size()) << "no focus in 95-112 um";
  const double c = (in[m - 1] - in[m + 1]) / (2 * (in[m - 1] - 2 * in[m] + in[m + 1]));
  z_peak = 95 + (double(m) + c) * dz;
  i_peak = in[m] - 0.25 * (in[m - 1] - in[m + 1]) * c;
  const double bfl = paraxial - L.t / 2;
  const double omega = std::pow(2 * L.a * std::cos(L.g * L.t) / bfl, 2);
  const double i_focus = 4 * L.a * L.a * omega / (lambda * lambda);
  std::printf(
      "peak at %.3f um (paraxial %.3f, corner rays %.3f, midway %.3f), intensity %.1f "
      "(P Omega / lambda^2 %.1f)\n",
      z_peak, paraxial, corner, 0.5 * (paraxial + corner), i_peak, i_focus);
  EXPECT_GT(z_peak, corner);
  EXPECT_LT(z_peak, paraxial);
  EXPECT_NEAR(i_peak / i_focus, 1.0, 0.03);
}

// The exit plane carries the power the lattice sent: for the phase object above (turned by
// 17 deg so that its edges cross the plane's grid at every offset), the branches send forward
// what met the slab (its square's area times |E0|^2) less its faces' reflections (below 1.2e-4
// of it) and the lattice's rim cells (the outline's length times the finest lattice step,
// either way); the plane's samples carry the same, to within the nodes along the sheet's
// straight edges: at 17 deg to the grid they pass the nodes at equidistributed offsets, so an
// edge of N steps holds O(log N) nodes too many or too few (the discrepancy of n tan 17 deg mod
// 1; Kuipers and Niederreiter, Uniform Distribution of Sequences, ch. 2), each h^2: 4 edges x
// ln 450 x h^2 x the sheet's |E|^2 (1.13) is 0.12 um^2, bounded here by 0.25. Fails when the
// field is not carried along the curved rays (0.6 % of the power lost: 5.5 um^2), and when the
// tube's amplitude leaves out the plane's obliquity (1 / sqrt(cos theta): 5.5 um^2).
TEST(RayField, PhaseObjectSendsOnThePowerThatMetIt) {
  const SlabLens L;
  const Scene s = LensSlab(L.a, L.t, L.g, L.nm, 17);
  const Simulator sim(s);
  const double k = 2 * M_PI * L.nm / s.wavelength_um;
  const SpectrumGrid g = L.Grid(k);
  const RaySpectrumSettings set;
  const RaySpectrum rs = RayAngularSpectrum(sim, {0, 0, 1}, {1.0, 0.0, 0.0}, {0, 0, 0}, g, set);
  const double area = 4 * L.a * L.a, outline = 8 * L.a;
  const double h_lattice = s.wavelength_um / L.nm / double(1 << set.refine_levels);
  std::printf("area %.3f, sent %.3f, on the plane %.3f (rim %.3f)\n", area, rs.branch_power,
              rs.plane_power, outline * h_lattice);
  EXPECT_NEAR(rs.shadow_area_um2, area, 1e-4 * area);
  EXPECT_LT(rs.branch_power, area + outline * h_lattice);
  EXPECT_GT(rs.branch_power, area * (1 - 1.2e-4) - outline * h_lattice);
  EXPECT_NEAR(rs.plane_power, rs.branch_power, 0.25);
}

// The same spectrum, bit for bit, on one thread and on all.
TEST(RayField, SameSpectrumForAnyThreadCount) {
  const Scene s = SphereIn(4, 1.40, 1.333);
  const Simulator sim(s);
  const SpectrumGrid g = GridFor(s, 4);
  const Vec3 din = Normalize(Vec3(0.1, 0.05, 1));
  const CVec3 e0 = {C(din.z, 0), 0.0, C(-din.x, 0)};
  const RaySpectrum all = RayAngularSpectrum(sim, din, e0, {0.2, 0, 0}, g);
  RaySpectrum one;
  {
    tbb::global_control only(tbb::global_control::max_allowed_parallelism, 1);
    one = RayAngularSpectrum(sim, din, e0, {0.2, 0, 0}, g);
  }
  ASSERT_EQ(one.a.size(), all.a.size());
  EXPECT_EQ(one.rays, all.rays);
  EXPECT_EQ(one.branch_power, all.branch_power);
  for (size_t p = 0; p < all.a.size(); ++p)
    for (int c = 0; c < 3; ++c) ASSERT_EQ(one.a[p][c], all.a[p][c]) << p;
}

}  // namespace
}  // namespace raymatch::simulate
