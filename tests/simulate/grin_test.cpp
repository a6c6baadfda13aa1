// Gradient-index media against exact answers (Sharma, Kumar and Ghatak, Appl. Opt. 21, 984 (1982);
// Luneburg lens, Maxwell fish-eye, parabolic media).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>

#include "raymatch/core/array_io.h"
#include "raymatch/core/rng.h"
#include "raymatch/simulate/index_field.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/tracer.h"
#include "raymatch/simulate/water.h"
#include "stats.h"
#include "temp_dir.h"
#include "test_scenes.h"

namespace raymatch::simulate {
namespace {

// An empty 3D grid field of nx x ny x nz samples (values to be filled in).
IndexField Grid3D(int nx, int ny, int nz, const Vec3& spacing_um, const Vec3& origin_um) {
  IndexField f;
  f.type = IndexFieldType::kGrid3D;
  f.nx = nx, f.ny = ny, f.nz = nz;
  f.spacing_um = spacing_um;
  f.origin_um = origin_um;
  return f;
}

// Linear n^2 = n0^2 + k.p gives R'' = k/2 (in t = s/n): an exact parabola
// R(t) = R0 + T0 t + k t^2 / 4, which the Sharma scheme reproduces exactly (up to rounding).
TEST(Grin, LinearN2GivesExactParabolasEvenWithHugeSteps) {
  IndexField f;
  f.type = IndexFieldType::kLinearN2;
  f.n0 = 1.5;
  f.k_per_um = {0.02, -0.01, 0.005};
  GrinState s{{1, 2, 3}, Normalize(Vec3(0.2, 0.1, 1)) * f.Index({1, 2, 3})};
  const GrinState s0 = s;
  const double dt = 7.0;
  for (int i = 0; i < 10; ++i) s = SharmaStep(f, Vec3(), s, dt);
  const double t = 10 * dt;
  const Vec3 exact = s0.r + s0.t * t + f.k_per_um * (t * t / 4);
  EXPECT_LT(Length(s.r - exact), 1e-10 * Length(exact)) << Length(s.r - exact);
}

// Parabolic medium n^2 = n0^2 (1 - g^2 (x^2 + y^2)): R'' = -n0^2 g^2 (x, y, 0), so skew rays
// are exact sinusoids in t with angular frequency w = n0 g, and z advances uniformly.
TEST(Grin, ParabolicMediumSkewRayFollowsTheSinusoid) {
  IndexField f;
  f.type = IndexFieldType::kParabolic;
  f.n0 = 1.5;
  f.g_per_um = 0.01;
  GrinSettings cfg;
  cfg.tolerance_um = 1e-9;
  const Vec3 r0(10, -5, 0);
  const Vec3 d0 = Normalize(Vec3(0.1, 0.2, 1));
  GrinState s{r0, d0 * f.Index(r0)};
  const Vec3 t0 = s.t;
  const double w = f.n0 * f.g_per_um;
  double t = 0, dt = 1, used;
  double worst = 0;
  while (t < 3 * 2 * M_PI / w) {  // three periods, ~2 mm of path
    AdaptiveStep(f, Vec3(), cfg, &s, &dt, &used);
    t += used;
    const Vec3 exact(r0.x * std::cos(w * t) + t0.x / w * std::sin(w * t),
                     r0.y * std::cos(w * t) + t0.y / w * std::sin(w * t), r0.z + t0.z * t);
    worst = std::max(worst, Length(s.r - exact));
  }
  // Global error <= steps x tolerance in the worst case; observed far below. Bound: 1e-5 um.
  EXPECT_LT(worst, 1e-5);
}

// Maxwell fish-eye n = n0 / (1 + (r/a)^2) images r1 to -a^2 r1 / |r1|^2 for every direction.
TEST(Grin, FishEyeImagesAPointToItsConjugate) {
  IndexField f;
  f.type = IndexFieldType::kFishEye;
  f.n0 = 2.0;
  f.radius_um = 10;
  GrinSettings cfg;
  cfg.tolerance_um = 1e-10;
  cfg.max_step_um = 0.05;
  const Vec3 r1(5, 0, 0), r2 = r1 * (-100.0 / 25.0);  // (-20, 0, 0)
  for (double ang : {0.3, 1.0, 1.7, 2.5}) {
    const Vec3 d(std::cos(ang), std::sin(ang) * 0.6, std::sin(ang) * 0.8);
    GrinState s{r1, d * f.Index(r1)};
    double dt = 0.01, used, best = 1e9;
    for (int i = 0; i < 200000 && best > 1e-9; ++i) {
      const Vec3 a = s.r;
      AdaptiveStep(f, Vec3(), cfg, &s, &dt, &used);
      // Distance from r2 to the segment a -> s.r.
      const Vec3 ab = s.r - a;
      const double u = std::clamp(Dot(r2 - a, ab) / Dot(ab, ab), 0.0, 1.0);
      best = std::min(best, Length(a + ab * u - r2));
      if (Length(s.r - r1) < 1e-3 && i > 100) break;  // full circle
    }
    // Chord-vs-arc error of a 0.05 um step on a ~20 um circle: 0.05^2 / (8 * 20) = 1.6e-5 um.
    EXPECT_LT(best, 5e-5) << "direction angle " << ang;
  }
}

Scene LensScene() {
  Scene s = testing::MicroscopeScene(3);
  s.camera.pixel_pitch_um = 0.2;  // 0.01 um at the object
  return s;
}

// A 20 deg cone over a 40 um field, imaged with 1 um pixels at the object.
Scene ConeScene() {
  Scene s = LensScene();
  s.camera.pixel_pitch_um = 20;
  s.source.type = SourceType::kCone;
  s.source.half_angle_deg = 20;
  s.source.field_radius_um = 40;
  return s;
}

// sum |a - b| / sum a over the pixels.
double RelativeL1(const PlaneResult& a, const PlaneResult& b) {
  double diff = 0, total = 0;
  for (size_t i = 0; i < a.counts.size(); ++i) {
    diff += std::abs(a.counts.pixels[i] - b.counts.pixels[i]);
    total += a.counts.pixels[i];
  }
  return diff / total;
}

// Luneburg lens n = sqrt(2 - (r/R)^2) (n = 1 at its surface, in vacuum) focuses a collimated
// beam onto its rear pole. Rays up to h = 0.4 R leave the pole within the NA 0.42.
TEST(Grin, LuneburgLensFocusesOnItsRearPole) {
  const double R = 20;
  Scene s = LensScene();
  s.objects = {testing::LuneburgSphere(R)};
  s.source.type = SourceType::kCollimated;
  s.source.field_radius_um = 0.4 * R;
  s.trace.grin.tolerance_um = 1e-7;
  Simulator sim(s);
  const uint64_t N = 3000;
  const PlaneResult r = sim.TracePlane(R, 0, N);  // focal plane through the rear pole
  EXPECT_EQ(r.counters.fates[int(Fate::kDetected)], N);
  double within = 0;  // hits within +-0.02 um of the axis (the 4x4 central pixels)
  for (int y = 30; y < 34; ++y)
    for (int x = 30; x < 34; ++x) within += r.counts.at(x, y);
  EXPECT_EQ(within, double(N));
  EXPECT_GT(r.counters.grin_steps, N * 10);
  EXPECT_EQ(r.counters.grin_segments, N);
}

// A grid of constant index behaves like the homogeneous sphere: with the same random streams
// the images agree up to rays whose fate changes by the exit-point tolerance.
TEST(Grin, UniformGridMatchesHomogeneousSphere) {
  Scene s = ConeScene();
  ObjectSpec o;
  o.shape = ShapeType::kSphere;
  o.radius_um = 10;
  o.index = 1.4;
  s.objects = {o};
  const PlaneResult a = Simulator(s).TracePlane(4, 0, 200000);
  auto f = std::make_shared<IndexField>();
  f->type = IndexFieldType::kGridRZ;
  f->nx = 12, f->ny = 1, f->nz = 23;
  f->spacing_um = {1, 1, 1};
  f->origin_um = {0, 0, -11};
  f->values.assign(12 * 23, 1.4);
  s.objects[0].index_field = f;
  // Curved steps everywhere (uniform-cell steps off), then straight steps across the uniform
  // cells (the default): both follow the straight rays of the homogeneous sphere.
  s.trace.grin.uniform_tolerance = -1;
  const PlaneResult b = Simulator(s).TracePlane(4, 0, 200000);
  s.trace.grin.uniform_tolerance = GrinSettings().uniform_tolerance;
  const PlaneResult c = Simulator(s).TracePlane(4, 0, 200000);
  for (const PlaneResult* r : {&b, &c}) EXPECT_LT(RelativeL1(a, *r), 1e-3);
  EXPECT_GT(b.counters.grin_steps, 0u);
  EXPECT_EQ(b.counters.grin_uniform_steps, 0u);
  EXPECT_GT(c.counters.grin_uniform_steps, 0u);
  EXPECT_LT(c.counters.grin_steps, b.counters.grin_steps / 10);
  EXPECT_EQ(a.counters.grin_steps, 0u);  // homogeneous objects never enter the integrator
}

// A 3D grid whose index varies along x only is piecewise linear in x: n = n_i + b_i (x - x_i)
// between nodes, with the gradient jumping at every x face. The optical direction's components
// T_y, T_z are conserved (also through the box's x faces, where the normal is x), so
// dy/dx = T_y / sqrt(n^2 - beta^2) with beta^2 = T_y^2 + T_z^2, and across one slab
// integral dx / sqrt(n^2 - beta^2) = [acosh(n / beta)] / b_i (Born & Wolf sec. 3.2.1 for the
// invariant; the integral is elementary). The exit point through the far face is exact.
struct SlabGrid {
  std::shared_ptr<IndexField> field;
  std::vector<double> n;  // node values along x
  double h = 0.5, x0 = -10;
};

SlabGrid MakeSlabGrid(uint64_t seed) {
  SlabGrid g;
  const int count = 41;  // 20 um in x, y and z
  RayRng rng(seed, 0, 0);
  for (int i = 0; i < count; ++i) g.n.push_back(1.35 + 0.25 * rng.Uniform());  // up to 0.5/um
  g.field = std::make_shared<IndexField>(
      Grid3D(count, count, count, {g.h, g.h, g.h}, {g.x0, g.x0, g.x0}));
  IndexField& f = *g.field;
  for (int k = 0; k < count; ++k)
    for (int j = 0; j < count; ++j)
      for (int i = 0; i < count; ++i) f.values.push_back(g.n[i]);
  return g;
}

// Exact exit point through x = -x0 of a ray that enters the face x = x0 at `entry` with the
// (unit) direction d from a medium of index 1.
Vec3 SlabExit(const SlabGrid& g, const Vec3& entry, const Vec3& d) {
  const double beta = std::hypot(d.y, d.z);
  double integral = 0;
  for (size_t i = 0; i + 1 < g.n.size(); ++i) {
    const double b = (g.n[i + 1] - g.n[i]) / g.h;
    integral += std::abs(b) < 1e-12
                    ? g.h / std::sqrt(g.n[i] * g.n[i] - beta * beta)
                    : (std::acosh(g.n[i + 1] / beta) - std::acosh(g.n[i] / beta)) / b;
  }
  return {-g.x0, entry.y + d.y * integral, entry.z + d.z * integral};
}

// Through the piecewise-linear slab grid: the exit point against the exact one, for steps that
// end on cell faces (the default) and for steps that straddle them (cell steps off: half-cell
// cap, the stages see the jump of the gradient inside the step). The local errors of the steps
// add up to at most steps x tolerance; a face-to-face step adds |jump of D| x kCellOvershoot to
// the direction, nothing here. A straddling step errs by |jump| x (part beyond the face)^2,
// which its error estimate sees only in part: it ends far outside that budget.
TEST(Grin, CellStepsFollowAPiecewiseLinearIndexExactly) {
  const SlabGrid g = MakeSlabGrid(5);
  ObjectSpec o = testing::BoxObject({10, 10, 10}, g.n[0]);
  o.index_field = g.field;
  auto trace = [&](double tolerance, bool cell_steps) {
    Scene s = LensScene();
    s.objects = {o};
    s.trace.grin.tolerance_um = tolerance;
    s.trace.grin.cell_steps = cell_steps;
    return Simulator(s);
  };
  const double tol = 1e-7;
  const Simulator cells = trace(tol, true), halves = trace(tol, false);
  const Simulator loose = trace(1e-3, true);
  RayRng rng(9, 0, 0);
  double worst_cells = 0, worst_halves = 0;
  for (int k = 0; k < 40; ++k) {
    const Vec3 d = Normalize(Vec3(1, 0.6 * (rng.Uniform() - 0.5), 0.6 * (rng.Uniform() - 0.5)));
    const Vec3 entry(-10, 4 * (rng.Uniform() - 0.5), 4 * (rng.Uniform() - 0.5));
    const Vec3 start = entry - d * (2 / d.x);
    const Vec3 exact = SlabExit(g, entry, d);
    const auto a = cells.TraceThroughObjects(start, d, k);
    const auto b = halves.TraceThroughObjects(start, d, k);
    ASSERT_FALSE(a.ended);
    ASSERT_FALSE(b.ended);
    const double err = Length(a.origin - exact);
    EXPECT_LT(err, tol * double(a.counters.grin_steps)) << k;
    worst_cells = std::max(worst_cells, err);
    worst_halves = std::max(worst_halves, Length(b.origin - exact));
    // Leaving into the medium of index 1 the ray has its incoming direction again.
    EXPECT_LT(Length(a.direction - d), 1e-6) << k;
    // Where the tolerance allows whole cells, one step per cell: a step to each face crossed
    // (40 in x, those in y and z), and the one that finds the far surface.
    auto faces = [&](double from, double to) {
      return std::abs(std::floor((to - g.x0) / g.h) - std::floor((from - g.x0) / g.h));
    };
    const double crossed = 40 + faces(entry.y, exact.y) + faces(entry.z, exact.z);
    EXPECT_LE(double(loose.TraceThroughObjects(start, d, k).counters.grin_steps), crossed + 2) << k;
  }
  EXPECT_LT(worst_cells * 100, worst_halves);
  std::printf("worst exit error at %g um: cell steps %.2e um, half-cell steps %.2e um\n", tol,
              worst_cells, worst_halves);
}

// The optical path (the integral of n ds) through the piecewise-linear slab grid against the
// exact one: with beta = |(d_y, d_z)| conserved, ds = n dx / sqrt(n^2 - beta^2), so a slab
// where n = n_i + b (x - x_i) adds integral n^2 dn / (b sqrt(n^2 - beta^2)) =
// [n sqrt(n^2 - beta^2) + beta^2 acosh(n / beta)] / (2 b). In front of the box and after its
// exit (the surface offset) the ray runs straight in the medium of index 1. A position error e
// changes the path by at most n e, so the bound is n_max x tolerance x steps, as for the exit.
TEST(OpticalPath, ThroughAPiecewiseLinearGridIsTheExactIntegral) {
  const SlabGrid g = MakeSlabGrid(5);
  ObjectSpec o = testing::BoxObject({10, 10, 10}, g.n[0]);
  o.index_field = g.field;
  Scene s = LensScene();
  s.objects = {o};
  const double tol = 1e-7;
  s.trace.grin.tolerance_um = tol;
  const Simulator sim(s);
  RayRng rng(11, 0, 0);
  double worst = 0;
  for (int k = 0; k < 40; ++k) {
    const Vec3 d = Normalize(Vec3(1, 0.6 * (rng.Uniform() - 0.5), 0.6 * (rng.Uniform() - 0.5)));
    const Vec3 entry(-10, 4 * (rng.Uniform() - 0.5), 4 * (rng.Uniform() - 0.5));
    const Vec3 start = entry - d * (2 / d.x);
    const double beta = std::hypot(d.y, d.z);
    double inside = 0;
    for (size_t i = 0; i + 1 < g.n.size(); ++i) {
      const double b = (g.n[i + 1] - g.n[i]) / g.h;
      auto F = [&](double n) {
        return 0.5 * (n * std::sqrt(n * n - beta * beta) + beta * beta * std::acosh(n / beta));
      };
      inside += std::abs(b) < 1e-12
                    ? g.h * g.n[i] * g.n[i] / std::sqrt(g.n[i] * g.n[i] - beta * beta)
                    : (F(g.n[i + 1]) - F(g.n[i])) / b;
    }
    const auto e = sim.TraceThroughObjects(start, d, k);
    ASSERT_FALSE(e.ended);
    const double exact = 2 / d.x + inside + Length(e.origin - SlabExit(g, entry, d));
    const double err = std::abs(e.optical_path_um - exact);
    EXPECT_LT(err, 1.6 * tol * double(e.counters.grin_steps)) << k;
    worst = std::max(worst, err);
  }
  std::printf("worst optical path error at %g um: %.2e um\n", tol, worst);
}

// Fermat's principle through a Luneburg lens n = sqrt(2 - (r/R)^2) in vacuum: a collimated beam
// focuses on the rear pole F = (0, 0, R), so every ray's optical path from the plane z = -2R to
// F is the same; on the axis it is R + R integral_{-1}^{1} sqrt(2 - u^2) du = R (2 + pi / 2).
// Each ray leaves just past F (the surface offset, with the integrator's error across it); the
// part beyond F along the ray is taken off. The bound is that of the slab above (n <= sqrt 2).
TEST(OpticalPath, EveryRayThroughALuneburgLensHasTheSamePathToItsFocus) {
  const double R = 20;
  Scene s = LensScene();
  s.objects = {testing::LuneburgSphere(R)};
  const double tol = 1e-7;
  s.trace.grin.tolerance_um = tol;
  const Simulator sim(s);
  const Vec3 focus(0, 0, R);
  double worst = 0;
  for (double h : {0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 0.97}) {
    const double phi = 2 * M_PI * h;  // skew the rays' planes too
    const Vec3 start(h * R * std::cos(phi), h * R * std::sin(phi), -2 * R);
    const auto e = sim.TraceThroughObjects(start, {0, 0, 1});
    ASSERT_FALSE(e.ended) << h;
    ASSERT_LT(Length(e.origin - focus), 1e-2) << h;
    const double to_focus = e.optical_path_um - Dot(e.direction, e.origin - focus);
    const double err = std::abs(to_focus - R * (2 + M_PI / 2));
    EXPECT_LT(err, 1.5 * tol * double(e.counters.grin_steps)) << h;
    worst = std::max(worst, err);
  }
  std::printf("worst Fermat error through the Luneburg lens at %g um: %.2e um\n", tol, worst);
}

// Through a homogeneous sphere (n 1.40 in water, 1.33) the path is straight in each medium:
// a ray at height h enters at z = -sqrt(R^2 - h^2) with sin(theta_i) = h / R, crosses the
// chord 2 R cos(theta_t) (Snell: n sin(theta_t) = n_m sin(theta_i)) and leaves at the chord's
// end, then runs on in the medium to the offset origin. Exact but for the surface offsets
// (1e-9 of the object's size, geometry.cpp), each of which moves the traced ray by that much.
TEST(OpticalPath, ThroughAHomogeneousSphereIsEachChordTimesItsIndex) {
  const double R = 10, n = 1.40, nm = 1.33, offset = 1e-9 * R;
  Scene s = LensScene();
  s.medium_index = nm;
  s.objects = {testing::SphereObject(R, n)};
  const Simulator sim(s);
  for (double h : {0.0, 2.0, 5.0, 8.0, 9.9}) {
    const auto e = sim.TraceThroughObjects({h, 0, -3 * R}, {0, 0, 1});
    ASSERT_FALSE(e.ended) << h;
    const double sin_i = h / R, sin_t = nm * sin_i / n;
    const double cos_i = std::sqrt(1 - sin_i * sin_i), cos_t = std::sqrt(1 - sin_t * sin_t);
    const Vec3 entry(h, 0, -R * cos_i);
    // Refracted towards the axis by theta_i - theta_t in the x-z plane.
    const double tilt = std::asin(sin_i) - std::asin(sin_t);
    const Vec3 exit = entry + Vec3(-std::sin(tilt), 0, std::cos(tilt)) * (2 * R * cos_t);
    ASSERT_LT(Length(e.origin - exit), 1e-6) << h;
    const double exact =
        nm * (3 * R - R * cos_i) + n * 2 * R * cos_t + nm * Length(e.origin - exit);
    EXPECT_NEAR(e.optical_path_um, exact, 4 * n * offset) << h;
  }
  // A ray that meets no object has travelled no optical path.
  EXPECT_EQ(sim.TraceThroughObjects({2 * R, 0, -3 * R}, {0, 0, 1}).optical_path_um, 0.0);
}

// Rays entering a box along z, parallel to the grid's faces and some exactly on its node planes,
// through n = a + b x (exactly trilinear): T_z = n0 is conserved, and the path is the catenary
// n(x(z)) = n0 cosh(b (z - z0) / n0) (from dz = n0 dx / sqrt(n^2 - n0^2)). The x faces are
// reached by the bending alone (the ray starts with no x velocity), the y faces never.
TEST(Grin, RaysParallelToGridFacesFollowTheCatenary) {
  const double a = 1.4, b = 0.04, h = 0.5;
  auto f = std::make_shared<IndexField>(Grid3D(25, 25, 25, {h, h, h}, {-6, -6, -6}));
  for (int k = 0; k < 25; ++k)
    for (int j = 0; j < 25; ++j)
      for (int i = 0; i < 25; ++i) f->values.push_back(a + b * (-6 + h * i));
  Scene s = LensScene();
  ObjectSpec o = testing::BoxObject({5, 5, 5}, a);
  o.index_field = f;
  s.objects = {o};
  s.trace.grin.tolerance_um = 1e-8;
  const Simulator sim(s);
  for (double x0 : {-4.0, -2.5, -1.3, 0.0, 0.5, 2.75}) {
    const double y0 = x0 == 0.0 ? 0.0 : 1.5;  // on a y node plane too
    const auto e = sim.TraceThroughObjects({x0, y0, -7}, {0, 0, 1});
    ASSERT_FALSE(e.ended) << x0;
    const double n0 = a + b * x0, n1 = n0 * std::cosh(b * 10 / n0);
    const Vec3 exact((n1 - a) / b, y0, 5);
    EXPECT_LT(Length(e.origin - exact), 1e-8 * double(e.counters.grin_steps) + 1e-9)
        << x0 << ": " << e.origin.x << " against " << exact.x;
  }
}

// The cell beyond a face (built incrementally while a step is computed) is the cell located
// from a point just past that face, for every face of cells inside the grid, at its edges and
// beyond them (where the field holds the edge values), and its polynomial is the field there.
TEST(Grin, NextCellIsTheCellBeyondTheFace) {
  IndexField f = Grid3D(5, 4, 6, {0.5, 0.7, 0.6}, {-1, -1.4, -1.8});
  RayRng rng(3, 0, 0);
  for (int i = 0; i < f.nx * f.ny * f.nz; ++i) f.values.push_back(1.33 + 0.1 * rng.Uniform());
  const double h[3] = {0.5, 0.7, 0.6}, o[3] = {-1, -1.4, -1.8};
  const int count[3] = {5, 4, 6};
  int checked = 0;
  for (int trial = 0; trial < 3000; ++trial) {
    // Points from a cell before the grid to one beyond it on every axis.
    Vec3 p;
    for (int a = 0; a < 3; ++a)
      (a == 0   ? p.x
       : a == 1 ? p.y
                : p.z) = o[a] + h[a] * (count[a] + 1) * (rng.Uniform() * 1.2 - 0.1) - h[a];
    const GridCell g = f.Cell(p);
    for (int a = 0; a < 3; ++a)
      for (int side : {-1, 1}) {
        const double face = side > 0 ? g.hi[a] : g.lo[a];
        if (std::isinf(face)) continue;
        // A point 1e-6 cells past the face, at the middle of it in the other axes.
        double u[3];
        for (int b = 0; b < 3; ++b) {
          const double lo = std::max(g.lo[b], -2.0), hi = std::min(g.hi[b], 2.0);
          u[b] = b == a ? face + side * 1e-6 : 0.5 * (lo + hi);
        }
        const Vec3 q(g.node.x + u[0] * h[0], g.node.y + u[1] * h[1], g.node.z + u[2] * h[2]);
        GridCell next;
        f.NextCell(g, a, side, &next);
        const GridCell located = f.Cell(q);
        for (int b = 0; b < 3; ++b) {
          ASSERT_EQ(next.k[b], located.k[b]) << trial << " axis " << a << " side " << side;
          ASSERT_EQ(next.lo[b], located.lo[b]);
          ASSERT_EQ(next.hi[b], located.hi[b]);
          ASSERT_EQ(next.stride[b], located.stride[b]);
        }
        ASSERT_EQ(next.base, located.base);
        for (int k = 0; k < 8; ++k) ASSERT_EQ(next.c[k], located.c[k]);
        double n_cell, n_field;
        Vec3 g_cell, g_field;
        IndexField::EvalInCell(next, q, &n_cell, &g_cell);
        f.Eval(q, &n_field, &g_field);
        ASSERT_NEAR(n_cell, n_field, 1e-14);
        ASSERT_LT(Length(g_cell - g_field), 1e-12);
        ++checked;
      }
  }
  EXPECT_GT(checked, 10000);
}

// A 3D grid smaller than its object, of the object's constant index: cell steps go into the
// grid, through it and out beyond its edges (where the edge values hold) and must follow the
// straight rays of the homogeneous sphere (same random streams: the images agree up to rays
// whose fate changes by the exit-point tolerance).
TEST(Grin, CellStepsThroughAGridSmallerThanItsObject) {
  Scene s = ConeScene();
  s.objects = {testing::SphereObject(10, 1.4)};
  const PlaneResult a = Simulator(s).TracePlane(4, 0, 100000);
  auto f = std::make_shared<IndexField>();
  f->type = IndexFieldType::kGrid3D;
  f->nx = 9, f->ny = 7, f->nz = 11;
  f->spacing_um = {1, 1.2, 0.9};
  f->origin_um = {-4, -3.6, -4.5};
  f->values.assign(size_t(9) * 7 * 11, 1.4);
  s.objects[0].index_field = f;
  s.trace.grin.uniform_tolerance = -1;  // curved steps everywhere
  s.trace.grin.max_steps = 10000;       // a few hundred cells at most: a stuck ray ends early
  const PlaneResult b = Simulator(s).TracePlane(4, 0, 100000);
  EXPECT_LT(RelativeL1(a, b), 2e-4);
  EXPECT_GT(b.counters.grin_steps, 0u);
  EXPECT_EQ(b.counters.fates[int(Fate::kGrinStepCap)], 0u);
  EXPECT_EQ(b.counters.fates[int(Fate::kLostInside)], 0u);
}

// The uniform-cell map: the Chebyshev distance in cells to the nearest non-uniform cell or the
// grid's edge, and a free length that never reaches a non-uniform cell (checked by sampling
// straight paths of that length in random directions from random points).
TEST(Grin, UniformCellsNeverReachANonUniformCell) {
  IndexField f = Grid3D(21, 17, 19, {0.5, 0.7, 0.6}, {-5, -5.6, -5.4});
  f.values.assign(size_t(f.nx) * f.ny * f.nz, 1.33);
  // A non-uniform blob: the node (12, 8, 9) raised (its 8 neighbouring cells change).
  f.values[(size_t(9) * f.ny + 8) * f.nx + 12] = 1.34;
  // Blocks of 4^3 cells (5 x 4 x 5, the last z block partial): the raised node touches cells
  // 11-12, 7-8, 8-9, i.e. 2 x 2 x 1 blocks of 64 cells, all others are uniform. The automatic
  // block of so small a grid is one cell: then only the 8 cells around the node are not.
  const UniformCells u4(f, 1e-13, 4), u(f, 1e-13);
  ASSERT_FALSE(u.empty());
  EXPECT_EQ(u4.uniform_cells(), size_t(20 * 16 * 18 - 4 * 64));
  EXPECT_EQ(u.block(), 1);
  EXPECT_EQ(u.uniform_cells(), size_t(20 * 16 * 18 - 8));
  // What a straight step needs: the index is the uniform value and its gradient zero all along
  // the path (inside the grid or beyond its edge, where the edge values hold).
  auto flat = [&](const Vec3& p) {
    double n;
    Vec3 g;
    f.Eval(p, &n, &g);
    return n == 1.33 && g.x == 0 && g.y == 0 && g.z == 0;
  };
  RayRng rng(7, 0, 0);
  for (const UniformCells* map : {&u4, &u}) {
    int positive = 0;
    for (int trial = 0; trial < 20000; ++trial) {
      const Vec3 p(-5 + 10 * rng.Uniform(), -5.6 + 11.2 * rng.Uniform(),
                   -5.4 + 10.8 * rng.Uniform());
      const double len = map->FreeLength(p);
      if (len <= 0) continue;
      ++positive;
      const Vec3 d = Normalize(Vec3(rng.Uniform() - 0.5, rng.Uniform() - 0.5, rng.Uniform() - 0.5));
      for (int k = 0; k <= 40; ++k)
        ASSERT_TRUE(flat(p + d * (len * k / 40 * (1 - 1e-12))))
            << map->block() << " " << trial << " " << k;
    }
    EXPECT_GT(positive, 10000);
  }
  // A grid of more than kMaxBlocks cells gets larger blocks.
  IndexField big = Grid3D(101, 101, 101, {0.5, 0.5, 0.5}, {-25, -25, -25});
  big.values.assign(size_t(101) * 101 * 101, 1.33);
  EXPECT_EQ(UniformCells(big, 1e-13).block(), 2);
  // An axisymmetric grid that starts on the axis continues through it: a point near the axis
  // far from the non-uniform cells may cross the axis.
  IndexField rz;
  rz.type = IndexFieldType::kGridRZ;
  rz.nx = 11, rz.ny = 1, rz.nz = 21;
  rz.spacing_um = {1, 1, 1};
  rz.origin_um = {0, 0, -10};
  rz.values.assign(size_t(rz.nx) * rz.nz, 1.4);
  const UniformCells urz(rz, 1e-13);
  EXPECT_GT(urz.FreeLength({0.2, 0.1, 0.3}), 3.0);
  // Outside the grid there is no free length (the field is extrapolated there).
  EXPECT_EQ(urz.FreeLength({0, 0, -12}), 0.0);
  EXPECT_EQ(u.FreeLength({100, 0, 0}), 0.0);
}

// An axisymmetric grid and the equivalent 3D grid give the same image statistically:
// chi-square of two independent Poisson images, sum (a-b)^2/(a+b), has mean = number of pixels.
TEST(Grin, AxisymmetricAndThreeDGridsAgree) {
  const double R = 10, h = 0.5;
  auto n_of = [](double r, double z) { return 1.33 + 0.06 * std::exp(-(r * r + z * z) / 25.0); };
  auto rz = std::make_shared<IndexField>();
  rz->type = IndexFieldType::kGridRZ;
  rz->nx = 24, rz->ny = 1, rz->nz = 47;
  rz->spacing_um = {h, 1, h};
  rz->origin_um = {0, 0, -11.5};
  for (int k = 0; k < rz->nz; ++k)
    for (int i = 0; i < rz->nx; ++i) rz->values.push_back(n_of(i * h, -11.5 + k * h));
  auto g3 = std::make_shared<IndexField>();
  g3->type = IndexFieldType::kGrid3D;
  g3->nx = g3->ny = g3->nz = 47;
  g3->spacing_um = {h, h, h};
  g3->origin_um = {-11.5, -11.5, -11.5};
  for (int k = 0; k < 47; ++k)
    for (int j = 0; j < 47; ++j)
      for (int i = 0; i < 47; ++i)
        g3->values.push_back(n_of(std::hypot(-11.5 + i * h, -11.5 + j * h), -11.5 + k * h));
  Scene s = ConeScene();
  s.camera.nx = s.camera.ny = 40;
  ObjectSpec o;
  o.shape = ShapeType::kSphere;
  o.radius_um = R;
  o.index_field = rz;
  s.objects = {o};
  s.trace.grin.tolerance_um = 1e-4;
  const PlaneResult a = Simulator(s).TracePlane(3, 0, 300000);
  s.objects[0].index_field = g3;
  const PlaneResult b = Simulator(s).TracePlane(3, 1, 300000);  // independent noise
  double chi2 = 0;
  int dof = 0;
  for (size_t i = 0; i < a.counts.size(); ++i) {
    const double x = a.counts.pixels[i], y = b.counts.pixels[i];
    if (x + y > 0) chi2 += (x - y) * (x - y) / (x + y), ++dof;
  }
  EXPECT_LT(std::abs(chi2 / dof - 1), 4 * std::sqrt(2.0 / dof)) << chi2 << " / " << dof;
}

// Shock front: bilinear interpolation never overshoots a jump (tricubic would ring).
TEST(Grin, InterpolantDoesNotOvershootAtAJump) {
  IndexField f;
  f.type = IndexFieldType::kGridRZ;
  f.nx = 20, f.ny = 1, f.nz = 20;
  f.spacing_um = {1, 1, 1};
  f.origin_um = {0, 0, -10};
  for (int k = 0; k < 20; ++k)
    for (int i = 0; i < 20; ++i) f.values.push_back(i < 8 ? 1.333 : 1.346);  // 40 kg/m^3 shock
  for (double r = 0; r < 20; r += 0.01) {
    double n;
    Vec3 g;
    f.Eval(Vec3(r, 0, 0.3), &n, &g);
    EXPECT_GE(n, 1.333 - 1e-15);
    EXPECT_LE(n, 1.346 + 1e-15);
    EXPECT_TRUE(std::isfinite(g.x));
    if (r > 7.01 && r < 7.99) EXPECT_NEAR(g.x, 0.013, 1e-12);  // the jump spreads over one cell
    if (r > 8.01) EXPECT_EQ(g.x, 0.0);
  }
}

// Gradients against central finite differences of the index, for every field type, at random
// points away from cell faces (where grid gradients are discontinuous by construction).
TEST(Grin, GradientsMatchFiniteDifferences) {
  std::vector<IndexField> fields(6);
  fields[0].type = IndexFieldType::kLuneburg, fields[0].n0 = 1.2, fields[0].radius_um = 7;
  fields[1].type = IndexFieldType::kFishEye, fields[1].n0 = 1.8, fields[1].radius_um = 5;
  fields[2].type = IndexFieldType::kParabolic, fields[2].n0 = 1.5, fields[2].g_per_um = 0.05;
  fields[3].type = IndexFieldType::kLinearN2, fields[3].n0 = 1.4,
  fields[3].k_per_um = {0.01, 0.02, -0.03};
  IndexField& rz = fields[4];
  rz.type = IndexFieldType::kGridRZ, rz.nx = 9, rz.ny = 1, rz.nz = 11;
  rz.spacing_um = {1, 1, 1}, rz.origin_um = {0, 0, -5};
  IndexField& g3 = fields[5];
  g3.type = IndexFieldType::kGrid3D, g3.nx = 9, g3.ny = 9, g3.nz = 11;
  g3.spacing_um = {1, 1, 1}, g3.origin_um = {-4, -4, -5};
  RayRng rng(1, 0, 0);
  for (int i = 0; i < 9 * 11; ++i) rz.values.push_back(1.33 + 0.05 * rng.Uniform());
  for (int i = 0; i < 9 * 9 * 11; ++i) g3.values.push_back(1.33 + 0.05 * rng.Uniform());
  for (const IndexField& f : fields)
    for (int k = 0; k < 200; ++k) {
      // Points at cell centres +- 0.3 cell, so +-h stays inside one cell.
      auto c = [&](double lo) {
        return std::floor(lo + 6 * rng.Uniform()) + 0.5 + 0.6 * (rng.Uniform() - 0.5);
      };
      const Vec3 p(c(-3), c(-3), c(-4));
      if (f.type == IndexFieldType::kGridRZ &&
          std::abs(std::hypot(p.x, p.y) - std::floor(std::hypot(p.x, p.y)) - 0.5) > 0.45)
        continue;  // radial cell faces are circles: skip points next to them
      double n;
      Vec3 g;
      f.Eval(p, &n, &g);
      const double h = 1e-5;
      for (int a = 0; a < 3; ++a) {
        Vec3 e;
        (a == 0 ? e.x : a == 1 ? e.y : e.z) = h;
        const double fd = (f.Index(p + e) - f.Index(p - e)) / (2 * h);
        // Central differences: O(h^2) truncation plus rounding ~1e-16/h: 1e-8 absolute.
        EXPECT_NEAR(g[a], fd, 1e-8) << "field type " << int(f.type) << " axis " << a;
      }
    }
}

const char* kGridScene = R"(name = "g"
[source]
type = "cone"
half_angle_deg = 20
[[object]]
type = "sphere"
radius_um = 5
[object.index_field]
type = "grid_rz"
file = "grid.npy"
spacing_um = [1, 1]
origin_um = [0, -6]
QUANTITY
[camera]
pixels = [16, 16]
pixel_pitch_um = 20
)";

std::string GridScene(const testing::TempDir& dir, const std::string& quantity) {
  std::string s = std::string(kGridScene) + testing::kOpticsToml;
  s.replace(s.find("QUANTITY"), 8, quantity);
  return dir.Write("scene.toml", s);
}

TEST(GridFiles, NanInAGridIsAClearError) {
  testing::TempDir dir;
  NdArray a{{13, 7}, std::vector<double>(91, 1.4)};
  a.values[40] = std::nan("");
  WriteNpy(dir / "grid.npy", a);
  try {
    LoadScene(GridScene(dir, ""));
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("grid value 40 (flat C-order index) is NaN or Inf"),
              std::string::npos)
        << e.what();
  }
}

