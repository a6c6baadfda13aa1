// Backend-independent parts: request checks, ROI, Bayer modes, the camera registry.
#include "raymatch/capture/camera.h"

#include <sstream>

#include "backends.h"
#include "raymatch/capture/unpack.h"
#include "raymatch/core/error.h"

namespace raymatch::capture {

namespace {
std::string Num(double v) {
  std::ostringstream os;
  os << v;
  return os.str();
}
}  // namespace

void ValidateSettings(const CameraInfo& info, const CaptureSettings& s) {
  const std::string cam = "camera " + info.id + ": ";
  if (!(s.exposure_us > 0) || !std::isfinite(s.exposure_us))
    throw Error(cam + "exposure " + Num(s.exposure_us) +
                " us: expected a positive time in microseconds");
  if (info.exposure_max_us > 0 &&
      (s.exposure_us < info.exposure_min_us || s.exposure_us > info.exposure_max_us))
    throw Error(cam + "exposure " + Num(s.exposure_us) + " us is outside the camera's range " +
                Num(info.exposure_min_us) + " to " + Num(info.exposure_max_us) + " us");
  if (!(s.analogue_gain > 0) || !std::isfinite(s.analogue_gain))
    throw Error(cam + "analogue gain " + Num(s.analogue_gain) + ": expected a positive factor");
  if (info.gain_max > 0 && (s.analogue_gain < info.gain_min || s.analogue_gain > info.gain_max))
    throw Error(cam + "analogue gain " + Num(s.analogue_gain) + " is outside the camera's range " +
                Num(info.gain_min) + " to " + Num(info.gain_max));
  const Roi& r = s.roi;
  if (!r.whole()) {
    if (r.width <= 0 || r.height <= 0 || r.x < 0 || r.y < 0 ||
        (info.width > 0 &&
         (int64_t(r.x) + r.width > info.width || int64_t(r.y) + r.height > info.height)))
      throw Error(cam + "ROI " + std::to_string(r.x) + "," + std::to_string(r.y) + "," +
                  std::to_string(r.width) + "," + std::to_string(r.height) +
                  " (x,y,width,height in pixels) does not fit the " + std::to_string(info.width) +
                  " x " + std::to_string(info.height) + " sensor");
  }
}

Image CropRoi(const Image& img, const Roi& roi) {
  if (roi.whole()) return img;
  if (roi.x < 0 || roi.y < 0 || roi.width <= 0 || roi.height <= 0 ||
      int64_t(roi.x) + roi.width > img.width || int64_t(roi.y) + roi.height > img.height)
    throw Error("ROI does not fit the " + std::to_string(img.width) + " x " +
                std::to_string(img.height) + " frame");
  Image out(roi.width, roi.height);
  for (int y = 0; y < roi.height; ++y)
    for (int x = 0; x < roi.width; ++x) out.at(x, y) = img.at(roi.x + x, roi.y + y);
  return out;
}

void ApplyBayerMode(Frame* f, BayerMode mode, bool mosaic_sensor, int bayer_order) {
  if (mode == BayerMode::kMosaic) return;
  if (!mosaic_sensor)
    throw Error("Bayer mode given for a mono sensor (format " + f->pixel_format +
                "): expected 'mosaic'");
  if (mode == BayerMode::kBin) {
    f->dn = BinBayer2x2(f->dn);
    f->bit_depth += 2;  // sums of four values of bit_depth bits
    if (f->black_level_dn) *f->black_level_dn *= 4;
    f->extra["bayer"] = "2x2 binned (sum of the four channels)";
    return;
  }
  const int plane = int(mode) - int(BayerMode::kPlane0);
  BayerPlanes b = SplitBayer(f->dn, BayerOrder(bayer_order));
  f->dn = std::move(b.planes[plane]);
  f->extra["bayer"] = "channel " + b.names[plane] + " only (half size)";
}

std::vector<CameraInfo> ListCameras(std::vector<std::string>* notes) {
  std::vector<CameraInfo> all;
#ifdef RAYMATCH_WITH_LIBCAMERA
  all = internal::ListLibcamera(notes);
#endif
  for (CameraInfo& c : internal::ListV4l2(notes)) all.push_back(std::move(c));
  return all;
}

std::vector<std::string> CompiledBackends() {
  std::vector<std::string> b = {"sim", "v4l2"};
#ifdef RAYMATCH_WITH_LIBCAMERA
  b.push_back("libcamera " + internal::LibcameraVersion());
#endif
  return b;
}

std::unique_ptr<Camera> OpenCamera(const std::string& id) {
  auto starts = [&](const std::string& p) { return id.rfind(p, 0) == 0; };
  if (starts("sim:")) return internal::OpenSimCamera(id.substr(4));
  if (starts("v4l2:")) return internal::OpenV4l2(id.substr(5));
  if (starts("/dev/video")) return internal::OpenV4l2(id);
  if (starts("libcamera:")) {
#ifdef RAYMATCH_WITH_LIBCAMERA
    return internal::OpenLibcamera(id.substr(10));
#else
    throw Error("camera '" + id +
                "': this raymatch was built without libcamera "
                "(RAYMATCH_WITH_LIBCAMERA=OFF or libcamera-dev missing); `raymatch --version` "
                "lists the compiled-in backends");
#endif
  }
  std::vector<std::string> notes;
  const std::vector<CameraInfo> cams = ListCameras(&notes);
  if (id.empty() || id == "auto") {
    if (cams.empty())
      throw Error(
          "no camera found (`raymatch capture list`); use --camera sim:SCENE.toml for the "
          "simulated camera");
    return OpenCamera(cams.front().id);
  }
  std::string have;
  for (const CameraInfo& c : cams) have += "\n  " + c.id + "  (" + c.model + ")";
  throw Error("unknown camera '" + id +
              "': expected sim:SCENE.toml, libcamera:ID, v4l2:/dev/videoN " +
              (cams.empty() ? std::string("(no camera found on this machine)")
                            : "or one of the cameras found:" + have));
}

}  // namespace raymatch::capture
