// The exact wave image of a sphere (optics = "mie"): known answers of the model's physics.
#include "raymatch/simulate/wave_image.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "raymatch/core/error.h"
#include "raymatch/simulate/mie.h"
#include "raymatch/simulate/tracer.h"
#include "test_scenes.h"

namespace raymatch::simulate {
namespace {

using testing::MicroscopeScene;
using testing::SphereObject;

/// The paper's microscope at 462 nm with a water-like sphere, a cone of `cone_deg`, 0.5 um
/// object pixels, 1000 photons per pixel.
Scene WaveScene(double radius, double n, double cone_deg, int pixels = 64) {
  Scene s = MicroscopeScene();
  s.camera.nx = s.camera.ny = pixels;
  s.camera.pixel_pitch_um = 10;  // 0.5 um at the object
  s.source.type = SourceType::kCone;
  s.source.half_angle_deg = cone_deg;
  s.objects = {SphereObject(radius, n)};
  s.trace.photons_per_pixel = 1000;
  s.trace.optics = ImageOptics::kMie;
  return s;
}

// A sphere of the medium's index scatters nothing (every a_n, b_n = 0): the image is the flat
// field, exactly photons_per_pixel in every pixel, as the ray model's flat field is on average.
TEST(WaveImage, FlatFieldIsExactlyThePhotonTarget) {
  for (double cone : {0.0, 10.0, 30.0}) {  // 30 deg: partly beyond the NA (24.8 deg)
    Scene s = WaveScene(5, 1.0, cone, 32);
    if (cone == 0) s.source.type = SourceType::kCollimated;
    const Image img = MieImager(s).Expected(3.0, 2);
    for (float v : img.pixels) ASSERT_NEAR(v, 1000.0, 1e-9 * 1000) << "cone " << cone;
  }
}

// The optical theorem at the camera: one plane wave along the axis (unit flux density) loses,
// summed over the image, the sphere's extinction cross section and gains back what it scatters
// into the objective's NA: sum_pixels (I - I_flat) / I_flat x pixel area = -C_ext + C_sca,NA
// with C_ext = Q_ext pi a^2 (Bohren and Huffman eq. 4.76) and
// C_sca,NA = 2 pi / k^2 integral_0^theta_NA (|S1|^2 + |S2|^2) / 2 sin(theta) d theta (an
// integral the image never computes: the image sums a Fourier grid of plane waves). This
// tests the angular-spectrum factor 1 / (-2 pi i k cos theta) and its phase: a wrong phase
// gives a wrong extinction, a wrong magnitude a wrong scattered power.
/// Checks that theorem for the collimated scene `s` (0.5 um pixels, 1000 photons per pixel, a
/// 60 um margin) whose scatterer has coefficients `c` and outer radius `radius`.
void ExpectExtinctionLessLightScatteredIntoTheNa(const Scene& s, const MieCoefficients& c,
                                                 double radius) {
  const MieImager imager(s);
  for (double defocus : {0.0, 6.0}) {
    const Image img = imager.Expected(defocus, 2);
    const double pix = 0.5;
    double removed = 0;
    for (float v : img.pixels) removed += (v / 1000.0 - 1) * pix * pix;
    const double k = 2 * M_PI / s.wavelength_um;
    const double c_ext = Efficiencies(c).q_ext * M_PI * radius * radius;
    const double t_na = std::asin(0.42);
    const int steps = 20000;
    double sca = 0;
    for (int i = 0; i <= steps; ++i) {  // Simpson
      const double t = t_na * i / steps;
      const MieAmplitudes a = Amplitudes(c, t);
      sca += (std::norm(a.s1) + std::norm(a.s2)) / 2 * std::sin(t) *
             (i == 0 || i == steps ? 1 : (i % 2 ? 4 : 2));
    }
    const double c_sca_na = 2 * M_PI / (k * k) * sca * t_na / steps / 3;
    SCOPED_TRACE("defocus " + std::to_string(defocus));
    // The sensor (60 um from the sphere to its edge) misses the diffraction tails of the NA's
    // sharp edge beyond it: for a circular pupil 1 - encircled energy ~ 2 / (pi v) at
    // v = k NA R (Born and Wolf sec. 8.5.2), 0.19 % of C_sca,NA here; plus 0.2 % of C_ext for
    // the discrete pupil (its edge cells are averaged over their Fourier cell, which takes the
    // sharp edge's far tails out of the window).
    const double tails = 2 / (M_PI * k * 0.42 * 60.0) * c_sca_na;
    EXPECT_NEAR(removed, -c_ext + c_sca_na, tails + 2e-3 * c_ext)
        << "C_ext " << c_ext << " C_sca,NA " << c_sca_na;
  }
}

TEST(WaveImage, LightRemovedIsExtinctionMinusLightScatteredIntoTheNa) {
  for (double n : {1.2, 1.45}) {
    SCOPED_TRACE("n = " + std::to_string(n));
    Scene s = WaveScene(2.0, n, 0, 240);
    s.source.type = SourceType::kCollimated;
    s.trace.mie.margin_um = 60;
    const double k = 2 * M_PI / s.wavelength_um;
    ExpectExtinctionLessLightScatteredIntoTheNa(s, ComputeMie({n, 0}, k * 2.0), 2.0);
  }
}

// The same for coated spheres (two concentric spheres in the scene, the core listed first or
// second): a 2 um drop of index 1.45 with a 0.6 um bubble, and a 2 um shell of 1.2 on a 1.2 um
// core of 1.6 with absorption 0.01; their coefficients from Yang's recursion (tested against
// published values in mie_test.cpp). Measured: 0.08 and 0.06 % of C_ext off. A bubble of half
// the drop's radius scatters more light to the pupil's edge and beyond the sensor than this
// tolerance's model allows for (0.36 % off at focus; 0.27 % with a sensor twice as wide).
TEST(WaveImage, CoatedSphereRemovesItsExtinctionLessWhatItScattersIntoTheNa) {
  const struct {
    double r_core, n_core, k_core, n_shell;
    bool core_first;
  } kCases[] = {{0.6, 1.0, 0, 1.45, false}, {1.2, 1.6, 0.01, 1.2, true}};
  for (const auto& c : kCases) {
    SCOPED_TRACE("core " + std::to_string(c.r_core) + " um of " + std::to_string(c.n_core));
    Scene s = WaveScene(2.0, c.n_shell, 0, 240);
    s.source.type = SourceType::kCollimated;
    s.trace.mie.margin_um = 60;
    ObjectSpec core = SphereObject(c.r_core, c.n_core);
    core.absorption_index = c.k_core;
    s.objects.insert(c.core_first ? s.objects.begin() : s.objects.end(), core);
    const double k = 2 * M_PI / s.wavelength_um;
    ExpectExtinctionLessLightScatteredIntoTheNa(
        s, ComputeCoatedMie({c.n_core, c.k_core}, k * c.r_core, {c.n_shell, 0}, k * 2.0), 2.0);
  }
}

// A coated sphere whose shell has the medium's index is its core alone: the same image as the
// homogeneous core's (in the same FFT window; the two Mie tables' steps differ, step 0.05 / x,
// so their interpolation differs by about 1e-5 of |S|).
TEST(WaveImage, CoatedSphereWithAShellOfTheMediumsIndexIsItsCore) {
  Scene core = WaveScene(2.0, 1.45, 15, 64);
  core.trace.mie.window_um = 60;
  Scene coated = core;
  coated.objects.push_back(SphereObject(4.0, 1.0));
  const Image a = MieImager(core).Expected(4.0, 2), b = MieImager(coated).Expected(4.0, 2);
  double worst = 0, change = 0;
  for (size_t i = 0; i < a.pixels.size(); ++i) {
    worst = std::max(worst, double(std::abs(a.pixels[i] - b.pixels[i])));
    change = std::max(change, double(std::abs(a.pixels[i] - 1000.0f)));
  }
  EXPECT_GT(change, 100);  // the core's image is not the flat field
  EXPECT_LT(worst, 1e-3 * change) << "of the largest change " << change;
}

TEST(WaveImage, SameImageForAnyThreadCount) {
  Scene s = WaveScene(4, 1.38, 15, 48);
  s.objects[0].center_um = Vec3(1.3, -0.7, 0.5);
  Scene spectrum = s;  // one class per direction: more wavelengths' nodes than one block
  spectrum.source.spectrum.type = SpectrumType::kGaussian;
  spectrum.source.spectrum.center_um = s.wavelength_um;
  spectrum.source.spectrum.fwhm_um = 0.02;
  spectrum.trace.mie.spectrum_nodes = 4;
  spectrum.trace.mie.spectrum_interleave = 1024;
  for (const Scene& t : {s, spectrum}) {
    // Separate imagers: the second must not reuse the first's fields.
    const Image a = MieImager(t).Expected(-2.0, 1), b = MieImager(t).Expected(-2.0, 3);
    ASSERT_EQ(a.pixels.size(), b.pixels.size());
    for (size_t i = 0; i < a.pixels.size(); ++i) ASSERT_EQ(a.pixels[i], b.pixels[i]) << i;
  }
  EXPECT_GT(MieImager(spectrum).sampling().wavelengths, 128);
}

// Moving the sphere by whole pixels moves its image by those pixels (the microscope is
// shift-invariant; the model computes about the sphere and renders at its position).
TEST(WaveImage, ShiftingTheSphereShiftsTheImage) {
  Scene s = WaveScene(3, 1.38, 12, 48);
  const Image a = MieImager(s).Expected(2.0, 2);
  s.objects[0].center_um = Vec3(2.0, 1.0, 0);  // 4 pixels right, 2 up (rows decrease)
  const Image b = MieImager(s).Expected(2.0, 2);
  double worst = 0;
  for (int r = 8; r < 40; ++r)
    for (int c = 8; c < 40; ++c)
      worst = std::max(worst, double(std::abs(b.at(c + 4, r - 2) - a.at(c, r))));
  EXPECT_LT(worst, 1e-3);
}

/// A light field over direction cosines, n x n cells of [-0.45, 0.45]^2: value f(u, v) inside
/// sin(theta) < 0.4, zero outside.
template <class F>
Scene LightFieldScene(F f, int n = 32) {
  Scene s = WaveScene(6, 1.4, 0, 48);
  s.source.type = SourceType::kLightField;
  s.source.angular_extent = 0.45;
  s.source.angular_map = Image(n, n);
  for (int y = 0; y < n; ++y)
    for (int x = 0; x < n; ++x) {
      const double u = -0.45 + (x + 0.5) * 0.9 / n, v = 0.45 - (y + 0.5) * 0.9 / n;
      s.source.angular_map.at(x, y) = std::hypot(u, v) < 0.4 ? float(f(u, v)) : 0.f;
    }
  return s;
}

// MoveAcross keeps the fields computed for each axial offset and renders them about the new
// centre: the image is the one a new imager of the moved sphere gives, bit for bit, for an
// asymmetric light field (azimuthal harmonics) and planes computed before and after the move.
TEST(WaveImage, MovingAcrossGivesTheImageOfTheMovedSphere) {
  Scene s = LightFieldScene([](double u, double v) { return 1 + 2 * u + 0.5 * v * v; });
  s.objects[0].center_um = Vec3(0.3, -0.2, 0.4);
  MieImager moved(s);
  const Image before = moved.Expected(2.0, 2);
  moved.MoveAcross(1.7, 0.9);
  const Image a = moved.Expected(2.0, 2), b = moved.Expected(-1.0, 2);
  s.objects[0].center_um = Vec3(1.7, 0.9, 0.4);
  const MieImager fresh(s);
  const Image fa = fresh.Expected(2.0, 2), fb = fresh.Expected(-1.0, 2);
  ASSERT_EQ(a.size(), fa.size());
  size_t differ = 0, moved_pixels = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    differ += a.pixels[i] != fa.pixels[i] || b.pixels[i] != fb.pixels[i];
    moved_pixels += a.pixels[i] != before.pixels[i];
  }
  EXPECT_EQ(differ, 0u);
  EXPECT_GT(moved_pixels, a.size() / 4);  // the move changed the image
}

// Turning the illumination by 90 degrees about the axis turns the image by 90 degrees about the
// sphere: the azimuthal harmonics carry the source's asymmetry with the right orientation and
// sign (u -> v, v -> -u turns the map counter-clockwise, and the image's +x to +y).
TEST(WaveImage, TurningTheLightFieldTurnsTheImage) {
  auto f = [](double u, double v) { return 1 + 1.5 * u + 0.6 * v * v; };
  const Image a = MieImager(LightFieldScene(f)).Expected(8.0, 2);
  const Image b =
      MieImager(LightFieldScene([&](double u, double v) { return f(v, -u); })).Expected(8.0, 2);
  // Pixel (c, r) at (x, y) = (c + 0.5 - 24, 24 - r - 0.5) pixels; turned: (-y, x).
  double worst = 0, asym = 0;
  for (int r = 0; r < 48; ++r)
    for (int c = 0; c < 48; ++c) {
      const int c2 = 47 - r, r2 = 47 - c;  // (x, y) -> (-y, x) -> pixel (c2, r2)
      worst = std::max(worst, double(std::abs(b.at(c2, r2) - a.at(c, r))));
      asym = std::max(asym, double(std::abs(a.at(c, r) - a.at(47 - c, r))));
    }
  EXPECT_GT(asym, 50.0);   // the tilted illumination makes the image asymmetric in x...
  EXPECT_LT(worst, 0.05);  // ...and the turned one is the turned image (photons of 1000)
}

// A light field that is a uniform disc is the cone source of that angle: the harmonics beyond
// the zeroth vanish, and the map's cells sampled on the quadrature's circles converge to the
// cone's weights as the cells shrink (the map's staircase rim is the difference).
TEST(WaveImage, UniformLightFieldConvergesToTheCone) {
  Scene cone = LightFieldScene([](double, double) { return 1.0; });
  cone.source = SourceSpec{};
  cone.source.type = SourceType::kCone;
  cone.source.half_angle_deg = std::asin(0.4) * 180 / M_PI;
  const Image ref = MieImager(cone).Expected(4.0, 2);
  std::vector<double> worst;
  for (int n : {32, 128}) {
    const Image a =
        MieImager(LightFieldScene([](double, double) { return 1.0; }, n)).Expected(4.0, 2);
    double w = 0;
    for (size_t i = 0; i < a.size(); ++i)
      w = std::max(w, double(std::abs(a.pixels[i] - ref.pixels[i])));
    worst.push_back(w);
  }
  EXPECT_LT(worst[0], 15.0);  // 1.5 % of the background with 32 cells across the map
  EXPECT_LT(worst[1], worst[0] / 2.5) << worst[0] << " -> " << worst[1];  // first order in the cell
}

// A soft edge's tail carries almost no light but reaches to the map's corners: directions whose
// power together is below 1e-9 of the source's are left out. A map falling as
// exp(-(s - 0.3) / 0.005) beyond s = 0.3 (e^-24 at 0.42) gives the image of the same map cut to
// zero beyond 0.42 (to 1e-6 of the background) with as many directions, give or take a panel
// (6); computing every node to the map's corner (s = 0.64) takes about 40 more.
TEST(WaveImage, SoftEdgeTailCostsNoDirections) {
  auto tail = [](double u, double v) {
    const double s = std::hypot(u, v);
    return s < 0.3 ? 1.0 : std::exp(-(s - 0.3) / 0.005);
  };
  Scene a = LightFieldScene([](double, double) { return 1.0; }), b = a;
  const int n = a.source.angular_map.width;
  for (int y = 0; y < n; ++y)
    for (int x = 0; x < n; ++x) {
      const double u = -0.45 + (x + 0.5) * 0.9 / n, v = 0.45 - (y + 0.5) * 0.9 / n;
      a.source.angular_map.at(x, y) = float(tail(u, v));
      b.source.angular_map.at(x, y) = std::hypot(u, v) < 0.42 ? float(tail(u, v)) : 0.f;
    }
  const MieImager ia(a), ib(b);
  const Image ea = ia.Expected(3.0, 2), eb = ib.Expected(3.0, 2);
  double worst = 0;
  for (size_t i = 0; i < ea.size(); ++i)
    worst = std::max(worst, double(std::abs(ea.pixels[i] - eb.pixels[i])));
  EXPECT_LT(worst, 1e-3);  // photons of 1000
  EXPECT_LE(ia.sampling().directions, ib.sampling().directions + 6);
  EXPECT_GT(ia.sampling().directions, 0);
}

// A spectrum is incoherent over its wavelengths: two lines give the power-weighted sum of the
// two monochromatic images (each with the sphere's index at its wavelength, Cauchy here), and
// the flat field stays the photon target.
TEST(WaveImage, SpectrumIsThePowerWeightedSumOfItsWavelengths) {
  Scene s = WaveScene(3, 1.4, 10, 32);
  s.objects[0].dispersion.law = DispersionLaw::kCauchy;
  s.objects[0].dispersion.coefficients = {1.38, 0.004};  // n = 1.38 + 0.004 / l^2
  s.source.spectrum.type = SpectrumType::kLines;
  s.source.spectrum.wavelengths_um = {0.45, 0.50};
  s.source.spectrum.weights = {0.3, 0.7};
  const Image both = MieImager(s).Expected(2.0, 2);
  Image sum(32, 32);
  std::vector<Image> line;
  for (int k = 0; k < 2; ++k) {
    Scene one = s;
    one.source.spectrum = SpectrumSpec{};
    one.wavelength_um = s.source.spectrum.wavelengths_um[k];
    one.objects[0].dispersion.law = DispersionLaw::kNone;
    one.objects[0].index = 1.38 + 0.004 / (one.wavelength_um * one.wavelength_um);
    line.push_back(MieImager(one).Expected(2.0, 2));
    for (size_t i = 0; i < sum.size(); ++i)
      sum.pixels[i] += float(s.source.spectrum.weights[k] * line[k].pixels[i]);
  }
  // The wavelengths' harmonics are summed on one radial grid (the finer of the two) and
  // rendered once: against each rendered from its own grid, 0.2 photons of 1000 at most here
  // (the render's radial interpolation; the convergence goal is 0.1 % of the background).
  // In RMS 0.035 photons here against the two lines' difference of 15.7: shares 0.005 off
  // would move the image by the bound below.
  double off = 0, apart = 0;
  for (size_t i = 0; i < sum.size(); ++i) {
    ASSERT_NEAR(both.pixels[i], sum.pixels[i], 0.5) << i;
    off += std::pow(both.pixels[i] - sum.pixels[i], 2);
    apart += std::pow(line[0].pixels[i] - line[1].pixels[i], 2);
  }
  EXPECT_LT(std::sqrt(off), std::sqrt(apart) / 200);
  s.objects[0].dispersion.coefficients = {1.0};  // no sphere: the flat field
  for (float v : MieImager(s).Expected(2.0, 2).pixels) ASSERT_NEAR(v, 1000.0, 1e-6);
}

// An interleaved spectrum (spectrum_interleave): the illumination directions in classes, each
// with its own shifted wavelengths. At one wavelength the classes add up to the full image (a
// spectrum a millionth of a nanometre wide; the flat field stays the photon target). Over a
// 30 nm band on a drop in air, 4 wavelengths per class in 8 classes come closer to 64 plain
// nodes than 4 plain nodes do (the sphere's fringes and resonances repeat every few nm).
TEST(WaveImage, InterleavedSpectrumClassesAddUpAndSampleTheBandFiner) {
  Scene s = WaveScene(3, 1.4, 10, 32);
  s.source.spectrum.type = SpectrumType::kGaussian;
  s.source.spectrum.center_um = s.wavelength_um;
  s.source.spectrum.fwhm_um = 1e-9;
  s.trace.mie.spectrum_nodes = 2;
  s.trace.mie.spectrum_interleave = 4;
  Scene mono = s;
  mono.source.spectrum = SpectrumSpec{};
  const Image one = MieImager(mono).Expected(2.0, 2), classes = MieImager(s).Expected(2.0, 2);
  for (size_t i = 0; i < one.size(); ++i) ASSERT_NEAR(classes.pixels[i], one.pixels[i], 2e-3) << i;
  EXPECT_EQ(MieImager(s).sampling().directions, MieImager(mono).sampling().directions);
  EXPECT_EQ(MieImager(s).sampling().wavelengths, 8);
  // More classes than illumination directions: one class per direction.
  Scene many = s;
  many.trace.mie.spectrum_interleave = 64;
  const int directions = MieImager(mono).sampling().directions;
  ASSERT_LT(directions, 64);
  const MieImager per_direction(many);
  EXPECT_EQ(per_direction.sampling().wavelengths, 2 * directions);
  EXPECT_EQ(per_direction.sampling().directions, directions);
  const Image each = per_direction.Expected(2.0, 2);
  for (size_t i = 0; i < one.size(); ++i) ASSERT_NEAR(each.pixels[i], one.pixels[i], 2e-3) << i;
  Scene flat = s;
  flat.objects[0].index = flat.medium_index;
  for (float v : MieImager(flat).Expected(2.0, 2).pixels) ASSERT_NEAR(v, 1000.0, 1e-6);

  s.source.spectrum.fwhm_um = 0.03;
  auto image = [&](int nodes, int interleave) {
    Scene t = s;
    t.trace.mie.spectrum_nodes = nodes;
    t.trace.mie.spectrum_interleave = interleave;
    return MieImager(t).Expected(2.0, 2);
  };
  const Image ref = image(64, 1), plain = image(4, 1), inter = image(4, 8);
  double e_plain = 0, e_inter = 0;
  for (size_t i = 0; i < ref.size(); ++i) {
    e_plain = std::max(e_plain, double(std::abs(plain.pixels[i] - ref.pixels[i])));
    e_inter = std::max(e_inter, double(std::abs(inter.pixels[i] - ref.pixels[i])));
  }
  std::printf("largest change against 64 nodes: 4 nodes %.2f, 4 x 8 interleaved %.2f photons\n",
              e_plain, e_inter);
  EXPECT_LT(e_inter, e_plain / 3);
}

// Motion during the pulse: the image is the average over the pulse's equal-power times of the
// images of the sphere where it is then (lateral moves share one field computation, axial ones
// do not; both must give that average).
TEST(WaveImage, MovingSphereIsTheAverageOverThePulse) {
  for (const Vec3 v : {Vec3(3, -2, 0), Vec3(1, 0, 4)}) {  // um per us
    Scene s = WaveScene(3, 1.38, 10, 32);
    s.objects[0].velocity_um_per_us = v;
    s.exposure.shape = PulseShape::kTopHat;
    s.exposure.duration_us = 0.5;
    s.trace.mie.motion_nodes = 4;
    const Image moving = MieImager(s).Expected(2.0, 2);
    Image mean(32, 32);
    for (int k = 0; k < 4; ++k) {
      Scene at = s;
      at.exposure = ExposureSpec{};
      at.objects[0].velocity_um_per_us = Vec3();
      at.objects[0].center_um = v * (0.5 * ((k + 0.5) / 4 - 0.5));
      const Image a = MieImager(at).Expected(2.0, 2);
      for (size_t i = 0; i < a.size(); ++i) mean.pixels[i] += a.pixels[i] / 4;
    }
    for (size_t i = 0; i < mean.size(); ++i)
      ASSERT_NEAR(moving.pixels[i], mean.pixels[i], 2e-3) << i;
    // and it differs from the sphere at rest by more than that
    Scene rest = s;
    rest.exposure = ExposureSpec{};
    rest.objects[0].velocity_um_per_us = Vec3();
    const Image still = MieImager(rest).Expected(2.0, 2);
    double d = 0;
    for (size_t i = 0; i < still.size(); ++i)
      d = std::max(d, double(std::abs(still.pixels[i] - moving.pixels[i])));
    EXPECT_GT(d, 10.0);
  }
}

// The corrector's zones apodise the pupil by angle, at the angle where a ray from the axis point
// meets each ring (r = d tan theta): a clear disc out to sin 0.3 and an opaque ring beyond is an
// objective of NA 0.3, to the sampling, which differs between the two scenes (their FFT grids
// follow their NA: 1.1 photons of 1000 apart at oversample 3; 9 at the default 1.5, whose
// interpolation this small sphere's fine fringes outrun).
TEST(WaveImage, OpaqueCorrectorRingIsASmallerAperture) {
  Scene zones = WaveScene(4, 1.38, 25, 40);
  zones.optics.corrector.enabled = true;
  zones.optics.corrector.ring_outer_mm = {10 * std::tan(std::asin(0.3)), 10.0};
  zones.optics.corrector.transmissions = {1.0, 0.0};
  zones.trace.mie.oversample = 3;
  Scene small = zones;
  small.optics.corrector = CorrectorSpec{};
  small.optics.na = 0.3;
  const Image a = MieImager(zones).Expected(3.0, 2), b = MieImager(small).Expected(3.0, 2);
  double worst = 0;
  for (size_t i = 0; i < a.size(); ++i)
    worst = std::max(worst, double(std::abs(a.pixels[i] - b.pixels[i])));
  EXPECT_LT(worst, 3.0);
}

TEST(WaveImage, PoissonSampleHasTheExpectedMeanAndVariance) {
  for (double mu : {0.7, 4.0, 35.0, 1000.0}) {
    Image e(200, 200, float(mu));
    const Image s = PoissonSample(e, 7, 3);
    double m = 0, v = 0;
    for (float x : s.pixels) m += x;
    m /= s.size();
    for (float x : s.pixels) v += (x - m) * (x - m);
    v /= s.size() - 1;
    // 40000 draws: the mean's standard error sqrt(mu / N), the variance's about
    // mu sqrt(2 / N) (plus the fourth cumulant mu / N): 5 standard errors.
    EXPECT_NEAR(m, mu, 5 * std::sqrt(mu / 40000.0)) << mu;
    EXPECT_NEAR(v, mu, 5 * std::sqrt((2 * mu * mu + mu) / 40000.0)) << mu;
    const Image again = PoissonSample(e, 7, 3);
    EXPECT_EQ(again.pixels, s.pixels);
  }
}

TEST(WaveImage, ScenesWithoutAnExactWaveImageAreRejected) {
  Scene s = WaveScene(3, 1.38, 12);
  s.objects.push_back(SphereObject(2, 1.4, Vec3(10, 0, 0)));
  EXPECT_NE(MieUnsupportedReason(s).find("concentric"), std::string::npos);
  EXPECT_THROW(MieImager{s}, Error);
  s.objects[1].center_um = s.objects[0].center_um;
  EXPECT_EQ(MieUnsupportedReason(s), "");  // a coated sphere
  s.objects[1].radius_um = 3;
  EXPECT_NE(MieUnsupportedReason(s).find("smaller than its shell"), std::string::npos);
  s.objects[1].radius_um = 2;
  s.objects[1].velocity_um_per_us = Vec3(1, 0, 0);
  EXPECT_NE(MieUnsupportedReason(s).find("move together"), std::string::npos);
  s.objects.push_back(SphereObject(1, 1.4));
  EXPECT_NE(MieUnsupportedReason(s).find("3 objects"), std::string::npos);
  s.objects = {testing::BoxObject(Vec3(2, 2, 2), 1.4)};
  EXPECT_NE(MieUnsupportedReason(s).find("needs a sphere"), std::string::npos);
  s.objects = {SphereObject(3, 1.38)};
  s.source.type = SourceType::kPoint;
  EXPECT_NE(MieUnsupportedReason(s).find("point source"), std::string::npos);
  s.source.type = SourceType::kCollimated;
  s.source.tilt_deg = 5;
  EXPECT_NE(MieUnsupportedReason(s).find("along the axis"), std::string::npos);
}

}  // namespace
}  // namespace raymatch::simulate
