#include "raymatch/core/image_io.h"

#include <OpenImageIO/imageio.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>

#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"

namespace raymatch {

namespace {

double TypeMax(OIIO::TypeDesc t) {
  switch (t.basetype) {
    case OIIO::TypeDesc::UINT8:
      return 255.0;
    case OIIO::TypeDesc::INT8:
      return 127.0;
    case OIIO::TypeDesc::UINT16:
      return 65535.0;
    case OIIO::TypeDesc::INT16:
      return 32767.0;
    case OIIO::TypeDesc::UINT32:
      return 4294967295.0;
    case OIIO::TypeDesc::INT32:
      return 2147483647.0;
    default:
      return 1.0;
  }
}

std::string FormatFor(const std::string& path) {
  std::string ext = std::filesystem::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
  if (ext == ".tif" || ext == ".tiff") return "tiff";
  if (ext == ".exr") return "openexr";
  if (ext == ".png") return "png";
  throw Error(FileLocation{path},
              "unsupported image extension '" + ext + "' (expected .tif, .tiff, .exr or .png)");
}

void WriteWithOiio(const std::string& path, const OIIO::ImageSpec& spec, OIIO::TypeDesc in_type,
                   const void* data) {
  const std::string format = FormatFor(path);
  auto out = OIIO::ImageOutput::create(format);
  if (!out) throw Error(FileLocation{path}, "OpenImageIO has no writer for " + format);
  const std::filesystem::path tmp = TemporaryPathFor(path);
  if (!out->open(tmp.string(), spec) || !out->write_image(in_type, data) || !out->close()) {
    std::string why = out->geterror();
    out.reset();                                      // closes the file before it is removed
    const std::string hint = WriteFailureHint(path);  // OpenImageIO's message rarely says why
    if (!hint.empty()) why = hint + ": " + why;
    DiscardTemporary(tmp);
    throw Error(FileLocation{path}, "cannot write image: " + why);
  }
  CommitTemporary(tmp, path);
}

template <class T>
double ValueAt(const unsigned char* p) {
  T v;
  std::memcpy(&v, p, sizeof(T));
  return static_cast<double>(v);
}

}  // namespace

void CheckDeclaredImageSize(const std::string& path, int64_t width, int64_t height,
                            int64_t channels, int64_t bytes_per_value,
                            const std::string& compression) {
  auto fail = [&](const std::string& why) {
    throw Error(FileLocation{path}, "declares " + std::to_string(width) + " x " +
                                        std::to_string(height) + " pixels x " +
                                        std::to_string(channels) + " channel(s): " + why);
  };
  if (width <= 0 || height <= 0 || channels <= 0) fail("expected positive sizes");
  if (width > kMaxImageSide || height > kMaxImageSide)
    fail("more than " + std::to_string(kMaxImageSide) + " pixels on a side");
  if (channels > 16) fail("more than 16 channels");
  if (width * height > kMaxImagePixels)
    fail("more than " + std::to_string(kMaxImagePixels) + " pixels in all");
  std::error_code ec;
  const uintmax_t file_bytes = std::filesystem::file_size(path, ec);
  if (ec) return;
  const uint64_t raw = uint64_t(width) * height * channels * bytes_per_value;
  // An uncompressed file stores every value; a compressed one cannot shrink data by more than
  // deflate's limit of about 1032:1 (taken as 2000:1 here, plus room for headers).
  const bool uncompressed = compression.empty() || compression == "none";
  const uint64_t limit = uncompressed ? uint64_t(file_bytes) : uint64_t(file_bytes) * 2000 + 65536;
  if (raw > limit)
    fail(std::to_string(raw) + " bytes of pixel data, but the file has only " +
         std::to_string(file_bytes) + " bytes (" + (uncompressed ? "uncompressed" : compression) +
         "); truncated or corrupt");
}

Image ReadImage(const std::string& path, ImageFileInfo* info) {
  if (!std::filesystem::exists(path)) throw Error(FileLocation{path}, "file not found");
  auto in = OIIO::ImageInput::open(path);
  if (!in) throw Error(FileLocation{path}, "cannot read image: " + OIIO::geterror());
  const OIIO::ImageSpec& spec = in->spec();
  if (spec.width <= 0 || spec.height <= 0 || spec.depth > 1)
    throw Error(FileLocation{path}, "not a 2D image");
  CheckDeclaredImageSize(path, spec.width, spec.height, spec.nchannels,
                         spec.format.size() ? spec.format.size() : 4,
                         spec.get_string_attribute("compression", "unknown"));
  const double tmax = TypeMax(spec.format);
  // Integer files are read in their own type: OIIO's conversion to float goes through a
  // normalised single-precision value, which multiplied back is off by up to 4e-3 code values.
  const bool integer = tmax > 1.0;
  const OIIO::TypeDesc read_type =
      integer ? OIIO::TypeDesc(OIIO::TypeDesc::BASETYPE(spec.format.basetype))
              : OIIO::TypeDesc(OIIO::TypeDesc::DOUBLE);
  const size_t values = size_t(spec.width) * spec.height * spec.nchannels;
  std::vector<unsigned char> raw(values * read_type.size());
  if (!in->read_image(0, 0, 0, spec.nchannels, read_type, raw.data()))
    throw Error(FileLocation{path}, "cannot read pixels: " + in->geterror());
  auto value = [&](size_t k) -> double {
    const unsigned char* p = raw.data() + k * read_type.size();
    switch (read_type.basetype) {
      case OIIO::TypeDesc::UINT8:
        return ValueAt<uint8_t>(p);
      case OIIO::TypeDesc::INT8:
        return ValueAt<int8_t>(p);
      case OIIO::TypeDesc::UINT16:
        return ValueAt<uint16_t>(p);
      case OIIO::TypeDesc::INT16:
        return ValueAt<int16_t>(p);
      case OIIO::TypeDesc::UINT32:
        return ValueAt<uint32_t>(p);
      case OIIO::TypeDesc::INT32:
        return ValueAt<int32_t>(p);
      default:
        return ValueAt<double>(p);
    }
  };
  Image img(spec.width, spec.height);
  // Average colour channels (ignoring alpha) so RGB captures of a grey scene still load.
  const int nc = spec.nchannels >= 3 ? 3 : 1;
  for (size_t i = 0; i < img.size(); ++i) {
    double s = 0;
    for (int c = 0; c < nc; ++c) s += value(i * spec.nchannels + c);
    const double v = s / nc;  // code values of an integer file, stored values of a float one
    if (!std::isfinite(v) || !std::isfinite(static_cast<float>(v)))
      throw Error(FileLocation{path}, "pixel (" + std::to_string(i % spec.width) + ", " +
                                          std::to_string(i / spec.width) + ") is NaN or Inf");
    img.pixels[i] = static_cast<float>(v);
  }
  if (info) {
    info->format = in->format_name();
    info->pixel_type = spec.format.c_str();
    info->channels = spec.nchannels;
    info->type_max = tmax;
  }
  return img;
}

void WriteFloatImage(const std::string& path, const Image& img, const std::string& description,
                     const std::map<std::string, std::string>& attributes) {
  for (size_t i = 0; i < img.size(); ++i)
    RAYMATCH_CHECK(std::isfinite(img.pixels[i]));  // never NaN in an output
  OIIO::ImageSpec spec(img.width, img.height, 1, OIIO::TypeDesc::FLOAT);
  spec.attribute("ImageDescription", description);
  spec.attribute("Software", "raymatch");
  // Uncompressed: zip with the float predictor needs extra codecs in Python (tifffile).
  spec.attribute("compression", "none");
  for (const auto& [k, v] : attributes) spec.attribute(k, v);
  WriteWithOiio(path, spec, OIIO::TypeDesc::FLOAT, img.pixels.data());
}

void WriteUint16Image(const std::string& path, const Image& img, const std::string& description) {
  std::vector<uint16_t> px(img.size());
  for (size_t i = 0; i < img.size(); ++i) {
    RAYMATCH_CHECK(std::isfinite(img.pixels[i]));
    px[i] = static_cast<uint16_t>(std::clamp(std::round(double(img.pixels[i])), 0.0, 65535.0));
  }
  OIIO::ImageSpec spec(img.width, img.height, 1, OIIO::TypeDesc::UINT16);
  if (!description.empty()) spec.attribute("ImageDescription", description);
  spec.attribute("Software", "raymatch");
  spec.attribute("compression", "none");
  WriteWithOiio(path, spec, OIIO::TypeDesc::UINT16, px.data());
}

void WriteRgbPng(const std::string& path, int width, int height, const unsigned char* rgb) {
  OIIO::ImageSpec spec(width, height, 3, OIIO::TypeDesc::UINT8);
  spec.attribute("Software", "raymatch");
  WriteWithOiio(path, spec, OIIO::TypeDesc::UINT8, rgb);
}

void WritePngPreview(const std::string& path, const Image& img, double lo, double hi) {
  std::vector<unsigned char> px(img.size());
  const double scale = hi > lo ? 255.0 / (hi - lo) : 0.0;
  for (size_t i = 0; i < img.size(); ++i)
    px[i] = static_cast<unsigned char>(std::clamp((img.pixels[i] - lo) * scale + 0.5, 0.0, 255.0));
  OIIO::ImageSpec spec(img.width, img.height, 1, OIIO::TypeDesc::UINT8);
  spec.attribute("Software", "raymatch");
  WriteWithOiio(path, spec, OIIO::TypeDesc::UINT8, px.data());
}

}  // namespace raymatch
