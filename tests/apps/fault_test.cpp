// Fault tests (issue 15, docs/reliability.md): SIGINT and SIGTERM during a multi-plane
// `raymatch simulate` and during `raymatch run`, a full disk and an unwritable output folder.
// Afterwards there must be no partial or misleading files (no `*.partial-*` temporary, no
// final-named file that does not read back whole, no index or report listing files that do not
// exist or describing a mix of two runs), a non-zero exit with a clear message (or the
// signal's own status), and a re-run must succeed.
//
// In `simulate` the signal is sent the moment a temporary `*.partial-*` file appears in the
// output folder (polled every 0.2 ms), i.e. while an output is being written: the hardest
// moment; in `run`, when its simulation has written its first file. Full disk
// and read-only folders use small tmpfs mounts and need root; without root (or where mount is
// refused) those tests are skipped with the reason, except the read-only folder, which falls
// back to chmod 0555 when not root.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/mount.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <nlohmann/json.hpp>
#include <set>
#include <sstream>
#include <thread>

#include "raymatch/core/image_io.h"
#include "temp_dir.h"

namespace fs = std::filesystem;

namespace raymatch {
namespace {

std::string Slurp(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

/// Starts `raymatch args...` with stdout and stderr to files; returns the child's pid.
pid_t Spawn(const std::vector<std::string>& args, const fs::path& out, const fs::path& err) {
  std::vector<std::string> all{RAYMATCH_BIN};
  all.insert(all.end(), args.begin(), args.end());
  const pid_t pid = fork();
  if (pid == 0) {
    FILE* o = std::freopen(out.c_str(), "w", stdout);
    FILE* e = std::freopen(err.c_str(), "w", stderr);
    if (!o || !e) _exit(126);
    std::vector<char*> argv;
    for (auto& a : all) argv.push_back(a.data());
    argv.push_back(nullptr);
    execv(argv[0], argv.data());
    _exit(127);
  }
  return pid;
}

/// Waits for the child; kills it after `limit_s` (a hang is a failure: status says SIGKILL).
int Wait(pid_t pid, double limit_s = 300) {
  const auto t0 = std::chrono::steady_clock::now();
  int status = 0;
  while (waitpid(pid, &status, WNOHANG) == 0) {
    if (std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() > limit_s) {
      kill(pid, SIGKILL);
      waitpid(pid, &status, 0);
      ADD_FAILURE() << "child " << pid << " ran past " << limit_s << " s";
      return status;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  return status;
}

std::vector<fs::path> Partials(const fs::path& dir) {
  std::vector<fs::path> v;
  std::error_code ec;
  for (auto it = fs::recursive_directory_iterator(dir, ec);
       !ec && it != fs::recursive_directory_iterator(); it.increment(ec))
    if (it->path().filename().string().find(".partial-") != std::string::npos)
      v.push_back(it->path());
  return v;
}

/// Polls `ready` every 0.2 ms until it holds, then sends `sig`; returns false when the child
/// ended first (or after `limit_s`).
bool SignalWhen(pid_t pid, const std::function<bool()>& ready, int sig, double limit_s = 120) {
  const auto t0 = std::chrono::steady_clock::now();
  while (std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() < limit_s) {
    if (ready()) return kill(pid, sig) == 0;
    siginfo_t info{};  // has the child ended? (WNOWAIT: Wait() reaps it)
    if (waitid(P_PID, pid, &info, WEXITED | WNOHANG | WNOWAIT) == 0 && info.si_pid == pid)
      return false;
    std::this_thread::sleep_for(std::chrono::microseconds(200));
  }
  return false;
}

/// True once any file under `dir` was modified after `since`.
bool NewFileUnder(const fs::path& dir, fs::file_time_type since) {
  std::error_code ec;
  for (auto it = fs::recursive_directory_iterator(dir, ec);
       !ec && it != fs::recursive_directory_iterator(); it.increment(ec))
    if (it->is_regular_file(ec) && it->last_write_time(ec) > since) return true;
  return false;
}

/// No temporary anywhere; every final image under `dir` reads back whole; every JSON parses;
/// every scan index lists only files that exist.
void ExpectNothingPartialOrMisleading(const fs::path& dir) {
  EXPECT_TRUE(Partials(dir).empty()) << "temporary left: " << Partials(dir)[0];
  for (const auto& e : fs::recursive_directory_iterator(dir)) {
    if (!e.is_regular_file()) continue;
    const std::string ext = e.path().extension().string();
    if (ext == ".tif" || ext == ".png") {
      EXPECT_NO_THROW(ReadImage(e.path().string())) << "incomplete final file " << e.path();
    } else if (ext == ".json") {
      nlohmann::json j;
      EXPECT_NO_THROW(j = nlohmann::json::parse(Slurp(e.path())))
          << "incomplete final file " << e.path();
      if (e.path().filename().string().ends_with("_scan.json"))
        for (const auto& p : j["planes"])
          for (const char* k : {"image", "sidecar", "png"}) {
            const std::string f = p.value(k, "");
            if (!f.empty())
              EXPECT_TRUE(fs::exists(e.path().parent_path() / f))
                  << e.path() << " lists missing " << f;
          }
    }
  }
}

// A 1024 x 1024 camera: each plane's TIFF (4 MB) and PNG take tens of ms to write, a window
// that polling catches; 8 planes of 300,000 rays take a few seconds on 2 cores.
const char* kScene = R"(name = "fault"
seed = 3
[source]
type = "cone"
half_angle_deg = 20
[[object]]
type = "sphere"
radius_um = 8
material = "water"
[objective]
focal_length_mm = 10
na = 0.42
[tube_lens]
focal_length_mm = 200
[camera]
pixels = [1024, 1024]
pixel_pitch_um = 2
[trace]
rays = 300000
[scan]
defocus_um = [-20, -15, -10, -5, 0, 5, 10, 15]
)";

int ExitCode(int status) { return WIFEXITED(status) ? WEXITSTATUS(status) : -1; }

std::string Describe(int status) {
  if (WIFEXITED(status)) return "exit " + std::to_string(WEXITSTATUS(status));
  if (WIFSIGNALED(status)) return std::string("signal ") + strsignal(WTERMSIG(status));
  return "status " + std::to_string(status);
}

class SimulateSignal : public ::testing::TestWithParam<int> {};

TEST_P(SimulateSignal, LeavesNoPartialOrStaleIndexAndReRunSucceeds) {
  const int sig = GetParam();
  testing::TempDir dir;
  const std::string scene = dir.Write("fault.toml", kScene);
  const fs::path out = dir.path() / "out";
  // A complete earlier scan in the same folder (another seed): its index must not survive an
  // interrupted scan, where it would describe a mix of old and new planes.
  const std::vector<std::string> args{"simulate", scene, "-o", out.string(), "--threads", "2"};
  std::vector<std::string> first = args;
  first.insert(first.end(), {"--seed", "1", "--defocus-um", "-20,-15"});
  ASSERT_EQ(ExitCode(Wait(Spawn(first, dir.path() / "o0.txt", dir.path() / "e0.txt"))), 0)
      << Slurp(dir.path() / "e0.txt");
  ASSERT_TRUE(fs::exists(out / "fault_scan.json"));

  const pid_t pid = Spawn(args, dir.path() / "o1.txt", dir.path() / "e1.txt");
  const bool sent = SignalWhen(
      pid, [&] { return !Partials(out).empty(); }, sig);
  const int status = Wait(pid);
  ASSERT_TRUE(sent) << "the scan ended before a temporary was seen: " << Describe(status);
  const std::string err = Slurp(dir.path() / "e1.txt");
  // The process ends by the signal itself (a shell shows 128 + signal number).
  EXPECT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == sig) << Describe(status) << "\n" << err;
  EXPECT_NE(err.find(sig == SIGINT ? "interrupted (SIGINT)" : "terminated (SIGTERM)"),
            std::string::npos)
      << err;
  EXPECT_FALSE(fs::exists(out / "fault_scan.json")) << "the earlier scan's index survived";
  EXPECT_FALSE(fs::exists(out / "fault_scan.csv"));
  ExpectNothingPartialOrMisleading(out);

  ASSERT_EQ(ExitCode(Wait(Spawn(args, dir.path() / "o2.txt", dir.path() / "e2.txt"))), 0)
      << Slurp(dir.path() / "e2.txt");
  const auto j = nlohmann::json::parse(Slurp(out / "fault_scan.json"));
  EXPECT_EQ(j["planes"].size(), 8u);
  ExpectNothingPartialOrMisleading(out);
}

INSTANTIATE_TEST_SUITE_P(Faults, SimulateSignal, ::testing::Values(SIGINT, SIGTERM),
                         [](const auto& info) {
                           return std::string(info.param == SIGINT ? "SIGINT" : "SIGTERM");
                         });

// `raymatch run` on the committed sample at ray fraction 0.005 (no fits, no mesh object; about
// 4 s): after a complete run, interrupted as soon as the simulation writes its first file (its
// 160 x 120 images are written too quickly to aim at a temporary; the large-image test above
// does that), first at another ray fraction, then at the first one again. The previous report
// and the simulation's stamp must go: otherwise the last run, whose inputs equal the first
// run's, would reuse a half-rewritten simulation.
TEST(Faults, RunInterruptedBySignalsThenReRunSucceeds) {
  testing::TempDir dir;
  const std::string sample = std::string(RAYMATCH_SOURCE_DIR) + "/datasets-sample/";
  const std::string pipeline = dir.Write(
      "pipeline.toml", "[calibration]\nlightfield = \"" + sample + "lightfield\"\ncorrector = \"" +
                           sample + "flatfield\"\n[experiment]\nscan = \"" + sample + "drop46\"\n");
  const fs::path out = dir.path() / "out";
  const std::vector<std::string> args{"run",   pipeline,    "-o", out.string(), "--ray-fraction",
                                      "0.005", "--threads", "2"};
  auto run = [&](std::vector<std::string> a, const std::string& tag) {
    const int status = Wait(Spawn(a, dir.path() / ("o" + tag), dir.path() / ("e" + tag)));
    return std::make_pair(status, Slurp(dir.path() / ("e" + tag)));
  };
  auto [s0, e0] = run(args, "0");
  ASSERT_TRUE(WIFEXITED(s0) && WEXITSTATUS(s0) <= 2) << Describe(s0) << "\n" << e0;
  ASSERT_TRUE(fs::exists(out / "index.html"));
  // stderr to a file: step lines, no progress bar (carriage returns) unless --progress.
  EXPECT_EQ(e0.find('\r'), std::string::npos) << "progress bar written to a file";
  EXPECT_NE(e0.find("raymatch run: simulating"), std::string::npos) << e0;

  int k = 1;
  for (int sig : {SIGINT, SIGTERM}) {
    // A changed ray fraction changes scene.toml: the simulation step runs, the calibration is
    // reused.
    std::vector<std::string> a = args;
    if (sig == SIGINT) a[5] = "0.006";
    const std::string tag = std::to_string(k++);
    const auto start = fs::file_time_type::clock::now();
    const pid_t pid = Spawn(a, dir.path() / ("o" + tag), dir.path() / ("e" + tag));
    const bool sent = SignalWhen(
        pid, [&] { return NewFileUnder(out / "simulation", start); }, sig);
    const int status = Wait(pid);
    const std::string err = Slurp(dir.path() / ("e" + tag));
    ASSERT_TRUE(sent) << "the run ended before the simulation wrote a file: " << Describe(status)
                      << "\n"
                      << err;
    EXPECT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == sig) << Describe(status) << "\n" << err;
    EXPECT_NE(err.find("unfinished output files removed"), std::string::npos) << err;
    EXPECT_FALSE(fs::exists(out / "index.html")) << "a report of an earlier run survived";
    EXPECT_FALSE(fs::exists(out / ".simulation.stamp"))
        << "an interrupted simulation looks finished";
    EXPECT_FALSE(fs::exists(out / "simulation/sim_scan.json"));
    ExpectNothingPartialOrMisleading(out);
  }
  // The re-run simulates again (nothing looks finished) and, with --progress, draws its bars
  // even into a file (each plane's bar line is cleared with a carriage return).
  std::vector<std::string> a = args;
  a.push_back("--progress");
  auto [s3, e3] = run(a, "3");
  ASSERT_TRUE(WIFEXITED(s3) && WEXITSTATUS(s3) <= 2) << Describe(s3) << "\n" << e3;
  EXPECT_EQ(e3.find("simulation unchanged: reusing"), std::string::npos)
      << "reused an interrupted simulation";
  EXPECT_NE(e3.find('\r'), std::string::npos) << "--progress wrote no progress bar";
  EXPECT_TRUE(fs::exists(out / "index.html"));
  ExpectNothingPartialOrMisleading(out);
  // -q: no step lines on stderr, no summary on stdout.
  a = args;
  a.push_back("-q");
  auto [s4, e4] = run(a, "4");
  ASSERT_TRUE(WIFEXITED(s4) && WEXITSTATUS(s4) <= 2) << Describe(s4) << "\n" << e4;
  EXPECT_EQ(e4.find("raymatch run: "), std::string::npos) << e4;
  EXPECT_EQ(Slurp(dir.path() / "o4"), "");
}

/// A tmpfs mounted over `dir` while the object lives (root only).
class Tmpfs {
 public:
  Tmpfs(const fs::path& dir, const std::string& options) : dir_(dir) {
    fs::create_directories(dir);
    if (geteuid() != 0) {
      why_ = "not root: cannot mount a tmpfs";
      return;
    }
    if (mount("tmpfs", dir.c_str(), "tmpfs", 0, options.c_str()) != 0) {
      why_ = std::string("mount -t tmpfs -o ") + options + " failed: " + std::strerror(errno);
      return;
    }
    mounted_ = true;
  }
  ~Tmpfs() {
    if (mounted_) umount2(dir_.c_str(), MNT_DETACH);
  }
  bool Remount(const std::string& options, unsigned long flags = 0) {
    return mount("tmpfs", dir_.c_str(), "tmpfs", MS_REMOUNT | flags, options.c_str()) == 0;
  }
  bool mounted() const { return mounted_; }
  const std::string& why() const { return why_; }

