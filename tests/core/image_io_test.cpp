#include "raymatch/core/image_io.h"

#include <gtest/gtest.h>

#include <filesystem>
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

}  // namespace
}  // namespace raymatch
