// Raw buffer unpacking. The CSI-2 layouts are those of the MIPI CSI-2 specification as the
// Linux media documentation draws them (pixfmt-srggb10p, pixfmt-srggb12p): the high bits of each
// pixel come first, one byte per pixel, then a byte with the low bits of the group, pixel 0 in
// the least significant bits.
#include "raymatch/capture/unpack.h"

#include <regex>

#include "raymatch/core/error.h"

namespace raymatch::capture {

int64_t MinimumStride(RawPacking packing, int width) {
  const int64_t w = width;
  switch (packing) {
    case RawPacking::kRaw8:
      return w;
    case RawPacking::kRaw10Csi2:
      return (w + 3) / 4 * 5;
    case RawPacking::kRaw12Csi2:
      return (w + 1) / 2 * 3;
    case RawPacking::kRaw16Le:
      return 2 * w;
  }
  return 0;
}

Image UnpackRaw(std::span<const uint8_t> buffer, int width, int height, int64_t stride,
                RawPacking packing) {
  if (width <= 0 || height <= 0)
    throw Error("raw frame: size " + std::to_string(width) + " x " + std::to_string(height) +
                " (expected positive)");
  const int64_t min_stride = MinimumStride(packing, width);
  if (stride < min_stride)
    throw Error("raw frame: stride " + std::to_string(stride) + " bytes is below the " +
                std::to_string(min_stride) + " a row of " + std::to_string(width) +
                " pixels needs");
  const int64_t need = stride * (height - 1) + min_stride;
  if (int64_t(buffer.size()) < need)
    throw Error("raw frame: buffer of " + std::to_string(buffer.size()) + " bytes, " +
                std::to_string(need) + " expected for " + std::to_string(width) + " x " +
                std::to_string(height) + " pixels with stride " + std::to_string(stride));
  Image img(width, height);
  for (int y = 0; y < height; ++y) {
    const uint8_t* row = buffer.data() + stride * y;
    float* out = &img.pixels[size_t(y) * width];
    switch (packing) {
      case RawPacking::kRaw8:
        for (int x = 0; x < width; ++x) out[x] = row[x];
        break;
      case RawPacking::kRaw10Csi2:
        for (int x = 0; x < width; ++x) {
          const uint8_t* g = row + (x / 4) * 5;
          const int k = x % 4;
          out[x] = float((uint32_t(g[k]) << 2) | ((g[4] >> (2 * k)) & 0x3));
        }
        break;
      case RawPacking::kRaw12Csi2:
        for (int x = 0; x < width; ++x) {
          const uint8_t* g = row + (x / 2) * 3;
          const int k = x % 2;
          out[x] = float((uint32_t(g[k]) << 4) | ((g[2] >> (4 * k)) & 0xF));
        }
        break;
      case RawPacking::kRaw16Le:
        for (int x = 0; x < width; ++x)
          out[x] = float(uint32_t(row[2 * x]) | (uint32_t(row[2 * x + 1]) << 8));
        break;
    }
  }
  return img;
}

namespace {
// Colour names of the 2 x 2 cell positions (0,0), (1,0), (0,1), (1,1) for each order.
void CellNames(BayerOrder order, std::string names[4]) {
  const char* table[5][4] = {{"P00", "P10", "P01", "P11"},
                             {"R", "Gr", "Gb", "B"},
                             {"Gr", "R", "B", "Gb"},
                             {"Gb", "B", "R", "Gr"},
                             {"B", "Gb", "Gr", "R"}};
  for (int i = 0; i < 4; ++i) names[i] = table[int(order)][i];
}
}  // namespace

BayerPlanes SplitBayer(const Image& mosaic, BayerOrder order) {
  BayerPlanes b;
  const int w = mosaic.width / 2, h = mosaic.height / 2;
  CellNames(order, b.names);
  for (int i = 0; i < 4; ++i) {
    b.planes[i] = Image(w, h);
    const int dx = i % 2, dy = i / 2;
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) b.planes[i].at(x, y) = mosaic.at(2 * x + dx, 2 * y + dy);
  }
  return b;
}

Image BinBayer2x2(const Image& mosaic) {
  const int w = mosaic.width / 2, h = mosaic.height / 2;
  Image out(w, h);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x)
      out.at(x, y) = mosaic.at(2 * x, 2 * y) + mosaic.at(2 * x + 1, 2 * y) +
                     mosaic.at(2 * x, 2 * y + 1) + mosaic.at(2 * x + 1, 2 * y + 1);
  return out;
}

