#pragma once
// The guided capture session: asks the user to set the stage, captures, shows the signal level
// and clipping, suggests the exposure for a target signal, and writes the folder with its
// metadata.toml in the layout `raymatch calibrate` / `raymatch run` read
// (docs/sample-data-format.md, docs/capture.md).
#include <iosfwd>
#include <string>
#include <vector>

#include "raymatch/capture/camera.h"

namespace raymatch::capture {

enum class SessionKind { kPinhole, kCones, kFlats, kFocusScan, kDark };

/// "pinhole", "cones", "flats", "focus-scan", "dark"; throws Error listing them otherwise.
SessionKind ParseSessionKind(const std::string& name);

struct SessionOptions {
  SessionKind kind = SessionKind::kPinhole;
  std::string folder;          ///< output folder (created; metadata.toml there is extended)
  CaptureSettings settings;    ///< starting exposure (us), analogue gain, ROI
  int average = 1;             ///< frames averaged per image (>1: float mean TIFFs)
  double target_signal = 0.6;  ///< exposure suggestions aim at this fraction of the well
};

/// Where the answers come from. Interactive: questions on `out`, answers typed on `in`.
/// Scripted (`scripted` = true: --answers FILE, or stdin not a terminal): one answer per line,
/// blank = the default shown, lines starting with '#' skipped; each question and the answer
/// taken are echoed on `out`; running out of answers is an error naming the question.
struct Prompter {
  std::istream* in = nullptr;
  std::ostream* out = nullptr;
  bool scripted = false;
  /// Asks; returns the answer, or `fallback` for a blank one (an empty fallback: required).
  std::string Ask(const std::string& question, const std::string& fallback);
  double AskNumber(const std::string& question, const std::string& fallback, double lo, double hi);
  std::vector<double> AskList(const std::string& question, const std::string& fallback);
  void WaitFor(const std::string& instruction);  ///< "... then press Enter"
};

struct SessionSummary {
  std::vector<std::string> files;  ///< images written
  std::string metadata;            ///< metadata.toml path
};

/// Runs the session. Throws Error (nothing half-written: every file is atomic; metadata.toml is
/// written last, so an interrupted session leaves complete frames and the previous metadata).
SessionSummary RunSession(Camera& cam, const SessionOptions& o, Prompter& ask);

}  // namespace raymatch::capture
