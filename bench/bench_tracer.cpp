// Rays per second per core for the reference scene: a 46 um water drop under a 27 deg
// cone, imaged by a 20x/0.42 objective onto a 300x200 sensor region (10 um pixels), single
// thread, with and without partial reflection, and with the camera's Gaussian PSF (the sample's
// calibrated 0.23 um at the object), on the SIMD packet path (the default) and on the scalar
// path (RunControl::simd = false) in the same run. Results: docs/performance.md.
//   build/release/bench/bench_tracer --benchmark_min_time=2
#include <benchmark/benchmark.h>

#include "raymatch/simulate/tracer.h"

namespace raymatch::simulate {
namespace {

Scene DropScene(PartialReflection pr, bool with_drop, double psf_sigma_um) {
  Scene s;
  s.wavelength_um = 0.462;
  s.source.type = SourceType::kCone;
  s.source.half_angle_deg = 27;
  if (with_drop) {
    ObjectSpec o;
    o.shape = ShapeType::kSphere;
    o.radius_um = 23;
    o.index = 1.3378;  // water at 462 nm, 20 degC (IAPWS R9-97)
    s.objects = {o};
  }
  s.optics.objective_focal_mm = 10;
  s.optics.na = 0.42;
  s.optics.tube_focal_mm = 200;
  s.camera.nx = 300;
  s.camera.ny = 200;
  s.camera.pixel_pitch_um = 10;
  s.camera.psf_sigma_um = psf_sigma_um;
  s.trace.partial_reflection = pr;
  return s;
}

void Run(benchmark::State& state, PartialReflection pr, bool drop, bool simd = true,
         double psf_sigma_um = 0) {
  const Simulator sim(DropScene(pr, drop, psf_sigma_um));
  RunControl one;
  one.threads = 1;
  one.simd = simd;
  const uint64_t rays = 2000000;
  uint32_t plane = 0;
  double hits = 0;
  for (auto _ : state) {
    const PlaneResult r = sim.TracePlane(0, plane++, rays, one);
    hits += r.counters.fates[int(Fate::kDetected)];
    benchmark::DoNotOptimize(r.counts.pixels.data());
  }
  state.SetItemsProcessed(state.iterations() * rays);
  state.counters["detected_fraction"] = hits / (double(state.iterations()) * rays);
}

void BM_Drop46_Cone27_PartialOff(benchmark::State& s) { Run(s, PartialReflection::kOff, true); }
void BM_Drop46_Cone27_Unpolarized(benchmark::State& s) {
  Run(s, PartialReflection::kUnpolarized, true);
}
void BM_Drop46_Cone27_Polarized(benchmark::State& s) {
  Run(s, PartialReflection::kPolarized, true);
}
void BM_FlatField_Cone27(benchmark::State& s) { Run(s, PartialReflection::kOff, false); }
void BM_Drop46_Cone27_PartialOff_Scalar(benchmark::State& s) {
  Run(s, PartialReflection::kOff, true, false);
}
void BM_Drop46_Cone27_Unpolarized_Scalar(benchmark::State& s) {
  Run(s, PartialReflection::kUnpolarized, true, false);
}
void BM_Drop46_Cone27_Polarized_Scalar(benchmark::State& s) {
  Run(s, PartialReflection::kPolarized, true, false);
}
void BM_FlatField_Cone27_Scalar(benchmark::State& s) {
  Run(s, PartialReflection::kOff, false, false);
}
void BM_Drop46_Cone27_Unpolarized_Psf(benchmark::State& s) {
  Run(s, PartialReflection::kUnpolarized, true, true, 0.23);
}
void BM_Drop46_Cone27_Unpolarized_Psf_Scalar(benchmark::State& s) {
  Run(s, PartialReflection::kUnpolarized, true, false, 0.23);
}

BENCHMARK(BM_Drop46_Cone27_PartialOff)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_Drop46_Cone27_PartialOff_Scalar)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_Drop46_Cone27_Unpolarized)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_Drop46_Cone27_Unpolarized_Scalar)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_Drop46_Cone27_Polarized)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_Drop46_Cone27_Polarized_Scalar)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_FlatField_Cone27)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_FlatField_Cone27_Scalar)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_Drop46_Cone27_Unpolarized_Psf)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_Drop46_Cone27_Unpolarized_Psf_Scalar)->Unit(benchmark::kMillisecond)->UseRealTime();

}  // namespace
}  // namespace raymatch::simulate

BENCHMARK_MAIN();
