// Tracing a subset of a plane's rays (the fit's "trace once what does not change"): the rays
// near a sphere plus all the others add up to the whole image bit for bit, for any thread count,
// and the rays far from the region never meet an object.
#include <gtest/gtest.h>

#include "raymatch/simulate/tracer.h"
#include "test_scenes.h"

namespace raymatch::simulate {
namespace {

Scene DropScene() {
  Scene s = testing::MicroscopeScene(77);
  s.objects = {testing::SphereObject(15, 1.333, Vec3(2, -1, 1))};
  s.source.type = SourceType::kCone;
  s.source.half_angle_deg = 25;
  s.camera.nx = 64, s.camera.ny = 48;
  s.camera.pixel_pitch_um = 20;
  s.trace.partial_reflection = PartialReflection::kUnpolarized;
  return s;
}

TEST(RaySubset, NearPlusFarEqualsWholeImageBitForBit) {
  const Scene s = DropScene();
  const Simulator sim(s);
  const uint64_t n = 400000;
  std::vector<uint64_t> near;
  std::vector<uint64_t> far;
  sim.SplitRaysBySphere(3, n, Vec3(2, -1, 1), 16, &near, &far);
  ASSERT_EQ(near.size() + far.size(), n);
  ASSERT_GT(near.size(), n / 50);  // the sphere covers a few percent of the source field
  ASSERT_GT(far.size(), n / 2);
  const PlaneResult whole = sim.TracePlane(-5, 3, n);
  for (int threads : {1, 3}) {
    RunControl rc;
    rc.threads = threads;
    const PlaneResult a = sim.TraceRays(-5, 3, near, rc);
    const PlaneResult b = sim.TracePlaneExcept(-5, 3, n, near, rc);
    const PlaneResult b_list = sim.TraceRays(-5, 3, far, rc);
    EXPECT_EQ(a.rays, near.size());
    EXPECT_EQ(b.rays, far.size());
    EXPECT_EQ(b.counts.pixels, b_list.counts.pixels);
    Image sum = a.counts;
    for (size_t i = 0; i < sum.size(); ++i) sum.pixels[i] += b.counts.pixels[i];
    EXPECT_EQ(sum.pixels, whole.counts.pixels) << "threads " << threads;
    // Rays whose straight line misses the region never reach an object.
    EXPECT_EQ(b.counters.rays_hitting_objects, 0u);
    EXPECT_EQ(b.counters.interface_events, 0u);
  }
}

// The fit's coarse-to-fine levels extend a background instead of re-tracing it: far rays of
// [0, m) plus far rays of [m, n), each found in the same pass that traces them, give the
// near list and the far image of [0, n) exactly, for any thread count; a far range traced
// against a known near list (another defocus) gives the same image.
TEST(RaySubset, FarRaysByRangesAddUpToTheSplitOfTheWhole) {
  const Scene s = DropScene();
  const Simulator sim(s);
  const uint64_t m = 70001, n = 400000;  // a range boundary inside a chunk
  std::vector<uint64_t> near;
  sim.SplitRaysBySphere(3, n, Vec3(2, -1, 1), 16, &near, nullptr);
  const PlaneResult far = sim.TracePlaneExcept(-5, 3, n, near);
  for (int threads : {1, 3}) {
    RunControl rc;
    rc.threads = threads;
    std::vector<uint64_t> found;
    const PlaneResult a = sim.TraceFarRays(-5, 3, 0, m, Vec3(2, -1, 1), 16, &found, rc);
    const PlaneResult b = sim.TraceFarRays(-5, 3, m, n, Vec3(2, -1, 1), 16, &found, rc);
    EXPECT_EQ(found, near) << "threads " << threads;
    EXPECT_EQ(a.rays + b.rays, far.rays);
    Image sum = a.counts;
    for (size_t i = 0; i < sum.size(); ++i) sum.pixels[i] += b.counts.pixels[i];
    EXPECT_EQ(sum.pixels, far.counts.pixels) << "threads " << threads;
    const PlaneResult c = sim.TraceRangeExcept(-5, 3, m, n, near, rc);
    EXPECT_EQ(c.counts.pixels, b.counts.pixels);
    EXPECT_EQ(c.rays, b.rays);
    std::vector<uint64_t> part;
    sim.SplitRaysBySphere(3, m, n, Vec3(2, -1, 1), 16, &part, nullptr);
    EXPECT_EQ(part,
              std::vector<uint64_t>(std::lower_bound(near.begin(), near.end(), m), near.end()));
  }
}

TEST(RaySubset, SplitDoesNotDependOnThreadsAndIsAscending) {
  const Simulator sim(DropScene());
  std::vector<uint64_t> a, b;
  sim.SplitRaysBySphere(0, 200000, Vec3(0, 0, 0), 20, &a, nullptr);
  sim.SplitRaysBySphere(0, 200000, Vec3(0, 0, 0), 20, &b, nullptr);
  EXPECT_EQ(a, b);
  EXPECT_TRUE(std::is_sorted(a.begin(), a.end()));
}

}  // namespace
}  // namespace raymatch::simulate