TEST(GridFiles, DensityGridUsesIapwsAndWarnsOutsideItsRange) {
  testing::TempDir dir;
  NdArray a{{13, 7}, std::vector<double>(91, 997.047435)};
  a.values[3] = 1100;  // a strong shock
  WriteNpy(dir / "grid.npy", a);
  const Scene s = LoadScene(GridScene(dir, "quantity = \"density\"\ntemperature_K = 298.15"));
  ASSERT_TRUE(s.objects[0].index_field);
  EXPECT_EQ(s.warnings.size(), 1u);
  EXPECT_NEAR(s.objects[0].index_field->min_n, 1.3370, 2e-3);
}

// perturbation_scale (issue 23): a grid's difference from a reference multiplied, in its own
// quantity (density before IAPWS R9-97). 1 leaves the grid bit for bit; 0 gives the reference
// everywhere; the default reference is the grid's mean on the sphere's surface: for 1000 + 2 z +
// 0.5 r (r from the axis; bilinear interpolation is exact for it) on a sphere of radius 5,
// 1000 + 2.5 pi / 4 (the mean of sin(theta) over a sphere is pi / 4), to the accuracy of the
// 1024-point Fibonacci lattice (measured 1e-5 kg/m^3; 1e-4 allowed, 3e-8 in the index).
TEST(GridFiles, PerturbationScaleMultipliesTheDifferenceFromAReference) {
  testing::TempDir dir;
  NdArray a{{13, 7}, std::vector<double>(91)};
  for (int iz = 0; iz < 13; ++iz)
    for (int ir = 0; ir < 7; ++ir) a.values[size_t(iz) * 7 + ir] = 1000 + 2 * (iz - 6) + 0.5 * ir;
  WriteNpy(dir / "grid.npy", a);
  auto values = [&](const std::string& keys) {
    return LoadScene(GridScene(dir, "quantity = \"density\"\n" + keys))
        .objects[0]
        .index_field->values;
  };
  const double wl = 0.462, T = 293.15;
  const std::vector<double> base = values("");
  EXPECT_EQ(values("perturbation_scale = 1\nreference_density_kg_m3 = 990"), base);
  const std::vector<double> two = values("perturbation_scale = 2\nreference_density_kg_m3 = 998");
  for (size_t i = 0; i < a.values.size(); ++i)
    EXPECT_EQ(two[i], WaterRefractiveIndex(T, 998 + 2 * (a.values[i] - 998), wl).n) << i;
  for (double v : values("perturbation_scale = 0\nreference_density_kg_m3 = 998"))
    EXPECT_EQ(v, WaterRefractiveIndex(T, 998, wl).n);
  for (double v : values("perturbation_scale = 0"))
    EXPECT_NEAR(v, WaterRefractiveIndex(T, 1000 + 2.5 * M_PI / 4, wl).n, 3e-8);
  auto error = [&](const std::string& text) {
    try {
      LoadScene(dir.Write("bad.toml", text));
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  std::string scene = std::string(kGridScene) + testing::kOpticsToml;
  scene.replace(scene.find("QUANTITY"), 8, "quantity = \"density\"\nreference_index = 1.33");
  EXPECT_NE(error(scene).find("'object[0].index_field.reference_index'"), std::string::npos)
      << error(scene);
  std::string box = std::string(kGridScene) + testing::kOpticsToml;
  box.replace(box.find("QUANTITY"), 8, "perturbation_scale = 2");
  const std::string sphere = "type = \"sphere\"\nradius_um = 5";
  box.replace(box.find(sphere), sphere.size(), "type = \"box\"\nsize_um = [8, 8, 8]");
  EXPECT_NE(error(box).find("defined for spheres"), std::string::npos) << error(box);
}

// A field's rotation (issue 23 item 4; `rotation_deg`, R = Rz Ry Rx about the object's centre,
// n(p) = n_grid(R^T p)). Known answer: a 3D grid symmetric about the centre, rotated by 90 deg
// about z, is the grid with its axes permuted, w(x, y) = v(y, -x), i.e. w[k][j][i] =
// v[k][n - 1 - i][j], exactly (the rotation's matrix elements are 0 and +-1 to rounding). A
// Gaussian blob off the axis (at +x) moves to +y. Checked: the index and gradient at random
// points; straight steps across the rotated field's uniform cells never reach the blob; and a
// traced image of a drop holding either field, same ray streams: the two integrators (adaptive
// steps for the rotated grid, cell steps for the permuted one) land the same rays in the same
// pixels but for the integrators' tolerance (relative L1 difference 2e-5, 2e-4 allowed; ignoring
// the rotation moves the blob's rays: 1.3e-2, 5e-3 required).
TEST(Grin, RotatedFieldIsTheFieldOfTheRotatedGrid) {
  const int n = 33;
  const double h = 0.5, o = -0.5 * (n - 1) * h;
  auto blob = [](double x, double y, double z) {
    return 1.33 + 0.1 * std::exp(-((x - 4) * (x - 4) + y * y + z * z) / 4.0) *
                      (std::abs(x - 4) < 3 && std::abs(y) < 3 && std::abs(z) < 3);
  };
  NdArray v{{size_t(n), size_t(n), size_t(n)}, {}}, w = v;
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i) v.values.push_back(blob(o + i * h, o + j * h, o + k * h));
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i)
        w.values.push_back(v.values[(size_t(k) * n + (n - 1 - i)) * n + j]);
  testing::TempDir dir;
  WriteNpy(dir / "v.npy", v);
  WriteNpy(dir / "w.npy", w);
  auto scene = [&](const std::string& field) {
    return dir.Write("s.toml", R"(name = "rot"
seed = 3
[source]
type = "cone"
half_angle_deg = 20
[[object]]
type = "sphere"
radius_um = 7.5
[object.index_field]
type = "grid_3d"
spacing_um = [0.5, 0.5, 0.5]
origin_um = [-8, -8, -8]
)" + field + R"(
[camera]
pixels = [24, 24]
pixel_pitch_um = 20
[trace]
rays = 400000
grin_tolerance_um = 1e-6
)" + testing::kOpticsToml);
  };
  const Scene rotated = LoadScene(scene("file = \"v.npy\"\nrotation_deg = [0, 0, 90]"));
  const Scene permuted = LoadScene(scene("file = \"w.npy\""));
  const IndexField& fr = *rotated.objects[0].index_field;
  const IndexField& fp = *permuted.objects[0].index_field;
  ASSERT_TRUE(fr.rotated);
  EXPECT_FALSE(UsesCellSteps(fr, rotated.trace.grin));
  RayRng rng(11, 0, 0);
  for (int t = 0; t < 2000; ++t) {
    const Vec3 p(-8 + 16 * rng.Uniform(), -8 + 16 * rng.Uniform(), -8 + 16 * rng.Uniform());
    double na, nb;
    Vec3 ga, gb;
    fr.Eval(p, &na, &ga);
    fp.Eval(p, &nb, &gb);
    ASSERT_NEAR(na, nb, 1e-12) << p.x << " " << p.y << " " << p.z;
    ASSERT_NEAR(Length(ga - gb), 0, 1e-9) << p.x << " " << p.y << " " << p.z;
  }
  // The blob is at +y now, not at +x.
  EXPECT_GT(fr.Index({0, 4, 0}), 1.42);
  EXPECT_NEAR(fr.Index({4, 0, 0}), 1.33, 1e-12);
  // Straight steps from the rotated field's uniform cells stay where it is flat.
  const UniformCells u(fr, 1e-13);
  int positive = 0;
  for (int t = 0; t < 20000; ++t) {
    const Vec3 p(-8 + 16 * rng.Uniform(), -8 + 16 * rng.Uniform(), -8 + 16 * rng.Uniform());
    const double len = u.FreeLength(p);
    if (len <= 0) continue;
    ++positive;
    const Vec3 d = Normalize(Vec3(rng.Uniform() - 0.5, rng.Uniform() - 0.5, rng.Uniform() - 0.5));
    for (int k = 0; k <= 20; ++k) {
      double nn;
      Vec3 g;
      fr.Eval(p + d * (len * k / 20 * (1 - 1e-12)), &nn, &g);
      ASSERT_TRUE(nn == 1.33 && Length(g) == 0) << t << " " << k;
    }
  }
  EXPECT_GT(positive, 5000);
  // Traced: the same rays through either field.
  const PlaneResult a = Simulator(rotated).TracePlane(2, 0, rotated.trace.rays);
  const PlaneResult b = Simulator(permuted).TracePlane(2, 0, permuted.trace.rays);
  EXPECT_GT(a.counters.grin_steps, 0u);
  EXPECT_GT(a.counters.grin_uniform_steps, 0u);
  EXPECT_LT(RelativeL1(a, b), 2e-4);
  const Scene plain = LoadScene(scene("file = \"v.npy\""));  // not rotated: the blob at +x
  const double moved = RelativeL1(Simulator(plain).TracePlane(2, 0, plain.trace.rays), b);
  EXPECT_GT(moved, 5e-3);
  // rotation_deg is read strictly.
  EXPECT_THROW(LoadScene(scene("file = \"v.npy\"\nrotation_deg = [0, 0]")), Error);
  EXPECT_THROW(LoadScene(scene("file = \"v.npy\"\nrotation_deg = [0, 0, 1000]")), Error);
}

}  // namespace
}  // namespace raymatch::simulate
