#pragma once
// Errors that carry where in an input they were found.
//
// Recoverable failures (bad input files, invalid options, I/O) are thrown as raymatch::Error,
// whose what() reads "file:line:col: error: message" (or "file: error: message" without a
// position). Apps catch it in main() and map it to a non-zero exit code. Programmer errors use
// RAYMATCH_CHECK, which prints the failed condition and aborts.
#include <cstdio>
#include <cstdlib>
#include <stdexcept>
#include <string>

namespace raymatch {

/// A position in an input file; line and column are 1-based, 0 means unknown.
struct FileLocation {
  std::string file;
  int line = 0;
  int column = 0;
  std::string ToString() const;  ///< "file:line:col", "file" or "" when empty.
};

/// A user-facing error. what() is the full "file:line:col: error: message" text.
class Error : public std::runtime_error {
 public:
  explicit Error(const std::string& message);
  Error(const FileLocation& where, const std::string& message);
  const FileLocation& where() const { return where_; }
  const std::string& message() const { return message_; }

 private:
  FileLocation where_;
  std::string message_;
};

}  // namespace raymatch

#define RAYMATCH_CHECK(cond)                                                        \
  do {                                                                              \
    if (!(cond)) {                                                                  \
      std::fprintf(stderr, "%s:%d: CHECK failed: %s\n", __FILE__, __LINE__, #cond); \
      std::abort();                                                                 \
    }                                                                               \
  } while (0)
