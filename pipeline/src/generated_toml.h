#pragma once
// Scene and fit files that the pipeline writes for its steps: built as toml::table (so every
// string is quoted and every key spelled once) and written atomically. Not installed.
#include <toml++/toml.h>

#include <filesystem>
#include <sstream>
#include <string>

#include "raymatch/core/atomic_file.h"

namespace raymatch::pipeline::internal {

/// A value as the generated files have always carried it: 10 significant digits (the files'
/// stamps and the simulations they drive stay what they were).
inline double Sig10(double v) {
  std::ostringstream s;
  s.precision(10);
  s << v;
  return std::stod(s.str());
}

/// `comment` (lines starting with #), then the table.
inline void WriteToml(const std::filesystem::path& file, const std::string& comment,
                      const toml::table& t) {
  std::ostringstream s;
  s << comment << "\n" << t << "\n";
  WriteTextFileAtomic(file, s.str());
}

}  // namespace raymatch::pipeline::internal
