// The SIMD packet path (simulate/src/packet.h) against the scalar path: the same random words
// as RayRng, and the same images, counters and near lists bit for bit, for every source, effect
// and selection mode it takes, on every instruction set this CPU has (Highway's run-time
// dispatch is pointed at each in turn).
#include "packet.h"

#include <gtest/gtest.h>
#include <hwy/targets.h>

#include <algorithm>
#include <cstring>
#include <set>

#include "raymatch/core/rng.h"
#include "raymatch/simulate/shapes.h"
#include "raymatch/simulate/tracer.h"
#include "test_scenes.h"

namespace raymatch::testing {
namespace {

using simulate::Fate;
using simulate::PlaneResult;
using simulate::RunControl;
using simulate::Simulator;
using simulate::SourceType;
namespace packet = simulate::packet;

/// Runs f once for every instruction set that is both compiled and supported here, with the
/// dispatch pointed at it; restores the real set afterwards.
template <class F>
void ForEachTarget(F&& f) {
  std::set<std::string> seen;
  for (int64_t target : hwy::SupportedAndGeneratedTargets()) {
    hwy::SetSupportedTargetsForTest(target);
    const std::string name = packet::TargetName();
    if (seen.insert(name).second) {
      SCOPED_TRACE("SIMD target " + name);
      f();
    }
  }
  hwy::SetSupportedTargetsForTest(0);  // 0: back to what the CPU supports
  EXPECT_GE(seen.size(), 1u);
  std::string names;
  for (const std::string& n : seen) names += " " + n;
  ::testing::Test::RecordProperty("simd_targets", names);
}

TEST(Packet, PhiloxWordsAreRayRngsWords) {
  const uint64_t seeds[] = {0, 12345, 0xFEDCBA9876543210ull};
  ForEachTarget([&] {
    for (uint64_t seed : seeds) {
      std::vector<uint64_t> rays(packet::kBatch);
      for (size_t i = 0; i < rays.size(); ++i)
        rays[i] = i * 0x9E3779B97F4A7Cull + (i % 3 == 0 ? (uint64_t(1) << 33) : 0) + i;
      auto r = std::make_unique<packet::Rays>();
      packet::PhiloxWords(seed, 7, rays.data(), rays.size(), r.get());
      int mismatches = 0;
      for (size_t i = 0; i < rays.size(); ++i) {
        RayRng rng(seed, 7, rays[i]);
        for (int w = 0; w < packet::kWords; ++w) mismatches += rng.NextU32() != r->words[w][i];
      }
      EXPECT_EQ(mismatches, 0) << "seed " << seed;
    }
  });
}

void ExpectSameResult(const PlaneResult& a, const PlaneResult& b) {
  ASSERT_EQ(a.counts.pixels.size(), b.counts.pixels.size());
  EXPECT_EQ(std::memcmp(a.counts.pixels.data(), b.counts.pixels.data(),
                        a.counts.pixels.size() * sizeof(float)),
            0)
      << "images differ";
  EXPECT_EQ(a.rays, b.rays);
  for (int f = 0; f < simulate::kNumFates; ++f)
    EXPECT_EQ(a.counters.fates[f], b.counters.fates[f]) << simulate::FateName(Fate(f));
  EXPECT_EQ(a.counters.interface_events, b.counters.interface_events);
  EXPECT_EQ(a.counters.fresnel_evaluations, b.counters.fresnel_evaluations);
  EXPECT_EQ(a.counters.corrector_tests, b.counters.corrector_tests);
  EXPECT_EQ(a.counters.shape_queries, b.counters.shape_queries);
  EXPECT_EQ(a.counters.mesh_queries, b.counters.mesh_queries);
  EXPECT_EQ(a.counters.rays_hitting_objects, b.counters.rays_hitting_objects);
  EXPECT_EQ(a.counters.path_class, b.counters.path_class);
}

/// The scalar image (one thread) against the packet image for 1 and 3 threads, every target.
/// Returns the scalar result.
PlaneResult ExpectPacketsMatchScalar(const Scene& scene, double defocus, uint64_t rays) {
  const Simulator sim(scene);
  RunControl scalar;
  scalar.simd = false;
  scalar.threads = 1;
  const PlaneResult ref = sim.TracePlane(defocus, 3, rays, scalar);
  EXPECT_GT(ref.counters.fates[int(Fate::kDetected)], rays / 20) << "scene images too little";
  ForEachTarget([&] {
    for (int threads : {1, 3}) {
      SCOPED_TRACE("threads " + std::to_string(threads));
      RunControl simd;
      simd.threads = threads;
      ExpectSameResult(ref, sim.TracePlane(defocus, 3, rays, simd));
    }
  });
  return ref;
}

Scene DropScene(PartialReflection pr) {
  Scene s = MicroscopeScene();
  s.source.half_angle_deg = 27;
  s.objects = {SphereObject(20, 1.3378, {3, -2, 1})};
  s.trace.partial_reflection = pr;
  return s;
}

void AddCorrector(Scene* s) {
  s->optics.corrector.enabled = true;
  s->optics.corrector.transmissions = {1.0, 0.97, 0.9, 0.8, 0.6};
}

TEST(Packet, ConeDropUnpolarisedMatchesScalar) {
  ExpectPacketsMatchScalar(DropScene(PartialReflection::kUnpolarized), 0, 400000);
}

// Motion (issue 22): rays that can meet the moving drop draw their time on the scalar path; the
// far ones stay in packets and draw nothing, so both paths give the same image (corrector and
// PSF words after the objects included).
TEST(Packet, MovingDropMatchesScalar) {
  Scene s = DropScene(PartialReflection::kUnpolarized);
  AddCorrector(&s);
  s.camera.psf_sigma_um = 0.7;
  s.exposure.shape = simulate::PulseShape::kGaussian;
  s.exposure.fwhm_us = 0.2;
  s.objects[0].velocity_um_per_us = {8, -3, 2};
  const PlaneResult r = ExpectPacketsMatchScalar(s, 2, 300000);
  EXPECT_GT(r.counters.motion_draws, 0u);
}

// The spectrum likewise: only rays near the dispersive drop draw a wavelength.
TEST(Packet, DispersiveDropUnderASpectrumMatchesScalar) {
  Scene s = DropScene(PartialReflection::kUnpolarized);
  AddCorrector(&s);
  s.source.spectrum.type = simulate::SpectrumType::kGaussian;
  s.source.spectrum.center_um = 0.462, s.source.spectrum.fwhm_um = 0.03;
  s.objects[0].dispersion.law = simulate::DispersionLaw::kCauchy;
  s.objects[0].dispersion.coefficients = {1.32, 0.004};
  s.objects[0].velocity_um_per_us = {0, 0, 5};  // and motion
  s.exposure.shape = simulate::PulseShape::kTopHat;
  s.exposure.duration_us = 0.4;
  const PlaneResult r = ExpectPacketsMatchScalar(s, -3, 300000);
  EXPECT_GT(r.counters.wavelength_draws, 0u);
  EXPECT_EQ(r.counters.wavelength_draws, r.counters.motion_draws);
}

TEST(Packet, SphereStageHardCasesMatchScalar) {
  // The sphere stage (rays that meet the scene's one homogeneous sphere): a bubble in water
  // (total internal reflection from outside), and a high-index sphere with a low interaction cap
  // (the cap, many internal reflections, and Fresnel draws past the batch's 12 words, which
  // send a ray back to the scalar path).
  Scene bubble = DropScene(PartialReflection::kUnpolarized);
  bubble.medium_index = 1.333;
  bubble.objects = {SphereObject(15, 1.0, {-4, 3, 2})};
  const PlaneResult b = ExpectPacketsMatchScalar(bubble, 3, 300000);
  EXPECT_GT(b.counters.path_class[0], 1000u);  // reflected at the first surface
  Scene dense = DropScene(PartialReflection::kUnpolarized);
  dense.objects = {SphereObject(18, 3.2, {2, 2, -3})};
  dense.trace.max_interactions = 4;
  const PlaneResult d = ExpectPacketsMatchScalar(dense, -2, 300000);
  EXPECT_GT(d.counters.fates[int(Fate::kInteractionCap)], 100u);
  EXPECT_GT(d.counters.path_class[3], 100u);  // two internal reflections
  Scene no_fresnel = dense;
  no_fresnel.trace.partial_reflection = PartialReflection::kOff;
  no_fresnel.trace.max_interactions = 100;
  ExpectPacketsMatchScalar(no_fresnel, 0, 300000);
}

TEST(Packet, PolarisedFresnelCorrectorAndTwoLensObjectiveMatchScalar) {
  Scene s = DropScene(PartialReflection::kPolarized);
  AddCorrector(&s);
  s.optics.model = simulate::ObjectiveModel::kTwoLens;
  s.optics.working_distance_mm = 20;  // the sample calibration's objective
  s.optics.back_focal_mm = 0;
  ExpectPacketsMatchScalar(s, -7.5, 400000);
}

TEST(Packet, LightFieldSourceWithCorrectorMatchesScalar) {
  Scene s = DropScene(PartialReflection::kUnpolarized);
  s.source.type = SourceType::kLightField;
  s.source.angular_extent = 0.5;
  // An uneven radiance map that reaches beyond the unit circle's cut (rejected rays), with
  // empty cells outside a disc and an empty row, as a measured map cut at the NA has.
  s.source.angular_map = Image(24, 24);
  for (int y = 0; y < 24; ++y)
    for (int x = 0; x < 24; ++x) {
      const bool inside = (x - 11.5) * (x - 11.5) + (y - 11.5) * (y - 11.5) < 13.5 * 13.5;
      s.source.angular_map.at(x, y) = inside && y != 5 ? float(1 + (x * 7 + y * 3) % 5) : 0.f;
    }
  AddCorrector(&s);
  ExpectPacketsMatchScalar(s, 4, 400000);
}

// The PSF's Box-Muller offsets (stages-inl.h, GaussianPair: its own logarithm, cosine and sine,
// so that every target and the one-lane path give the same bits) against the formula in long
// double: r = sigma sqrt(-2 ln(1 - u1)), (du, dv) = r (cos 2 pi u2, sin 2 pi u2) within 8 units
// in the last place of r (libm's own functions are within 1-4), at the edges of the reductions
// (u1 = 0 and 1 - 2^-32, every power-of-two boundary, the quadrant boundaries of u2) and over
// 2^17 words of a ray stream; and the same bits on every instruction set.
TEST(Packet, GaussianOffsetsAreBoxMullerToTheLastBitsOnEveryTarget) {
  std::vector<double> u1s, u2s;
  for (int k = 0; k <= 32; ++k)
    for (double d : {-0x1p-32, 0.0, 0x1p-32}) {
      const double u = 1 - std::ldexp(1.0, -k) + d;  // 1 - u near every power of two
      if (u >= 0 && u < 1) u1s.push_back(u);
    }
  for (int q = 0; q <= 16; ++q)  // quadrant and octant boundaries of 2 pi u2
    for (double d : {-0x1p-32, 0.0, 0x1p-32}) {
      const double u = q / 16.0 + d;
      if (u >= 0 && u < 1) u2s.push_back(u);
    }
  std::vector<double> a, b;
  for (double u1 : u1s)
    for (double u2 : u2s) a.push_back(u1), b.push_back(u2);
  RayRng rng(99, 3, 12345);
  for (int i = 0; i < (1 << 17); ++i) {
    a.push_back(rng.Uniform());
    b.push_back(rng.Uniform());
  }
  const double sigma = 0.7;
  std::vector<double> first_du, first_dv;  // the first target's bits
  ForEachTarget([&] {
    auto r = std::make_unique<packet::Rays>();
    std::vector<double> du(a.size()), dv(a.size());
    for (size_t at = 0; at < a.size(); at += 37) {  // batches of 37: a partial vector at the end
      const size_t n = std::min<size_t>(37, a.size() - at);
      std::fill(std::begin(r->psf_du), std::end(r->psf_du), 0.0);
      std::fill(std::begin(r->psf_dv), std::end(r->psf_dv), 0.0);
      std::copy_n(a.begin() + at, n, r->psf_du);
      std::copy_n(b.begin() + at, n, r->psf_dv);
      packet::GaussianOffsets(sigma, n, r.get());
      std::copy_n(r->psf_du, n, du.begin() + at);
      std::copy_n(r->psf_dv, n, dv.begin() + at);
    }
    int bad = 0;
    for (size_t i = 0; i < a.size(); ++i) {
      const long double rr = sigma * std::sqrt(-2.0L * std::log1p(-(long double)a[i]));
      const long double phi = 2 * 3.141592653589793238462643383279503L * b[i];
      const long double tol = 8 * 0x1p-52L * std::max(rr, (long double)0x1p-1074);
      if (std::fabs(du[i] - rr * std::cos(phi)) > tol ||
          std::fabs(dv[i] - rr * std::sin(phi)) > tol) {
        if (++bad <= 5)
          ADD_FAILURE() << "u1 " << a[i] << " u2 " << b[i] << ": (" << du[i] << ", " << dv[i]
                        << "), expected (" << double(rr * std::cos(phi)) << ", "
                        << double(rr * std::sin(phi)) << ")";
      }
    }
    EXPECT_EQ(bad, 0);
    if (first_du.empty()) {
      first_du = du, first_dv = dv;
    } else {
      EXPECT_TRUE(du == first_du && dv == first_dv) << "the targets' offsets differ";
    }
  });
}

// The camera PSF (two words after the corrector's: PsfDraws) on both the straight rays and the
// sphere stage's, with and without a corrector, and a light field continued beyond its NA cut.
TEST(Packet, CameraPsfAndLightFieldEdgeMatchScalar) {
  for (bool corrector : {false, true}) {
    Scene s = DropScene(PartialReflection::kUnpolarized);
    s.camera.psf_sigma_um = 0.7;
    if (corrector) {
      AddCorrector(&s);
      s.source.type = SourceType::kLightField;
      s.source.angular_extent = 0.5;
      s.source.angular_map = Image(24, 24);
      for (int y = 0; y < 24; ++y)
        for (int x = 0; x < 24; ++x) {
          const double u = (2 * (x + 0.5) / 24 - 1) * 0.5, v = (1 - 2 * (y + 0.5) / 24) * 0.5;
          s.source.angular_map.at(x, y) =
              std::hypot(u, v) < 0.35 ? float(1 + (x * 7 + y * 3) % 5) : 0.f;
        }
      s.source.map_na_limit = 0.35;
      s.source.edge_half_angle_deg = 22, s.source.edge_width_deg = 1.5;
    }
    const Simulator sim(s);
    ASSERT_TRUE(std::find(sim.Effects().begin(), sim.Effects().end(), "simd_packets") !=
                sim.Effects().end());
    ExpectPacketsMatchScalar(s, corrector ? 4 : -6, 300000);
  }
}

TEST(Packet, CollimatedRectangleFieldBoxAndSphereFlippedOffsetCameraMatchScalar) {
  Scene s = MicroscopeScene();
  s.source.type = SourceType::kCollimated;
  s.source.tilt_deg = 12;
  s.source.azimuth_deg = 30;
  s.source.field_shape = simulate::FieldShape::kRect;
  s.source.field_size_um = {80, 60};
  s.source.field_center_um = {4, -3, 0};
  s.objects = {SphereObject(10, 1.5, {-12, 0, 0}), BoxObject({6, 8, 5}, 1.4, {14, 5, 2})};
  s.trace.partial_reflection = PartialReflection::kUnpolarized;
  s.camera.flip = true;
  s.camera.offset_um = {30, -40};
  ExpectPacketsMatchScalar(s, 2, 300000);
}

TEST(Packet, FlatFieldMatchesScalar) {
  Scene s = MicroscopeScene();
  s.source.half_angle_deg = 20;
  AddCorrector(&s);
  ExpectPacketsMatchScalar(s, 0, 300000);
}

TEST(Packet, SelectionsMatchScalar) {
  // TraceRangeExcept and TraceFarRays (the fit's split) on both paths: images and near lists.
  // With a corrector: a ray whose corrector draw lies past the batch's words is traced again on
  // the scalar path, and must still be split (in ray order) like the others.
  Scene scene = DropScene(PartialReflection::kUnpolarized);
  AddCorrector(&scene);
  const Simulator sim(scene);
  RunControl scalar, simd;
  scalar.simd = false;
  std::vector<uint64_t> excluded;
  for (uint64_t i = 1000; i < 150000; i += 7) excluded.push_back(i);
  ForEachTarget([&] {
    ExpectSameResult(sim.TraceRangeExcept(0, 1, 500, 200000, excluded, scalar),
                     sim.TraceRangeExcept(0, 1, 500, 200000, excluded, simd));
    std::vector<uint64_t> near_scalar, near_simd;
    ExpectSameResult(sim.TraceFarRays(0, 1, 300, 250000, {2, 1, 0}, 26, &near_scalar, scalar),
                     sim.TraceFarRays(0, 1, 300, 250000, {2, 1, 0}, 26, &near_simd, simd));
    EXPECT_EQ(near_scalar, near_simd);
    EXPECT_GT(near_simd.size(), 1000u);
  });
}

TEST(Packet, MeshSceneMatchesScalar) {
  // A mesh (an octahedron, Embree) next to nothing else: rays that meet nothing still count one
  // shape query and one mesh query each, as on the scalar path.
  Scene s = DropScene(PartialReflection::kUnpolarized);
  auto mesh = std::make_shared<simulate::TriangleMesh>();
  const double a = 15;
  mesh->vertices = {{a, 0, 0}, {-a, 0, 0}, {0, a, 0}, {0, -a, 0}, {0, 0, a}, {0, 0, -a}};
  mesh->triangles = {{0, 2, 4}, {2, 1, 4}, {1, 3, 4}, {3, 0, 4},
                     {2, 0, 5}, {1, 2, 5}, {3, 1, 5}, {0, 3, 5}};
  ObjectSpec o;
  o.shape = simulate::ShapeType::kMesh;
  o.mesh = mesh;
  o.index = 1.45;
  o.center_um = {2, -3, 0};
  s.objects = {o};
  const PlaneResult r = ExpectPacketsMatchScalar(s, 0, 200000);
  EXPECT_GT(r.counters.mesh_queries, 200000u);
}

TEST(Packet, CorrectorWithoutZonesBlocksEverythingOnBothPaths) {
  Scene s = DropScene(PartialReflection::kUnpolarized);
  s.optics.corrector.enabled = true;  // no zones: no ray passes (a scene built in code only)
  const Simulator sim(s);
  RunControl scalar;
  scalar.simd = false;
  const PlaneResult a = sim.TracePlane(0, 1, 50000, scalar), b = sim.TracePlane(0, 1, 50000);
  ExpectSameResult(a, b);
  EXPECT_EQ(b.counters.fates[int(Fate::kDetected)], 0u);
}

}  // namespace
}  // namespace raymatch::testing
