// libFuzzer harness: NumPy .npy arrays (ReadNpy: grids, ray lists).
#include "fuzz_input.h"
#include "raymatch/core/array_io.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string path = raymatch::fuzz::WriteInput(data, size, ".npy");
  return raymatch::fuzz::Expect([&] { raymatch::ReadNpy(path); });
}
