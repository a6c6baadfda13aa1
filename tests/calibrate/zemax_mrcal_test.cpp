// Zemax binary source files (layout, round trip, sampler statistics) and the mrcal
// .cameramodel light-field path against synthetic truth.
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <random>

#include "raymatch/calibrate/lightfield.h"
#include "raymatch/calibrate/mrcal_lightfield.h"
#include "raymatch/calibrate/zemax_source.h"
#include "raymatch/core/calibration_file.h"
#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "temp_dir.h"

namespace raymatch::calibrate {
namespace {

std::string Bytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}
int32_t I32At(const std::string& b, size_t off) {
  int32_t v;
  std::memcpy(&v, b.data() + off, 4);  // host is little-endian (x86/ARM): checked below
  return v;
}
float F32At(const std::string& b, size_t off) {
  float v;
  std::memcpy(&v, b.data() + off, 4);
  return v;
}

TEST(ZemaxSource, HeaderLayoutIsTheDocumentedOne) {
  const uint16_t probe = 1;
  ASSERT_EQ(*reinterpret_cast<const uint8_t*>(&probe), 1) << "test assumes a little-endian host";
  testing::TempDir dir;
  ZemaxSourceFile f;
  ZemaxSourceHeader& h = f.header;
  // Distinct values everywhere so a shifted field cannot pass.
  h.description = "layout probe";
  h.source_flux = 2.5f, h.ray_set_flux = 1.25f, h.wavelength_um = 0.405f;
  h.inclination_begin = 1, h.inclination_end = 2, h.azimuth_begin = 3, h.azimuth_end = 4;
  h.dimension_units = 2;
  h.location = {5, 6, 7}, h.rotation = {8, 9, 10}, h.scale = {11, 12, 13};
  h.unused = {14, 15, 16, 17};
  h.ray_format = 2, h.flux_type = 1, h.reserved = {18, 19};
  f.rays = {{0.1f, 0.2f, 0.3f, 0.6f, 0.0f, 0.8f, 0.5f, 0.462f}, {1, 2, 3, 0, 0, 1, 0.25f, 0.5f}};
  WriteZemaxSourceFile(dir / "probe.dat", f);
  const std::string b = Bytes(dir / "probe.dat");
  ASSERT_EQ(b.size(), 208u + 2 * 32);
  EXPECT_EQ(I32At(b, 0), 1010);
  EXPECT_EQ(I32At(b, 4), 2);
  EXPECT_EQ(std::string(b.data() + 8), "layout probe");
  EXPECT_EQ(b[8 + 99], '\0');
  EXPECT_EQ(F32At(b, 108), 2.5f);
  EXPECT_EQ(F32At(b, 112), 1.25f);
  EXPECT_EQ(F32At(b, 116), 0.405f);
  for (int i = 0; i < 4; ++i) EXPECT_EQ(F32At(b, 120 + 4 * i), float(1 + i));
  EXPECT_EQ(I32At(b, 136), 2);
  for (int i = 0; i < 13; ++i)
    EXPECT_EQ(F32At(b, 140 + 4 * i), float(5 + i)) << "offset " << 140 + 4 * i;
  EXPECT_EQ(I32At(b, 192), 2);
  EXPECT_EQ(I32At(b, 196), 1);
  EXPECT_EQ(I32At(b, 200), 18);
  EXPECT_EQ(I32At(b, 204), 19);
  EXPECT_EQ(F32At(b, 208 + 3 * 4), 0.6f);    // first ray's l
  EXPECT_EQ(F32At(b, 208 + 7 * 4), 0.462f);  // first ray's wavelength
  // Reading gives back every field bit-exactly.
  const ZemaxSourceFile g = ReadZemaxSourceFile(dir / "probe.dat");
  EXPECT_EQ(g.header.description, h.description);
  EXPECT_EQ(std::memcmp(&g.header.source_flux, &h.source_flux, 7 * sizeof(float)), 0);
  EXPECT_EQ(g.header.location, h.location);
  EXPECT_EQ(g.header.rotation, h.rotation);
  EXPECT_EQ(g.header.scale, h.scale);
  EXPECT_EQ(g.header.unused, h.unused);
  EXPECT_EQ(g.header.reserved, h.reserved);
  EXPECT_EQ(g.header.dimension_units, 2);
  EXPECT_EQ(g.header.flux_type, 1);
  ASSERT_EQ(g.rays.size(), 2u);
  EXPECT_EQ(std::memcmp(&g.rays[0], &f.rays[0], sizeof(ZemaxRay)), 0);
  EXPECT_EQ(std::memcmp(&g.rays[1], &f.rays[1], sizeof(ZemaxRay)), 0);
}

TEST(ZemaxSource, BadFilesSayWhatIsWrong) {
  testing::TempDir dir;
  ZemaxSourceFile f;
  f.rays.resize(3);
  WriteZemaxSourceFile(dir / "ok.dat", f);
  std::string b = Bytes(dir / "ok.dat");
  ASSERT_EQ(b.size(), 208u + 3 * 28);
  std::ofstream(dir / "short.dat", std::ios::binary) << b.substr(0, b.size() - 5);
  try {
    ReadZemaxSourceFile(dir / "short.dat");
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("3 rays of 28 bytes need 292"), std::string::npos)
        << e.what();
  }
  b[0] = 0x12;
  std::ofstream(dir / "id.dat", std::ios::binary) << b;
  try {
    ReadZemaxSourceFile(dir / "id.dat");
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("byte 0: identifier"), std::string::npos) << e.what();
  }
  EXPECT_THROW(ReadZemaxSourceFile(dir / "missing.dat"), Error);
  f.header.ray_format = 1;
  EXPECT_THROW(WriteZemaxSourceFile(dir / "fmt.dat", f), Error);
  EXPECT_FALSE(std::filesystem::exists(dir / "fmt.dat"));
}

