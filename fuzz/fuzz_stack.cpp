// libFuzzer harness: focus-stack indexes (compare::ReadStack, docs/compare.md), the CSV
// "defocus_um,file" and the simulator's JSON <name>_scan.json. An input whose first non-blank
// byte is '{' or '[' is written as index.json, any other as index.csv, into a scratch folder
// holding the 16 x 8 images the seed corpus names (a.tif, b.tif, and small.tif of another
// size), so that mutants reach the image reads. A harness passes when ReadStack returns a stack
// of finite focus positions, one image per position, or throws a CompareError (an Error):
// anything else (nlohmann::json exceptions included) is a finding.
#include <cctype>

#include "fuzz_input.h"
#include "raymatch/compare/focus_scan.h"
#include "raymatch/core/image_io.h"

namespace {

std::string Folder() {
  const std::string dir = raymatch::fuzz::ScratchFolder("stack", {});
  raymatch::Image a(16, 8, 100.f), b(16, 8, 90.f);
  a.at(8, 4) = 20.f;
  raymatch::WriteFloatImage(dir + "/a.tif", a, "fuzz a");
  raymatch::WriteFloatImage(dir + "/b.tif", b, "fuzz b");
  raymatch::WriteFloatImage(dir + "/small.tif", raymatch::Image(4, 4, 1.f), "fuzz small");
  return dir;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const std::string dir = Folder();
  size_t i = 0;
  while (i < size && std::isspace(data[i])) ++i;
  const bool json = i < size && (data[i] == '{' || data[i] == '[');
  const std::string path = dir + (json ? "/index.json" : "/index.csv");
  raymatch::fuzz::WriteInputTo(path, data, size);
  return raymatch::fuzz::Expect([&] {
    const raymatch::compare::Stack s = raymatch::compare::ReadStack(path);
    if (s.defocus_um.size() != s.images.size() || s.files.size() != s.images.size() ||
        s.images.empty())
      raymatch::fuzz::CheckFinite(NAN, "one image per focus position");
    for (double z : s.defocus_um) raymatch::fuzz::CheckFinite(z, "defocus_um");
  });
}
