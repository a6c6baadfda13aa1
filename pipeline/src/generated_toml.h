#pragma once
// Scene and fit files that the pipeline writes for its steps: built as toml::table (so every
// string is quoted and every key spelled once) and written atomically. Not installed.
#include <toml++/toml.h>

#include <cctype>
#include <charconv>
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

/// TOML text with each float written in its shortest form that reads back as the same double
/// (toml++ as Debian builds it writes 17 digits: 293.14999999999998 for 293.15). Quoted strings
/// and comments are left alone.
inline std::string ShortestFloats(const std::string& in) {
  std::string out;
  char quote = 0;
  bool comment = false;
  for (size_t i = 0; i < in.size(); ++i) {
    const char c = in[i];
    if (comment || quote) {
      out += c;
      if (c == '\n') comment = false;
      if (quote && c == quote && in[i - 1] != '\\') quote = 0;
      continue;
    }
    if (c == '#') comment = true;
    if (c == '"' || c == '\'') quote = c;
    const bool starts = (c == '-' || std::isdigit(static_cast<unsigned char>(c))) &&
                        (i == 0 || std::string(" [,=").find(in[i - 1]) != std::string::npos);
    if (!starts) {
      out += c;
      continue;
    }
    size_t j = i + 1;
    while (j < in.size() && std::string("0123456789.eE+-").find(in[j]) != std::string::npos) ++j;
    const std::string token = in.substr(i, j - i);
    if (token.find_first_of(".eE") == std::string::npos) {  // an integer: as it is
      out += token, i = j - 1;
      continue;
    }
    const double v = std::stod(token);
    // The shortest digits that read back as v, in fixed notation where that takes at most 12
    // characters (a defocus of -20 reads "-20.0", not "-2e+01"), else the shortest of the two.
    char fixed[400], general[64];
    const auto f = std::to_chars(fixed, fixed + sizeof fixed, v, std::chars_format::fixed);
    const auto g = std::to_chars(general, general + sizeof general, v);
    std::string best = token;
    if (f.ec == std::errc() && f.ptr - fixed <= 12)
      best.assign(fixed, f.ptr);
    else if (g.ec == std::errc())
      best.assign(general, g.ptr);
    if (best.find_first_of(".eEn") == std::string::npos) best += ".0";  // stays a float
    out += best, i = j - 1;
  }
  return out;
}

/// `comment` (lines starting with #), then the table.
inline void WriteToml(const std::filesystem::path& file, const std::string& comment,
                      const toml::table& t) {
  std::ostringstream s;
  s << comment << "\n" << t << "\n";
  WriteTextFileAtomic(file, ShortestFloats(s.str()));
}

}  // namespace raymatch::pipeline::internal
