#include "raymatch/core/image_io.h"

#include <ImfChannelList.h>
#include <ImfFrameBuffer.h>
#include <ImfHeader.h>
#include <ImfOutputFile.h>
#include <gtest/gtest.h>
#include <png.h>
#include <tiffio.h>

#include <filesystem>
#include <fstream>
#include <tuple>

#include "raymatch/core/error.h"
#include "temp_dir.h"

namespace raymatch {
namespace {

TEST(ImageIo, FloatTiffRoundTripIsExact) {
  testing::TempDir dir;
  Image img(5, 3);
  for (size_t i = 0; i < img.size(); ++i) img.pixels[i] = 0.25f * i + 1e-3f;
  WriteFloatImage(dir / "a.tif", img, "{\"k\":1}");
  ImageFileInfo info;
  Image back = ReadImage(dir / "a.tif", &info);
  ASSERT_EQ(back.width, 5);
  ASSERT_EQ(back.height, 3);
  EXPECT_EQ(back.pixels, img.pixels);
  EXPECT_EQ(info.pixel_type, "float");
  // No temporary file left behind.
  const auto n = std::distance(std::filesystem::directory_iterator(dir.path()),
                               std::filesystem::directory_iterator());
  EXPECT_EQ(n, 1);
}

TEST(ImageIo, PngPreviewKeepsCodeValues) {
  testing::TempDir dir;
  Image img(2, 1);
  img.pixels = {0.f, 10.f};
  WritePngPreview(dir / "p.png", img, 0, 10);
  ImageFileInfo info;
  Image back = ReadImage(dir / "p.png", &info);
  EXPECT_FLOAT_EQ(back.pixels[0], 0.f);
  EXPECT_FLOAT_EQ(back.pixels[1], 255.f);  // 8-bit code values, not normalised
  EXPECT_DOUBLE_EQ(info.type_max, 255.0);
}

TEST(ImageIo, Uint16KeepsTwelveBitCodeValues) {
  testing::TempDir dir;
  Image img(3, 1);
  img.pixels = {0.4f, 4095.f, 70000.f};
  WriteUint16Image(dir / "c.tif", img, "12-bit data");
  ImageFileInfo info;
  const Image back = ReadImage(dir / "c.tif", &info);
  EXPECT_EQ(back.pixels, (std::vector<float>{0.f, 4095.f, 65535.f}));
  EXPECT_EQ(info.pixel_type, "uint16");
}

TEST(ImageIo, MissingAndBadFilesSayWhich) {
  testing::TempDir dir;
  try {
    ReadImage(dir / "none.tif");
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("none.tif: error: file not found"), std::string::npos);
  }
  const std::string junk = dir.Write("junk.tif", "not an image");
  EXPECT_THROW(ReadImage(junk), Error);
  EXPECT_THROW(WriteFloatImage(dir / "x.bmpx", Image(1, 1), ""), Error);
}

// Issue 15 defect 1: integer pixels came back through a normalised float and were multiplied
// back, off by up to 3.9e-3 in a 16-bit ramp. Every code value must read back exactly.
TEST(ImageIo, EverySixteenBitCodeValueReadsBackExactly) {
  testing::TempDir dir;
  Image ramp(256, 256);
  for (size_t i = 0; i < ramp.size(); ++i) ramp.pixels[i] = static_cast<float>(i);
  WriteUint16Image(dir / "ramp16.tif", ramp, "");
  WriteUint16Image(dir / "ramp16.png", ramp, "");
  WriteFloatImage(dir / "ramp.tif", ramp, "");
  const Image tif = ReadImage(dir / "ramp16.tif"), png = ReadImage(dir / "ramp16.png");
  const Image flt = ReadImage(dir / "ramp.tif");
  EXPECT_EQ(tif.pixels, ramp.pixels);
  EXPECT_EQ(png.pixels, ramp.pixels);
  EXPECT_EQ(flt.pixels, tif.pixels);  // integer and float files of the same values agree
}

TEST(ImageIo, EveryEightBitCodeValueReadsBackExactly) {
  testing::TempDir dir;
  std::vector<unsigned char> rgb(256 * 3);
  Image ramp(256, 1);
  for (int i = 0; i < 256; ++i) {
    rgb[3 * i] = rgb[3 * i + 1] = rgb[3 * i + 2] = static_cast<unsigned char>(i);
    ramp.pixels[i] = static_cast<float>(i);
  }
  WriteRgbPng(dir / "ramp8.png", 256, 1, rgb.data());
  ImageFileInfo info;
  EXPECT_EQ(ReadImage(dir / "ramp8.png", &info).pixels, ramp.pixels);
  EXPECT_EQ(info.pixel_type, "uint8");
}

// A little-endian uncompressed float TIFF header that claims width x height pixels but holds
// only one strip of 16 bytes.
std::string TiffClaiming(uint32_t width, uint32_t height) {
  std::string t = std::string("II*\0", 4);
  auto u16 = [&](uint16_t v) { t.append(reinterpret_cast<const char*>(&v), 2); };
  auto u32 = [&](uint32_t v) { t.append(reinterpret_cast<const char*>(&v), 4); };
  u32(8);
  const uint16_t n = 10;
  u16(n);
  auto entry = [&](uint16_t tag, uint16_t type, uint32_t value) {
    u16(tag), u16(type), u32(1);
    if (type == 3)
      u16(static_cast<uint16_t>(value)), u16(0);
    else
      u32(value);
  };
  const uint32_t data = 8 + 2 + n * 12 + 4;
  entry(256, 4, width);   // ImageWidth
  entry(257, 4, height);  // ImageLength
  entry(258, 3, 32);      // BitsPerSample
  entry(259, 3, 1);       // Compression: none
  entry(262, 3, 1);       // Photometric: min-is-black
  entry(273, 4, data);    // StripOffsets
  entry(277, 3, 1);       // SamplesPerPixel
  entry(278, 4, height);  // RowsPerStrip
  entry(279, 4, 16);      // StripByteCounts
  entry(339, 3, 3);       // SampleFormat: IEEE float
  u32(0);
  t.append(16, '\0');
  return t;
}

// Issue 15 defect 4: a TIFF claiming a huge size made `compare` allocate ~14 GB before failing.
TEST(ImageIo, DeclaredSizeIsCheckedBeforeAllocating) {
  testing::TempDir dir;
  for (auto [w, h, what] :
       {std::tuple{70000u, 1u, "pixels on a side"}, std::tuple{20000u, 20000u, "pixels in all"},
        std::tuple{4000u, 4000u, "bytes of pixel data"}}) {
    const std::string f = dir.Write("huge.tif", TiffClaiming(w, h));
    try {
      ReadImage(f);
      ADD_FAILURE() << w << " x " << h << " was read";
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find("huge.tif: error: declares"), std::string::npos)
          << e.what();
      EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
    }
  }
  // The same header with the data it claims is read.
  std::string ok = TiffClaiming(2, 2);
  EXPECT_EQ(ReadImage(dir.Write("ok.tif", ok)).pixels, (std::vector<float>(4, 0.f)));
}

