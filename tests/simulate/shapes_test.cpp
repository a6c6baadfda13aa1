// Shapes from outlines, silhouettes and volume fractions; mesh checks (issue 6).
#include "raymatch/simulate/shapes.h"

#include <gtest/gtest.h>

#include <cmath>

#include "raymatch/core/array_io.h"
#include "raymatch/core/error.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/tracer.h"
#include "stats.h"
#include "temp_dir.h"
#include "test_scenes.h"

namespace raymatch::simulate {
namespace {

Outline Semicircle(double R, int n) {
  Outline o;
  for (int i = 0; i <= n; ++i) {
    const double t = M_PI * i / n;  // from the -z pole to the +z pole
    o.push_back({R * std::sin(t), -R * std::cos(t)});
  }
  o.front()[0] = o.back()[0] = 0;
  return o;
}

// A revolved semicircle is a closed polyhedral sphere; its volume converges to 4/3 pi R^3 from
// below as O(1/n^2): with 256 segments and 200 rings the deficit is < 0.05 %.
TEST(Revolution, SemicircleGivesAClosedSphere) {
  TriangleMesh m = RevolveOutline(Semicircle(10, 200), 256);
  const MeshReport rep = CheckAndOrientMesh(&m);
  EXPECT_TRUE(rep.ok()) << rep.Summary();
  const double v = 4.0 / 3 * M_PI * 1000;
  EXPECT_LT(rep.signed_volume_um3, v);
  EXPECT_GT(rep.signed_volume_um3, v * (1 - 5e-4));
  // Open ends get flat caps and still close.
  TriangleMesh cyl = RevolveOutline({{5, -3}, {5, 3}}, 64);
  EXPECT_TRUE(CheckAndOrientMesh(&cyl).ok());
}

// The revolved sphere refracts like the analytic one: the Debye direct-transmission fraction
// P1 agrees within shot noise plus a faceting allowance (facet normals deviate by <= pi/256).
TEST(Revolution, RevolvedSphereRefractsLikeTheAnalyticSphere) {
  Scene s = testing::MicroscopeScene();
  s.camera.nx = s.camera.ny = 32;
  s.source.type = SourceType::kCollimated;
  s.source.field_radius_um = 9.9;
  s.trace.partial_reflection = PartialReflection::kUnpolarized;
  ObjectSpec o;
  o.shape = ShapeType::kSphere;
  o.radius_um = 10;
  o.index = 1.5;
  s.objects = {o};
  const uint64_t N = 400000;
  const PlaneResult a = Simulator(s).TracePlane(0, 0, N);
  o.shape = ShapeType::kMesh;
  o.mesh = std::make_shared<TriangleMesh>(RevolveOutline(Semicircle(10, 200), 256));
  s.objects = {o};
  const PlaneResult b = Simulator(s).TracePlane(0, 1, N);
  const double pa = double(a.counters.path_class[1]) / a.counters.rays_hitting_objects;
  const double pb = double(b.counters.path_class[1]) / b.counters.rays_hitting_objects;
  EXPECT_LT(std::abs(pa - pb), 4 * std::sqrt(2.0) * testing::BinomialSigma(pa, N) + 2e-3)
      << pa << " vs " << pb;
  EXPECT_EQ(b.counters.fates[int(Fate::kLostInside)], 0u);
}

// A synthetic silhouette: a dark ellipse (semi-axes 30 px across, 20 px along the axis) on a
// bright background; the outline recovers the half-width and length within one pixel and the
// axis within 0.1 px.
TEST(Silhouette, EllipseOutlineIsRecovered) {
  Image img(120, 80, 1000.f);
  const double cx = 57.3, cy = 41.0;
  for (int y = 0; y < 80; ++y)
    for (int x = 0; x < 120; ++x) {
      const double u = (x + 0.5 - cx) / 30, v = (y + 0.5 - cy) / 20;
      if (u * u + v * v < 1) img.at(x, y) = (u * u + v * v > 0.8) ? 100.f : 700.f;  // dark rim
    }
  SilhouetteOptions so;
  so.pixel_um = 0.5;
  so.threshold = 0.8;  // the bright interior is filled from the rim's contour
  double axis = 0;
  const Outline o = OutlineFromSilhouette(img, so, &axis);
  EXPECT_NEAR(axis, cx, 0.1);
  double rmax = 0;
  for (const auto& p : o) rmax = std::max(rmax, p[0]);
  EXPECT_NEAR(rmax, 30 * 0.5, 0.5);
  EXPECT_NEAR(o.back()[1] - o.front()[1], 40 * 0.5, 0.5);
  TriangleMesh m = RevolveOutline(o, 128);
  EXPECT_TRUE(CheckAndOrientMesh(&m).ok());
  EXPECT_THROW(OutlineFromSilhouette(Image(10, 10, 5.f), so), Error);
}

// OpenVDB iso-surface of a sphere's volume fraction (a smooth 0..1 step of width 1 um).
TEST(VolumeFraction, IsoSurfaceOfASphere) {
  const int n = 40;
  const double h = 0.5, R = 7;
  NdArray f{{size_t(n), size_t(n), size_t(n)}, {}};
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i) {
        const double r = std::sqrt(std::pow((i - n / 2.0) * h, 2) + std::pow((j - n / 2.0) * h, 2) +
                                   std::pow((k - n / 2.0) * h, 2));
        f.values.push_back(0.5 * (1 - std::tanh((r - R) / 0.5)));
      }
  TriangleMesh m = MeshFromVolumeFraction(f, {h, h, h}, {-10, -10, -10}, 0.5);
  const MeshReport rep = CheckAndOrientMesh(&m);
  EXPECT_TRUE(rep.ok()) << rep.Summary();
  // Linear interpolation of a smooth profile at 0.5 um spacing: volume within 2 %.
  EXPECT_NEAR(rep.signed_volume_um3, 4.0 / 3 * M_PI * R * R * R, 0.02 * 4.0 / 3 * M_PI * R * R * R);
  double maxr = 0;
  for (const Vec3& v : m.vertices) maxr = std::max(maxr, Length(v));
  EXPECT_NEAR(maxr, R, 0.1);
}

TEST(MeshChecks, OpenSelfIntersectingAndInwardMeshes) {
  // A cube without its top face: 4 open edges.
  TriangleMesh cube;
  cube.vertices = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0},
                   {0, 0, 1}, {1, 0, 1}, {1, 1, 1}, {0, 1, 1}};
  cube.triangles = {{0, 2, 1}, {0, 3, 2}, {0, 1, 5}, {0, 5, 4}, {1, 2, 6},
                    {1, 6, 5}, {2, 3, 7}, {2, 7, 6}, {3, 0, 4}, {3, 4, 7}};
  TriangleMesh open = cube;
  MeshReport r = CheckAndOrientMesh(&open);
  EXPECT_EQ(r.open_edges, 4u);
  EXPECT_FALSE(r.ok());
  // Closed cube, wound inward: flipped, fine.
  TriangleMesh closed = cube;
  closed.triangles.push_back({4, 5, 6});
  closed.triangles.push_back({4, 6, 7});
  for (auto& t : closed.triangles) std::swap(t[1], t[2]);
  r = CheckAndOrientMesh(&closed);
  EXPECT_TRUE(r.ok()) << r.Summary();
  EXPECT_TRUE(r.flipped);
  EXPECT_NEAR(r.signed_volume_um3, 1.0, 1e-12);
  // Two interpenetrating closed cubes in one mesh: self-intersections.
  TriangleMesh two = closed;
  const unsigned base = static_cast<unsigned>(two.vertices.size());
  for (size_t i = 0; i < 8; ++i) two.vertices.push_back(two.vertices[i] + Vec3(0.5, 0.5, 0.5));
  for (size_t t = 0; t < 12; ++t)
    two.triangles.push_back({closed.triangles[t][0] + base, closed.triangles[t][1] + base,
                             closed.triangles[t][2] + base});
  r = CheckAndOrientMesh(&two);
  EXPECT_GT(r.self_intersections, 0u) << r.Summary();
}

