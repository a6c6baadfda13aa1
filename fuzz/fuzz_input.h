#pragma once
// Shared by the libFuzzer harnesses: every parser a user feeds reads a path, so each input is
// written to a file first. A harness passes when the parser returns or throws raymatch::Error;
// any other exception, a crash or a sanitizer report is a finding.
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <fstream>
#include <string>

#include "raymatch/core/error.h"

namespace raymatch::fuzz {

/// A per-process scratch file with `extension`, rewritten for every input.
inline std::string WriteInput(const uint8_t* data, size_t size, const std::string& extension) {
  const std::string path = "/tmp/raymatch-fuzz-" + std::to_string(getpid()) + extension;
  std::ofstream(path, std::ios::binary).write(reinterpret_cast<const char*>(data),
                                              static_cast<std::streamsize>(size));
  return path;
}

/// Runs `parse`, accepting raymatch::Error; anything else aborts with its message.
template <class F>
int Expect(F&& parse) {
  try {
    parse();
  } catch (const Error&) {
  } catch (const std::exception& e) {
    std::fprintf(stderr, "raymatch fuzz: unexpected exception: %s\n", e.what());
    std::abort();
  }
  return 0;
}

}  // namespace raymatch::fuzz
