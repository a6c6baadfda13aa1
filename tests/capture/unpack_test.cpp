// Pixel-format unpacking against hand-made buffers (issue 12). Each buffer is built by hand from
// the CSI-2 layout (high bits first, then the low-bit byte, pixel 0 in the least significant
// bits), not by the code under test.
#include "raymatch/capture/unpack.h"

#include <gtest/gtest.h>

#include <vector>

#include "raymatch/core/error.h"

namespace raymatch::capture {
namespace {

std::vector<float> Row(const Image& img, int y) {
  return std::vector<float>(img.pixels.begin() + size_t(y) * img.width,
                            img.pixels.begin() + size_t(y + 1) * img.width);
}

TEST(Unpack, Raw10Csi2OneGroup) {
  // Pixels 0x3FF, 0x000, 0x155, 0x2AA: high bytes FF 00 55 AA; low bits 11, 00, 01, 10
  // -> byte 4 = 10 01 00 11 (pixel 3 .. pixel 0) = 0x93.
  const std::vector<uint8_t> buf = {0xFF, 0x00, 0x55, 0xAA, 0x93};
  const Image img = UnpackRaw(buf, 4, 1, 5, RawPacking::kRaw10Csi2);
  EXPECT_EQ(Row(img, 0), (std::vector<float>{1023, 0, 341, 682}));
}

TEST(Unpack, Raw10Csi2StrideAndPartialGroup) {
  // 6 pixels per row: one full group + a partial one (2 pixels in 5 bytes), row padded to 12.
  // Row 0: 1, 2, 3, 4 | 1020, 513. Row 1: all 512 (high byte 0x80, low bits 0).
  std::vector<uint8_t> buf(24, 0xEE);  // padding bytes must be ignored
  // pixel v -> high = v >> 2, low = v & 3
  const int v0[6] = {1, 2, 3, 4, 1020, 513};
  for (int g = 0; g < 2; ++g) {
    uint8_t low = 0;
    for (int k = 0; k < 4; ++k) {
      const int x = 4 * g + k;
      const int v = x < 6 ? v0[x] : 0;
      buf[5 * g + k] = uint8_t(v >> 2);
      low |= uint8_t((v & 3) << (2 * k));
    }
    buf[5 * g + 4] = low;
  }
  for (int k = 0; k < 10; ++k) buf[12 + k] = (k % 5 == 4) ? 0x00 : 0x80;
  const Image img = UnpackRaw(buf, 6, 2, 12, RawPacking::kRaw10Csi2);
  EXPECT_EQ(Row(img, 0), (std::vector<float>{1, 2, 3, 4, 1020, 513}));
  EXPECT_EQ(Row(img, 1), (std::vector<float>(6, 512)));
}

TEST(Unpack, Raw12Csi2) {
  // 0xABC, 0x123: high bytes AB 12; low nibbles C (pixel 0) and 3 (pixel 1) -> 0x3C.
  // 0xFFF, 0x000: FF 00 0F.
  const std::vector<uint8_t> buf = {0xAB, 0x12, 0x3C, 0xFF, 0x00, 0x0F};
  const Image img = UnpackRaw(buf, 4, 1, 6, RawPacking::kRaw12Csi2);
  EXPECT_EQ(Row(img, 0), (std::vector<float>{0xABC, 0x123, 4095, 0}));
}

TEST(Unpack, Raw16LittleEndian) {
  const std::vector<uint8_t> buf = {0x34, 0x12, 0xFF, 0x0F, 0x00, 0x00, 0xFF, 0xFF};
  const Image img = UnpackRaw(buf, 2, 2, 4, RawPacking::kRaw16Le);
  EXPECT_EQ(Row(img, 0), (std::vector<float>{0x1234, 0x0FFF}));
  EXPECT_EQ(Row(img, 1), (std::vector<float>{0, 65535}));
}

TEST(Unpack, Raw8) {
  const std::vector<uint8_t> buf = {0, 7, 255, 9, 1, 2};
  const Image img = UnpackRaw(buf, 2, 2, 3, RawPacking::kRaw8);
  EXPECT_EQ(Row(img, 0), (std::vector<float>{0, 7}));
  EXPECT_EQ(Row(img, 1), (std::vector<float>{9, 1}));
}

TEST(Unpack, RejectsShortBuffersAndStrides) {
  const std::vector<uint8_t> buf(9);
  EXPECT_THROW(UnpackRaw(buf, 4, 2, 5, RawPacking::kRaw10Csi2), Error);  // needs 10 bytes
  EXPECT_THROW(UnpackRaw(buf, 4, 1, 4, RawPacking::kRaw10Csi2), Error);  // stride < 5
  EXPECT_THROW(UnpackRaw(buf, 0, 1, 4, RawPacking::kRaw8), Error);
  EXPECT_EQ(MinimumStride(RawPacking::kRaw10Csi2, 6), 10);
  EXPECT_EQ(MinimumStride(RawPacking::kRaw12Csi2, 3), 6);
}

TEST(Bayer, SplitKeepsChannelsSeparate) {
  // RGGB 4 x 2 mosaic: R = 10+x, Gr = 20+x, Gb = 30+x, B = 40+x (x = cell column).
  Image m(4, 2);
  for (int cx = 0; cx < 2; ++cx) {
    m.at(2 * cx, 0) = 10 + cx;
    m.at(2 * cx + 1, 0) = 20 + cx;
    m.at(2 * cx, 1) = 30 + cx;
    m.at(2 * cx + 1, 1) = 40 + cx;
  }
  const BayerPlanes b = SplitBayer(m, BayerOrder::kRGGB);
  EXPECT_EQ(b.names[0], "R");
  EXPECT_EQ(b.names[3], "B");
  for (int i = 0; i < 4; ++i) {
    ASSERT_EQ(b.planes[i].width, 2);
    ASSERT_EQ(b.planes[i].height, 1);
    EXPECT_EQ(b.planes[i].at(0, 0), 10 * (i + 1));
    EXPECT_EQ(b.planes[i].at(1, 0), 10 * (i + 1) + 1);
  }
  EXPECT_EQ(SplitBayer(m, BayerOrder::kBGGR).names[0], "B");
  EXPECT_EQ(SplitBayer(m, BayerOrder::kGRBG).names[1], "R");
}

TEST(Bayer, BinSumsCellsAndDropsOddEdge) {
  Image m(5, 3, 1.0f);
  m.at(0, 0) = 4;
  const Image b = BinBayer2x2(m);
  ASSERT_EQ(b.width, 2);
  ASSERT_EQ(b.height, 1);
  EXPECT_EQ(b.at(0, 0), 7);
  EXPECT_EQ(b.at(1, 0), 4);
}

TEST(Formats, LibcameraAndV4l2Names) {
  RawPacking p;
  int bits = 0;
  BayerOrder o;
  ASSERT_TRUE(DescribeRawFormat("SRGGB10_CSI2P", &p, &bits, &o));
  EXPECT_EQ(p, RawPacking::kRaw10Csi2);
  EXPECT_EQ(bits, 10);
  EXPECT_EQ(o, BayerOrder::kRGGB);
  ASSERT_TRUE(DescribeRawFormat("R12_CSI2P", &p, &bits, &o));
  EXPECT_EQ(p, RawPacking::kRaw12Csi2);
  EXPECT_EQ(o, BayerOrder::kNone);
  ASSERT_TRUE(DescribeRawFormat("SBGGR16", &p, &bits, &o));
  EXPECT_EQ(p, RawPacking::kRaw16Le);
  EXPECT_EQ(bits, 16);
  ASSERT_TRUE(DescribeRawFormat("Y16 ", &p, &bits, &o));  // V4L2 fourcc with its space
  EXPECT_EQ(bits, 16);
  ASSERT_TRUE(DescribeRawFormat("pRCC", &p, &bits, &o));
  EXPECT_EQ(p, RawPacking::kRaw12Csi2);
  ASSERT_TRUE(DescribeRawFormat("R8", &p, &bits, &o));
  EXPECT_EQ(p, RawPacking::kRaw8);
  EXPECT_FALSE(DescribeRawFormat("YUYV", &p, &bits, &o));
  EXPECT_FALSE(DescribeRawFormat("MJPG", &p, &bits, &o));
  EXPECT_FALSE(DescribeRawFormat("SRGGB14_CSI2P", &p, &bits, &o));  // not supported
}

}  // namespace
}  // namespace raymatch::capture
