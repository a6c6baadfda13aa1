// libFuzzer harness: calibration TOML files (ReadCalibrationFile, docs/calibration-format.md).
#include "fuzz_input.h"
#include "raymatch/core/calibration_file.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string path = raymatch::fuzz::WriteInput(data, size, ".toml");
  return raymatch::fuzz::Expect([&] { raymatch::ReadCalibrationFile(path); });
}
