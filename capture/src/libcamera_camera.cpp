// libcamera cameras (Debian 12: libcamera 0.0.3). Raw stream role only: the sensor's own data,
// no ISP processing; auto exposure off, exposure and analogue gain set on every request.
// Packed CSI-2 formats are unpacked with unpack.h; SensorBlackLevels (16-bit scale, libcamera's
// convention) are converted to the format's bit depth.
#include <libcamera/libcamera.h>
#include <libcamera/version.h>
#include <sys/mman.h>

#include <chrono>
#include <condition_variable>
#include <cstdlib>
#include <mutex>
#include <sstream>

#include "backends.h"
#include "raymatch/capture/unpack.h"
#include "raymatch/core/error.h"
#include "raymatch/core/provenance.h"

namespace raymatch::capture::internal {

namespace lc = libcamera;

namespace {

// One manager per process (libcamera allows only one).
lc::CameraManager& Manager() {
  static std::unique_ptr<lc::CameraManager> m = [] {
    // libcamera logs INFO/WARN lines on stderr; keep errors only unless the user chose levels.
    setenv("LIBCAMERA_LOG_LEVELS", "*:ERROR", 0);
    auto cm = std::make_unique<lc::CameraManager>();
    if (const int r = cm->start(); r != 0)
      throw Error("libcamera: the camera manager did not start (error " + std::to_string(r) + ")");
    return cm;
  }();
  return *m;
}

CameraInfo Describe(const std::shared_ptr<lc::Camera>& cam, std::string* best_format) {
  CameraInfo info;
  info.id = "libcamera:" + cam->id();
  info.backend = "libcamera";
  const lc::ControlList& props = cam->properties();
  info.model = props.get(lc::properties::Model).value_or("unknown model");
  if (auto sz = props.get(lc::properties::PixelArraySize))
    info.width = int(sz->width), info.height = int(sz->height);
  if (auto cell = props.get(lc::properties::UnitCellSize))
    info.pixel_pitch_um = cell->width / 1000.0;  // nm
  const auto& ctrls = cam->controls();
  if (auto it = ctrls.find(&lc::controls::ExposureTime); it != ctrls.end())
    info.exposure_min_us = it->second.min().get<int32_t>(),
    info.exposure_max_us = it->second.max().get<int32_t>();
  if (auto it = ctrls.find(&lc::controls::AnalogueGain); it != ctrls.end())
    info.gain_min = it->second.min().get<float>(), info.gain_max = it->second.max().get<float>();
  std::unique_ptr<lc::CameraConfiguration> cfg = cam->generateConfiguration({lc::StreamRole::Raw});
  int best = -1;
  if (cfg && !cfg->empty()) {
    for (const lc::PixelFormat& pf : cfg->at(0).formats().pixelformats()) {
      const std::string name = pf.toString();
      int bits = 0;
      const bool raw = DescribeRawFormat(name, nullptr, &bits, nullptr);
      info.pixel_formats.push_back(name + (raw ? " (raw " + std::to_string(bits) + "-bit)" : ""));
      if (raw && bits > best) best = bits, info.raw_format = name, info.bit_depth = bits;
    }
  }
  if (best < 0) info.notes = "no raw format supported by unpack.h: not usable for calibration";
  if (best_format) *best_format = info.raw_format;
  if (info.bit_depth > 0) info.datasheet["bit_depth"] = info.bit_depth;
  if (info.pixel_pitch_um > 0) info.datasheet["pixel_pitch_um"] = info.pixel_pitch_um;
  return info;
}

class LibcameraCamera : public Camera {
 public:
  explicit LibcameraCamera(std::shared_ptr<lc::Camera> cam) : cam_(std::move(cam)) {
    info_ = Describe(cam_, nullptr);
    if (info_.raw_format.empty())
      throw Error("camera " + info_.id + " offers no raw format raymatch can unpack");
    DescribeRawFormat(info_.raw_format, &packing_, nullptr, &order_);
    if (cam_->acquire() != 0) throw Error("camera " + info_.id + " is in use by another program");
    acquired_ = true;
    config_ = cam_->generateConfiguration({lc::StreamRole::Raw});
    lc::StreamConfiguration& sc = config_->at(0);
    for (const lc::PixelFormat& pf : sc.formats().pixelformats())
      if (pf.toString() == info_.raw_format) sc.pixelFormat = pf;
    if (info_.width > 0) sc.size = lc::Size(info_.width, info_.height);
    sc.bufferCount = 1;
    if (config_->validate() == lc::CameraConfiguration::Invalid ||
        cam_->configure(config_.get()) != 0)
      throw Error("camera " + info_.id + ": cannot configure the raw stream " + info_.raw_format);
    if (sc.pixelFormat.toString() != info_.raw_format)
      throw Error("camera " + info_.id + ": the raw stream came out as " +
                  sc.pixelFormat.toString() + ", not " + info_.raw_format);
    width_ = int(sc.size.width), height_ = int(sc.size.height), stride_ = sc.stride;
    stream_ = sc.stream();
    allocator_ = std::make_unique<lc::FrameBufferAllocator>(cam_);
    if (allocator_->allocate(stream_) <= 0)
      throw Error("camera " + info_.id + ": cannot allocate frame buffers");
    cam_->requestCompleted.connect(this, &LibcameraCamera::Completed);
  }
  ~LibcameraCamera() override {
    if (started_) cam_->stop();
    cam_->requestCompleted.disconnect(this);
    allocator_.reset();
    if (acquired_) cam_->release();
  }
  const CameraInfo& info() const override { return info_; }

