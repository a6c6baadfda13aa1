#pragma once
// Runs a command line as a user would (through the shell), for CLI tests.
#include <string>

#include "temp_dir.h"

namespace raymatch::testing {

struct ShellRun {
  int code;         ///< exit status; -1 when the command did not exit normally (a signal)
  std::string err;  ///< what it wrote on stderr
};

/// Runs `command` with stdout to `dir`/stdout.txt and stderr to `dir`/stderr.txt.
ShellRun RunShell(const std::string& command, const TempDir& dir);

}  // namespace raymatch::testing