// Writes a TIFF the way other programs do (tiles, separate planes, compression) with libtiff
// itself; `value(x, y, c)` gives the samples, stored as T.
template <class T, class F>
void WriteTiffWith(const std::string& path, int w, int h, int spp, uint16_t format, bool tiled,
                   bool separate, uint16_t compression, F value) {
  TIFF* t = TIFFOpen(path.c_str(), "w");
  ASSERT_NE(t, nullptr);
  TIFFSetField(t, TIFFTAG_IMAGEWIDTH, uint32_t(w));
  TIFFSetField(t, TIFFTAG_IMAGELENGTH, uint32_t(h));
  TIFFSetField(t, TIFFTAG_SAMPLESPERPIXEL, uint16_t(spp));
  TIFFSetField(t, TIFFTAG_BITSPERSAMPLE, uint16_t(8 * sizeof(T)));
  TIFFSetField(t, TIFFTAG_SAMPLEFORMAT, format);
  TIFFSetField(t, TIFFTAG_PHOTOMETRIC, spp >= 3 ? PHOTOMETRIC_RGB : PHOTOMETRIC_MINISBLACK);
  TIFFSetField(t, TIFFTAG_PLANARCONFIG, separate ? PLANARCONFIG_SEPARATE : PLANARCONFIG_CONTIG);
  TIFFSetField(t, TIFFTAG_COMPRESSION, compression);
  const int planes = separate ? spp : 1, per = separate ? 1 : spp;
  if (tiled) {
    const int tw = 16, th = 16;
    TIFFSetField(t, TIFFTAG_TILEWIDTH, uint32_t(tw));
    TIFFSetField(t, TIFFTAG_TILELENGTH, uint32_t(th));
    std::vector<T> tile(size_t(tw) * th * per);
    for (int p = 0; p < planes; ++p)
      for (int y0 = 0; y0 < h; y0 += th)
        for (int x0 = 0; x0 < w; x0 += tw) {
          for (int y = 0; y < th; ++y)
            for (int x = 0; x < tw; ++x)
              for (int c = 0; c < per; ++c)
                tile[(size_t(y) * tw + x) * per + c] = value(x0 + x, y0 + y, separate ? p : c);
          ASSERT_GE(TIFFWriteTile(t, tile.data(), x0, y0, 0, uint16_t(p)), 0);
        }
  } else {
    TIFFSetField(t, TIFFTAG_ROWSPERSTRIP, 3u);
    std::vector<T> row(size_t(w) * per);
    for (int p = 0; p < planes; ++p)
      for (int y = 0; y < h; ++y) {
        for (int x = 0; x < w; ++x)
          for (int c = 0; c < per; ++c) row[size_t(x) * per + c] = value(x, y, separate ? p : c);
        ASSERT_GE(TIFFWriteScanline(t, row.data(), uint32_t(y), uint16_t(p)), 0);
      }
  }
  TIFFClose(t);
}