  Frame Capture(const CaptureSettings& s) override {
    ValidateSettings(info_, s);
    if (!started_) {
      if (cam_->start() != 0) throw Error("camera " + info_.id + ": cannot start streaming");
      started_ = true;
    }
    std::unique_ptr<lc::Request> req = cam_->createRequest();
    const std::unique_ptr<lc::FrameBuffer>& buf = allocator_->buffers(stream_).front();
    req->addBuffer(stream_, buf.get());
    req->controls().set(lc::controls::AeEnable, false);
    req->controls().set(lc::controls::ExposureTime, int32_t(std::lround(s.exposure_us)));
    req->controls().set(lc::controls::AnalogueGain, float(s.analogue_gain));
    {
      std::lock_guard<std::mutex> l(mu_);
      done_ = nullptr;
    }
    if (cam_->queueRequest(req.get()) != 0)
      throw Error("camera " + info_.id + ": cannot queue a request");
    std::unique_lock<std::mutex> l(mu_);
    const double wait_s = 5 + 3 * s.exposure_us * 1e-6;
    if (!cv_.wait_for(l, std::chrono::duration<double>(wait_s), [&] { return done_ != nullptr; }))
      throw Error("camera " + info_.id + ": no frame within " + std::to_string(int(wait_s)) + " s");
    if (req->status() != lc::Request::RequestComplete)
      throw Error("camera " + info_.id + ": the request was cancelled");
    const lc::FrameBuffer::Plane& plane = buf->planes().front();
    const size_t len = plane.offset + plane.length;
    void* mem = mmap(nullptr, len, PROT_READ, MAP_SHARED, plane.fd.get(), 0);
    if (mem == MAP_FAILED) throw Error("camera " + info_.id + ": cannot map the frame buffer");
    Frame f;
    try {
      f.dn = CropRoi(UnpackRaw({static_cast<const uint8_t*>(mem) + plane.offset, plane.length},
                               width_, height_, stride_, packing_),
                     s.roi);
    } catch (...) {
      munmap(mem, len);
      throw;
    }
    munmap(mem, len);
    const lc::ControlList& md = req->metadata();
    f.bit_depth = info_.bit_depth;
    f.pixel_format = info_.raw_format;
    f.exposure_us = md.get(lc::controls::ExposureTime).value_or(int32_t(s.exposure_us));
    f.analogue_gain = md.get(lc::controls::AnalogueGain).value_or(float(s.analogue_gain));
    if (auto bl = md.get(lc::controls::SensorBlackLevels))
      f.black_level_dn = double((*bl)[0]) / double(1 << (16 - info_.bit_depth));
    if (auto t = md.get(lc::controls::SensorTemperature)) f.temperature_c = *t;
    f.sensor_timestamp_ns = md.get(lc::controls::SensorTimestamp).value_or(0);
    f.timestamp_utc = UtcTimestamp();
    f.extra = {
        {"libcamera_id", cam_->id()}, {"stride_bytes", stride_}, {"bayer_order", int(order_)}};
    ApplyBayerMode(&f, s.bayer, order_ != BayerOrder::kNone, int(order_));
    return f;
  }

 private:
  void Completed(lc::Request* r) {
    std::lock_guard<std::mutex> l(mu_);
    done_ = r;
    cv_.notify_all();
  }
  std::shared_ptr<lc::Camera> cam_;
  CameraInfo info_;
  RawPacking packing_ = RawPacking::kRaw16Le;
  BayerOrder order_ = BayerOrder::kNone;
  std::unique_ptr<lc::CameraConfiguration> config_;
  std::unique_ptr<lc::FrameBufferAllocator> allocator_;
  lc::Stream* stream_ = nullptr;
  int width_ = 0, height_ = 0;
  unsigned stride_ = 0;
  bool acquired_ = false, started_ = false;
  std::mutex mu_;
  std::condition_variable cv_;
  lc::Request* done_ = nullptr;
};

}  // namespace

std::string LibcameraVersion() { return lc::CameraManager::version(); }

std::vector<CameraInfo> ListLibcamera(std::vector<std::string>* notes) {
  std::vector<CameraInfo> out;
  try {
    for (const auto& cam : Manager().cameras()) out.push_back(Describe(cam, nullptr));
  } catch (const Error& e) {
    if (notes) notes->push_back(e.what());
  }
  return out;
}

std::unique_ptr<Camera> OpenLibcamera(const std::string& id) {
  std::shared_ptr<lc::Camera> cam = Manager().get(id);
  if (!cam) {
    std::string have;
    for (const auto& c : Manager().cameras()) have += "\n  libcamera:" + c->id();
    throw Error("unknown camera 'libcamera:" + id + "': " +
                (have.empty() ? std::string("libcamera finds no camera on this machine")
                              : "libcamera has:" + have));
  }
  return std::make_unique<LibcameraCamera>(cam);
}

}  // namespace raymatch::capture::internal
