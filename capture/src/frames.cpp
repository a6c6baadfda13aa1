#include "raymatch/capture/frames.h"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <sstream>

#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/provenance.h"

namespace raymatch::capture {

namespace fs = std::filesystem;

FrameSet CaptureSet(Camera& cam, const CaptureSettings& s, int count, bool mean) {
  if (count < 1) throw Error("frame count " + std::to_string(count) + ": expected at least 1");
  if (count > 1 && !mean) throw Error("several frames into one image need mean = true");
  FrameSet set;
  set.mean = mean && count > 1;
  set.count = count;
  std::vector<double> sum;
  for (int i = 0; i < count; ++i) {
    Frame f = cam.Capture(s);
    if (sum.empty()) sum.assign(f.dn.size(), 0.0);
    if (f.dn.size() != sum.size())
      throw Error("camera " + cam.info().id + ": frame size changed during a set");
    for (size_t k = 0; k < sum.size(); ++k) sum[k] += f.dn.pixels[k];
    if (i + 1 == count) {
      set.image = f.dn;
      if (set.mean)
        for (size_t k = 0; k < sum.size(); ++k) set.image.pixels[k] = float(sum[k] / count);
    }
    f.dn = Image();
    set.frames.push_back(std::move(f));
  }
  return set;
}

nlohmann::json FrameSidecar(const CameraInfo& info, const FrameSet& set, const std::string& what) {
  const Frame& f = set.frames.back();
  nlohmann::json j;
  j["what"] = what;
  j["provenance"] = ProvenanceJson();
  j["camera"] = {{"id", info.id}, {"backend", info.backend}, {"model", info.model}};
  if (info.pixel_pitch_um > 0) j["camera"]["pixel_pitch_um"] = info.pixel_pitch_um;
  j["sensor"] = {{"width", info.width}, {"height", info.height}};
  j["image"] = {{"width", set.image.width},
                {"height", set.image.height},
                {"stored_as", set.mean ? "float32 mean of code values" : "uint16 code values"}};
  j["format"] = {{"pixel_format", f.pixel_format},
                 {"bit_depth", f.bit_depth},
                 {"max_code_value", (int64_t(1) << f.bit_depth) - 1}};
  j["exposure_us"] = f.exposure_us;
  j["analogue_gain"] = f.analogue_gain;
  j["black_level_dn"] =
      f.black_level_dn ? nlohmann::json(*f.black_level_dn) : nlohmann::json(nullptr);
  if (f.temperature_c) j["temperature_c"] = *f.temperature_c;
  j["frame_count"] = set.count;
  j["statistic"] = set.mean ? "mean" : "single frame";
  nlohmann::json ts = nlohmann::json::array();
  for (const Frame& fr : set.frames)
    ts.push_back({{"utc", fr.timestamp_utc}, {"sensor_ns", fr.sensor_timestamp_ns}});
  j["timestamps"] = ts;
  j["backend"] = f.extra;
  return j;
}

void CheckOutputPath(const fs::path& path) {
  const std::string ext = path.extension().string();
  if (ext != ".tif" && ext != ".tiff")
    throw Error(path.string() + ": expected a .tif or .tiff file name (DIR/NAME.tif)");
  const fs::path dir = path.parent_path().empty() ? fs::path(".") : path.parent_path();
  EnsureDirectory(dir);
  if (access(dir.c_str(), W_OK) != 0) {
    const std::string hint = WriteFailureHint(path);
    throw Error(dir.string() + ": cannot write in this folder" +
                (hint.empty() ? "" : " (" + hint + ")"));
  }
}

void WriteFrameSet(const fs::path& path, const FrameSet& set, const nlohmann::json& sidecar) {
  const std::string desc = sidecar.dump();
  if (set.mean)
    WriteFloatImage(path.string(), set.image, desc);
  else
    WriteUint16Image(path.string(), set.image, desc);
  fs::path side = path;
  side.replace_extension(".json");
  WriteTextFileAtomic(side, sidecar.dump(2) + "\n");
}

SignalLevel MeasureSignal(const Image& dn, double black_dn, double max_dn, double e_per_dn,
                          double well_e) {
  SignalLevel s;
  if (dn.empty()) return s;
  std::vector<float> v = dn.pixels;
  const double to_fraction = e_per_dn / well_e;
  size_t clipped = 0;
  float top = v[0];
  for (float x : v) {
    // Clipped: at the top code value, or at the full well (where a camera whose well maps below
    // the top code value saturates); 0.5 % below the well allows for read noise.
    clipped += x >= max_dn - 0.5 || (x - black_dn) * to_fraction >= 0.995;
    top = std::max(top, x);
  }
  const size_t k = (v.size() - 1) / 2;
  std::nth_element(v.begin(), v.begin() + k, v.end());
  s.median_fraction = (double(v[k]) - black_dn) * to_fraction;
  // The brightest pixel: a pinhole image covers only a few pixels, so any percentile would
  // miss it; it is what saturates first.
  s.peak_fraction = (double(top) - black_dn) * to_fraction;
  s.clipped_fraction = double(clipped) / double(v.size());
  return s;
}

double SuggestExposure(double exposure_us, double level, bool clipped, double target,
                       const CameraInfo& info) {
  double e = clipped          ? exposure_us / 2
             : level <= 0.005 ? exposure_us * 10
                              : exposure_us * target / level;
  if (info.exposure_max_us > 0) e = std::clamp(e, info.exposure_min_us, info.exposure_max_us);
  return std::round(e);
}

namespace {
// "PATH: mean M DN, sd S DN, min .. max, N pixels at the top code value" for checks by eye.
std::string Described(const fs::path& p, const FrameSet& set) {
  const PixelStats st = ComputeStats(set.image);
  const double top = double((int64_t(1) << set.frames.back().bit_depth) - 1);
  size_t clipped = 0;
  for (float v : set.image.pixels) clipped += v >= top - 0.5;
  std::ostringstream os;
  os << p.string() << ": mean " << st.mean << " DN, sd " << std::sqrt(st.variance) << " DN, min "
     << st.min << ", max " << st.max << ", " << clipped << " pixels at " << top;
  return os.str();
}
}  // namespace

std::vector<std::string> CaptureFramesToFiles(Camera& cam, const FramesOptions& o, std::istream& in,
                                              std::ostream& out) {
  CheckOutputPath(o.output);
  if (o.count < 1) throw Error("--count " + std::to_string(o.count) + ": expected at least 1");
  std::vector<std::string> written;
  auto write_sets = [&](const fs::path& base, const std::string& what) {
    if (o.mean || o.count == 1) {
      FrameSet set = CaptureSet(cam, o.settings, o.count, o.mean);
      WriteFrameSet(base, set, FrameSidecar(cam.info(), set, what));
      written.push_back(Described(base, set));
      return;
    }
    for (int i = 0; i < o.count; ++i) {
      char suffix[32];
      std::snprintf(suffix, sizeof suffix, "_%04d", i);
      fs::path p = base.parent_path() / (base.stem().string() + suffix + base.extension().string());
      FrameSet set = CaptureSet(cam, o.settings, 1, false);
      WriteFrameSet(p, set,
                    FrameSidecar(cam.info(), set,
                                 what + " (frame " + std::to_string(i + 1) + " of " +
                                     std::to_string(o.count) + ")"));
      written.push_back(Described(p, set));
    }
  };
  StageState stage;
  cam.SetStage(stage);
  write_sets(o.output, "frames");
  if (o.dark) {
    out << "Block the light (lamp off or shutter closed) for the dark frames, then press Enter.\n";
    std::string line;
    std::getline(in, line);
    stage.lamp_on = false;
    cam.SetStage(stage);
    const fs::path dark = o.output.parent_path() /
                          (o.output.stem().string() + "_dark" + o.output.extension().string());
    write_sets(dark, "dark frames");
  }
  return written;
}

}  // namespace raymatch::capture
