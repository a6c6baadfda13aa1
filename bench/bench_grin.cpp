// Gradient-index accuracy and time (issue 6). Single thread.
//   build/release/bench/bench_grin
// * LuneburgTolerance/<k>: tolerance 10^-k um; error of the exit point against the exact rear
//   pole for 200 collimated rays at heights up to 0.9 R (R = 23 um), and wall time per ray.
// * DropImageTolerance/<k>: a 46 um drop with a spherical pressure-wave shell in an n(r, z)
//   grid; relative L1 difference of its image against a 10^-9 um reference (same rays).
// * Grid3DDropImage/<variant>/<k>: the same drop from a 3D grid (96^3): rays per second (so
//   the time of a photon-matched image can be extrapolated) and the relative L1 difference of
//   its image against a 10^-9 um step-doubling reference and a 10^-10 um cell-step reference
//   (same rays).
#include <benchmark/benchmark.h>

#include <cmath>

#include "raymatch/simulate/tracer.h"

namespace raymatch::simulate {
namespace {

Scene Optics() {
  Scene s;
  s.optics.objective_focal_mm = 10;
  s.optics.na = 0.42;
  s.optics.tube_focal_mm = 200;
  s.camera.nx = 300;
  s.camera.ny = 200;
  s.camera.pixel_pitch_um = 10;
  s.trace.partial_reflection = PartialReflection::kUnpolarized;
  return s;
}

/// Integrator variants compared in the same run (issue 13): 0 = the former step doubling
/// without uniform-cell steps, 1 = the embedded controller alone, 2 = embedded + uniform cells,
/// 3 = embedded + uniform cells + cell steps on 3D grids (the default; the same as 2 for
/// analytic fields and r-z grids).
void SetVariant(GrinSettings* g, int64_t variant) {
  g->step_doubling = variant == 0;
  if (variant < 2) g->uniform_tolerance = -1;
  g->cell_steps = variant >= 3;
}

/// sum |image - reference| / sum reference over the pixels.
double RelativeL1(const PlaneResult& image, const PlaneResult& reference) {
  double diff = 0, total = 0;
  for (size_t i = 0; i < reference.counts.size(); ++i) {
    diff += std::abs(image.counts.pixels[i] - reference.counts.pixels[i]);
    total += reference.counts.pixels[i];
  }
  return diff / total;
}

void BM_LuneburgTolerance(benchmark::State& state) {
  const double R = 23, tol = std::pow(10.0, -double(state.range(0)));
  Scene s = Optics();
  s.trace.partial_reflection = PartialReflection::kOff;
  s.trace.grin.tolerance_um = tol;
  SetVariant(&s.trace.grin, state.range(1));
  ObjectSpec o;
  o.shape = ShapeType::kSphere;
  o.radius_um = R;
  auto f = std::make_shared<IndexField>();
  f->type = IndexFieldType::kLuneburg;
  f->radius_um = R;
  o.index_field = f;
  s.objects = {o};
  const Simulator sim(s);
  const int K = 200;
  double err_sum = 0, err_max = 0, steps = 0;
  for (auto _ : state) {
    err_sum = err_max = steps = 0;
    for (int i = 0; i < K; ++i) {
      const double h = 0.9 * R * (i + 0.5) / K;
      const auto e = sim.TraceThroughObjects({h, 0, -2 * R}, {0, 0, 1}, i);
      const double err = Length(e.origin - Vec3(0, 0, R));
      err_sum += err, err_max = std::max(err_max, err);
      steps += e.counters.grin_steps;
    }
  }
  state.SetItemsProcessed(state.iterations() * K);
  state.counters["tolerance_um"] = tol;
  state.counters["mean_error_um"] = err_sum / K;
  state.counters["max_error_um"] = err_max;
  state.counters["steps_per_ray"] = steps / K;
  state.counters["steps_per_s"] =
      benchmark::Counter(steps * state.iterations(), benchmark::Counter::kIsRate);
}
BENCHMARK(BM_LuneburgTolerance)
    ->ArgsProduct({benchmark::CreateDenseRange(3, 9, 1), {0, 1}})
    ->ArgNames({"tol_exp", "variant"})
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

/// Water drop (R = 23 um) with a spherical compression shell (+20 kg/m^3 at r = 15 um, width
/// 1.5 um) as an n(r, z) grid with 0.25 um spacing, or the same as a 3D grid.
std::shared_ptr<IndexField> DropField(bool three_d) {
  auto f = std::make_shared<IndexField>();
  auto n_at = [](double r) {
    const double rho = 998.2 + 20 * std::exp(-std::pow((r - 15) / 1.5, 2));
    // Linearised water index near 1.3378 at 462 nm: dn/drho ~ 3.3e-4 m^3/kg (IAPWS slope).
    return 1.3378 + 3.3e-4 * (rho - 998.2);
  };
  if (!three_d) {
    const double h = 0.25;
    f->type = IndexFieldType::kGridRZ;
    f->nx = 97, f->ny = 1, f->nz = 193;
    f->spacing_um = {h, 1, h};
    f->origin_um = {0, 0, -24};
    for (int k = 0; k < f->nz; ++k)
      for (int i = 0; i < f->nx; ++i) f->values.push_back(n_at(std::hypot(i * h, -24 + k * h)));
  } else {
    const int n = 96;
    const double h = 48.0 / (n - 1);
    f->type = IndexFieldType::kGrid3D;
    f->nx = f->ny = f->nz = n;
    f->spacing_um = {h, h, h};
    f->origin_um = {-24, -24, -24};
    for (int k = 0; k < n; ++k)
      for (int j = 0; j < n; ++j)
        for (int i = 0; i < n; ++i)
          f->values.push_back(n_at(std::sqrt(std::pow(-24 + i * h, 2) + std::pow(-24 + j * h, 2) +
                                             std::pow(-24 + k * h, 2))));
  }
  return f;
}

Scene DropScene(bool three_d, double tol) {
  Scene s = Optics();
  s.source.type = SourceType::kCone;
  s.source.half_angle_deg = 27;
  s.source.field_radius_um = 30;  // rays that can hit the drop
  ObjectSpec o;
  o.shape = ShapeType::kSphere;
  o.radius_um = 23;
  o.index_field = DropField(three_d);
  s.objects = {o};
  s.trace.grin.tolerance_um = tol;
  return s;
}

void BM_DropImageTolerance(benchmark::State& state) {
  RunControl one;
  one.threads = 1;
  const uint64_t rays = 100000;
  // Reference: the former integrator at 1e-9 um, without uniform-cell steps.
  static const PlaneResult ref = [&] {
    Scene r = DropScene(false, 1e-9);
    SetVariant(&r.trace.grin, 0);
    return Simulator(r).TracePlane(0, 0, rays, one);
  }();
  Scene scene = DropScene(false, std::pow(10.0, -double(state.range(0))));
  SetVariant(&scene.trace.grin, state.range(1));
  const Simulator sim(scene);
  PlaneResult last;
  for (auto _ : state) last = sim.TracePlane(0, 0, rays, one);
  state.SetItemsProcessed(state.iterations() * rays);
  state.counters["tolerance_um"] = std::pow(10.0, -double(state.range(0)));
  state.counters["rel_L1_vs_ref"] = RelativeL1(last, ref);
  state.counters["steps_per_ray"] = double(last.counters.grin_steps) / rays;
}
BENCHMARK(BM_DropImageTolerance)
    ->ArgsProduct({benchmark::CreateDenseRange(2, 8, 1), {0, 2}})
    ->ArgNames({"tol_exp", "variant"})
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

void BM_Grid3DDropImage(benchmark::State& state) {
  RunControl one;
  one.threads = 1;
  const uint64_t rays = 50000;
  // References (same rays): the former integrator at 1e-9 um without uniform-cell steps, and
  // cell steps at 1e-10 um.
  static const PlaneResult ref = [&] {
    Scene r = DropScene(true, 1e-9);
    SetVariant(&r.trace.grin, 0);
    return Simulator(r).TracePlane(0, 0, rays, one);
  }();
  static const PlaneResult ref_cells = [&] {
    Scene r = DropScene(true, 1e-10);
    SetVariant(&r.trace.grin, 3);
    return Simulator(r).TracePlane(0, 0, rays, one);
  }();
  Scene scene = DropScene(true, std::pow(10.0, -double(state.range(1))));
  SetVariant(&scene.trace.grin, state.range(0));
  const Simulator sim(scene);
  PlaneResult last;
  for (auto _ : state) last = sim.TracePlane(0, 0, rays, one);
  state.SetItemsProcessed(state.iterations() * rays);
  state.counters["steps_per_ray"] = double(last.counters.grin_steps) / rays;
  state.counters["uniform_steps_per_ray"] = double(last.counters.grin_uniform_steps) / rays;
  state.counters["rel_L1_vs_ref"] = RelativeL1(last, ref);
  state.counters["rel_L1_vs_cells_ref"] = RelativeL1(last, ref_cells);
}
BENCHMARK(BM_Grid3DDropImage)
    ->ArgsProduct({{0, 1, 2, 3}, {5}})
    ->Args({0, 7})
    ->Args({3, 7})
    ->ArgNames({"variant", "tol_exp"})
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

}  // namespace
}  // namespace raymatch::simulate

BENCHMARK_MAIN();
