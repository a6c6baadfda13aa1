// libFuzzer harness: fit files (LoadFitSpec, docs/fit.md). The input is written as fit.toml into
// a scratch folder holding what the seed corpus names: scene.toml (a small sphere scene needing
// no calibration, 32 x 16 pixels) and 32 x 16 images image.tif and dark.tif, so that a mutated
// file reaches the image, parameter-key and ray-schedule checks. Other names must give a
// located error.
#include <cmath>

#include "fuzz_input.h"
#include "raymatch/core/image_io.h"
#include "raymatch/fit/fit.h"

namespace {

const char kScene[] = R"(name = "fuzz"
[source]
type = "collimated"
field_radius_um = 20
[[object]]
name = "drop"
type = "sphere"
center_um = [0, 0, 0]
radius_um = 10
index = 1.337
[objective]
focal_length_mm = 10
na = 0.42
[tube_lens]
focal_length_mm = 200
[camera]
pixels = [32, 16]
pixel_pitch_um = 20
[trace]
rays = 1000
)";

std::string Folder() {
  const std::string dir = raymatch::fuzz::ScratchFolder("fit", {{"scene.toml", kScene}});
  // Not constant: an image with more than half its pixels at its maximum is refused as
  // saturated before the parameter checks.
  raymatch::Image img(32, 16), dark(32, 16, 10.f);
  for (int y = 0; y < 16; ++y)
    for (int x = 0; x < 32; ++x) img.at(x, y) = float(100 + (x * 7 + y * 3) % 11);
  img.at(16, 8) = 20.f;
  raymatch::WriteFloatImage(dir + "/image.tif", img, "fuzz image");
  raymatch::WriteFloatImage(dir + "/dark.tif", dark, "fuzz dark");
  return dir;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const std::string dir = Folder();
  const std::string path = dir + "/fit.toml";
  raymatch::fuzz::WriteInputTo(path, data, size);
  return raymatch::fuzz::Expect([&] {
    const raymatch::fit::FitSpec f = raymatch::fit::LoadFitSpec(path);
    for (const auto& p : f.parameters) {
      raymatch::fuzz::CheckFinite(p.lower + p.upper + p.start + p.step, "parameter bounds");
      if (p.points < 1) raymatch::fuzz::CheckFinite(NAN, "grid points >= 1");
    }
    for (const auto& im : f.images)
      raymatch::fuzz::CheckFinite(im.defocus_um * im.gain_e_per_dn, "image numbers");
  });
}
