#include "raymatch/core/provenance.h"

#include <unistd.h>

#include <ctime>
#include <fstream>

#include "raymatch/core/error.h"
#include "raymatch/core/version.h"

namespace raymatch {

static std::string& CommandLineStorage() {
  static std::string s;
  return s;
}

void SetCommandLine(int argc, char** argv) {
  std::string s;
  for (int i = 0; i < argc; ++i) {
    std::string a = argv[i];
    if (a.find_first_of(" \t\"'") != std::string::npos) a = "'" + a + "'";
    s += (i ? " " : "") + a;
  }
  CommandLineStorage() = s;
}

const std::string& CommandLine() { return CommandLineStorage(); }

std::string UtcTimestamp() {
  std::time_t t = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

nlohmann::json ProvenanceJson() {
  char host[256] = {0};
  gethostname(host, sizeof host - 1);
  return {{"tool", "raymatch"},
          {"version", kVersion},
          {"date_utc", UtcTimestamp()},
          {"command_line", CommandLine()},
          {"host", host}};
}

std::string FileChecksum(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(FileLocation{path}, "cannot open file for reading");
  uint64_t h = 1469598103934665603ull;
  char buf[1 << 16];
  while (in) {
    in.read(buf, sizeof buf);
    for (std::streamsize i = 0; i < in.gcount(); ++i) {
      h ^= static_cast<unsigned char>(buf[i]);
      h *= 1099511628211ull;
    }
  }
  char out[17];
  std::snprintf(out, sizeof out, "%016llx", static_cast<unsigned long long>(h));
  return out;
}

}  // namespace raymatch
