#include "temp_dir.h"

#include <cstdlib>
#include <fstream>
#include <stdexcept>

namespace raymatch::testing {

TempDir::TempDir() {
  std::string tmpl = (std::filesystem::temp_directory_path() / "raymatch-test-XXXXXX").string();
  if (!mkdtemp(tmpl.data())) throw std::runtime_error("mkdtemp failed");
  path_ = tmpl;
}

TempDir::~TempDir() {
  std::error_code ec;
  std::filesystem::remove_all(path_, ec);
}

std::string TempDir::Write(const std::string& name, const std::string& text) const {
  const auto p = path_ / name;
  std::ofstream(p) << text;
  return p.string();
}

}  // namespace raymatch::testing