 private:
  fs::path dir_;
  bool mounted_ = false;
  std::string why_;
};

TEST(Faults, FullDiskGivesAClearErrorAndNoPartialFiles) {
  testing::TempDir dir;
  const std::string scene = dir.Write("fault.toml", kScene);
  const fs::path disk = dir.path() / "disk";
  Tmpfs fs_(disk, "size=1m");
  if (!fs_.mounted()) GTEST_SKIP() << fs_.why();
  // Each plane's TIFF is 4 MB: the first one fills the 1 MB disk.
  const std::vector<std::string> args{"simulate",  scene, "-o",     (disk / "out").string(),
                                      "--threads", "2",   "--rays", "20000"};
  const int status = Wait(Spawn(args, dir.path() / "o1.txt", dir.path() / "e1.txt"));
  const std::string err = Slurp(dir.path() / "e1.txt");
  EXPECT_EQ(ExitCode(status), 1) << Describe(status) << "\n" << err;
  EXPECT_NE(err.find("fault_z-020.00um"), std::string::npos)
      << "the message names the file: " << err;
  EXPECT_NE(err.find("the disk is full"), std::string::npos) << err;
  ExpectNothingPartialOrMisleading(disk);
  EXPECT_FALSE(fs::exists(disk / "out/fault_z-020.00um.tif"));
  EXPECT_FALSE(fs::exists(disk / "out/fault_scan.json"));
  // Space freed: the same command succeeds.
  ASSERT_TRUE(fs_.Remount("size=128m")) << std::strerror(errno);
  const int again = Wait(Spawn(args, dir.path() / "o2.txt", dir.path() / "e2.txt"));
  EXPECT_EQ(ExitCode(again), 0) << Slurp(dir.path() / "e2.txt");
  EXPECT_TRUE(fs::exists(disk / "out/fault_scan.json"));
  ExpectNothingPartialOrMisleading(disk);
}

TEST(Faults, UnwritableOutputFolderGivesAClearErrorAndNoFiles) {
  testing::TempDir dir;
  const std::string scene = dir.Write("fault.toml", kScene);
  const fs::path ro = dir.path() / "ro";
  std::unique_ptr<Tmpfs> mnt;
  if (geteuid() == 0) {
    // Root ignores permissions: a read-only tmpfs instead of chmod.
    mnt = std::make_unique<Tmpfs>(ro, "size=64m");
    if (!mnt->mounted())
      GTEST_SKIP() << "root, and " << mnt->why() << ": cannot make an unwritable folder";
    fs::create_directories(ro / "out");
    ASSERT_TRUE(mnt->Remount("size=64m", MS_RDONLY)) << std::strerror(errno);
  } else {
    fs::create_directories(ro / "out");
    fs::permissions(ro / "out", fs::perms::owner_read | fs::perms::owner_exec |
                                    fs::perms::group_read | fs::perms::group_exec |
                                    fs::perms::others_read | fs::perms::others_exec);
  }
  const std::vector<std::string> args{"simulate",  scene, "-o",     (ro / "out").string(),
                                      "--threads", "2",   "--rays", "20000"};
  const int status = Wait(Spawn(args, dir.path() / "o1.txt", dir.path() / "e1.txt"));
  const std::string err = Slurp(dir.path() / "e1.txt");
  EXPECT_EQ(ExitCode(status), 1) << Describe(status) << "\n" << err;
  EXPECT_NE(err.find((ro / "out").string()), std::string::npos)
      << "the message names the folder: " << err;
  EXPECT_NE(err.find(mnt ? "read-only file system" : "no permission to write"), std::string::npos)
      << err;
  EXPECT_TRUE(fs::is_empty(ro / "out"));
  // Made writable: the same command succeeds.
  if (mnt) {
    ASSERT_TRUE(mnt->Remount("size=64m")) << std::strerror(errno);
  } else {
    fs::permissions(ro / "out", fs::perms::owner_all, fs::perm_options::add);
  }
  const int again = Wait(Spawn(args, dir.path() / "o2.txt", dir.path() / "e2.txt"));
  EXPECT_EQ(ExitCode(again), 0) << Slurp(dir.path() / "e2.txt");
  EXPECT_TRUE(fs::exists(ro / "out/fault_scan.json"));
  ExpectNothingPartialOrMisleading(ro);
}

}  // namespace
}  // namespace raymatch
