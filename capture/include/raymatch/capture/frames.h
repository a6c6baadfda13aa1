#pragma once
// Capturing frames to files: raw 16-bit TIFFs (or 32-bit float means of N frames), each with a
// JSON sidecar (also in the TIFF ImageDescription): camera, sensor, format, exposure, gain,
// black level, temperature if reported, time stamps, frame count, provenance. Every file goes
// to a temporary name and is renamed when complete (core/atomic_file.h), so an interrupted
// capture leaves complete frames only.
#include <filesystem>
#include <iosfwd>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "raymatch/capture/camera.h"

namespace raymatch::capture {

/// N frames with the same settings, reduced to one image.
struct FrameSet {
  Image image;        ///< one frame's code values, or the mean of `count` frames
  bool mean = false;  ///< image is a float mean
  int count = 1;
  std::vector<Frame> frames;  ///< per-frame records (pixels of all but the last released)
};

/// Captures `count` frames (>= 1) and, when `mean`, averages them (double accumulation).
FrameSet CaptureSet(Camera& cam, const CaptureSettings& s, int count, bool mean);

/// The sidecar JSON of a frame set: `what` says what it shows (e.g. "pinhole in focus").
nlohmann::json FrameSidecar(const CameraInfo& info, const FrameSet& set, const std::string& what);

/// Writes `path` (.tif/.tiff: uint16 for single frames, float32 for means) and `path` with
/// .json; both atomic. Throws Error naming the file on failure (nothing is left behind).
void WriteFrameSet(const std::filesystem::path& path, const FrameSet& set,
                   const nlohmann::json& sidecar);

/// Throws Error naming `path` when it is not a .tif/.tiff path in a folder that exists (or can be
/// created) and is writable, before anything is captured.
void CheckOutputPath(const std::filesystem::path& path);

/// Signal level of a frame relative to the well and its clipping.
struct SignalLevel {
  double median_fraction = 0;   ///< median (dn - black) x e/dn over the well capacity
  double peak_fraction = 0;     ///< the brightest pixel, the same way
  double clipped_fraction = 0;  ///< pixels at the top code value or at the full well
};
SignalLevel MeasureSignal(const Image& dn, double black_dn, double max_dn, double e_per_dn,
                          double well_e);

/// Exposure (us) that brings `level` (a well fraction measured at `exposure_us`) to `target`;
/// halves the exposure when `clipped`, multiplies by 10 when there is no signal; kept within
/// the camera's range.
double SuggestExposure(double exposure_us, double level, bool clipped, double target,
                       const CameraInfo& info);

/// `raymatch capture frames`: what to capture and where.
struct FramesOptions {
  CaptureSettings settings;
  int count = 1;                 ///< frames
  bool mean = false;             ///< write their mean (float) instead of each frame
  bool dark = false;             ///< also a dark frame set (lamp off), NAME_dark.tif
  std::filesystem::path output;  ///< DIR/NAME.tif
};

/// Captures and writes; returns one line per file written: its path and statistics (mean,
/// standard deviation, min, max in code values, pixels at the top code value).
/// `prompt_in`/`prompt_out` ask the user to block the light before the dark frames (EOF on
/// `prompt_in` is taken as "ready").
std::vector<std::string> CaptureFramesToFiles(Camera& cam, const FramesOptions& o,
                                              std::istream& prompt_in, std::ostream& prompt_out);

}  // namespace raymatch::capture
