#pragma once
// Image similarity measures: MSE, PSNR, SSIM, MS-SSIM, CW-SSIM and noise-aware photon-count
// measures. All functions take two images of the same size (throw CompareError otherwise) and
// compute in double precision. The dynamic range L (the span of possible pixel values, e.g.
// 4095 for 12-bit data stored in 16-bit files) is always an explicit argument: nothing is
// guessed from the file type. See docs/compare.md for the exact algorithms.
#include <string>
#include <vector>

#include "raymatch/core/error.h"
#include "raymatch/core/image.h"

namespace raymatch::compare {

/// What kind of input failure happened; apps map it to an exit code (docs/compare.md).
enum class FailureKind {
  kInvalidInput,  ///< Bad options, NaN pixels, empty stacks, too small images.
  kSizeMismatch,  ///< The two images cannot be brought to the same size.
  kFileError,     ///< A file is missing, unreadable or unwritable.
};

/// A raymatch::Error that also says which kind of failure it is.
class CompareError : public raymatch::Error {
 public:
  CompareError(FailureKind kind, const std::string& message)
      : raymatch::Error(message), kind_(kind) {}
  CompareError(FailureKind kind, const FileLocation& where, const std::string& message)
      : raymatch::Error(where, message), kind_(kind) {}
  FailureKind kind() const { return kind_; }

