#pragma once
// Cameras behind one small interface: libcamera (optional at build time), V4L2 video devices and
// a simulated camera that renders frames with raymatch's own simulator (sim_camera.cpp).
// Units: exposure in microseconds, analogue gain as a factor (1 = unity), ROI in sensor pixels.
#include <cstdint>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "raymatch/core/image.h"

namespace raymatch::capture {

/// Region of interest in sensor pixels (x, y of the top-left corner, columns and rows going
/// right and down as stored). width = height = 0: the whole sensor.
struct Roi {
  int x = 0, y = 0, width = 0, height = 0;
  bool whole() const { return width == 0 && height == 0; }
};

/// What a camera is and can do, for `capture list` and for checking requests.
struct CameraInfo {
  std::string id;       ///< what --camera takes: "sim:FILE", "libcamera:ID", "v4l2:/dev/videoN"
  std::string backend;  ///< "sim", "libcamera", "v4l2"
  std::string model;
  int width = 0, height = 0;               ///< full sensor (or device) size, pixels
  double pixel_pitch_um = 0;               ///< 0 = not reported
  std::vector<std::string> pixel_formats;  ///< raw formats first; all the device offers
  std::string raw_format;  ///< the format capture uses (deepest raw); "" = none usable
  int bit_depth = 0;       ///< data bits of raw_format
  double exposure_min_us = 0, exposure_max_us = 0;  ///< 0, 0 = not reported
  double gain_min = 0, gain_max = 0;                ///< analogue gain; 0, 0 = not reported
  std::string notes;  ///< e.g. "no raw format: cannot capture for calibration"
  /// Values a session may offer as defaults for metadata.toml's [camera] and [optics] keys
  /// (the simulated camera knows them all; a real camera at most pixel_pitch_um and bit_depth).
  nlohmann::json datasheet = nlohmann::json::object();
};

/// Bayer handling of a mosaic sensor (mono sensors ignore it). Documented in docs/capture.md.
enum class BayerMode {
  kMosaic,  ///< the colour-filter mosaic as recorded: every pixel its own channel, no demosaic
  kBin,     ///< 2 x 2 sums: half-size mono image of all four channels (saturates at 4 x max)
  kPlane0,
  kPlane1,
  kPlane2,
  kPlane3,  ///< one colour plane, half size (unpack.h SplitBayer)
};

/// One request. Raw frames only: no auto exposure, no auto gain, no white balance.
struct CaptureSettings {
  double exposure_us = 10000;  ///< exposure time, microseconds
  double analogue_gain = 1;    ///< sensor analogue gain factor (1 = unity)
  Roi roi;                     ///< sensor pixels; whole sensor by default
  BayerMode bayer = BayerMode::kMosaic;
};

/// One frame in code values (float holding integers), with what the camera reported.
struct Frame {
  Image dn;
  int bit_depth = 0;  ///< data bits: code values 0 .. 2^bit_depth - 1 (x4 binned)
  std::string pixel_format;
  double exposure_us = 0;  ///< as applied (reported by the camera when it does)
  double analogue_gain = 0;
  std::optional<double> black_level_dn;  ///< sensor black level, code values
  std::optional<double> temperature_c;   ///< sensor temperature when reported
  std::string timestamp_utc;             ///< when the frame was received
  int64_t sensor_timestamp_ns = 0;       ///< the driver's start-of-exposure time stamp (0 = none)
  nlohmann::json extra = nlohmann::json::object();  ///< backend details (sim: rays, seed, stage)
};

/// How the stage is set (pinhole, focus, iris, lamp). A real camera ignores it; the simulated
/// camera renders it. The guided session passes on what the user says they set.
struct StageState {
  bool lamp_on = true;
  bool pinhole = false;  ///< a pinhole at the object plane (else: the open field)
  double pinhole_diameter_um = 2;
  double focus_um = 0;   ///< focal plane position (+ = towards the camera, conventions.md)
  double iris_deg = 0;   ///< illumination half-angle limited to this; 0 = iris open
  bool objects = false;  ///< the scene's objects are in the field (focus scans)
};

class Camera {
 public:
  virtual ~Camera() = default;
  virtual const CameraInfo& info() const = 0;
  /// Captures one raw frame. Throws Error for settings the camera cannot honour (exposure or
  /// gain outside its range, ROI outside the sensor) and on device failures.
  virtual Frame Capture(const CaptureSettings& settings) = 0;
  virtual void SetStage(const StageState&) {}
  virtual bool simulated() const { return false; }
};

/// Throws Error naming the setting, its value and the allowed range when `s` is not possible
/// on `info` (ranges the camera does not report are not checked).
void ValidateSettings(const CameraInfo& info, const CaptureSettings& s);

/// Every camera found by the compiled-in backends (libcamera first, then every V4L2 capture
/// device: a UVC camera libcamera drives shows in both). Backend problems (a device that cannot
/// be opened) are appended to `notes` (not fatal).
std::vector<CameraInfo> ListCameras(std::vector<std::string>* notes);

/// Opens a camera by id: "sim:SCENE.toml", "libcamera:ID", "v4l2:/dev/videoN" (or a bare
/// /dev/videoN), or "auto"/"" for the first camera found. Throws Error naming the id and listing
/// what exists when there is no such camera.
std::unique_ptr<Camera> OpenCamera(const std::string& id);

/// The capture backends compiled into this build, e.g. {"sim", "v4l2", "libcamera 0.0.3"}.
std::vector<std::string> CompiledBackends();

/// Crops `img` to `roi` (whole(): unchanged); throws Error when the ROI leaves the image.
Image CropRoi(const Image& img, const Roi& roi);

/// Applies the Bayer mode to a mosaic frame (mono frames: only kMosaic is allowed).
void ApplyBayerMode(Frame* frame, BayerMode mode, bool mosaic_sensor, int bayer_order);

}  // namespace raymatch::capture
