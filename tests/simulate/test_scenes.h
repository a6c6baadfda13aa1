#pragma once
// Scenes shared by the simulator tests: the paper's microscope (20x / NA 0.42 objective, 200 mm
// tube lens, M = -20) and simple objects.
#include <algorithm>
#include <memory>
#include <string>
#include <vector>

#include "raymatch/core/array_io.h"
#include "raymatch/simulate/scene.h"
#include "temp_dir.h"

namespace raymatch::testing {

using simulate::IndexField;
using simulate::IndexFieldType;
using simulate::ObjectSpec;
using simulate::PartialReflection;
using simulate::Scene;
using simulate::ShapeType;

/// 64x64 camera with 20 um pixels (1 um at the object); partial reflection off; fixed seed.
inline Scene MicroscopeScene(uint64_t seed = 12345) {
  Scene s;
  s.name = "test";
  s.optics.objective_focal_mm = 10;
  s.optics.na = 0.42;
  s.optics.tube_focal_mm = 200;
  s.camera.nx = s.camera.ny = 64;
  s.camera.pixel_pitch_um = 20;
  s.trace.partial_reflection = PartialReflection::kOff;
  s.trace.seed = seed;
  return s;
}

inline ObjectSpec SphereObject(double r, double n, Vec3 c = {}) {
  ObjectSpec o;
  o.shape = ShapeType::kSphere;
  o.radius_um = r;
  o.index = n;
  o.center_um = c;
  return o;
}

inline ObjectSpec BoxObject(Vec3 half, double n, Vec3 c = {}) {
  ObjectSpec o;
  o.shape = ShapeType::kBox;
  o.semi_axes_um = half;
  o.index = n;
  o.center_um = c;
  return o;
}

/// The microscope's [objective] and [tube_lens] tables for scene files.
inline const std::string kOpticsToml =
    "[objective]\nfocal_length_mm = 10\nna = 0.42\n[tube_lens]\nfocal_length_mm = 200\n";

/// A Luneburg lens n = sqrt(2 - (r/R)^2) of radius R in vacuum (n = 1 at its surface).
inline ObjectSpec LuneburgSphere(double R) {
  ObjectSpec o;
  o.shape = ShapeType::kSphere;
  o.radius_um = R;
  auto f = std::make_shared<IndexField>();
  f->type = IndexFieldType::kLuneburg;
  f->n0 = 1.0;
  f->radius_um = R;
  o.index_field = f;
  o.index = f->Index(Vec3());
  return o;
}

/// A water drop whose density falls from 1040 kg/m^3 at its centre to 998 at `falloff_um` from
/// it (a gradient-index lens): the grid written to `dir`/rho.npy (r 0..half_um, z -half_um..
/// half_um, 0.5 um apart) and the TOML of a sphere of `radius_um` with that grid as its water
/// density field at 293.15 K (`extra`: more keys of the object).
inline std::string DensityDropObject(const TempDir& dir, int half_um, double falloff_um,
                                     double radius_um, const std::string& extra = "") {
  const int nr = 2 * half_um + 1, nz = 4 * half_um + 1;
  NdArray rho{{size_t(nz), size_t(nr)}, std::vector<double>(size_t(nr) * nz)};
  for (int iz = 0; iz < nz; ++iz)
    for (int ir = 0; ir < nr; ++ir) {
      const double r = 0.5 * ir, z = -half_um + 0.5 * iz;
      rho.values[size_t(iz) * nr + ir] =
          998 + 42 * std::max(0.0, 1 - (r * r + z * z) / (falloff_um * falloff_um));
    }
  WriteNpy(dir / "rho.npy", rho);
  return "[[object]]\ntype = \"sphere\"\nradius_um = " + std::to_string(radius_um) + "\n" + extra +
         "[object.index_field]\ntype = \"grid_rz\"\nfile = \"rho.npy\"\nspacing_um = [0.5, 0.5]\n"
         "origin_um = [0, " +
         std::to_string(-half_um) + "]\nquantity = \"density\"\ntemperature_K = 293.15\n";
}

}  // namespace raymatch::testing