 private:
  FailureKind kind_;
};

/// Throws CompareError(kSizeMismatch) unless a and b have the same non-zero size, and
/// CompareError(kInvalidInput) if either holds a NaN or infinite pixel. `what` names the pair.
void CheckComparable(const Image& a, const Image& b, const std::string& what = "images");

// ---------------------------------------------------------------------------------------------
// MSE / PSNR

/// Mean squared difference over all pixels, in (pixel value units)^2. 0 for identical images.
double MeanSquaredError(const Image& a, const Image& b);

/// 10 log10(L^2 / MSE) in dB. Identical images give +infinity mathematically; this returns
/// kPsnrCapDb (a finite cap, so that no output holds Inf/NaN) instead.
double PeakSignalToNoiseRatio(const Image& a, const Image& b, double data_range);
inline constexpr double kPsnrCapDb = 999.0;

// ---------------------------------------------------------------------------------------------
// SSIM (Wang et al. 2004) exactly as MATLAB's ssim() by default.

struct SsimOptions {
  double data_range = 0;  ///< L, required (> 0): C1 = (k1 L)^2, C2 = (k2 L)^2.
  double sigma = 1.5;     ///< Gaussian window sigma, pixels. Filter size 2*ceil(3 sigma)+1.
  double k1 = 0.01;       ///< Luminance constant.
  double k2 = 0.03;       ///< Contrast/structure constant.
  bool keep_map = false;  ///< Keep the per-pixel SSIM map in the result.
  void Validate() const;  ///< Throws CompareError(kInvalidInput) naming the bad field.
};

struct SsimResult {
  double ssim = 0;            ///< Mean of the SSIM map over all pixels ('same'-size map).
  double mean_luminance = 0;  ///< Mean of the luminance term l(x,y).
  double mean_cs = 0;         ///< Mean of the contrast-structure term cs(x,y).
  Image map;                  ///< Per-pixel SSIM (only when keep_map).
};

/// MATLAB ssim(): separable Gaussian window (sigma, 2*ceil(3 sigma)+1 taps, normalised to
/// sum 1), replicate padding, map the size of the image, mean over all pixels, exponents 1.
SsimResult Ssim(const Image& a, const Image& b, const SsimOptions& options);

// ---------------------------------------------------------------------------------------------
// MS-SSIM (Wang, Simoncelli, Bovik 2003) as MATLAB's multissim().

enum class MsSsimWeights {
  kMatlab,    ///< MATLAB multissim default: fspecial('gaussian',[1 M],1), i.e. Gaussian over
              ///< the scale index with sigma 1 centred on the middle scale, normalised.
  kWang2003,  ///< [0.0448 0.2856 0.3001 0.2363 0.1333] (first M taken), normalised to sum 1.
  kCustom,    ///< MsSsimOptions::custom_weights (normalised to sum 1, as MATLAB does).
};

/// "matlab", "wang2003" or "custom" (the names --ms-ssim-weights takes and the JSON records).
const char* MsSsimWeightsName(MsSsimWeights w);

struct MsSsimOptions {
  double data_range = 0;  ///< L, required (> 0).
  int num_scales = 0;     ///< Number of scales M; 0 = default: MaxMsSsimScales() - 1.
  MsSsimWeights weights = MsSsimWeights::kMatlab;
  std::vector<double> custom_weights;  ///< Used with kCustom; size must equal M.
  double sigma = 1.5;                  ///< Gaussian window sigma at every scale, pixels.
  double k1 = 0.01, k2 = 0.03;
  void Validate() const;
};

/// Values at one scale (scale 1 = full resolution; each next scale is 2x smaller).
struct MsSsimScale {
  int width = 0, height = 0;  ///< Image size at this scale, pixels.
  double weight = 0;          ///< Normalised exponent used for this scale.
  double cs = 0;              ///< Mean contrast-structure map at this scale (map clamped at 1).
  double ssim = 0;            ///< Mean SSIM map at this scale (clamped at 1; used at scale M).
};

struct MsSsimResult {
  double ms_ssim = 0;  ///< prod_{j<M} cs_j^w_j * ssim_M^w_M (see MsSsim()).
  int num_scales = 0;  ///< M actually used.
  int max_scales = 0;  ///< MaxMsSsimScales() for this image size.
  std::vector<MsSsimScale> scales;
};

/// The most scales MATLAB multissim accepts for this size: every scale but the last must be
/// at least 2 pixels in both directions (sizes go n -> ceil(n/2)), i.e.
/// ceil(log2(min(width, height))) + 1; 1 for a 1-pixel-wide image. The coarsest scales are
/// then tiny (1-2 pixels), which is why the paper's default is one scale fewer.
int MaxMsSsimScales(int width, int height);

/// The number of scales MsSsim() uses for this size: options.num_scales, or for 0 one below
/// MaxMsSsimScales() (the paper's choice), at least 1.
int MsSsimScalesFor(const MsSsimOptions& options, int width, int height);

/// The MS-SSIM weights for M scales (normalised to sum 1).
std::vector<double> MsSsimScaleWeights(MsSsimWeights kind, int num_scales,
                                       const std::vector<double>& custom = {});

/// Downsampling between scales, as multissim: imfilter(x, ones(2)/4, 'replicate') (the 2x2
/// mean of a pixel and its right/lower neighbours, the last row/column replicated), then
/// every second pixel starting with the first: output size ceil(n/2).
Image DownsampleByTwo(const Image& img);

/// MATLAB multissim(): at scales 1..M-1 the contrast-structure map
/// (2 cov + C2) / (var_x + var_y + C2), at scale M the full SSIM map, each with the SSIM
/// window and replicate padding, variances clamped at 0 and map values at 1; the score is the
/// product of the map means raised to their weights, a negative mean counting as 0 when its
/// weight is not an integer (so the result is real and finite). Throws
/// CompareError(kInvalidInput) for more scales than MaxMsSsimScales().
MsSsimResult MsSsim(const Image& a, const Image& b, const MsSsimOptions& options);

// ---------------------------------------------------------------------------------------------
// CW-SSIM (Sampat et al. 2009) as cwssim_index.m, on a complex steerable pyramid
// (Portilla-Simoncelli buildSCFpyr, built in the frequency domain).

struct CwSsimOptions {
  double data_range = 0;  ///< L, required (> 0); images are scaled by 255/L (see k).
  int level = 0;          ///< Pyramid level whose bands are compared (1 = finest);
                          ///< 0 = default: MaxCwSsimLevel() - 1 (one below the maximum).
  int orientations = 16;  ///< Number of oriented bands (cwssim_index's `or`), 1..16.
  int guard_band = 0;     ///< Pixels discarded at each border, in full-resolution pixels
                          ///< (divided by 2^(level-1) as in cwssim_index).
  double k = 0;           ///< Stabilising constant (cwssim_index's K; its default 0), in units
                          ///< of (coefficient of an image scaled to 0..255)^2, i.e. as for
                          ///< cwssim_index on 8-bit data. K = 0 makes CW-SSIM scale-invariant.
  int window = 7;         ///< Side of the square averaging window, pixels at the band.
  void Validate() const;
};

struct CwSsimResult {
  double cw_ssim = 0;                   ///< Mean over orientations of the band CW-SSIM values.
  int level = 0;                        ///< Level used.
  int max_level = 0;                    ///< MaxCwSsimLevel() for this image size.
  std::vector<double> per_orientation;  ///< Gaussian-weighted CW-SSIM of each band.
};

/// floor(log2(min(width, height))) - 2, as maxPyrHt() for buildSCFpyr; at least 1.
int MaxCwSsimLevel(int width, int height);

/// The level CwSsim() uses for this size: options.level, or for 0 one below MaxCwSsimLevel()
/// (the paper's choice), at least 1.
int CwSsimLevelFor(const CwSsimOptions& options, int width, int height);

/// CW-SSIM between two images: per orientation, the local index
/// (2 |sum c1 c2*| + K) / (sum |c1|^2 + |c2|^2 + K) over every window x window block lying
/// wholly inside the band (MATLAB filter2 'valid'), averaged with Gaussian weights
/// (sigma = band rows / 4, normalised); then the mean over orientations.
CwSsimResult CwSsim(const Image& a, const Image& b, const CwSsimOptions& options);

/// The complex bands of one pyramid level, for reuse when one image is compared with many.
struct CwSsimBands {
  int width = 0, height = 0;                ///< Band size after the guard band, pixels.
  int band_rows = 0;                        ///< Band rows before the guard band (sigma).
  std::vector<std::vector<double>> re, im;  ///< [orientation][row-major pixel].
};
/// Builds the bands that CwSsim() compares (after scaling by 255/L and cropping guard bands).
CwSsimBands ComputeCwSsimBands(const Image& img, const CwSsimOptions& options, int level);
/// CW-SSIM from precomputed bands (same options and level for both).
CwSsimResult CwSsimFromBands(const CwSsimBands& a, const CwSsimBands& b,
                             const CwSsimOptions& options, int level, int max_level);

// ---------------------------------------------------------------------------------------------
// Noise-aware measures for photon-count images (both images carry Poisson shot noise).
// Under the null hypothesis "both pixels are Poisson draws with the same mean", each of these
// has expectation close to 1 per pixel (for counts >~ 5); larger values mean a worse match.
// Negative values (possible after dark subtraction) are clamped to 0 and counted.

struct PoissonResult {
  double chi2_per_pixel = 0;      ///< mean over pixels of (a-b)^2/(a+b); pixels a+b=0 give 0.
  double deviance_per_pixel = 0;  ///< mean of 2[a ln(a/m) + b ln(b/m)], m=(a+b)/2 (0 ln 0 = 0).
  long clamped_pixels = 0;        ///< Pixels with a negative value in either image.
};
PoissonResult PoissonMeasures(const Image& counts_a, const Image& counts_b);

}  // namespace raymatch::compare