// The reader is libtiff's (issue 24): files from other programs, tiled, with separate colour
// planes or compressed, give the same values as the plain strips raymatch writes.
TEST(ImageIo, TiledPlanarAndCompressedTiffsGiveTheirValues) {
  testing::TempDir dir;
  const int w = 37, h = 21;  // not a multiple of the 16 x 16 tiles or the 3-row strips
  auto grey = [](int x, int y, int) { return uint16_t(1000 * y + 7 * x); };
  Image expect(w, h);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) expect.at(x, y) = float(grey(x, y, 0));
  for (bool tiled : {false, true})
    for (uint16_t comp : {COMPRESSION_NONE, COMPRESSION_LZW, COMPRESSION_ADOBE_DEFLATE}) {
      const std::string f = dir / ("g" + std::to_string(tiled) + std::to_string(comp) + ".tif");
      WriteTiffWith<uint16_t>(f, w, h, 1, SAMPLEFORMAT_UINT, tiled, false, comp, grey);
      ImageFileInfo info;
      EXPECT_EQ(ReadImage(f, &info).pixels, expect.pixels) << f;
      EXPECT_EQ(info.pixel_type, "uint16");
    }
  // RGB (+ alpha, ignored): the mean of R, G and B, whether interleaved or in planes.
  auto rgba = [](int x, int y, int c) { return uint8_t(c == 3 ? 255 : 10 * c + x + y); };
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) expect.at(x, y) = float(10 + x + y);
  for (bool tiled : {false, true})
    for (bool separate : {false, true}) {
      const std::string f = dir / ("c" + std::to_string(tiled) + std::to_string(separate) + ".tif");
      WriteTiffWith<uint8_t>(f, w, h, 4, SAMPLEFORMAT_UINT, tiled, separate, COMPRESSION_NONE,
                             rgba);
      ImageFileInfo info;
      EXPECT_EQ(ReadImage(f, &info).pixels, expect.pixels) << f;
      EXPECT_EQ(info.channels, 4);
    }
  // Doubles and signed integers keep their values.
  WriteTiffWith<double>(dir / "d.tif", w, h, 1, SAMPLEFORMAT_IEEEFP, true, false,
                        COMPRESSION_ADOBE_DEFLATE, [](int x, int y, int) { return 0.25 * x - y; });
  WriteTiffWith<int16_t>(dir / "s.tif", w, h, 1, SAMPLEFORMAT_INT, false, false, COMPRESSION_NONE,
                         [](int x, int y, int) { return int16_t(100 * x - 1000 * y); });
  const Image d = ReadImage(dir / "d.tif"), i16 = ReadImage(dir / "s.tif");
  EXPECT_FLOAT_EQ(d.at(36, 20), 0.25f * 36 - 20);
  EXPECT_FLOAT_EQ(i16.at(3, 20), -19700.f);
}

TEST(ImageIo, ExrFloatRoundTripAndColourChannels) {
  testing::TempDir dir;
  Image img(7, 5);
  for (size_t i = 0; i < img.size(); ++i) img.pixels[i] = 1.5f * i - 3.25f;
  WriteFloatImage(dir / "y.exr", img, "a comment");
  ImageFileInfo info;
  EXPECT_EQ(ReadImage(dir / "y.exr", &info).pixels, img.pixels);
  EXPECT_EQ(info.format, "openexr");
  // An RGB file of another program, with a data window that does not start at (0, 0).
  Imf::Header hd(Imath::Box2i({0, 0}, {9, 9}), Imath::Box2i({2, 3}, {4, 4}));
  for (const char* c : {"R", "G", "B"}) hd.channels().insert(c, Imf::Channel(Imf::FLOAT));
  std::vector<float> rgb(3 * 3 * 2);
  for (size_t k = 0; k < rgb.size(); ++k) rgb[k] = float(k);
  {
    Imf::OutputFile out((dir / "rgb.exr").c_str(), hd);
    Imf::FrameBuffer fb;
    const size_t xs = 3 * sizeof(float), ys = 3 * xs;
    char* base = reinterpret_cast<char*>(rgb.data()) - 2 * xs - 3 * ys;
    const char* names[3] = {"R", "G", "B"};
    for (int c = 0; c < 3; ++c)
      fb.insert(names[c], Imf::Slice(Imf::FLOAT, base + c * sizeof(float), xs, ys));
    out.setFrameBuffer(fb);
    out.writePixels(2);
  }
  const Image back = ReadImage(dir / "rgb.exr");
  ASSERT_EQ(back.width, 3);
  ASSERT_EQ(back.height, 2);
  for (size_t p = 0; p < 6; ++p) EXPECT_FLOAT_EQ(back.pixels[p], float(3 * p + 1)) << p;
}

