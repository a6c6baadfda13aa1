#pragma once
// Shared by the libFuzzer harnesses: every parser a user feeds reads a path, so each input is
// written to a file first. A harness passes when the parser returns or throws raymatch::Error;
// any other exception, a crash or a sanitizer report is a finding.
#include <unistd.h>

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <filesystem>
#include <fstream>
#include <initializer_list>
#include <string>
#include <utility>

#include "raymatch/core/error.h"

namespace raymatch::fuzz {

/// A per-process scratch file with `extension`, rewritten for every input.
inline std::string WriteInput(const uint8_t* data, size_t size, const std::string& extension) {
  const std::string path = "/tmp/raymatch-fuzz-" + std::to_string(getpid()) + extension;
  std::ofstream(path, std::ios::binary)
      .write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(size));
  return path;
}

/// A per-process scratch folder (created once) for harnesses whose file names other files:
/// `files` maps names inside it (sub-folders created) to contents; a name ending in '/' is a
/// folder. Returns the folder's path.
inline std::string ScratchFolder(
    const std::string& name,
    const std::initializer_list<std::pair<std::string, std::string>>& files) {
  const std::filesystem::path dir = std::filesystem::temp_directory_path() /
                                    ("raymatch-fuzz-" + name + "-" + std::to_string(getpid()));
  for (const auto& [f, text] : files) {
    const std::filesystem::path p = dir / f;
    if (!f.empty() && f.back() == '/') {
      std::filesystem::create_directories(p);
      continue;
    }
    std::filesystem::create_directories(p.parent_path());
    std::ofstream(p, std::ios::binary) << text;
  }
  std::filesystem::create_directories(dir);
  return dir.string();
}

/// Writes one input to `path` (inside a ScratchFolder).
inline void WriteInputTo(const std::string& path, const uint8_t* data, size_t size) {
  std::ofstream(path, std::ios::binary)
      .write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(size));
}

/// Aborts (a finding) when a parsed number that must be finite is not.
inline void CheckFinite(double v, const char* what) {
  if (!std::isfinite(v)) {
    std::fprintf(stderr, "raymatch fuzz: %s is not finite (%g)\n", what, v);
    std::abort();
  }
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
