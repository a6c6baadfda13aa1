// Image files through the formats' reference libraries: libtiff, libpng and OpenEXR (Debian's
// libtiff-dev, libpng-dev, libopenexr-dev). Not OpenImageIO: its Debian build links a few hundred
// shared libraries (ffmpeg, GDAL, DCMTK, ...), whose loading would dominate every raymatch
// command's start-up, for the three formats raymatch reads and writes.
#include "raymatch/core/image_io.h"

#include <ImfChannelList.h>
#include <ImfFrameBuffer.h>
#include <ImfHeader.h>
#include <ImfInputFile.h>
#include <ImfOutputFile.h>
#include <ImfStandardAttributes.h>
#include <ImfStringAttribute.h>
#include <png.h>
#include <tiffio.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdarg>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <memory>

#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"

namespace raymatch {

namespace {

namespace fs = std::filesystem;

// ---------------------------------------------------------------------------------------------
// Sample types and the channel average every reader ends in.

enum class Sample { kU8, kI8, kU16, kI16, kU32, kI32, kF32, kF64 };

const char* SampleName(Sample s) {
  static constexpr std::array<const char*, 8> kNames = {"uint8",  "int8",  "uint16", "int16",
                                                        "uint32", "int32", "float",  "double"};
  return kNames[size_t(s)];
}

double SampleMax(Sample s) {
  switch (s) {
    case Sample::kU8:
      return 255.0;
    case Sample::kI8:
      return 127.0;
    case Sample::kU16:
      return 65535.0;
    case Sample::kI16:
      return 32767.0;
    case Sample::kU32:
      return 4294967295.0;
    case Sample::kI32:
      return 2147483647.0;
    default:
      return 1.0;
  }
}

template <class T>
double Load(const unsigned char* p) {
  T v;
  std::memcpy(&v, p, sizeof(T));
  return static_cast<double>(v);
}

/// Value k of a row of samples of type s (host byte order).
double ValueAt(Sample s, const unsigned char* row, size_t k) {
  switch (s) {
    case Sample::kU8:
      return Load<uint8_t>(row + k);
    case Sample::kI8:
      return Load<int8_t>(row + k);
    case Sample::kU16:
      return Load<uint16_t>(row + 2 * k);
    case Sample::kI16:
      return Load<int16_t>(row + 2 * k);
    case Sample::kU32:
      return Load<uint32_t>(row + 4 * k);
    case Sample::kI32:
      return Load<int32_t>(row + 4 * k);
    case Sample::kF64:
      return Load<double>(row + 8 * k);
    default:
      return Load<float>(row + 4 * k);
  }
}

/// Sums the first `used` channels of every pixel (the grey value, or R + G + B; alpha and
/// further channels ignored), then divides: integer code values come back exactly.
struct ChannelMean {
  ChannelMean(int width, int height, int channels)
      : w(width), h(height), used(channels >= 3 ? 3 : 1), sum(size_t(width) * height, 0.0) {}
  /// Adds the samples of `row` (n interleaved channels starting at channel c0) to row y.
  void AddRow(int y, Sample s, const unsigned char* row, int n, int c0, int x0 = 0, int nx = -1) {
    if (nx < 0) nx = w;
    for (int c = c0; c < c0 + n; ++c) {
      if (c >= used) continue;
      for (int x = 0; x < nx && x0 + x < w; ++x)
        sum[size_t(y) * w + x0 + x] += ValueAt(s, row, size_t(x) * n + (c - c0));
    }
  }
  Image Finish(const std::string& path) const {
    Image img(w, h);
    for (size_t i = 0; i < img.size(); ++i) {
      const double v = sum[i] / used;
      if (!std::isfinite(v) || !std::isfinite(static_cast<float>(v)))
        throw Error(FileLocation{path}, "pixel (" + std::to_string(i % w) + ", " +
                                            std::to_string(i / w) + ") is NaN or Inf");
      img.pixels[i] = static_cast<float>(v);
    }
    return img;
  }
  int w, h, used;
  std::vector<double> sum;
};

enum class Format { kTiff, kPng, kExr };

/// The format of a file to read, from its first bytes (an extension can be wrong).
Format SniffFormat(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  unsigned char m[8] = {};
  f.read(reinterpret_cast<char*>(m), 8);
  if ((m[0] == 'I' && m[1] == 'I' && (m[2] == 42 || m[2] == 43) && m[3] == 0) ||
      (m[0] == 'M' && m[1] == 'M' && m[2] == 0 && (m[3] == 42 || m[3] == 43)))
    return Format::kTiff;
  if (std::memcmp(m, "\x89PNG\r\n\x1a\n", 8) == 0) return Format::kPng;
  if (m[0] == 0x76 && m[1] == 0x2f && m[2] == 0x31 && m[3] == 0x01) return Format::kExr;
  throw Error(FileLocation{path},
              "cannot read image: not a TIFF, PNG or OpenEXR file (expected 8/16-bit TIFF or PNG, "
              "or float TIFF or EXR)");
}

/// The format to write, from the extension.
Format FormatFor(const std::string& path) {
  std::string ext = fs::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
  if (ext == ".tif" || ext == ".tiff") return Format::kTiff;
  if (ext == ".exr") return Format::kExr;
  if (ext == ".png") return Format::kPng;
  throw Error(FileLocation{path},
              "unsupported image extension '" + ext + "' (expected .tif, .tiff, .exr or .png)");
}

/// Writes through `write(tmp)` to a temporary file that becomes `path` only when complete.
template <class F>
void WriteAtomically(const std::string& path, F&& write) {
  const fs::path tmp = TemporaryPathFor(path);
  std::string why;
  try {
    write(tmp.string());
  } catch (const std::exception& e) {
    why = e.what();
  }
  if (!why.empty()) {
    const std::string hint = WriteFailureHint(path);  // the libraries rarely say why
    DiscardTemporary(tmp);
    throw Error(FileLocation{path}, "cannot write image: " + (hint.empty() ? why : hint));
  }
  CommitTemporary(tmp, path);
}

/// Pixels to write: interleaved samples of one type.
struct Raster {
  int width = 0, height = 0, channels = 1;
  Sample sample = Sample::kF32;
  const void* data = nullptr;
  size_t RowBytes() const {
    const size_t b = sample == Sample::kU8 ? 1 : sample == Sample::kU16 ? 2 : 4;
    return size_t(width) * channels * b;
  }
  const unsigned char* Row(int y) const {
    return static_cast<const unsigned char*>(data) + RowBytes() * y;
  }
};

// ---------------------------------------------------------------------------------------------
// TIFF (libtiff 4.5: per-file error handlers, so reading is thread safe).

int TiffError(TIFF*, void* user, const char* module, const char* fmt, va_list ap) {
  char buf[512];
  std::vsnprintf(buf, sizeof buf, fmt, ap);
  std::string& msg = *static_cast<std::string*>(user);
  if (msg.empty()) msg = (module && *module ? std::string(module) + ": " : "") + buf;
  return 1;
}

int TiffWarning(TIFF*, void*, const char*, const char*, va_list) { return 1; }  // quiet

struct TiffFile {
  TiffFile(const std::string& path, const char* mode) {
    TIFFOpenOptions* o = TIFFOpenOptionsAlloc();
    TIFFOpenOptionsSetErrorHandlerExtR(o, TiffError, &error);
    TIFFOpenOptionsSetWarningHandlerExtR(o, TiffWarning, nullptr);
    tif = TIFFOpenExt(path.c_str(), mode, o);
    TIFFOpenOptionsFree(o);
  }
  ~TiffFile() {
    if (tif) TIFFClose(tif);
  }
  std::string error;  // the first message libtiff gave
  TIFF* tif = nullptr;
};

Image ReadTiff(const std::string& path, ImageFileInfo* info) {
  TiffFile f(path, "r");
  auto fail = [&](const std::string& what) {
    throw Error(FileLocation{path}, what + (f.error.empty() ? "" : ": " + f.error));
  };
  if (!f.tif) fail("cannot read image");
  TIFF* t = f.tif;
  uint32_t w = 0, h = 0;
  uint16_t spp = 1, bits = 1, format = SAMPLEFORMAT_UINT, planar = PLANARCONFIG_CONTIG, comp = 1;
  TIFFGetField(t, TIFFTAG_IMAGEWIDTH, &w);
  TIFFGetField(t, TIFFTAG_IMAGELENGTH, &h);
  TIFFGetFieldDefaulted(t, TIFFTAG_SAMPLESPERPIXEL, &spp);
  TIFFGetFieldDefaulted(t, TIFFTAG_BITSPERSAMPLE, &bits);
  TIFFGetFieldDefaulted(t, TIFFTAG_SAMPLEFORMAT, &format);
  TIFFGetFieldDefaulted(t, TIFFTAG_PLANARCONFIG, &planar);
  TIFFGetFieldDefaulted(t, TIFFTAG_COMPRESSION, &comp);
  uint32_t depth = 1;
  if (TIFFGetField(t, TIFFTAG_IMAGEDEPTH, &depth) && depth > 1)
    throw Error(FileLocation{path}, "not a 2D image");
  const TIFFCodec* codec = TIFFFindCODEC(comp);
  const std::string comp_name = comp == COMPRESSION_NONE ? "none"
                                : codec                  ? codec->name
                                                         : "code " + std::to_string(comp);
  CheckDeclaredImageSize(path, w, h, spp, std::max(1, bits / 8), comp_name);
  Sample s;
  if (format == SAMPLEFORMAT_IEEEFP && bits == 32)
    s = Sample::kF32;
  else if (format == SAMPLEFORMAT_IEEEFP && bits == 64)
    s = Sample::kF64;
  else if ((format == SAMPLEFORMAT_UINT || format == SAMPLEFORMAT_INT) &&
           (bits == 8 || bits == 16 || bits == 32)) {
    const bool u = format == SAMPLEFORMAT_UINT;
    s = bits == 8    ? (u ? Sample::kU8 : Sample::kI8)
        : bits == 16 ? (u ? Sample::kU16 : Sample::kI16)
                     : (u ? Sample::kU32 : Sample::kI32);
  } else {
    throw Error(FileLocation{path}, "unsupported TIFF samples: " + std::to_string(bits) +
                                        "-bit, sample format " + std::to_string(format) +
                                        " (expected 8/16/32-bit integers or 32/64-bit floats)");
  }
  ChannelMean mean(int(w), int(h), spp);
  const bool separate = planar == PLANARCONFIG_SEPARATE && spp > 1;
  const int planes = separate ? std::min<int>(spp, mean.used) : 1;
  const int per = separate ? 1 : spp;  // samples interleaved in one strip or tile row
  if (TIFFIsTiled(t)) {
    uint32_t tw = 0, th = 0;
    TIFFGetField(t, TIFFTAG_TILEWIDTH, &tw);
    TIFFGetField(t, TIFFTAG_TILELENGTH, &th);
    std::vector<unsigned char> tile(TIFFTileSize(t));
    const size_t tile_row = TIFFTileRowSize(t);
    if (tile.empty() || tw == 0 || th == 0) fail("cannot read tiles");
    for (int p = 0; p < planes; ++p)
      for (uint32_t y0 = 0; y0 < h; y0 += th)
        for (uint32_t x0 = 0; x0 < w; x0 += tw) {
          if (TIFFReadTile(t, tile.data(), x0, y0, 0, uint16_t(p)) < 0) fail("cannot read pixels");
          for (uint32_t y = y0; y < std::min(h, y0 + th); ++y)
            mean.AddRow(int(y), s, tile.data() + (y - y0) * tile_row, per, p, int(x0), int(tw));
        }
  } else {
    std::vector<unsigned char> line(TIFFScanlineSize(t));
    if (line.empty()) fail("cannot read scanlines");
    for (int p = 0; p < planes; ++p)
      for (uint32_t y = 0; y < h; ++y) {
        if (TIFFReadScanline(t, line.data(), y, uint16_t(p)) < 0) fail("cannot read pixels");
        mean.AddRow(int(y), s, line.data(), per, p);
      }
  }
  if (info) *info = {"tiff", SampleName(s), spp, SampleMax(s)};
  return mean.Finish(path);
}

void WriteTiff(const std::string& path, const Raster& r, const std::string& description) {
  TiffFile f(path, "w");
  auto check = [&](bool ok) {
    if (!ok) throw std::runtime_error(f.error.empty() ? "libtiff failed" : f.error);
  };
  check(f.tif != nullptr);
  TIFF* t = f.tif;
  const uint16_t bits = r.sample == Sample::kU8 ? 8 : r.sample == Sample::kU16 ? 16 : 32;
  check(TIFFSetField(t, TIFFTAG_IMAGEWIDTH, uint32_t(r.width)));
  check(TIFFSetField(t, TIFFTAG_IMAGELENGTH, uint32_t(r.height)));
  check(TIFFSetField(t, TIFFTAG_SAMPLESPERPIXEL, uint16_t(r.channels)));
  check(TIFFSetField(t, TIFFTAG_BITSPERSAMPLE, bits));
  check(TIFFSetField(t, TIFFTAG_SAMPLEFORMAT,
                     r.sample == Sample::kF32 ? SAMPLEFORMAT_IEEEFP : SAMPLEFORMAT_UINT));
  check(TIFFSetField(t, TIFFTAG_PHOTOMETRIC,
                     r.channels >= 3 ? PHOTOMETRIC_RGB : PHOTOMETRIC_MINISBLACK));
  check(TIFFSetField(t, TIFFTAG_PLANARCONFIG, PLANARCONFIG_CONTIG));
  // Uncompressed: zip with the float predictor needs extra codecs in Python (tifffile).
  check(TIFFSetField(t, TIFFTAG_COMPRESSION, COMPRESSION_NONE));
  check(TIFFSetField(t, TIFFTAG_ROWSPERSTRIP, TIFFDefaultStripSize(t, 0)));
  check(TIFFSetField(t, TIFFTAG_SOFTWARE, "raymatch"));
  if (!description.empty()) check(TIFFSetField(t, TIFFTAG_IMAGEDESCRIPTION, description.c_str()));
  std::vector<unsigned char> line(r.RowBytes());  // libtiff may modify the buffer it is given
  for (int y = 0; y < r.height; ++y) {
    std::memcpy(line.data(), r.Row(y), line.size());
    check(TIFFWriteScanline(t, line.data(), uint32_t(y), 0) >= 0);
  }
  check(TIFFWriteDirectory(t) != 0);
  TIFFClose(t);
  f.tif = nullptr;
  check(f.error.empty());
}

// ---------------------------------------------------------------------------------------------
// PNG (libpng's classic interface: its simplified one converts 16-bit values through a gamma).

struct PngMessage {
  char text[256] = {};
};

[[noreturn]] void PngError(png_structp png, png_const_charp msg) {
  auto* m = static_cast<PngMessage*>(png_get_error_ptr(png));
  std::snprintf(m->text, sizeof m->text, "%s", msg);
  png_longjmp(png, 1);
}

void PngWarning(png_structp, png_const_charp) {}

/// Decodes into `pixels`, rows addressed through `row_ptrs` (both the caller's: nothing with a
/// destructor lives across setjmp in this function); false on a libpng error (its message in
/// `m`).
bool PngDecode(FILE* fp, PngMessage* m, std::vector<unsigned char>* pixels,
               std::vector<png_bytep>* row_ptrs, int* width, int* height, int* channels, int* bits,
               const std::string& path) {
  png_structp png = png_create_read_struct(PNG_LIBPNG_VER_STRING, m, PngError, PngWarning);
  if (!png) return false;
  png_infop info = png_create_info_struct(png);
  if (!info || setjmp(png_jmpbuf(png))) {
    png_destroy_read_struct(&png, &info, nullptr);
    return false;
  }
  png_init_io(png, fp);
  png_read_info(png, info);
  const png_uint_32 w = png_get_image_width(png, info), h = png_get_image_height(png, info);
  const int color = png_get_color_type(png, info);
  if (color == PNG_COLOR_TYPE_PALETTE) png_set_palette_to_rgb(png);
  if (color == PNG_COLOR_TYPE_GRAY && png_get_bit_depth(png, info) < 8)
    png_set_expand_gray_1_2_4_to_8(png);
  if (png_get_bit_depth(png, info) == 16) png_set_swap(png);  // to the host's little-endian
  png_set_interlace_handling(png);
  png_read_update_info(png, info);
  *width = int(w), *height = int(h);
  *channels = png_get_channels(png, info);
  *bits = png_get_bit_depth(png, info);
  try {  // before any allocation of the declared size (no libpng frame below this throw)
    CheckDeclaredImageSize(path, w, h, *channels, *bits / 8, "deflate");
  } catch (...) {
    png_destroy_read_struct(&png, &info, nullptr);
    throw;
  }
  const size_t row_bytes = png_get_rowbytes(png, info);
  pixels->assign(row_bytes * h, 0);
  row_ptrs->resize(h);
  for (png_uint_32 y = 0; y < h; ++y) (*row_ptrs)[y] = pixels->data() + row_bytes * y;
  png_read_image(png, row_ptrs->data());
  png_read_end(png, nullptr);
  png_destroy_read_struct(&png, &info, nullptr);
  return true;
}

Image ReadPng(const std::string& path, ImageFileInfo* info) {
  std::unique_ptr<FILE, int (*)(FILE*)> fp(std::fopen(path.c_str(), "rb"), std::fclose);
  if (!fp) throw Error(FileLocation{path}, "cannot read image: cannot open the file");
  PngMessage m;
  std::vector<unsigned char> px;
  std::vector<png_bytep> rows;
  int w = 0, h = 0, nc = 1, bits = 8;
  if (!PngDecode(fp.get(), &m, &px, &rows, &w, &h, &nc, &bits, path))
    throw Error(FileLocation{path}, std::string("cannot read image: ") + m.text);
  const Sample s = bits == 16 ? Sample::kU16 : Sample::kU8;
  ChannelMean mean(w, h, nc);
  const size_t row = px.size() / size_t(h);
  for (int y = 0; y < h; ++y) mean.AddRow(y, s, px.data() + row * y, nc, 0);
  if (info) *info = {"png", SampleName(s), nc, SampleMax(s)};
  return mean.Finish(path);
}

bool PngEncode(FILE* fp, PngMessage* m, const Raster& r, const char* description) {
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, m, PngError, PngWarning);
  if (!png) return false;
  png_infop info = png_create_info_struct(png);
  if (!info || setjmp(png_jmpbuf(png))) {
    png_destroy_write_struct(&png, &info);
    return false;
  }
  png_init_io(png, fp);
  png_set_IHDR(png, info, uint32_t(r.width), uint32_t(r.height), r.sample == Sample::kU16 ? 16 : 8,
               r.channels >= 3 ? PNG_COLOR_TYPE_RGB : PNG_COLOR_TYPE_GRAY, PNG_INTERLACE_NONE,
               PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
  png_text text[2] = {};
  text[0].compression = text[1].compression = PNG_TEXT_COMPRESSION_NONE;
  text[0].key = const_cast<char*>("Software");
  text[0].text = const_cast<char*>("raymatch");
  text[1].key = const_cast<char*>("Description");
  text[1].text = const_cast<char*>(description);
  png_set_text(png, info, text, description[0] ? 2 : 1);
  png_write_info(png, info);
  if (r.sample == Sample::kU16) png_set_swap(png);  // the host's little-endian to PNG's order
  for (int y = 0; y < r.height; ++y) png_write_row(png, r.Row(y));
  png_write_end(png, nullptr);
  png_destroy_write_struct(&png, &info);
  return true;
}

void WritePng(const std::string& path, const Raster& r, const std::string& description) {
  std::unique_ptr<FILE, int (*)(FILE*)> fp(std::fopen(path.c_str(), "wb"), std::fclose);
  if (!fp) throw std::runtime_error("cannot open the file");
  PngMessage m;
  if (!PngEncode(fp.get(), &m, r, description.c_str())) throw std::runtime_error(m.text);
  if (std::fclose(fp.release()) != 0) throw std::runtime_error("cannot close the file");
}

// ---------------------------------------------------------------------------------------------
// OpenEXR: a "Y" channel, or the mean of R, G and B, or the first channel; read as float.

Image ReadExr(const std::string& path, ImageFileInfo* info) {
  try {
    Imf::InputFile in(path.c_str());
    const Imath::Box2i dw = in.header().dataWindow();
    const int w = dw.max.x - dw.min.x + 1, h = dw.max.y - dw.min.y + 1;
    const Imf::ChannelList& cl = in.header().channels();
    std::vector<std::string> names;
    if (cl.findChannel("Y")) {
      names = {"Y"};
    } else if (cl.findChannel("R") && cl.findChannel("G") && cl.findChannel("B")) {
      names = {"R", "G", "B"};
    } else if (cl.begin() != cl.end()) {
      names = {cl.begin().name()};
    } else {
      throw Error(FileLocation{path}, "cannot read image: no channels");
    }
    int count = 0;
    for (auto it = cl.begin(); it != cl.end(); ++it) ++count;
    const Imf::PixelType type = cl.findChannel(names[0])->type;
    CheckDeclaredImageSize(path, w, h, count, type == Imf::HALF ? 2 : 4,
                           in.header().compression() == Imf::NO_COMPRESSION ? "none" : "exr");
    std::vector<float> px(size_t(w) * h * names.size());
    Imf::FrameBuffer fb;
    for (size_t c = 0; c < names.size(); ++c) {
      // The frame buffer is addressed by data-window coordinates.
      char* base = reinterpret_cast<char*>(px.data() + c) -
                   (ptrdiff_t(dw.min.x) + ptrdiff_t(dw.min.y) * w) * names.size() * sizeof(float);
      fb.insert(names[c], Imf::Slice(Imf::FLOAT, base, sizeof(float) * names.size(),
                                     sizeof(float) * names.size() * size_t(w)));
    }
    in.setFrameBuffer(fb);
    in.readPixels(dw.min.y, dw.max.y);
    ChannelMean mean(w, h, int(names.size()));
    const size_t row = size_t(w) * names.size() * sizeof(float);
    for (int y = 0; y < h; ++y)
      mean.AddRow(y, Sample::kF32, reinterpret_cast<const unsigned char*>(px.data()) + row * y,
                  int(names.size()), 0);
    if (info)
      *info = {"openexr",
               type == Imf::HALF   ? "half"
               : type == Imf::UINT ? "uint32"
                                   : "float",
               count, type == Imf::UINT ? 4294967295.0 : 1.0};
    return mean.Finish(path);
  } catch (const Error&) {
    throw;
  } catch (const std::exception& e) {
    throw Error(FileLocation{path}, std::string("cannot read image: ") + e.what());
  }
}

void WriteExr(const std::string& path, const Raster& r, const std::string& description) {
  Imf::Header header(r.width, r.height);
  header.compression() = Imf::ZIP_COMPRESSION;
  header.channels().insert("Y", Imf::Channel(Imf::FLOAT));
  if (!description.empty()) Imf::addComments(header, description);
  header.insert("software", Imf::StringAttribute("raymatch"));
  Imf::OutputFile out(path.c_str(), header);
  Imf::FrameBuffer fb;
  fb.insert("Y", Imf::Slice(Imf::FLOAT, static_cast<char*>(const_cast<void*>(r.data)),
                            sizeof(float), sizeof(float) * size_t(r.width)));
  out.setFrameBuffer(fb);
  out.writePixels(r.height);
}

void WriteRaster(const std::string& path, const Raster& r, const std::string& description) {
  const Format f = FormatFor(path);
  if (f == Format::kExr && (r.sample != Sample::kF32 || r.channels != 1))
    throw Error(FileLocation{path}, "OpenEXR files hold the float images only (use .tif or .png)");
  if (f == Format::kPng && r.sample == Sample::kF32)
    throw Error(FileLocation{path}, "PNG holds integer images only (use .tif or .exr)");
  WriteAtomically(path, [&](const std::string& tmp) {
    if (f == Format::kTiff) WriteTiff(tmp, r, description);
    if (f == Format::kPng) WritePng(tmp, r, description);
    if (f == Format::kExr) WriteExr(tmp, r, description);
  });
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
  const uintmax_t file_bytes = fs::file_size(path, ec);
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
  if (!fs::exists(path)) throw Error(FileLocation{path}, "file not found");
  switch (SniffFormat(path)) {
    case Format::kTiff:
      return ReadTiff(path, info);
    case Format::kPng:
      return ReadPng(path, info);
    default:
      return ReadExr(path, info);
  }
}

void WriteFloatImage(const std::string& path, const Image& img, const std::string& description) {
  for (size_t i = 0; i < img.size(); ++i)
    RAYMATCH_CHECK(std::isfinite(img.pixels[i]));  // never NaN in an output
  WriteRaster(path, {img.width, img.height, 1, Sample::kF32, img.pixels.data()}, description);
}

void WriteUint16Image(const std::string& path, const Image& img, const std::string& description) {
  std::vector<uint16_t> px(img.size());
  for (size_t i = 0; i < img.size(); ++i) {
    RAYMATCH_CHECK(std::isfinite(img.pixels[i]));
    px[i] = static_cast<uint16_t>(std::clamp(std::round(double(img.pixels[i])), 0.0, 65535.0));
  }
  WriteRaster(path, {img.width, img.height, 1, Sample::kU16, px.data()}, description);
}

void WriteRgbPng(const std::string& path, int width, int height, const unsigned char* rgb) {
  WriteRaster(path, {width, height, 3, Sample::kU8, rgb}, "");
}

void WritePngPreview(const std::string& path, const Image& img, double lo, double hi) {
  std::vector<unsigned char> px(img.size());
  const double scale = hi > lo ? 255.0 / (hi - lo) : 0.0;
  for (size_t i = 0; i < img.size(); ++i)
    px[i] = static_cast<unsigned char>(std::clamp((img.pixels[i] - lo) * scale + 0.5, 0.0, 255.0));
  WriteRaster(path, {img.width, img.height, 1, Sample::kU8, px.data()}, "");
}

}  // namespace raymatch