// A PNG written by libpng itself: `color` PNG_COLOR_TYPE_*, 8-bit rows of `row_bytes` from
// `pixel(x, y)` (a palette index or a grey value), optionally Adam7-interlaced.
void WritePngWith(const std::string& path, int w, int h, int color, bool interlaced,
                  const std::vector<png_color>& palette, int (*pixel)(int, int)) {
  FILE* fp = std::fopen(path.c_str(), "wb");
  ASSERT_NE(fp, nullptr);
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
  png_infop info = png_create_info_struct(png);
  png_init_io(png, fp);
  png_set_IHDR(png, info, w, h, 8, color, interlaced ? PNG_INTERLACE_ADAM7 : PNG_INTERLACE_NONE,
               PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
  if (!palette.empty()) png_set_PLTE(png, info, palette.data(), int(palette.size()));
  png_write_info(png, info);
  std::vector<png_byte> rows(size_t(w) * h);
  std::vector<png_bytep> ptr(h);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) rows[size_t(y) * w + x] = png_byte(pixel(x, y));
    ptr[y] = rows.data() + size_t(y) * w;
  }
  png_write_image(png, ptr.data());
  png_write_end(png, nullptr);
  png_destroy_write_struct(&png, &info);
  std::fclose(fp);
}

// Palette images come back as the mean of their colours' R, G and B; interlaced ones in order.
TEST(ImageIo, PalettedAndInterlacedPngsGiveTheirValues) {
  testing::TempDir dir;
  const int w = 13, h = 9;
  const std::vector<png_color> pal = {{0, 0, 0}, {30, 60, 90}, {255, 255, 0}};
  WritePngWith(dir / "pal.png", w, h, PNG_COLOR_TYPE_PALETTE, false, pal,
               [](int x, int y) { return (x + y) % 3; });
  const Image p = ReadImage(dir / "pal.png");
  EXPECT_FLOAT_EQ(p.at(0, 0), 0.f);
  EXPECT_FLOAT_EQ(p.at(1, 0), 60.f);
  EXPECT_FLOAT_EQ(p.at(1, 1), 170.f);
  WritePngWith(dir / "adam7.png", w, h, PNG_COLOR_TYPE_GRAY, true, {},
               [](int x, int y) { return 17 * y + x; });
  const Image a = ReadImage(dir / "adam7.png");
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) ASSERT_FLOAT_EQ(a.at(x, y), float(17 * y + x)) << x << ", " << y;
}

// libpng reports errors by longjmp: a truncated file must become an Error naming it, with no
// file left open and no crash; likewise a file whose name says PNG but whose bytes do not.
TEST(ImageIo, TruncatedAndMislabelledFilesAreRefusedByName) {
  testing::TempDir dir;
  Image ramp(64, 64);
  for (size_t i = 0; i < ramp.size(); ++i) ramp.pixels[i] = float(i % 4096);
  WriteUint16Image(dir / "r.png", ramp, "");
  WriteFloatImage(dir / "r.exr", ramp, "");
  WriteFloatImage(dir / "r.tif", ramp, "");
  for (const char* name : {"r.png", "r.exr", "r.tif"}) {
    std::ifstream in(dir / name, std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    const std::string cut =
        dir.Write(std::string("cut_") + name, bytes.substr(0, bytes.size() / 2));
    try {
      ReadImage(cut);
      ADD_FAILURE() << name << " was read";
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find("cut_" + std::string(name) + ": error:"),
                std::string::npos)
          << e.what();
    }
  }
  const std::string fake = dir.Write("fake.png", "GIF89a and more");
  try {
    ReadImage(fake);
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("not a TIFF, PNG or OpenEXR file"), std::string::npos);
  }
}

}  // namespace
}  // namespace raymatch
