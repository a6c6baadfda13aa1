#include "raymatch/core/error.h"

namespace raymatch {

std::string FileLocation::ToString() const {
  if (file.empty()) return {};
  std::string s = file;
  if (line > 0) {
    s += ":" + std::to_string(line);
    if (column > 0) s += ":" + std::to_string(column);
  }
  return s;
}

static std::string Compose(const FileLocation& where, const std::string& message) {
  const std::string loc = where.ToString();
  return loc.empty() ? "error: " + message : loc + ": error: " + message;
}

Error::Error(const std::string& message)
    : std::runtime_error("error: " + message), message_(message) {}

Error::Error(const FileLocation& where, const std::string& message)
    : std::runtime_error(Compose(where, message)), where_(where), message_(message) {}

}  // namespace raymatch