TEST(MeshChecks, SceneWithAnOpenMeshIsRejectedClearly) {
  testing::TempDir dir;
  dir.Write("open.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\n");
  const std::string scene = dir.Write("s.toml", R"(
[source]
type = "cone"
half_angle_deg = 20
[[object]]
type = "mesh"
file = "open.obj"
scale_um = 10
index = 1.5
[camera]
pixels = [16, 16]
pixel_pitch_um = 20
)" + testing::kOpticsToml);
  try {
    Simulator sim(LoadScene(scene));
    FAIL() << "open mesh accepted";
  } catch (const Error& e) {
    const std::string w = e.what();
    EXPECT_NE(w.find("s.toml:5:1: error: mesh"), std::string::npos) << w;
    EXPECT_NE(w.find("3 open edges (not watertight)"), std::string::npos) << w;
  }
}

// A mesh file is read once for scenes built again and again (fits); an edited file is read anew.
TEST(MeshChecks, EditedMeshFileIsReadAgain) {
  testing::TempDir dir;
  const char* tet = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n";
  dir.Write("m.obj", tet);
  const std::string scene = dir.Write("s.toml", R"(
[source]
type = "cone"
half_angle_deg = 20
[[object]]
type = "mesh"
file = "m.obj"
scale_um = 10
index = 1.5
[camera]
pixels = [16, 16]
pixel_pitch_um = 20
)" + testing::kOpticsToml);
  const Scene s = LoadScene(scene);
  const double r1 = Simulator(s).ObjectBounds()[0].second;
  EXPECT_EQ(Simulator(s).ObjectBounds()[0].second, r1);  // from the cache: the same mesh
  // The same tetrahedron twice as large (a different size and modification time).
  dir.Write("m.obj", "v 0 0 0\nv 2 0 0\nv 0 2 0\nv 0 0 2\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n");
  EXPECT_NEAR(Simulator(s).ObjectBounds()[0].second, 2 * r1, 1e-9 * r1);
  // An edit that leaves a hole is caught again (nothing stale is reused).
  dir.Write("m.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\n");
  EXPECT_THROW(Simulator{s}, Error);
}

TEST(MeshChecks, RevolutionSceneFromOutlinePoints) {
  testing::TempDir dir;
  const std::string scene = dir.Write("s.toml", R"(
[source]
type = "cone"
half_angle_deg = 20
[[object]]
type = "revolution"
outline_rz_um = [[0, -10], [6, -8], [9, 0], [6, 8], [0, 10]]
segments = 64
rotation_deg = [-90, 0, 0]
index = 1.33
[camera]
pixels = [32, 32]
pixel_pitch_um = 20
)" + testing::kOpticsToml);
  const Scene s = LoadScene(scene);
  ASSERT_TRUE(s.objects[0].mesh);
  Simulator sim(s);
  EXPECT_TRUE(sim.has_mesh_bvh());
  const PlaneResult r = sim.TracePlane(0, 0, 50000);
  EXPECT_GT(r.counters.interface_events, 1000u);
  EXPECT_EQ(r.counters.fates[int(Fate::kLostInside)], 0u);
}

}  // namespace
}  // namespace raymatch::simulate