// A soft-edged 20 deg cone with a radial rise and an off-axis centre, as an angular map.
CalibrationData ConeCalibration(int n, double extent) {
  CalibrationData c;
  c.angular_map = Image(n, n);
  c.angular_extent = extent;
  c.field_radius_um = 150;
  c.wavelength_um = 0.462;
  const double se = std::sin(20 * M_PI / 180);
  for (int y = 0; y < n; ++y)
    for (int x = 0; x < n; ++x) {
      const double u = (2 * (x + 0.5) / n - 1) * extent - 0.02,
                   v = (1 - 2 * (y + 0.5) / n) * extent;
      const double s = std::hypot(u, v);
      c.angular_map.at(x, y) =
          float((1 + 0.2 * s * s / (se * se)) * 0.5 * (1 - std::tanh((s - se) / 0.01)));
    }
  return c;
}

TEST(ZemaxSource, ExportImportRoundTripMatchesTheMapStatistically) {
  testing::TempDir dir;
  const int n = 32;
  const double ext = 0.45;
  const CalibrationData cal = ConeCalibration(n, ext);
  ZemaxExportOptions eo;
  eo.num_rays = 400000;
  eo.seed = 7;
  const ZemaxSourceFile f = SampleZemaxSource(cal, eo);
  WriteZemaxSourceFile(dir / "lf.dat", f);
  const ZemaxSourceFile g = ReadZemaxSourceFile(dir / "lf.dat");
  ASSERT_EQ(g.rays.size(), f.rays.size());
  for (size_t i = 0; i < f.rays.size(); i += 997)
    ASSERT_EQ(std::memcmp(&g.rays[i], &f.rays[i], 7 * sizeof(float)), 0) << "ray " << i;
  ZemaxImportOptions io;
  io.map_size = n;
  io.extent = ext;
  const ZemaxImportSummary s = AngularMapFromZemax(g, io);
  EXPECT_EQ(s.rays_used, eo.num_rays);
  // Uniform disc: sqrt(2) x RMS radius estimates R with relative sd ~0.58 / sqrt(N) / 2 < 1e-3.
  EXPECT_NEAR(s.data.field_radius_um, 150, 0.5);
  // Cell counts against the map's probabilities: chi-square per degree of freedom within
  // 1 + 5 sqrt(2 / dof) (Poisson counts, CONVENTIONS 9), and no rays where the map is zero.
  double total = 0;
  for (float v : cal.angular_map.pixels) total += v;
  const double cell = (2 * ext / n) * (2 * ext / n), per_ray = 1.0 / eo.num_rays;
  double chi2 = 0;
  int dof = 0;
  for (size_t i = 0; i < cal.angular_map.size(); ++i) {
    const double expected = eo.num_rays * cal.angular_map.pixels[i] / total;
    const double observed = s.data.angular_map.pixels[i] * cell / per_ray;
    if (expected < 1e-9) {
      EXPECT_LT(observed, 0.5) << "cell " << i;
      continue;
    }
    if (expected < 20) continue;  // chi-square needs enough counts per cell
    chi2 += (observed - expected) * (observed - expected) / expected;
    ++dof;
  }
  ASSERT_GT(dof, 300);
  EXPECT_LT(chi2 / dof, 1 + 5 * std::sqrt(2.0 / dof)) << "dof " << dof;
  EXPECT_GT(chi2 / dof, 1 - 5 * std::sqrt(2.0 / dof)) << "dof " << dof;
  // Within a cell the directions are uniform: on a grid twice as fine each sub-cell expects a
  // quarter of its parent's rays (catches e.g. rays placed at cell centres).
  io.map_size = 2 * n;
  const ZemaxImportSummary fine = AngularMapFromZemax(g, io);
  const double fine_cell = cell / 4;
  double chi2f = 0;
  int doff = 0;
  for (int y = 0; y < 2 * n; ++y)
    for (int x = 0; x < 2 * n; ++x) {
      const double expected = eo.num_rays * cal.angular_map.at(x / 2, y / 2) / total / 4;
      if (expected < 20) continue;
      const double observed = fine.data.angular_map.at(x, y) * fine_cell / per_ray;
      chi2f += (observed - expected) * (observed - expected) / expected;
      ++doff;
    }
  ASSERT_GT(doff, 1000);
  EXPECT_LT(chi2f / doff, 1 + 5 * std::sqrt(2.0 / doff)) << "dof " << doff;
  // A different seed gives different rays (the sampler is not degenerate).
  eo.seed = 8;
  EXPECT_NE(SampleZemaxSource(cal, eo).rays[0].l, f.rays[0].l);
  // Import into a calibration file that reads back.
  CalibrationData base = cal;
  base.objective_focal_mm = 10, base.working_distance_mm = 20, base.na = 0.42,
  base.tube_focal_mm = 200;
  base.pixel_pitch_um = 10;
  const ZemaxImportSummary imp = ImportZemaxLightField(g, io, base, dir / "lf.dat");
  WriteCalibrationFile(dir / "imported.toml", imp.data);
  const CalibrationData back = ReadCalibrationFile(dir / "imported.toml");
  EXPECT_EQ(back.angular_map.pixels, imp.data.angular_map.pixels);
  EXPECT_NE(back.provenance["light_field_inputs"].get<std::string>().find("lf.dat"),
            std::string::npos);
}

