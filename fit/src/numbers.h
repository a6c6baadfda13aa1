#pragma once
// Numbers in the fit library's reports: text with a given precision ("n/a" for NaN or Inf) and
// JSON numbers (null for NaN or Inf: never NaN in an output). Not installed.
#include <cmath>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>

namespace raymatch::fit::internal {

inline std::string Num(double v, int prec = 6) {
  if (!std::isfinite(v)) return "n/a";
  std::ostringstream os;
  os.precision(prec);
  os << v;
  return os.str();
}

inline nlohmann::json J(double v) {
  return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr);
}

}  // namespace raymatch::fit::internal
