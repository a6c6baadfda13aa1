#pragma once
// Image files: TIFF (libtiff), PNG (libpng) and OpenEXR. Writers are atomic: the file appears
// complete or not at all.
#include <cstdint>
#include <string>

#include "raymatch/core/image.h"

namespace raymatch {

/// What a file held before conversion to float.
struct ImageFileInfo {
  std::string format;      ///< "tiff", "png" or "openexr".
  std::string pixel_type;  ///< "uint8", "uint16", "float", ...
  int channels = 1;
  double type_max = 1.0;  ///< Largest code value of an integer type (255, 65535), 1 for float.
};

/// Limits on declared image sizes, checked before any pixel memory is allocated.
inline constexpr int64_t kMaxImageSide = 65536;
inline constexpr int64_t kMaxImagePixels = int64_t(1) << 28;  ///< 16384 x 16384

/// Throws Error naming `path` when a header's declared size is beyond the limits above or
/// larger than the file can hold (`compression` "none" or "": every byte stored).
void CheckDeclaredImageSize(const std::string& path, int64_t width, int64_t height,
                            int64_t channels, int64_t bytes_per_value,
                            const std::string& compression);

/// Reads the first channel (or the mean of RGB) as float in the file's own code values:
/// a 16-bit file gives 0..65535, an 8-bit file 0..255, a float file its stored values.
/// Integer pixels are read in their own type, so integer code values come back exactly.
/// Throws Error naming the file when it cannot be read or holds NaN/Inf.
Image ReadImage(const std::string& path, ImageFileInfo* info = nullptr);

/// Writes a 32-bit float single-channel image (uncompressed TIFF or ZIP-compressed EXR, by
/// extension). `description` goes to the TIFF's ImageDescription tag or the EXR's comments.
void WriteFloatImage(const std::string& path, const Image& img, const std::string& description);

/// Writes a 16-bit unsigned single-channel TIFF or PNG (camera-like data): values rounded and
/// clamped to [0, 65535]. `description` goes to ImageDescription (TIFF).
void WriteUint16Image(const std::string& path, const Image& img, const std::string& description);

/// Writes an 8-bit RGB PNG from interleaved rgb bytes (3 * width * height); atomic.
void WriteRgbPng(const std::string& path, int width, int height, const unsigned char* rgb);

/// Writes an 8-bit PNG preview: values mapped linearly from [lo, hi] to [0, 255].
void WritePngPreview(const std::string& path, const Image& img, double lo, double hi);

}  // namespace raymatch