bool DescribeRawFormat(const std::string& name_in, RawPacking* packing, int* bits,
                       BayerOrder* order) {
  std::string name = name_in;
  while (!name.empty() && name.back() == ' ') name.pop_back();  // V4L2 fourcc "Y16 "
  BayerOrder o = BayerOrder::kNone;
  int b = 0;
  RawPacking p = RawPacking::kRaw16Le;
  // V4L2 fourccs of the usual raw formats.
  static const struct {
    const char* fourcc;
    BayerOrder order;
    int bits;
    RawPacking packing;
  } kV4l2[] = {
      {"GREY", BayerOrder::kNone, 8, RawPacking::kRaw8},
      {"Y10", BayerOrder::kNone, 10, RawPacking::kRaw16Le},
      {"Y12", BayerOrder::kNone, 12, RawPacking::kRaw16Le},
      {"Y16", BayerOrder::kNone, 16, RawPacking::kRaw16Le},
      {"Y10P", BayerOrder::kNone, 10, RawPacking::kRaw10Csi2},
      {"RGGB", BayerOrder::kRGGB, 8, RawPacking::kRaw8},
      {"GRBG", BayerOrder::kGRBG, 8, RawPacking::kRaw8},
      {"GBRG", BayerOrder::kGBRG, 8, RawPacking::kRaw8},
      {"BA81", BayerOrder::kBGGR, 8, RawPacking::kRaw8},
      {"RG10", BayerOrder::kRGGB, 10, RawPacking::kRaw16Le},
      {"BA10", BayerOrder::kGRBG, 10, RawPacking::kRaw16Le},
      {"GB10", BayerOrder::kGBRG, 10, RawPacking::kRaw16Le},
      {"BG10", BayerOrder::kBGGR, 10, RawPacking::kRaw16Le},
      {"RG12", BayerOrder::kRGGB, 12, RawPacking::kRaw16Le},
      {"BA12", BayerOrder::kGRBG, 12, RawPacking::kRaw16Le},
      {"GB12", BayerOrder::kGBRG, 12, RawPacking::kRaw16Le},
      {"BG12", BayerOrder::kBGGR, 12, RawPacking::kRaw16Le},
      {"pRAA", BayerOrder::kRGGB, 10, RawPacking::kRaw10Csi2},
      {"pgAA", BayerOrder::kGRBG, 10, RawPacking::kRaw10Csi2},
      {"pGAA", BayerOrder::kGBRG, 10, RawPacking::kRaw10Csi2},
      {"pBAA", BayerOrder::kBGGR, 10, RawPacking::kRaw10Csi2},
      {"pRCC", BayerOrder::kRGGB, 12, RawPacking::kRaw12Csi2},
      {"pgCC", BayerOrder::kGRBG, 12, RawPacking::kRaw12Csi2},
      {"pGCC", BayerOrder::kGBRG, 12, RawPacking::kRaw12Csi2},
      {"pBCC", BayerOrder::kBGGR, 12, RawPacking::kRaw12Csi2},
      {"RG16", BayerOrder::kRGGB, 16, RawPacking::kRaw16Le},
      {"GR16", BayerOrder::kGRBG, 16, RawPacking::kRaw16Le},
      {"GB16", BayerOrder::kGBRG, 16, RawPacking::kRaw16Le},
      {"BYR2", BayerOrder::kBGGR, 16, RawPacking::kRaw16Le},
  };
  for (const auto& f : kV4l2)
    if (name == f.fourcc) {
      if (packing) *packing = f.packing;
      if (bits) *bits = f.bits;
      if (order) *order = f.order;
      return true;
    }
  // libcamera names: S<order><bits>[_CSI2P] (Bayer) and R<bits>[_CSI2P] (mono).
  static const std::regex kLibcamera(R"((?:S(RGGB|GRBG|GBRG|BGGR)|R)(8|10|12|14|16)(_CSI2P)?)");
  std::smatch m;
  if (!std::regex_match(name, m, kLibcamera)) return false;
  if (m[1].matched) {
    const std::string s = m[1];
    o = s == "RGGB"   ? BayerOrder::kRGGB
        : s == "GRBG" ? BayerOrder::kGRBG
        : s == "GBRG" ? BayerOrder::kGBRG
                      : BayerOrder::kBGGR;
  }
  b = std::stoi(m[2]);
  const bool csi2 = m[3].matched;
  if (b == 8) {
    if (csi2) return false;
    p = RawPacking::kRaw8;
  } else if (csi2) {
    if (b == 10)
      p = RawPacking::kRaw10Csi2;
    else if (b == 12)
      p = RawPacking::kRaw12Csi2;
    else
      return false;  // RAW14 CSI-2 (4 in 7 bytes) is not supported
  } else {
    p = RawPacking::kRaw16Le;
  }
  if (packing) *packing = p;
  if (bits) *bits = b;
  if (order) *order = o;
  return true;
}

}  // namespace raymatch::capture
