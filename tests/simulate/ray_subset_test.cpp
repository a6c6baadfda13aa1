// Tracing a subset of a plane's rays (the fit's "trace once what does not change"): the rays
// near a sphere plus all the others add up to the whole image bit for bit, for any thread count,
// and the rays far from the region never meet an object.
#include <gtest/gtest.h>

#include <algorithm>
#include <iterator>

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

// Simulator::Trace with the selections its entry points name, composed: a range split by the
// sphere, less a list of rays, plus the near rays it reports and the listed rays, is the whole
// plane bit for bit; each part is the entry point's image of the same rays.
TEST(RaySubset, ComposedSelectionsOfTraceAddUpToThePlane) {
  const Simulator sim(DropScene());
  const uint64_t first = 1000, last = 300000;
  const Vec3 c(2, -1, 1);
  std::vector<uint64_t> left_out;  // every 97th ray of the range, ascending
  for (uint64_t r = first + 5; r < last; r += 97) left_out.push_back(r);
  std::vector<uint64_t> near;
  const PlaneResult far =
      sim.Trace(4, 2, RaySelection::Range(first, last).SplitBy(c, 16).Except(left_out), {}, &near);
  ASSERT_FALSE(near.empty());
  EXPECT_TRUE(std::is_sorted(near.begin(), near.end()));
  for (uint64_t r : left_out) EXPECT_FALSE(std::binary_search(near.begin(), near.end(), r));
  EXPECT_EQ(far.rays + near.size() + left_out.size(), last - first);
  EXPECT_EQ(far.counters.interface_events, 0u);  // the far rays never meet the sphere
  const PlaneResult near_image = sim.Trace(4, 2, RaySelection::Of(near));
  const PlaneResult listed = sim.TraceRays(4, 2, left_out);
  const PlaneResult whole = sim.Trace(4, 2, RaySelection::Range(first, last));
  Image sum = far.counts;
  for (size_t i = 0; i < sum.size(); ++i)
    sum.pixels[i] += near_image.counts.pixels[i] + listed.counts.pixels[i];
  EXPECT_EQ(sum.pixels, whole.counts.pixels);
  // The same rays through the entry points.
  std::vector<uint64_t> near_b;
  const PlaneResult far_b = sim.TraceFarRays(4, 2, first, last, c, 16, &near_b);
  std::vector<uint64_t> merged;  // the split's near rays, left-out ones included
  std::set_union(near.begin(), near.end(), left_out.begin(), left_out.end(),
                 std::back_inserter(merged));
  std::vector<uint64_t> near_or_listed;
  std::set_union(near_b.begin(), near_b.end(), left_out.begin(), left_out.end(),
                 std::back_inserter(near_or_listed));
  EXPECT_EQ(merged, near_or_listed);
  const PlaneResult rest = sim.TraceRangeExcept(4, 2, first, last, near_or_listed);
  EXPECT_EQ(rest.counts.pixels, far.counts.pixels);
  EXPECT_EQ(sim.TracePlane(4, 2, last).counts.pixels,
            sim.TraceRangeExcept(4, 2, 0, last, {}).counts.pixels);
}

}  // namespace
}  // namespace raymatch::simulate
