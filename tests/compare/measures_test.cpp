// Similarity measures: known answers, monotonic behaviour, and agreement with independent
// implementations (scikit-image; a NumPy/SciPy MATLAB-style reference).
#include "raymatch/compare/measures.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>

#include "raymatch/core/image_io.h"
#include "raymatch/core/rng.h"
#include "temp_dir.h"

namespace raymatch::compare {
namespace {

// A smooth test scene: a dark ring and a bright blob on a mid background, 0..1000.
Image Scene(int w = 96, int h = 80, double dx = 0) {
  Image img(w, h);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      const double r = std::hypot(x - 40 - dx, y - 38);
      img.at(x, y) = float(600 - 400 * std::exp(-std::pow((r - 18) / 4, 2)) +
                           300 * std::exp(-std::pow(std::hypot(x - 70 - dx, y - 20) / 6, 2)));
    }
  return img;
}

Image Noisy(const Image& a, double sigma, uint64_t seed) {
  Image b = a;
  for (size_t i = 0; i < b.size(); ++i) {
    RayRng r(seed, 0, i);
    b.pixels[i] +=
        float(sigma * std::sqrt(-2 * std::log(1 - r.Uniform())) * std::cos(2 * M_PI * r.Uniform()));
  }
  return b;
}

Image Poisson(const Image& mean, uint64_t seed) {
  std::mt19937_64 g(seed);
  Image out = mean;
  for (float& v : out.pixels) v = float(std::poisson_distribution<int>(v)(g));
  return out;
}

TEST(Measures, IdenticalImages) {
  const Image a = Scene();
  EXPECT_EQ(MeanSquaredError(a, a), 0.0);
  EXPECT_EQ(PeakSignalToNoiseRatio(a, a, 1000), kPsnrCapDb);
  SsimOptions so;
  so.data_range = 1000;
  EXPECT_NEAR(Ssim(a, a, so).ssim, 1.0, 1e-12);
  MsSsimOptions mo;
  mo.data_range = 1000;
  EXPECT_NEAR(MsSsim(a, a, mo).ms_ssim, 1.0, 1e-12);
  CwSsimOptions co;
  co.data_range = 1000;
  EXPECT_NEAR(CwSsim(a, a, co).cw_ssim, 1.0, 1e-12);
}

/// MSE, SSIM, MS-SSIM and CW-SSIM between a and b (L = 1000, defaults otherwise).
struct AllMeasures {
  double mse, ssim, ms_ssim, cw_ssim;
};
AllMeasures MeasureAll(const Image& a, const Image& b) {
  SsimOptions so;
  so.data_range = 1000;
  MsSsimOptions mo;
  mo.data_range = 1000;
  CwSsimOptions co;
  co.data_range = 1000;
  return {MeanSquaredError(a, b), Ssim(a, b, so).ssim, MsSsim(a, b, mo).ms_ssim,
          CwSsim(a, b, co).cw_ssim};
}

/// Every image in `worse` must be further from `a` than the one before it by every measure.
std::vector<AllMeasures> ExpectEveryMeasureWorsens(const Image& a,
                                                   const std::vector<Image>& worse) {
  std::vector<AllMeasures> all;
  AllMeasures prev{0, 1, 1, 1};
  for (size_t i = 0; i < worse.size(); ++i) {
    const AllMeasures m = MeasureAll(a, worse[i]);
    EXPECT_GT(m.mse, prev.mse) << "step " << i;
    EXPECT_LT(m.ssim, prev.ssim) << "step " << i;
    EXPECT_LT(m.ms_ssim, prev.ms_ssim) << "step " << i;
    EXPECT_LT(m.cw_ssim, prev.cw_ssim) << "step " << i;
    all.push_back(prev = m);
  }
  return all;
}

TEST(Measures, MoreNoiseIsWorseForEveryMeasure) {
  const Image a = Scene();
  const std::vector<double> sigmas = {5.0, 20.0, 60.0};
  std::vector<Image> noisy;
  for (double s : sigmas) noisy.push_back(Noisy(a, s, 3));
  const std::vector<AllMeasures> m = ExpectEveryMeasureWorsens(a, noisy);
  for (size_t i = 0; i < sigmas.size(); ++i)  // Gaussian noise: MSE = sigma^2 (+-10 % for 7680 px)
    EXPECT_NEAR(m[i].mse, sigmas[i] * sigmas[i], 0.1 * sigmas[i] * sigmas[i]);
}

// Defocus-like blur: a wider Gaussian blur of the same scene raises MSE and lowers every
// similarity (all structure is lost progressively; no noise, so the order is exact).
TEST(Measures, MoreBlurIsWorseForEveryMeasure) {
  const Image a = Scene();
  auto blur = [&](double sigma) {
    const int r = int(std::ceil(3 * sigma));
    std::vector<double> k(2 * r + 1);
    double ks = 0;
    for (int i = -r; i <= r; ++i) ks += k[i + r] = std::exp(-i * i / (2 * sigma * sigma));
    Image tmp = a, out = a;
    for (int pass = 0; pass < 2; ++pass) {  // rows, then columns; replicate at the edges
      const Image& src = pass == 0 ? a : tmp;
      Image& dst = pass == 0 ? tmp : out;
      for (int y = 0; y < a.height; ++y)
        for (int x = 0; x < a.width; ++x) {
          double s = 0;
          for (int i = -r; i <= r; ++i) {
            const int xx = std::clamp(pass == 0 ? x + i : x, 0, a.width - 1);
            const int yy = std::clamp(pass == 1 ? y + i : y, 0, a.height - 1);
            s += k[i + r] * src.at(xx, yy);
          }
          dst.at(x, y) = float(s / ks);
        }
    }
    return out;
  };
  ExpectEveryMeasureWorsens(a, {blur(1.0), blur(2.0), blur(4.0)});
}

// CW-SSIM is designed to tolerate small translations (Sampat 2009): a 1-pixel shift costs it
// much less than it costs SSIM.
TEST(Measures, CwSsimToleratesSmallShifts) {
  const Image a = Scene(), b = Scene(96, 80, 1.0);
  SsimOptions so;
  so.data_range = 1000;
  CwSsimOptions co;
  co.data_range = 1000;
  const double ssim_loss = 1 - Ssim(a, b, so).ssim, cw_loss = 1 - CwSsim(a, b, co).cw_ssim;
  EXPECT_LT(cw_loss, 0.5 * ssim_loss) << "SSIM loss " << ssim_loss << ", CW-SSIM loss " << cw_loss;
}

// Two independent Poisson images with the same mean: E[(a-b)^2/(a+b)] = 1 per pixel for large
// counts (mean 500 here; the bias is O(1/mean)); the estimate over 7680 px has sd ~ sqrt(2/7680).
TEST(Measures, PoissonChiSquareIsOneForMatchingShotNoise) {
  const Image mean = Scene();
  const PoissonResult r = PoissonMeasures(Poisson(mean, 1), Poisson(mean, 2));
  EXPECT_NEAR(r.chi2_per_pixel, 1.0, 5 * std::sqrt(2.0 / 7680));
  EXPECT_NEAR(r.deviance_per_pixel, 1.0, 5 * std::sqrt(2.0 / 7680) + 0.01);
  Image brighter = mean;
  for (float& v : brighter.pixels) v *= 1.1f;
  EXPECT_GT(PoissonMeasures(Poisson(mean, 1), Poisson(brighter, 2)).chi2_per_pixel, 2.0);
}

TEST(Measures, BadInputsAreClearErrors) {
  const Image a = Scene();
  try {
    MeanSquaredError(a, Scene(90, 80));
    FAIL();
  } catch (const CompareError& e) {
    EXPECT_EQ(e.kind(), FailureKind::kSizeMismatch);
  }
  Image n = a;
  n.pixels[5] = std::nanf("");
  try {
    MeanSquaredError(a, n);
    FAIL();
  } catch (const CompareError& e) {
    EXPECT_EQ(e.kind(), FailureKind::kInvalidInput);
  }
  SsimOptions so;  // data_range missing
  EXPECT_THROW(Ssim(a, a, so), CompareError);
}

/// Mean of a map without `border` pixels at each edge (what scikit-image and IPOL average).
double InteriorMean(const Image& map, int border) {
  double sum = 0;
  int n = 0;
  for (int y = border; y < map.height - border; ++y)
    for (int x = border; x < map.width - border; ++x) sum += map.at(x, y), ++n;
  return sum / n;
}

/// Runs a Python reference script and reads the numbers it prints (one line).
std::vector<double> RunReference(const std::string& script, const std::string& args) {
  const std::string cmd = "/usr/bin/python3 " + std::string(RAYMATCH_SOURCE_DIR) +
                          "/tests/compare/" + script + " " + args;
  FILE* p = popen(cmd.c_str(), "r");
  std::vector<double> out;
  if (!p) return out;
  double v = 0;
  while (std::fscanf(p, "%lf", &v) == 1) out.push_back(v);
  pclose(p);
  return out;
}

// Against independent implementations, to 1e-6 (both compute in double; float inputs).
TEST(Measures, AgreesWithScikitImageAndMatlabStyleReference) {
  if (std::system("/usr/bin/python3 -c 'import skimage, scipy, tifffile' 2>/dev/null") != 0)
    GTEST_SKIP() << "python3-skimage not installed";
  testing::TempDir dir;
  int pair = 0;
  struct Pair {
    int w, h;
    double noise;
  };
  for (const Pair& c : {Pair{96, 80, 10.0}, Pair{96, 80, 80.0}, Pair{97, 83, 30.0}}) {
    const double noise = c.noise;
    const Image a = Scene(c.w, c.h), b = Noisy(Scene(c.w, c.h, 0.7), noise, 7 + pair);
    WriteFloatImage(dir / "a.tif", a, "");
    WriteFloatImage(dir / "b.tif", b, "");
    const double L = 1000;
    MsSsimOptions mo;
    mo.data_range = L;
    const MsSsimResult ms = MsSsim(a, b, mo);
    const std::vector<double> ref =
        RunReference("reference_ssim.py", (dir / "a.tif") + " " + (dir / "b.tif") + " 1000 " +
                                              std::to_string(ms.num_scales));
    ASSERT_EQ(ref.size(), 3u);
    const double sk = ref[0], matlab = ref[1], msref = ref[2];
    SsimOptions so;
    so.data_range = L;
    so.keep_map = true;
    const SsimResult s = Ssim(a, b, so);
    SCOPED_TRACE(::testing::Message() << c.w << "x" << c.h << ", noise " << noise << ", "
                                      << ms.num_scales << " MS-SSIM scales");
    EXPECT_NEAR(InteriorMean(s.map, 5), sk, 1e-6);  // map stored as float: ~1e-7
    EXPECT_NEAR(s.ssim, matlab, 1e-6);
    EXPECT_NEAR(ms.ms_ssim, msref, 1e-6);
    ++pair;
  }
}

// Against MATLAB itself: multissim values from MATLAB R2025b for a deterministic pair,
// [X,Y] = meshgrid(1:32,1:32), A = uint8(X+Y), B = uint8(X+2*Y), multissim(A,B,...), as recorded
// in the public regression test libs/image/tests/multissim_test.cpp of hotredman/numkit
// (commit 065b2c2). MATLAB computes double inputs in double: A/255, B/255 with L = 1 gave
// 0.8983752005 (10 digits printed), which raymatch must match to 1e-9. uint8 inputs are
// computed in single precision (relative rounding 6e-8 per operation, summed over 11x11
// windows and 1024 pixels), which moves the printed values by up to ~3e-7 from the exact
// double result: 1e-6 for those.
TEST(Measures, MsSsimMatchesMatlabMultissim) {
  Image a(32, 32), b(32, 32);
  for (int y = 0; y < 32; ++y)
    for (int x = 0; x < 32; ++x) {
      a.at(x, y) = float((x + 1) + (y + 1));      // X + Y, X the column index
      b.at(x, y) = float((x + 1) + 2 * (y + 1));  // X + 2Y
    }
  EXPECT_EQ(MaxMsSsimScales(32, 32), 6);  // multissim accepts 'NumScales' up to 6 here
  auto run = [&](int scales, double range, double sigma, MsSsimWeights weights) {
    MsSsimOptions o;
    o.data_range = range;
    o.num_scales = scales;
    o.sigma = sigma;
    o.weights = weights;
    return MsSsim(a, b, o).ms_ssim;
  };
  const auto kGauss = MsSsimWeights::kMatlab;
  EXPECT_NEAR(run(5, 255, 1.5, kGauss), 0.8983752005, 1e-9);  // double inputs A/255, B/255
  EXPECT_NEAR(run(5, 255, 1.5, kGauss), 0.8983750939, 1e-6);  // uint8 (single precision)
  EXPECT_NEAR(run(1, 255, 1.5, kGauss), 0.8935790062, 1e-6);  // 'NumScales', 1
  EXPECT_NEAR(run(3, 255, 1.5, kGauss), 0.9119560719, 1e-6);  // 'NumScales', 3
  EXPECT_NEAR(run(5, 255, 1.5, MsSsimWeights::kWang2003), 0.8920533657, 1e-6);
  EXPECT_NEAR(run(5, 255, 0.5, kGauss), 0.9531264305, 1e-6);  // 'Sigma', 0.5
  EXPECT_NEAR(run(5, 128, 1.5, kGauss), 0.8723636866, 1e-6);  // 'DynamicRange', 128
  EXPECT_NO_THROW(run(6, 255, 1.5, kGauss));
  EXPECT_THROW(run(7, 255, 1.5, kGauss), CompareError);  // multissim: "too many scales"
  EXPECT_THROW(run(20, 255, 1.5, kGauss), CompareError);
}

// CW-SSIM against tests/compare/reference_cwssim.py, an independent implementation organised
// like Sampat's cwssim_index.m and matlabPyrTools (lookup-table masks, fftshift grids,
// filter2 'valid', fspecial weights). Pairs: noise, a sub-pixel shift, a rotation and a
// brightness change; sizes even and odd (the spectrum's centre and crops differ); levels 1 to
// the maximum; odd and even filter orders; K = 0 and 0.01; a guard band. Tolerance 1e-6: the
// reference interpolates its masks in tables (~1e-5 on a mask), raymatch uses closed forms.
TEST(Measures, CwSsimAgreesWithIndependentReference) {
  if (std::system("/usr/bin/python3 -c 'import numpy, scipy, tifffile' 2>/dev/null") != 0)
    GTEST_SKIP() << "python3-scipy/tifffile not installed";
  testing::TempDir dir;
  struct Case {
    int w, h;
    double shift, noise, gain, angle_deg;
    int level, orientations, guard;
    double k;
  };
  const Case cases[] = {
      {96, 80, 0.7, 10, 1.0, 0, 0, 16, 0, 0.0},    // default level (2 of max 3)
      {96, 80, 0.0, 80, 1.0, 0, 1, 8, 0, 0.01},    // finest level, K scaled by 255/L
      {97, 83, 1.3, 20, 1.0, 0, 3, 5, 0, 0.0},     // odd size, odd orientation count, max level
      {128, 128, 0.0, 15, 1.0, 4, 2, 16, 8, 0.0},  // rotation, guard band
      {75, 101, 0.0, 5, 1.2, 0, 1, 4, 0, 0.01},    // brightness change, odd sizes
  };
  for (const Case& c : cases) {
    Image a = Scene(c.w, c.h), b(c.w, c.h);
    const double ca = std::cos(c.angle_deg * M_PI / 180), sa = std::sin(c.angle_deg * M_PI / 180);
    const Image shifted = Scene(c.w, c.h, c.shift);
    for (int y = 0; y < c.h; ++y)
      for (int x = 0; x < c.w; ++x) {
        // Rotation about the ring centre (40, 38), sampled from the analytic scene.
        const double u = x - 40, v = y - 38;
        const double xs = 40 + ca * u - sa * v, ys = 38 + sa * u + ca * v;
        const double r = std::hypot(xs - 40 - c.shift, ys - 38);
        b.at(x, y) = float(
            c.gain * (600 - 400 * std::exp(-std::pow((r - 18) / 4, 2)) +
                      300 * std::exp(-std::pow(std::hypot(xs - 70 - c.shift, ys - 20) / 6, 2))));
      }
    if (c.angle_deg == 0 && c.gain == 1.0) b = shifted;
    b = Noisy(b, c.noise, 11);
    WriteFloatImage(dir / "a.tif", a, "");
    WriteFloatImage(dir / "b.tif", b, "");
    CwSsimOptions co;
    co.data_range = 1000;
    co.level = c.level;
    co.orientations = c.orientations;
    co.guard_band = c.guard;
    co.k = c.k;
    const CwSsimResult r = CwSsim(a, b, co);
    char args[256];
    std::snprintf(args, sizeof args, "%s %s 1000 %d %d %.17g %d", (dir / "a.tif").c_str(),
                  (dir / "b.tif").c_str(), r.level, c.orientations, c.k, c.guard);
    const std::vector<double> ref = RunReference("reference_cwssim.py", args);
    ASSERT_EQ(ref.size(), size_t(c.orientations) + 1) << args;
    SCOPED_TRACE(::testing::Message()
                 << c.w << "x" << c.h << " level " << r.level << " of " << r.max_level << ", "
                 << c.orientations << " orientations, K " << c.k << ", guard " << c.guard);
    EXPECT_NEAR(r.cw_ssim, ref[0], 1e-6);
    EXPECT_LT(r.cw_ssim, 1.0);
    for (int k = 0; k < c.orientations; ++k)
      EXPECT_NEAR(r.per_orientation[k], ref[k + 1], 1e-6) << "orientation " << k;
  }
}

// Against a published value: the IPOL reference implementation's mean SSIM for scikit-image's
// camera image and its noisy copy (tests/compare/published_ssim_images.py has the provenance).
// IPOL averages the valid interior (5 pixels cropped at each border), where raymatch's
// replicate padding plays no part; the 8-bit inputs are exact, so only IPOL's single-precision
// arithmetic separates the two: 1e-4 (we see 5e-6).
TEST(Measures, SsimMatchesThePublishedIpolValue) {
  if (std::system("/usr/bin/python3 -c 'import skimage, tifffile' 2>/dev/null") != 0)
    GTEST_SKIP() << "python3-skimage not installed";
  testing::TempDir dir;
  const std::string cmd = "/usr/bin/python3 " + std::string(RAYMATCH_SOURCE_DIR) +
                          "/tests/compare/published_ssim_images.py " + dir.path().string();
  ASSERT_EQ(std::system(cmd.c_str()), 0);
  const Image a = ReadImage(dir / "camera.tif"), b = ReadImage(dir / "camera_noisy.tif");
  ASSERT_EQ(a.width, 512);
  SsimOptions so;
  so.data_range = 255;
  so.keep_map = true;
  const SsimResult s = Ssim(a, b, so);
  EXPECT_NEAR(InteriorMean(s.map, 5), 0.357959091663361, 1e-4);
}

}  // namespace
}  // namespace raymatch::compare