// ---- mrcal path -------------------------------------------------------------------------

constexpr int kW = 200, kH = 160;
constexpr double kF = 300;  // focal length, pixels
constexpr double kU0 = 0.03, kV0 = -0.02, kEdgeDeg = 12;

double TruthRadiance(double u, double v) {  // per du dv, plateau ~1 with a radial rise
  const double se = std::sin(kEdgeDeg * M_PI / 180), s = std::hypot(u - kU0, v - kV0);
  return (1 + 0.1 * s * s / (se * se)) * 0.5 * (1 - std::tanh((s - se) / 0.004));
}

void WriteMrcalFolder(const testing::TempDir& dir, double photons_scale, int imager_w = kW) {
  const double cx = (kW - 1) / 2.0, cy = (kH - 1) / 2.0;  // mrcal: pixel centres at integers
  std::ofstream(dir / "cam.cameramodel")
      << "# a pinhole camera focused at infinity, looking back at the source\n"
      << "{\n    'lensmodel':  'LENSMODEL_PINHOLE',\n    'intrinsics': [ " << kF << ", " << kF
      << ", " << cx << ", " << cy << " ],\n    'imagersize': [ " << imager_w << ", " << kH
      << " ],\n    'extrinsics': [ 0., 0., 0., 0., 0., 0. ],\n}\n";
  std::mt19937_64 rng(5);
  Image dn(kW, kH);
  for (int y = 0; y < kH; ++y)
    for (int x = 0; x < kW; ++x) {
      // Analytic pinhole unprojection (independent of mrcal): camera ray (a, b, 1); light
      // direction u = -a / |d|, v = b / |d|; pixel area in (u, v): 1 / (f^2 (1 + a^2 + b^2)^2).
      const double a = (x - cx) / kF, b = (y - cy) / kF, len = std::sqrt(1 + a * a + b * b);
      const double area = 1 / (kF * kF * std::pow(1 + a * a + b * b, 2));
      const double mean = photons_scale * TruthRadiance(-a / len, b / len) * area;
      dn.at(x, y) = float(100 + std::poisson_distribution<int>(mean)(rng));
    }
  WriteUint16Image(dir / "sky.tif", dn, "");
  WriteUint16Image(dir / "dark.tif", Image(kW, kH, 100.f), "");
  std::ofstream(dir / "metadata.toml")
      << "camera_model = \"cam.cameramodel\"\ndark = \"dark.tif\"\nfield_radius_um = 100\n"
      << "[[direction]]\nfile = \"sky.tif\"\n"
      << "[camera]\npixel_pitch_um = 10\nbit_depth = 16\n"
      << "[optics]\nobjective_focal_mm = 10\nna = 0.42\ntube_focal_mm = 200\n";
}

