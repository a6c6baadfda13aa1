// V4L2 video devices through the V4L2 ioctls directly: listing (capabilities, formats, frame
// sizes, control ranges) and mmap streaming of the driver's raw buffers, which this file unpacks
// with unpack.h. Exposure: V4L2_CID_EXPOSURE_ABSOLUTE counts 100 us. (Not OpenCV's videoio: its
// Debian build loads a few hundred shared libraries into every raymatch process, and its raw
// mode delivers the same buffers.)
#include <fcntl.h>
#include <linux/videodev2.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <filesystem>

#include "backends.h"
#include "raymatch/capture/unpack.h"
#include "raymatch/core/error.h"
#include "raymatch/core/provenance.h"

namespace raymatch::capture::internal {

namespace {

std::string FourccName(uint32_t f) {
  std::string s;
  for (int i = 0; i < 4; ++i) s += char((f >> (8 * i)) & 0xFF);
  while (!s.empty() && s.back() == ' ') s.pop_back();
  return s;
}

int Xioctl(int fd, unsigned long req, void* arg) {
  int r;
  do r = ioctl(fd, req, arg);
  while (r == -1 && errno == EINTR);
  return r;
}

struct Fd {
  int fd = -1;
  ~Fd() {
    if (fd >= 0) close(fd);
  }
};

// Probes one device node; false when it is not a video capture device.
bool Probe(const std::string& dev, CameraInfo* info, uint32_t* raw_fourcc, std::string* note,
           double* gain_unity = nullptr) {
  Fd f;
  f.fd = open(dev.c_str(), O_RDWR | O_NONBLOCK);
  if (f.fd < 0) {
    *note = dev + ": cannot open (" + std::strerror(errno) +
            "); docs/capture.md says how to get access";
    return false;
  }
  v4l2_capability cap{};
  if (Xioctl(f.fd, VIDIOC_QUERYCAP, &cap) != 0) return false;
  const uint32_t caps =
      (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
  if (!(caps & V4L2_CAP_VIDEO_CAPTURE)) return false;
  info->id = "v4l2:" + dev;
  info->backend = "v4l2";
  info->model = std::string(reinterpret_cast<const char*>(cap.card)) + " (" +
                reinterpret_cast<const char*>(cap.driver) + ")";
  int best_bits = -1;
  v4l2_fmtdesc fd{};
  fd.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  for (fd.index = 0; Xioctl(f.fd, VIDIOC_ENUM_FMT, &fd) == 0; ++fd.index) {
    const std::string name = FourccName(fd.pixelformat);
    int bits = 0;
    const bool raw = DescribeRawFormat(name, nullptr, &bits, nullptr);
    info->pixel_formats.push_back(name + (raw ? " (raw " + std::to_string(bits) + "-bit)" : ""));
    if (raw && bits > best_bits) {
      best_bits = bits;
      *raw_fourcc = fd.pixelformat;
      info->raw_format = name;
      info->bit_depth = bits;
    }
  }
  if (best_bits < 0) {
    info->notes = "no raw format: not usable for calibration (needs unprocessed sensor data)";
  } else {
    v4l2_frmsizeenum fs{};
    fs.pixel_format = *raw_fourcc;
    for (fs.index = 0; Xioctl(f.fd, VIDIOC_ENUM_FRAMESIZES, &fs) == 0; ++fs.index) {
      int w = fs.type == V4L2_FRMSIZE_TYPE_DISCRETE ? fs.discrete.width : fs.stepwise.max_width;
      int h = fs.type == V4L2_FRMSIZE_TYPE_DISCRETE ? fs.discrete.height : fs.stepwise.max_height;
      if (int64_t(w) * h > int64_t(info->width) * info->height) info->width = w, info->height = h;
      if (fs.type != V4L2_FRMSIZE_TYPE_DISCRETE) break;
    }
  }
  v4l2_queryctrl q{};
  q.id = V4L2_CID_EXPOSURE_ABSOLUTE;
  if (Xioctl(f.fd, VIDIOC_QUERYCTRL, &q) == 0 && !(q.flags & V4L2_CTRL_FLAG_DISABLED))
    info->exposure_min_us = 100.0 * q.minimum, info->exposure_max_us = 100.0 * q.maximum;
  q = {};
  q.id = V4L2_CID_ANALOGUE_GAIN;
  if (Xioctl(f.fd, VIDIOC_QUERYCTRL, &q) == 0 && !(q.flags & V4L2_CTRL_FLAG_DISABLED) &&
      q.default_value > 0) {
    // Sensor drivers count gain in their own steps; the default is unity on most of them.
    info->gain_min = double(q.minimum) / q.default_value;
    info->gain_max = double(q.maximum) / q.default_value;
    if (gain_unity) *gain_unity = q.default_value;
  }
  if (info->bit_depth > 0) info->datasheet["bit_depth"] = info->bit_depth;
  return true;
}

// V4L2 streaming (mmap buffers): the ioctls of the V4L2 capture example, nothing more.
class DirectStream {
 public:
  DirectStream(const std::string& dev, uint32_t fourcc, int width, int height) : dev_(dev) {
    fd_.fd = open(dev.c_str(), O_RDWR | O_NONBLOCK);
    if (fd_.fd < 0) Fail("cannot open");
    v4l2_format f{};
    f.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    f.fmt.pix.width = width, f.fmt.pix.height = height;
    f.fmt.pix.pixelformat = fourcc;
    f.fmt.pix.field = V4L2_FIELD_NONE;
    if (Xioctl(fd_.fd, VIDIOC_S_FMT, &f) != 0) Fail("VIDIOC_S_FMT " + FourccName(fourcc));
    if (f.fmt.pix.pixelformat != fourcc)
      throw Error("camera v4l2:" + dev_ + ": the driver set format " +
                  FourccName(f.fmt.pix.pixelformat) + " instead of " + FourccName(fourcc));
    width_ = int(f.fmt.pix.width), height_ = int(f.fmt.pix.height),
    stride_ = f.fmt.pix.bytesperline;
    v4l2_requestbuffers req{};
    req.count = 2, req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE, req.memory = V4L2_MEMORY_MMAP;
    if (Xioctl(fd_.fd, VIDIOC_REQBUFS, &req) != 0 || req.count < 1) Fail("VIDIOC_REQBUFS");
    for (uint32_t i = 0; i < req.count; ++i) {
      v4l2_buffer b{};
      b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE, b.memory = V4L2_MEMORY_MMAP, b.index = i;
      if (Xioctl(fd_.fd, VIDIOC_QUERYBUF, &b) != 0) Fail("VIDIOC_QUERYBUF");
      void* m = mmap(nullptr, b.length, PROT_READ | PROT_WRITE, MAP_SHARED, fd_.fd, b.m.offset);
      if (m == MAP_FAILED) Fail("mmap");
      bufs_.push_back({m, b.length});
      if (Xioctl(fd_.fd, VIDIOC_QBUF, &b) != 0) Fail("VIDIOC_QBUF");
    }
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (Xioctl(fd_.fd, VIDIOC_STREAMON, &type) != 0) Fail("VIDIOC_STREAMON");
  }
  ~DirectStream() {
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (fd_.fd >= 0) Xioctl(fd_.fd, VIDIOC_STREAMOFF, &type);
    for (auto& b : bufs_) munmap(b.first, b.second);
  }
  /// The next frame's bytes (waits up to `timeout_s`).
  std::vector<uint8_t> Next(double timeout_s, int64_t* timestamp_ns) {
    pollfd p{fd_.fd, POLLIN, 0};
    if (poll(&p, 1, int(timeout_s * 1000)) <= 0)
      Fail("no frame within " + std::to_string(int(timeout_s)) + " s");
    v4l2_buffer b{};
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE, b.memory = V4L2_MEMORY_MMAP;
    if (Xioctl(fd_.fd, VIDIOC_DQBUF, &b) != 0) Fail("VIDIOC_DQBUF");
    const uint8_t* d = static_cast<const uint8_t*>(bufs_[b.index].first);
    std::vector<uint8_t> out(d, d + b.bytesused);
    *timestamp_ns = int64_t(b.timestamp.tv_sec) * 1000000000 + int64_t(b.timestamp.tv_usec) * 1000;
    if (Xioctl(fd_.fd, VIDIOC_QBUF, &b) != 0) Fail("VIDIOC_QBUF");
    return out;
  }
  int width_ = 0, height_ = 0;
  int64_t stride_ = 0;

 private:
  [[noreturn]] void Fail(const std::string& what) {
    throw Error("camera v4l2:" + dev_ + ": " + what + " failed (" + std::strerror(errno) + ")");
  }
  std::string dev_;
  Fd fd_;
  std::vector<std::pair<void*, size_t>> bufs_;
};

class V4l2Camera : public Camera {
 public:
  V4l2Camera(const std::string& dev, CameraInfo info, uint32_t fourcc, double gain_unity)
      : dev_(dev), info_(std::move(info)), fourcc_(fourcc), gain_unity_(gain_unity) {
    if (info_.raw_format.empty())
      throw Error("camera " + info_.id + " (" + info_.model + ") offers no raw format (" +
                  Join(info_.pixel_formats) + "): capture needs unprocessed sensor data");
    DescribeRawFormat(info_.raw_format, &packing_, nullptr, &order_);
    ctrl_.fd = open(dev_.c_str(), O_RDWR | O_NONBLOCK);
    if (ctrl_.fd < 0)
      throw Error("camera " + info_.id + ": cannot open " + dev_ + " (" + std::strerror(errno) +
                  ")");
    stream_ = std::make_unique<DirectStream>(dev_, fourcc_, info_.width, info_.height);
  }
  const CameraInfo& info() const override { return info_; }

  Frame Capture(const CaptureSettings& s) override {
    ValidateSettings(info_, s);
    SetControls(s);
    std::vector<uint8_t> bytes;
    int64_t ts = 0;
    const double timeout = 5 + 3 * s.exposure_us * 1e-6;
    for (int i = 0; i < 3; ++i)
      bytes = stream_->Next(timeout, &ts);  // two frames may predate the settings
    Frame f;
    f.dn = CropRoi(UnpackRaw(bytes, stream_->width_, stream_->height_, stream_->stride_, packing_),
                   s.roi);
    f.bit_depth = info_.bit_depth;
    f.pixel_format = info_.raw_format;
    f.exposure_us = s.exposure_us;
    f.analogue_gain = s.analogue_gain;
    f.timestamp_utc = UtcTimestamp();
    f.sensor_timestamp_ns = ts;
    f.extra = {{"device", dev_},
               {"stride_bytes", stream_->stride_},
               {"bayer_order", int(order_)},
               {"path", "V4L2 ioctls (mmap streaming)"}};
    ApplyBayerMode(&f, s.bayer, order_ != BayerOrder::kNone, int(order_));
    return f;
  }

 private:
  // Exposure and gain through the device's controls (any open file of the device may set them):
  // manual exposure, V4L2_CID_EXPOSURE_ABSOLUTE in 100 us, V4L2_CID_ANALOGUE_GAIN in the
  // driver's steps with unity at the control's default.
  void SetControls(const CaptureSettings& s) {
    auto set = [&](uint32_t id, int32_t v, const std::string& what) {
      v4l2_control c{};
      c.id = id, c.value = v;
      if (Xioctl(ctrl_.fd, VIDIOC_S_CTRL, &c) != 0)
        throw Error("camera " + info_.id + ": the driver refused " + what + " (" +
                    std::strerror(errno) + ")");
    };
    if (info_.exposure_max_us > 0) {
      set(V4L2_CID_EXPOSURE_AUTO, V4L2_EXPOSURE_MANUAL, "manual exposure");
      set(V4L2_CID_EXPOSURE_ABSOLUTE, int32_t(std::lround(s.exposure_us / 100.0)),
          "exposure " + std::to_string(s.exposure_us) + " us");
    }
    if (info_.gain_max > 0)
      set(V4L2_CID_ANALOGUE_GAIN, int32_t(std::lround(s.analogue_gain * gain_unity_)),
          "analogue gain " + std::to_string(s.analogue_gain));
  }

  static std::string Join(const std::vector<std::string>& v) {
    std::string s;
    for (const auto& x : v) s += (s.empty() ? "" : ", ") + x;
    return s.empty() ? "none" : s;
  }
  std::string dev_;
  CameraInfo info_;
  uint32_t fourcc_;
  RawPacking packing_ = RawPacking::kRaw16Le;
  BayerOrder order_ = BayerOrder::kNone;
  std::unique_ptr<DirectStream> stream_;
  Fd ctrl_;                ///< the device, for controls
  double gain_unity_ = 1;  ///< driver gain steps at unity gain (the control's default)
};

}  // namespace

std::vector<CameraInfo> ListV4l2(std::vector<std::string>* notes) {
  std::vector<std::string> devs;
  std::error_code ec;
  for (const auto& e : std::filesystem::directory_iterator("/dev", ec))
    if (e.path().filename().string().rfind("video", 0) == 0) devs.push_back(e.path().string());
  std::sort(devs.begin(), devs.end());
  std::vector<CameraInfo> out;
  for (const std::string& d : devs) {
    CameraInfo info;
    uint32_t fourcc = 0;
    std::string note;
    if (Probe(d, &info, &fourcc, &note))
      out.push_back(info);
    else if (!note.empty() && notes)
      notes->push_back(note);
  }
  return out;
}

std::unique_ptr<Camera> OpenV4l2(const std::string& dev) {
  CameraInfo info;
  uint32_t fourcc = 0;
  double unity = 1;
  std::string note;
  if (!std::filesystem::exists(dev))
    throw Error("unknown camera 'v4l2:" + dev +
                "': no such device (`raymatch capture list` shows the cameras found)");
  if (!Probe(dev, &info, &fourcc, &note, &unity))
    throw Error("camera 'v4l2:" + dev +
                "': " + (note.empty() ? "not a video capture device" : note));
  return std::make_unique<V4l2Camera>(dev, info, fourcc, unity);
}

}  // namespace raymatch::capture::internal
