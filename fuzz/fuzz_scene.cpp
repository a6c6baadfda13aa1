// libFuzzer harness: scene TOML files (LoadScene, docs/scene-format.md).
#include "fuzz_input.h"
#include "raymatch/simulate/scene.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string path = raymatch::fuzz::WriteInput(data, size, ".toml");
  return raymatch::fuzz::Expect([&] { raymatch::simulate::LoadScene(path); });
}