// The ray list keeps each ray exactly: units converted to um (cm here), rays not towards +z
// skipped and counted.
TEST(ZemaxSource, RayListKeepsTheRaysInMicrometres) {
  ZemaxSourceFile f;
  f.header.dimension_units = 2;  // cm
  f.rays = {{0.001f, -0.002f, 0, 0.1f, 0.2f, std::sqrt(0.95f), 2.5f, 0},
            {0, 0, 0, 0, 0, -1, 1, 0},  // backwards: skipped
            {-0.0005f, 0, 0, 0, 0, 1, 1, 0}};
  uint64_t skipped = 0;
  const NdArray a = ZemaxRayList(f, &skipped);
  ASSERT_EQ(a.shape, (std::vector<size_t>{2, 5}));
  EXPECT_EQ(skipped, 1u);
  EXPECT_NEAR(a.values[0], 10, 1e-3);  // 0.001 cm = 10 um
  EXPECT_NEAR(a.values[1], -20, 1e-3);
  EXPECT_NEAR(a.values[2], 0.1, 1e-7);
  EXPECT_NEAR(a.values[3], 0.2, 1e-7);
  EXPECT_EQ(a.values[4], 2.5);
  EXPECT_NEAR(a.values[5], -5, 1e-3);
}

TEST(MrcalLightField, RecoversConeAndProfileFromAPinholeCameraModel) {
  if (!MrcalAvailable()) GTEST_SKIP() << "built without mrcal";
  testing::TempDir dir;
  const double scale = 2000 * kF * kF;  // ~2000 photons per plateau pixel
  WriteMrcalFolder(dir, scale);
  LightFieldOptions o;
  o.map_size = 48;
  const LightFieldSummary s = CalibrateLightField(ReadLightFieldInput(dir.path().string()), o);
  const CalibrationData& d = s.data;
  EXPECT_EQ(d.na_limit, 0);
  EXPECT_EQ(d.field_radius_um, 100);
  // Edge from the area above half the plateau: cells of 0.02 in (u, v) classified along a
  // perimeter of ~65 cells give ~1 % in area, 0.07 deg; 0.3 deg is > 4 sigma.
  EXPECT_NEAR(d.cone_half_angle_deg, kEdgeDeg, 0.3) << s.BriefReport();
  // Orientation (the 180 degree turn of a camera looking back): the map's centroid is the
  // cone centre (kU0, kV0) to within a tenth of a cell.
  const Image& m = d.angular_map;
  const int n = m.width;
  const double ext = d.angular_extent;
  double w = 0, su = 0, sv = 0, ratio = 0, ratio2 = 0;
  int cells = 0;
  for (int y = 0; y < n; ++y)
    for (int x = 0; x < n; ++x) {
      const double u = (2 * (x + 0.5) / n - 1) * ext, v = (1 - 2 * (y + 0.5) / n) * ext;
      w += m.at(x, y), su += m.at(x, y) * u, sv += m.at(x, y) * v;
      // Profile: radiance per du dv against truth well inside the edge. ~36 pixels x 2000
      // photons per cell: 0.4 % Poisson; rms of the ratio < 1.5 %, its mean within 0.5 %.
      if (std::hypot(u - kU0, v - kV0) < 0.8 * std::sin(kEdgeDeg * M_PI / 180)) {
        const double r = m.at(x, y) / (scale * TruthRadiance(u, v));
        ratio += r, ratio2 += r * r, ++cells;
      }
    }
  EXPECT_NEAR(su / w, kU0, 0.002);
  EXPECT_NEAR(sv / w, kV0, 0.002);
  ASSERT_GT(cells, 100);
  const double mean = ratio / cells, rms = std::sqrt(ratio2 / cells - mean * mean);
  EXPECT_NEAR(mean, 1, 0.005);
  EXPECT_LT(rms, 0.015);
}

TEST(MrcalLightField, ImagerSizeMismatchIsAnError) {
  if (!MrcalAvailable()) GTEST_SKIP() << "built without mrcal";
  testing::TempDir dir;
  WriteMrcalFolder(dir, 1e7, kW + 2);
  try {
    CalibrateLightField(ReadLightFieldInput(dir.path().string()), {});
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("imager is 202x160 but the image is 200x160"),
              std::string::npos)
        << e.what();
  }
  std::ofstream(dir / "cam.cameramodel") << "{ 'lensmodel': 'LENSMODEL_NOPE' }\n";
  EXPECT_THROW(CalibrateLightField(ReadLightFieldInput(dir.path().string()), {}), Error);
}

}  // namespace
}  // namespace raymatch::calibrate
