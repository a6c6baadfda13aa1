#include "raymatch/core/atomic_file.h"

#include <unistd.h>

#include <atomic>
#include <fstream>
#include <random>

#include "raymatch/core/error.h"

namespace fs = std::filesystem;

namespace raymatch {

fs::path TemporaryPathFor(const fs::path& final_path) {
  static std::atomic<unsigned> counter{0};
  const unsigned tag = (static_cast<unsigned>(getpid()) * 2654435761u) ^ (counter++ * 40503u);
  char buf[16];
  std::snprintf(buf, sizeof buf, "%08x", tag);
  fs::path tmp = final_path;
  tmp.replace_filename(final_path.stem().string() + ".partial-" + buf +
                       final_path.extension().string());
  return tmp;
}

void CommitTemporary(const fs::path& tmp, const fs::path& final_path) {
  std::error_code ec;
  fs::rename(tmp, final_path, ec);
  if (ec) {
    fs::remove(tmp, ec);
    throw Error(FileLocation{final_path.string()}, "cannot move finished file into place");
  }
}

void WriteTextFileAtomic(const fs::path& path, const std::string& text) {
  const fs::path tmp = TemporaryPathFor(path);
  {
    std::ofstream out(tmp, std::ios::binary);
    if (!out) throw Error(FileLocation{path.string()}, "cannot open file for writing");
    out << text;
    out.flush();
    if (!out) {
      std::error_code ec;
      fs::remove(tmp, ec);
      throw Error(FileLocation{path.string()}, "write failed (disk full?)");
    }
  }
  CommitTemporary(tmp, path);
}

void EnsureDirectory(const fs::path& dir) {
  if (dir.empty()) return;
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec || !fs::is_directory(dir))
    throw Error(FileLocation{dir.string()}, "cannot create output directory: " + ec.message());
}

}  // namespace raymatch
