// The physical-optics image (optics = "physical"): known answers, and the exact sphere (Mie) as
// the ruler of its accuracy.
#include "raymatch/simulate/physical_image.h"

#include <gtest/gtest.h>
#include <toml++/toml.h>

#include <cmath>
#include <cstdio>

#include "raymatch/core/array_io.h"
#include "raymatch/core/error.h"
#include "raymatch/simulate/wave_image.h"
#include "temp_dir.h"
#include "test_scenes.h"

namespace raymatch::simulate {
namespace {

using testing::MicroscopeScene;
using testing::SphereObject;

/// Water, 0.55 um, 0.5 um object pixels, 1000 photons per pixel, a collimated axial wave.
Scene PhysicalScene(int pixels = 48) {
  Scene s = MicroscopeScene();
  s.wavelength_um = 0.55;
  s.medium_index = 1.333;
  s.camera.nx = s.camera.ny = pixels;
  s.camera.pixel_pitch_um = 10;
  s.source.type = SourceType::kCollimated;
  s.trace.photons_per_pixel = 1000;
  s.trace.optics = ImageOptics::kPhysical;
  return s;
}

/// Chi-square per pixel of `a` against the expected image `ref` (Poisson variance ref).
double Chi2PerPixel(const Image& a, const Image& ref) {
  double sum = 0;
  for (size_t i = 0; i < a.pixels.size(); ++i)
    sum += (a.pixels[i] - ref.pixels[i]) * double(a.pixels[i] - ref.pixels[i]) / ref.pixels[i];
  return sum / double(a.pixels.size());
}

/// A corrector of three zones out to the NA's edge at the corrector plane (sin theta 0.08,
/// 0.16 and the rest), transmitting 1, 0.6 and 0.3.
CorrectorSpec ThreeZones(const Scene& s) {
  CorrectorSpec c;
  c.enabled = true;
  const double f = s.optics.objective_focal_mm;
  const double edge = f * std::tan(std::asin(s.optics.na / s.medium_index)) * 1.02;
  c.ring_outer_mm = {f * std::tan(std::asin(0.08)), f * std::tan(std::asin(0.16)), edge};
  c.transmissions = {1.0, 0.6, 0.3};
  return c;
}

/// An LED-like Gaussian spectrum (0.55 um, 0.08 um FWHM) and a sphere of 1.40 at 0.55 um with
/// a Cauchy dispersion (n = 1.38 + 0.00605 / l^2), moving 2 um across the axis over a 0.5 us
/// top-hat pulse.
void SpectrumAndMotion(Scene* s) {
  s->source.spectrum.type = SpectrumType::kGaussian;
  s->source.spectrum.center_um = 0.55;
  s->source.spectrum.fwhm_um = 0.2;
  s->exposure.shape = PulseShape::kTopHat;
  s->exposure.duration_us = 0.5;
  for (ObjectSpec& o : s->objects) {
    o.dispersion.law = DispersionLaw::kCauchy;
    o.dispersion.coefficients = {1.38, 0.00605};
    o.index = o.dispersion.IndexAt(0.55);
    o.velocity_um_per_us = Vec3(4, 0, 0);
  }
}

// Without objects the image is the flat field: exactly photons_per_pixel, for a collimated wave
// and for a cone partly beyond the NA (its direct light beyond it does not reach the camera),
// with and without the corrector and the PSF, and under a spectrum.
TEST(PhysicalImage, FlatFieldIsExactlyThePhotonTarget) {
  for (double cone : {0.0, 30.0})
    for (int extra = 0; extra < 3; ++extra) {
      Scene s = PhysicalScene(24);
      if (cone > 0) s.source.type = SourceType::kCone, s.source.half_angle_deg = cone;
      if (extra == 1) s.optics.corrector = ThreeZones(s), s.camera.psf_sigma_um = 0.4;
      if (extra == 2) SpectrumAndMotion(&s);
      const Image img = PhysicalImager(s).Expected(2.0, 2);
      for (float v : img.pixels) ASSERT_NEAR(v, 1000.0, 1e-9 * 1000) << "cone " << cone;
    }
}

// A spectrum and motion as the exact image has them (the same wavelengths, 4 equal-power
// quantiles of a 0.2 um wide spectrum, the sphere's dispersion at each, and the same 4 times of
// the pulse): the 3 um sphere of 1.40 in water under a collimated wave, moving 2 um, in focus
// and 4 um past it. The physical image stays within the chi-square per pixel it has without
// them (under 1, measured 0.24 and 0.41). Still and monochromatic it is 3.2 and 4.3 off (the
// test fails when the motion is ignored). The spectrum changes this small sphere's image by
// little (0.03 and 0.05 per pixel in the exact model), so its change is compared: the physical
// model's change from its monochromatic image differs from the exact model's by 0.28-0.34 of
// the latter (1 when the spectrum is ignored; bound 0.5).
TEST(PhysicalImage, SpectrumAndMotionAsTheExactImageHasThem) {
  Scene s = PhysicalScene();
  s.objects = {SphereObject(3.0, 1.40)};
  SpectrumAndMotion(&s);
  s.trace.physical.spectrum_nodes = s.trace.physical.motion_nodes = 4;
  Scene w = s;
  w.trace.optics = ImageOptics::kMie;
  w.trace.mie.spectrum_nodes = w.trace.mie.motion_nodes = 4;
  Scene still = s, mono = s, mie_mono = w;
  still.exposure = ExposureSpec{};
  still.source.spectrum = SpectrumSpec{};
  mono.source.spectrum = mie_mono.source.spectrum = SpectrumSpec{};
  const PhysicalImager phys(s), phys_still(still), phys_mono(mono);
  EXPECT_EQ(phys.sampling().wavelengths, 4);
  EXPECT_EQ(phys.sampling().times, 4);
  const MieImager mie(w), mie_m(mie_mono);
  for (double dz : {0.0, 4.0}) {
    const Image ref = mie.Expected(dz, 2), ref_mono = mie_m.Expected(dz, 2);
    const Image a = phys.Expected(dz, 2), a_mono = phys_mono.Expected(dz, 2);
    const double chi2 = Chi2PerPixel(a, ref);
    const double chi2_still = Chi2PerPixel(phys_still.Expected(dz, 2), ref);
    double exact_change = 0, change_error = 0;
    for (size_t i = 0; i < a.pixels.size(); ++i) {
      const double d = a.pixels[i] - a_mono.pixels[i], e = ref.pixels[i] - ref_mono.pixels[i];
      exact_change += e * e / ref.pixels[i], change_error += (d - e) * (d - e) / ref.pixels[i];
    }
    std::printf(
        "defocus %.0f um: chi-square per pixel %.3f (still and monochromatic %.2f); the "
        "spectrum's change %.4f, the physical change off it by %.4f\n",
        dz, chi2, chi2_still, exact_change / a.size(), change_error / a.size());
    EXPECT_LT(chi2, 1.0) << dz;
    EXPECT_GT(chi2_still, 3 * chi2) << dz;
    EXPECT_LT(change_error, 0.5 * exact_change) << dz;
  }
}

// Against the exact image of a sphere (the Mie model, wave_image.h: the same microscope, the
// same photon scale): a 3 um sphere of 1.40 in water, in focus and 4 um past it, under a
// collimated wave and an 8 deg cone (2 x 4 directions). The physical image must explain most of
// what the sphere does to the image: its chi-square per pixel against the exact one at 1000
// photons is far below the flat field's (6-38) and below 1 (measured 0.36-0.69; the ray model's
// is 1.9-16.6, docs/physical-optics.md). A wrong sign of the defocus phase gives 22-36, a wrong
// sign of the direct wave's interference 1500-2100.
//
// A 20 deg cone reaches beyond the NA (sin 20 deg = 0.342 > 0.42 / 1.333): its directions are
// split there, where the direct light stops reaching the camera. 4 um past focus with 2 x 4
// directions per side the excess is 0.88 of the flat field's 1.51 (4.4 without the split; 0.45
// with 4 x 8 directions: a cone at the NA's edge needs many directions).
TEST(PhysicalImage, ConeBeyondTheNaIsSplitAtIt) {
  Scene s = PhysicalScene();
  s.objects = {SphereObject(3.0, 1.40)};
  s.source.type = SourceType::kCone;
  s.source.half_angle_deg = 20;
  s.trace.physical.polar_nodes = 2;
  s.trace.physical.azimuths = 4;
  Scene w = s;
  w.trace.optics = ImageOptics::kMie;
  const Image a = PhysicalImager(s).Expected(4.0, 2), ref = MieImager(w).Expected(4.0, 2);
  Image flat = ref;
  for (float& v : flat.pixels) v = 1000;
  const double chi2 = Chi2PerPixel(a, ref), chi2_flat = Chi2PerPixel(flat, ref);
  std::printf("20 deg cone, 4 um past focus: chi-square per pixel %.3f (flat field %.2f)\n", chi2,
              chi2_flat);
  EXPECT_LT(chi2, 0.7 * chi2_flat);
}

TEST(PhysicalImage, SphereComesCloseToTheExactImage) {
  for (double cone : {0.0, 8.0}) {
    Scene s = PhysicalScene();
    s.objects = {SphereObject(3.0, 1.40)};
    if (cone > 0) s.source.type = SourceType::kCone, s.source.half_angle_deg = cone;
    s.trace.physical.polar_nodes = 2;
    s.trace.physical.azimuths = 4;
    Scene w = s;
    w.trace.optics = ImageOptics::kMie;
    const PhysicalImager phys(s);
    const MieImager mie(w);
    for (double dz : {0.0, 4.0}) {
      const Image a = phys.Expected(dz, 2), ref = mie.Expected(dz, 2);
      Image flat = ref;
      for (float& v : flat.pixels) v = 1000;
      const double chi2 = Chi2PerPixel(a, ref), chi2_flat = Chi2PerPixel(flat, ref);
      std::printf("cone %.0f deg, defocus %.0f um: chi-square per pixel %.3f (flat field %.2f)\n",
                  cone, dz, chi2, chi2_flat);
      EXPECT_LT(chi2, 0.1 * chi2_flat) << "cone " << cone << ", defocus " << dz;
      EXPECT_LT(chi2, 1.0) << "cone " << cone << ", defocus " << dz;
    }
  }
}

// The corrector and the PSF as the exact image has them: the 3 um sphere under a 12 deg cone
// (its directions reach past two zone edges), three zones transmitting 1, 0.2 and 0.02
// apodising the pupil and the direct light, a PSF of 0.4 um, in focus and 4 um past it. The
// physical image comes within a chi-square per pixel of 0.2 of the exact one (measured 0.111
// at both planes; the flat field's is 2.9); the same physical image without the corrector is
// 0.42 and 2.8 off, without the PSF 0.31 and 0.22, so the test fails when either is ignored.
// (With 3 x 6 directions: the coarser 2 x 4 of the tests above leave 1.3 here, the
// corrector's zones being sampled by one ring each.)
TEST(PhysicalImage, CorrectorAndPsfAsTheExactImageHasThem) {
  Scene s = PhysicalScene();
  s.objects = {SphereObject(3.0, 1.40)};
  s.source.type = SourceType::kCone;
  s.source.half_angle_deg = 12;
  s.trace.physical.polar_nodes = 3;
  s.trace.physical.azimuths = 6;
  s.optics.corrector = ThreeZones(s);
  s.optics.corrector.transmissions = {1.0, 0.2, 0.02};
  s.camera.psf_sigma_um = 0.4;
  Scene w = s;
  w.trace.optics = ImageOptics::kMie;
  const PhysicalImager phys(s);
  const MieImager mie(w);
  for (double dz : {0.0, 4.0}) {
    const Image ref = mie.Expected(dz, 2);
    Image flat = ref;
    for (float& v : flat.pixels) v = 1000;
    const double chi2 = Chi2PerPixel(phys.Expected(dz, 2), ref);
    std::printf("defocus %.0f um: chi-square per pixel %.3f (flat field %.2f)\n", dz, chi2,
                Chi2PerPixel(flat, ref));
    EXPECT_LT(chi2, 0.2) << dz;
  }
}

// A water density field under a spectrum: each wavelength sees the grid's index there (its
// index at the grid's wavelength mapped affinely, WaterIndexMap, within 1e-5 of IAPWS R9-97). A
// drop whose density falls from 1040 kg/m^3 at its centre to 998 at its surface (a
// gradient-index lens), under lines at 0.3 and 1.0 um in a medium of 1.34 between them: the
// image is the mean of the images of the scene loaded at each line, whose grids hold IAPWS's
// index there (measured within 0.016 photons: the map's residual; bound 0.05); at the
// spectrum's mean wavelength alone it is 133 photons off.
TEST(PhysicalImage, WaterDensityFieldFollowsTheWavelength) {
  testing::TempDir dir;
  const std::string drop = testing::DensityDropObject(dir, 5, 4, 4.5);
  auto scene = [&](const std::string& light) {
    return LoadScene(dir.Write(
        "s.toml",
        light + R"(medium_index = 1.34
[source]
type = "collimated"
)" +
            (light.empty() ? "spectrum = { type = \"lines\", wavelengths_um = [0.3, 1.0], "
                             "weights = [0.5, 0.5] }\n"
                           : "") +
            drop + R"([camera]
pixels = [24, 24]
pixel_pitch_um = 20
[trace]
optics = "physical"
photons_per_pixel = 1000
)" + testing::kOpticsToml));
  };
  const Image both = PhysicalImager(scene("")).Expected(2.0, 2);
  const Image blue = PhysicalImager(scene("wavelength_um = 0.3\n")).Expected(2.0, 2);
  const Image red = PhysicalImager(scene("wavelength_um = 1.0\n")).Expected(2.0, 2);
  const Image mean = PhysicalImager(scene("wavelength_um = 0.65\n")).Expected(2.0, 2);
  double worst = 0, off_mean = 0;
  for (size_t i = 0; i < both.size(); ++i) {
    worst = std::max(worst, std::abs(both.pixels[i] - 0.5 * (blue.pixels[i] + red.pixels[i])));
    off_mean = std::max(off_mean, double(std::abs(both.pixels[i] - mean.pixels[i])));
  }
  std::printf(
      "largest difference from the lines' mean %.4f photons, from the mean wavelength "
      "%.1f\n",
      worst, off_mean);
  EXPECT_LT(worst, 0.05);
  EXPECT_GT(off_mean, 20.0);
}

/// A light field over direction cosines, 32 x 32 cells of [-0.45, 0.45]^2: f(u, v) inside
/// sin(theta) < `reach`, zero outside.
template <class F>
Scene LightFieldScene(F f, double reach = 0.25) {
  Scene s = PhysicalScene();
  s.source.type = SourceType::kLightField;
  s.source.angular_extent = 0.45;
  const int n = 32;
  s.source.angular_map = Image(n, n);
  for (int y = 0; y < n; ++y)
    for (int x = 0; x < n; ++x) {
      const double u = -0.45 + (x + 0.5) * 0.9 / n, v = 0.45 - (y + 0.5) * 0.9 / n;
      s.source.angular_map.at(x, y) = std::hypot(u, v) < reach ? float(f(u, v)) : 0.f;
    }
  return s;
}

// A light field as the exact image has it: an asymmetric angular map (1 + 1.5 u + 0.6 v^2
// within sin theta 0.25) on the 3 um sphere, 4 um past focus, 3 x 6 directions. The physical
// image comes as close to the exact one as under a cone (under 1 per pixel; measured 0.62, and
// 0.40 with 6 x 12 directions); it is over twice as far (2.0) from the exact image of the map
// mirrored in u, so the tilt is sampled with its sign (the mirror's exact image is 1.5 from
// the map's).
TEST(PhysicalImage, LightFieldAsTheExactImageHasIt) {
  auto f = [](double u, double v) { return 1 + 1.5 * u + 0.6 * v * v; };
  Scene s = LightFieldScene(f);
  s.objects = {SphereObject(3.0, 1.40)};
  s.trace.physical.polar_nodes = 3;
  s.trace.physical.azimuths = 6;
  Scene w = s, mirrored = LightFieldScene([&](double u, double v) { return f(-u, v); });
  w.trace.optics = ImageOptics::kMie;
  mirrored.objects = s.objects;
  mirrored.trace.optics = ImageOptics::kMie;
  const Image ref = MieImager(w).Expected(4.0, 2), ref_m = MieImager(mirrored).Expected(4.0, 2);
  const PhysicalImager phys(s);
  const Image a = phys.Expected(4.0, 2);
  const double chi2 = Chi2PerPixel(a, ref), chi2_m = Chi2PerPixel(a, ref_m);
  std::printf(
      "light field, 4 um past focus: chi-square per pixel %.3f, against the mirrored "
      "map's %.3f; %d directions\n",
      chi2, chi2_m, phys.sampling().directions);
  EXPECT_LT(chi2, 1.0);
  EXPECT_GT(chi2_m, 2 * chi2);
}

// A soft edge's far tail costs no spectra: a map falling as exp(-(s - 0.3) / 0.005) beyond
// s = 0.3 out to the map's corner (s 0.64) is sampled on 3 rings inside the NA and 3 beyond it
// (0.315-0.64); the outer two beyond it carry e^-35 and less of the power and are left out
// (TailStart, the exact model's rule), the first (e^-10) is kept: 24 directions, 34 without the
// rule (the outermost ring loses the sectors beyond the map).
TEST(PhysicalImage, SoftEdgeTailCostsNoDirections) {
  Scene s = LightFieldScene(
      [](double u, double v) {
        const double r = std::hypot(u, v);
        return r < 0.3 ? 1.0 : std::exp(-(r - 0.3) / 0.005);
      },
      1.0);
  s.trace.physical.polar_nodes = 3;
  s.trace.physical.azimuths = 6;
  EXPECT_EQ(PhysicalImager(s).sampling().directions, 4 * 6);
}

// A light field's spatial map is the image's envelope: without objects each pixel is the photon
// target times the map there over its mean on the sensor (a map falling along x by half).
TEST(PhysicalImage, SpatialMapIsTheEnvelope) {
  Scene s = LightFieldScene([](double, double) { return 1.0; });
  s.camera.nx = s.camera.ny = 16;
  s.source.spatial_map = Image(8, 8);
  for (int y = 0; y < 8; ++y)
    for (int x = 0; x < 8; ++x) s.source.spatial_map.at(x, y) = float(1 - 0.5 * x / 7.0);
  s.source.field_size_um = {8, 8};  // the sensor's view is 16 x 0.5 um
  const PhysicalImager im(s);
  const Image img = im.Expected(1.0, 2);
  double mean = 0;
  for (float v : img.pixels) mean += v / double(img.size());
  EXPECT_NEAR(mean, 1000, 1e-6 * 1000);
  for (int r = 0; r < 16; ++r)
    for (int c = 0; c < 15; ++c) {
      const int a = c / 2, b = (c + 1) / 2;  // the map's cells under the two pixels
      EXPECT_NEAR(img.at(c + 1, r) / img.at(c, r),
                  s.source.spatial_map.at(b, 0) / s.source.spatial_map.at(a, 0), 1e-6);
    }
}

TEST(PhysicalImage, SameImageForAnyThreadCount) {
  Scene s = PhysicalScene(32);
  s.objects = {SphereObject(2.0, 1.40)};
  const PhysicalImager im(s);
  const Image a = im.Expected(3.0, 1), b = im.Expected(3.0, 2);
  ASSERT_EQ(a.pixels.size(), b.pixels.size());
  for (size_t i = 0; i < a.pixels.size(); ++i) ASSERT_EQ(a.pixels[i], b.pixels[i]) << i;
}

/// The second difference of the image in one of the sphere's parameters (radius or index, set
/// by `set`) at `step`: sum over pixels of (I(p + step) - 2 I(p) + I(p - step))^2 / I(p), its
/// chi-square as a Poisson deviation; with `layouts`, the three imagers share them.
double SecondDifference(void (*set)(Scene*, double), double step,
                        const std::shared_ptr<FieldLayouts>& layouts) {
  Image img[3];
  for (int k = 0; k < 3; ++k) {
    Scene s = PhysicalScene(40);
    s.trace.physical.window_um = 40;  // as a fit fixes it
    s.objects = {SphereObject(3.0, 1.40)};
    set(&s, (k - 1) * step);
    PhysicalImager im(s);
    if (layouts) im.KeepLayouts(layouts);
    img[k] = im.Expected(3.0, 2);
  }
  double sum = 0;
  for (size_t i = 0; i < img[1].pixels.size(); ++i) {
    const double d = double(img[2].pixels[i]) - 2.0 * img[1].pixels[i] + img[0].pixels[i];
    sum += d * d / img[1].pixels[i];
  }
  return sum;
}

// A fit differentiates the image by central differences a tenth of a parameter's step apart, so
// the image must change smoothly with every parameter. Where it jumps, the second difference
// does not fall as the step's fourth power. Radius: with the layouts kept, the lattice scales
// with the sphere (the same rays hit it) and every refinement decision stays: at a 1e-4 um step
// the second difference is 5e-9 (a smooth function's), against 1.6e-3 without them, where a
// cell count or a refinement test flips. Index: the focal lines are counted between the
// triangles the rays share on each surface and on the exit plane, so a caustic that crosses a
// surface or the plane leaves the field continuous; at a 1e-3 step the second difference is
// 0.03 (the first difference 97), against 3.0 when each segment's count was taken between
// sections at equal optical path. Both with the sheets rasterised by each node's covered share
// of its cell (ray_field.cpp), without which a sheet's edge crossing a node jumps (1.2 at a
// 1e-3 um step of the radius). The bounds lie a factor of 10 or more from either side.
TEST(PhysicalImage, KeptLayoutsMakeTheImageSmoothInRadiusAndIndex) {
  auto radius = [](Scene* s, double d) { s->objects[0].radius_um += d; };
  auto index = [](Scene* s, double d) { s->objects[0].index += d; };
  const double r = SecondDifference(radius, 1e-4, std::make_shared<FieldLayouts>());
  const double n = SecondDifference(index, 1e-3, std::make_shared<FieldLayouts>());
  std::printf("second differences: radius (1e-4 um) %.3g, index (1e-3) %.3g\n", r, n);
  EXPECT_LT(r, 1e-5);
  EXPECT_LT(n, 0.3);
}

TEST(PhysicalImage, ScenesItCannotImageAreRefusedWithTheReason) {
  Scene s = PhysicalScene();
  s.source.type = SourceType::kPoint;
  EXPECT_NE(PhysicalUnsupportedReason(s).find("point source"), std::string::npos);
  EXPECT_THROW(PhysicalImager{s}, Error);
  s = PhysicalScene();
  s.source.type = SourceType::kRayList;
  EXPECT_NE(PhysicalUnsupportedReason(s).find("ray list"), std::string::npos);
  s = PhysicalScene();
  EXPECT_EQ(PhysicalUnsupportedReason(s), "");
}

// The scene keys: [trace] optics = "physical" with its [trace.physical] sampling; that table
// without the optics, and a scene the model cannot image, are refused at the key.
TEST(PhysicalImage, SceneKeysSelectTheModelAndItsSampling) {
  const std::string head =
      "[source]\ntype = \"cone\"\nhalf_angle_deg = 10\n[objective]\nna = 0.42\n"
      "focal_length_mm = 10\n[tube_lens]\nfocal_length_mm = 200\n[camera]\n"
      "pixels = [16, 16]\npixel_pitch_um = 10\n";
  auto load = [&](const std::string& trace) {
    return LoadScene(toml::parse(head + "[trace]\nphotons_per_pixel = 100\n" + trace), "t.toml");
  };
  const Scene s = load(
      "optics = \"physical\"\n[trace.physical]\npolar_nodes = 2\nazimuths = 5\n"
      "spectrum_nodes = 3\nmotion_nodes = 6\n");
  EXPECT_EQ(s.trace.optics, ImageOptics::kPhysical);
  EXPECT_EQ(s.trace.physical.polar_nodes, 2);
  EXPECT_EQ(s.trace.physical.azimuths, 5);
  EXPECT_EQ(s.trace.physical.spectrum_nodes, 3);
  EXPECT_EQ(s.trace.physical.motion_nodes, 6);
  EXPECT_STREQ(ImageOpticsName(s.trace.optics), "physical");
  auto refused = [&](const std::string& trace, const std::string& says) {
    try {
      load(trace);
      ADD_FAILURE() << "expected an error for " << trace;
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(says), std::string::npos) << e.what();
    }
  };
  refused("[trace.physical]\npolar_nodes = 2\n", "needs optics = \"physical\"");
  refused("optics = \"physical\"\n[trace.physical]\npolar_nodes = 0\n", "polar_nodes");
  // A field ray follows at most 8 surface events.
  refused("optics = \"physical\"\n[trace.physical]\nmax_events = 9\n", "max_events");
}

}  // namespace
}  // namespace raymatch::simulate
