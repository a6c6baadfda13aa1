#pragma once
// Raw sensor buffers -> code values. Pure functions on byte buffers, shared by the libcamera and
// V4L2 backends and tested against hand-made buffers (tests/capture/unpack_test.cpp).
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "raymatch/core/image.h"

namespace raymatch::capture {

/// How code values are laid out in a row of the buffer.
enum class RawPacking {
  kRaw8,       ///< one byte per pixel
  kRaw10Csi2,  ///< MIPI CSI-2 RAW10: 4 pixels in 5 bytes (4 high bytes, then 4 x 2 low bits)
  kRaw12Csi2,  ///< MIPI CSI-2 RAW12: 2 pixels in 3 bytes (2 high bytes, then 2 x 4 low bits)
  kRaw16Le,    ///< 16-bit little-endian words, value in the low bits (V4L2 Y16/Y10/Y12, BYR2)
};

/// Colour-filter mosaic of a raw format: the colours of the top-left 2 x 2 cell, row by row.
enum class BayerOrder { kNone, kRGGB, kGRBG, kGBRG, kBGGR };

/// Bytes a row of `width` pixels needs at least (a buffer's stride may be larger).
int64_t MinimumStride(RawPacking packing, int width);

/// Unpacks `height` rows of `width` pixels, each row starting `stride` bytes after the previous,
/// into code values (0 .. 2^bits - 1, as float holding integers). Throws Error when the buffer
/// is too small for the geometry or the stride is below MinimumStride.
Image UnpackRaw(std::span<const uint8_t> buffer, int width, int height, int64_t stride,
                RawPacking packing);

/// The four colour planes of a Bayer mosaic, each (width/2) x (height/2): planes[0..3] are the
/// pixels at (0,0), (1,0), (0,1), (1,1) of every 2 x 2 cell; `names` says their colours for
/// `order` (e.g. RGGB: "R", "Gr", "Gb", "B"). Odd trailing rows/columns are dropped.
struct BayerPlanes {
  Image planes[4];
  std::string names[4];
};
BayerPlanes SplitBayer(const Image& mosaic, BayerOrder order);

/// 2 x 2 sums of a mosaic: a mono image at half the resolution whose values are the photons of
/// all four colours (saturation at 4 x (2^bits - 1)). Odd trailing rows/columns are dropped.
Image BinBayer2x2(const Image& mosaic);

/// Packing, bit depth and mosaic of a fourcc-style format name ("SRGGB10_CSI2P", "R12_CSI2P",
/// "Y16", "SBGGR12", "R8", ...: libcamera and V4L2 names). Returns false for formats that are
/// not raw (YUYV, MJPG, RGB888, ...).
bool DescribeRawFormat(const std::string& name, RawPacking* packing, int* bits, BayerOrder* order);

}  // namespace raymatch::capture
