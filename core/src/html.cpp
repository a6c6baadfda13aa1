#include "raymatch/core/html.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <fstream>
#include <sstream>

namespace raymatch {

std::string Base64(const std::string& in) {
  static const char* t = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  size_t i = 0;
  for (; i + 2 < in.size(); i += 3) {
    const unsigned v = (uint8_t(in[i]) << 16) | (uint8_t(in[i + 1]) << 8) | uint8_t(in[i + 2]);
    out += {t[v >> 18], t[(v >> 12) & 63], t[(v >> 6) & 63], t[v & 63]};
  }
  if (i + 1 == in.size()) {
    const unsigned v = uint8_t(in[i]) << 16;
    out += {t[v >> 18], t[(v >> 12) & 63], '=', '='};
  } else if (i + 2 == in.size()) {
    const unsigned v = (uint8_t(in[i]) << 16) | (uint8_t(in[i + 1]) << 8);
    out += {t[v >> 18], t[(v >> 12) & 63], t[(v >> 6) & 63], '='};
  }
  return out;
}

std::string ReadFileBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

std::string HtmlEscape(const std::string& text) {
  std::string o;
  for (char c : text) {
    switch (c) {
      case '&':
        o += "&amp;";
        break;
      case '<':
        o += "&lt;";
        break;
      case '>':
        o += "&gt;";
        break;
      case '\'':
        o += "&#39;";
        break;
      case '"':
        o += "&quot;";
        break;
      default:
        o += c;
    }
  }
  return o;
}

std::string EmbeddedPng(const std::string& png, const std::string& alt) {
  return "<img alt='" + HtmlEscape(alt) + "' src='data:image/png;base64," +
         Base64(ReadFileBytes(png)) + "'>";
}

std::string FormatUncertainty(double u) {
  if (!(std::isfinite(u) && u > 0)) return "not computed";
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.2g", u);
  return buf;
}

std::string FormatValue(double v, double u, int digits) {
  char buf[64];
  if (!std::isfinite(v)) return "not computed";
  if (!(std::isfinite(u) && u > 0)) {
    std::snprintf(buf, sizeof buf, "%.*g", digits, v);
    return buf;
  }
  // Decimals down to the uncertainty's second significant digit (none above the units).
  const int decimals = std::max(0, 1 - int(std::floor(std::log10(u))));
  std::snprintf(buf, sizeof buf, "%.*f", std::min(decimals, 17), v);
  return buf;
}

}  // namespace raymatch
