#include "shell.h"

#include <sys/wait.h>

#include <cstdlib>
#include <fstream>
#include <sstream>

namespace raymatch::testing {

ShellRun RunShell(const std::string& command, const TempDir& dir) {
  const std::string err = dir / "stderr.txt";
  const std::string cmd = command + " >" + (dir / "stdout.txt") + " 2>" + err;
  const int status = std::system(cmd.c_str());
  std::ifstream in(err);
  std::stringstream ss;
  ss << in.rdbuf();
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, ss.str()};
}

}  // namespace raymatch::testing
