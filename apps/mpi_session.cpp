#include "mpi_session.h"

#include <fcntl.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <thread>

#include "raymatch/core/cluster.h"
#include "raymatch/core/error.h"

#ifdef RAYMATCH_HAVE_MPI
#define OMPI_SKIP_MPICXX 1  // the C API only (Open MPI's deprecated C++ bindings otherwise)
#define MPICH_SKIP_MPICXX 1
#include <mpi.h>
#endif

namespace fs = std::filesystem;

namespace raymatch::apps {

namespace {
bool g_started = false;
std::string g_scratch;    // this rank's scratch output folder (ranks > 0)
int g_saved_stderr = -1;  // ranks > 0: the real stderr, for error messages

void RemoveScratch() {
  std::error_code ec;
  if (!g_scratch.empty()) fs::remove_all(g_scratch, ec);
}

bool LaunchedByMpi() {
  for (const char* v : {"OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK"})
    if (std::getenv(v)) return true;
  return false;
}
}  // namespace

bool MpiCompiledIn() {
#ifdef RAYMATCH_HAVE_MPI
  return true;
#else
  return false;
#endif
}

MpiSession::MpiSession(int* argc, char*** argv) {
#ifdef RAYMATCH_HAVE_MPI
  if (!LaunchedByMpi()) return;
  int provided = 0;
  // Only the thread that calls the tracer calls MPI, one call at a time.
  MPI_Init_thread(argc, argv, MPI_THREAD_SERIALIZED, &provided);
  g_started = true;
  Cluster c;
  MPI_Comm_rank(MPI_COMM_WORLD, &c.rank);
  MPI_Comm_size(MPI_COMM_WORLD, &c.size);
  if (c.size > 1) {
    c.sum = [](uint64_t* v, size_t n) {
      // Chunks below 2^30 values (MPI counts are int).
      for (size_t off = 0; off < n; off += size_t(1) << 30) {
        const int cnt = static_cast<int>(std::min(n - off, size_t(1) << 30));
        MPI_Allreduce(MPI_IN_PLACE, v + off, cnt, MPI_UINT64_T, MPI_SUM, MPI_COMM_WORLD);
      }
    };
  }
  if (c.rank > 0) {
    // Ranks > 0 print nothing but errors: stdout and stderr go to /dev/null, the real stderr
    // is kept for AbortJobIfParallel's message.
    std::fflush(stdout), std::fflush(stderr);
    g_saved_stderr = dup(STDERR_FILENO);
    const int null = open("/dev/null", O_WRONLY);
    if (null >= 0) {
      dup2(null, STDOUT_FILENO), dup2(null, STDERR_FILENO);
      close(null);
    }
  }
  SetCluster(std::move(c));
#else
  (void)argc, (void)argv;
#endif
}

MpiSession::~MpiSession() {
  RemoveScratch();
#ifdef RAYMATCH_HAVE_MPI
  if (g_started) MPI_Finalize();
#endif
}

std::string RankOutput(const std::string& dir) {
  const Cluster& c = GetCluster();
  if (c.is_root()) return dir;
  if (g_scratch.empty()) {
    std::error_code ec;
    const fs::path tmp = fs::temp_directory_path(ec);
    if (ec) {
      const char* env = std::getenv("TMPDIR");
      throw Error(FileLocation{env ? env : "/tmp"},
                  "this rank's scratch output folder cannot be made in the temporary folder "
                  "(TMPDIR): " +
                      ec.message());
    }
    g_scratch = (tmp / ("raymatch-rank" + std::to_string(c.rank) + "-" + std::to_string(getpid())))
                    .string();
  }
  return g_scratch;
}

std::string RankPrefix() {
  const Cluster& c = GetCluster();
  if (c.size <= 1) return "";
  return "rank " + std::to_string(c.rank) + " of " + std::to_string(c.size) + ": ";
}

void ReportError(const std::string& line, int code) {
  const Cluster& c = GetCluster();
  auto print = [&](const std::string& text) {
    const int fd = g_saved_stderr >= 0 ? g_saved_stderr : STDERR_FILENO;
    std::fflush(stderr);
    for (size_t off = 0; off < text.size();) {
      const ssize_t w = write(fd, text.data() + off, text.size() - off);
      if (w <= 0) break;
      off += size_t(w);
    }
  };
  if (c.size <= 1) {
    print(line);
    return;
  }
#ifdef RAYMATCH_HAVE_MPI
  if (!c.is_root()) std::this_thread::sleep_for(std::chrono::seconds(3));
  print(line.rfind("raymatch: ", 0) == 0 ? "raymatch: " + RankPrefix() + line.substr(10)
                                         : RankPrefix() + line);
  RemoveScratch();
  MPI_Abort(MPI_COMM_WORLD, code);
#endif
  std::_Exit(code);
}

}  // namespace raymatch::apps
