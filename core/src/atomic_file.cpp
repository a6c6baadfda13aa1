#include "raymatch/core/atomic_file.h"

#include <signal.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstring>
#include <fstream>
#include <mutex>
#include <vector>

#include "raymatch/core/error.h"

namespace fs = std::filesystem;

namespace raymatch {

namespace {

// The registry of temporaries in flight: a fixed array, so that the signal handler needs no
// allocation or lock. A slot is kFree, kBusy while a thread fills or clears it, or kLive when it
// holds a NUL-terminated absolute path that the handler may unlink.
constexpr int kSlots = 256;
constexpr size_t kPathBytes = 4096;
enum : int { kFree = 0, kBusy = 1, kLive = 2 };
struct Slot {
  std::atomic<int> state{kFree};
  char path[kPathBytes];
};
static_assert(std::atomic<int>::is_always_lock_free, "the signal handler needs lock-free atomics");
Slot g_slots[kSlots];

extern "C" void RemoveTemporariesAndDie(int sig) {
  const int saved_errno = errno;
  for (Slot& s : g_slots)
    if (s.state.load(std::memory_order_acquire) == kLive) unlink(s.path);
  static const char kInt[] = "\nraymatch: interrupted (SIGINT); unfinished output files removed\n";
  static const char kTerm[] = "\nraymatch: terminated (SIGTERM); unfinished output files removed\n";
  static const char kHup[] = "\nraymatch: hang-up (SIGHUP); unfinished output files removed\n";
  const char* m = sig == SIGINT ? kInt : sig == SIGTERM ? kTerm : kHup;
  const size_t n = sig == SIGINT ? sizeof kInt : sig == SIGTERM ? sizeof kTerm : sizeof kHup;
  [[maybe_unused]] const ssize_t w = write(STDERR_FILENO, m, n - 1);
  errno = saved_errno;
  // SA_RESETHAND restored the default action; the signal is blocked while this handler runs,
  // so it is delivered on return and ends the process with the signal's status.
  raise(sig);
}

void InstallSignalHandlers() {
  for (int sig : {SIGINT, SIGTERM, SIGHUP}) {
    struct sigaction old {};
    if (sigaction(sig, nullptr, &old) != 0) continue;
    // Leave a signal alone when it is ignored (nohup) or the program handles it itself.
    if ((old.sa_flags & SA_SIGINFO) || old.sa_handler != SIG_DFL) continue;
    struct sigaction sa {};
    sa.sa_handler = RemoveTemporariesAndDie;
    sigemptyset(&sa.sa_mask);
    sa.sa_flags = SA_RESETHAND;
    sigaction(sig, &sa, nullptr);
  }
}

std::string Absolute(const fs::path& p) {
  std::error_code ec;
  const fs::path a = fs::absolute(p, ec);
  return ec ? p.string() : a.lexically_normal().string();
}

void Register(const fs::path& tmp) {
  static std::once_flag once;
  std::call_once(once, InstallSignalHandlers);
  const std::string a = Absolute(tmp);
  if (a.size() >= kPathBytes) return;  // not tracked: removed on errors, not on signals
  for (Slot& s : g_slots) {
    int expected = kFree;
    if (!s.state.compare_exchange_strong(expected, kBusy, std::memory_order_acquire)) continue;
    std::memcpy(s.path, a.c_str(), a.size() + 1);
    s.state.store(kLive, std::memory_order_release);
    return;
  }
  // All slots in use: this temporary is not tracked (removed on errors, not on signals).
}

void Unregister(const fs::path& tmp) noexcept {
  std::string a;
  try {
    a = Absolute(tmp);
  } catch (...) {
    return;
  }
  for (Slot& s : g_slots) {
    if (s.state.load(std::memory_order_acquire) != kLive || std::strcmp(s.path, a.c_str()) != 0)
      continue;
    int expected = kLive;
    if (s.state.compare_exchange_strong(expected, kBusy, std::memory_order_acq_rel)) {
      s.path[0] = '\0';
      s.state.store(kFree, std::memory_order_release);
      return;
    }
  }
}

}  // namespace

fs::path TemporaryPathFor(const fs::path& final_path) {
  static std::atomic<unsigned> counter{0};
  const unsigned tag = (static_cast<unsigned>(getpid()) * 2654435761u) ^ (counter++ * 40503u);
  char buf[16];
  std::snprintf(buf, sizeof buf, "%08x", tag);
  fs::path tmp = final_path;
  tmp.replace_filename(final_path.stem().string() + ".partial-" + buf +
                       final_path.extension().string());
  Register(tmp);
  return tmp;
}

void CommitTemporary(const fs::path& tmp, const fs::path& final_path) {
  std::error_code ec;
  fs::rename(tmp, final_path, ec);
  if (ec) {
    DiscardTemporary(tmp);
    throw Error(FileLocation{final_path.string()},
                "cannot move finished file into place: " + ec.message());
  }
  Unregister(tmp);
}

void DiscardTemporary(const fs::path& tmp) noexcept {
  std::error_code ec;
  fs::remove(tmp, ec);
  Unregister(tmp);
}

int RegisteredTemporaries() noexcept {
  int n = 0;
  for (const Slot& s : g_slots) n += s.state.load(std::memory_order_acquire) == kLive;
  return n;
}

std::string WriteFailureHint(const fs::path& path) {
  fs::path dir = path.parent_path();
  if (dir.empty()) dir = ".";
  struct statvfs st {};
  if (statvfs(dir.c_str(), &st) == 0) {
    if (st.f_flag & ST_RDONLY) return "read-only file system";
    const unsigned long long free_bytes =
        static_cast<unsigned long long>(st.f_bavail) * st.f_frsize;
    if (free_bytes < (1u << 20))
      return "the disk is full (" + std::to_string(free_bytes) + " bytes free)";
  }
  if (access(dir.c_str(), W_OK) != 0) return "no permission to write in " + dir.string();
  return "";
}

void WriteTextFileAtomic(const fs::path& path, const std::string& text) {
  const fs::path tmp = TemporaryPathFor(path);
  auto why = [&] {
    const std::string hint = WriteFailureHint(path);
    return !hint.empty() ? hint : std::string(errno ? std::strerror(errno) : "unknown reason");
  };
  {
    errno = 0;
    std::ofstream out(tmp, std::ios::binary);
    if (!out) {
      const std::string reason = why();
      DiscardTemporary(tmp);
      throw Error(FileLocation{path.string()}, "cannot open file for writing: " + reason);
    }
    out << text;
    out.flush();
    out.close();  // a full disk can show only here
    if (!out) {
      const std::string reason = why();
      DiscardTemporary(tmp);
      throw Error(FileLocation{path.string()}, "write failed (disk full?): " + reason);
    }
  }
  CommitTemporary(tmp, path);
}

namespace {
std::mutex g_created_mutex;
std::vector<fs::path> g_created;  // folders EnsureDirectory made, parents first
}  // namespace

void EnsureDirectory(const fs::path& dir) {
  if (dir.empty()) return;
  std::error_code ec;
  // The folders this call will create (the missing ancestors, outermost first), remembered so
  // that a command that fails can remove them again while they are empty.
  std::vector<fs::path> missing;
  fs::path p = fs::absolute(dir, ec).lexically_normal();
  if (!p.has_filename()) p = p.parent_path();  // "a/b/" -> "a/b"
  while (!ec && !p.empty() && p != p.root_path()) {
    std::error_code e2;
    if (fs::exists(fs::symlink_status(p, e2))) break;
    missing.insert(missing.begin(), p);
    p = p.parent_path();
  }
  ec.clear();
  fs::create_directories(dir, ec);
  if (ec || !fs::is_directory(dir))
    throw Error(FileLocation{dir.string()}, "cannot create output directory: " + ec.message());
  std::lock_guard<std::mutex> lock(g_created_mutex);
  for (const fs::path& m : missing)
    if (fs::is_directory(m)) g_created.push_back(m);
}

int RemoveCreatedEmptyDirectories() noexcept {
  std::lock_guard<std::mutex> lock(g_created_mutex);
  int removed = 0;
  for (auto it = g_created.rbegin(); it != g_created.rend(); ++it) {  // innermost first
    std::error_code ec;
    if (fs::is_directory(fs::symlink_status(*it, ec)) && fs::is_empty(*it, ec) && !ec &&
        fs::remove(*it, ec))
      ++removed;
  }
  g_created.clear();
  return removed;
}

void RemoveStaleOutput(const fs::path& path) {
  std::error_code ec;
  if (!fs::exists(fs::symlink_status(path, ec))) return;  // (a read-only folder may hold none)
  fs::remove(path, ec);
  if (ec)
    throw Error(FileLocation{path.string()},
                "cannot remove the previous run's file: " + ec.message());
}

}  // namespace raymatch
