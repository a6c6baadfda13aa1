#pragma once
// Scenes shared by the simulator tests: the paper's microscope (20x / NA 0.42 objective, 200 mm
// tube lens, M = -20) and simple objects.
#include <memory>
#include <string>

#include "raymatch/simulate/scene.h"

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

}  // namespace raymatch::testing
