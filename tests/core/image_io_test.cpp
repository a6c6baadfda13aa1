#include "raymatch/core/image_io.h"

#include <gtest/gtest.h>

#include <filesystem>

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

}  // namespace
}  // namespace raymatch
