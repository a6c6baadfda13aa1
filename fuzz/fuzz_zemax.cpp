// libFuzzer harness: Zemax binary source files (ray lists: ReadZemaxSourceFile), and what
// `calibrate zemax-import` makes of them (the angular map and the .npy ray list): no crash,
// and no NaN or Inf in what is made from a file the reader accepted.
#include "fuzz_input.h"
#include "raymatch/calibrate/zemax_source.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string path = raymatch::fuzz::WriteInput(data, size, ".dat");
  using raymatch::fuzz::CheckFinite;
  raymatch::calibrate::ZemaxSourceFile f;
  bool ok = false;
  raymatch::fuzz::Expect([&] {
    f = raymatch::calibrate::ReadZemaxSourceFile(path);
    ok = true;
  });
  if (!ok) return 0;
  raymatch::fuzz::Expect([&] {
    const auto s = raymatch::calibrate::AngularMapFromZemax(f, {});
    for (float v : s.data.angular_map.pixels) CheckFinite(v, "angular map pixel");
    CheckFinite(s.data.angular_extent, "angular extent");
    CheckFinite(s.data.field_radius_um, "field radius");
  });
  return raymatch::fuzz::Expect([&] {
    for (double v : raymatch::calibrate::ZemaxRayList(f, nullptr).values)
      CheckFinite(v, "ray list value");
  });
}
