// Golden tests of `raymatch simulate` as a user runs it.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <nlohmann/json.hpp>
#include <set>
#include <sstream>

#include "raymatch/core/image_io.h"
#include "shell.h"
#include "temp_dir.h"

namespace fs = std::filesystem;

namespace raymatch {
namespace {

using CliRun = testing::ShellRun;

CliRun Raymatch(const std::string& args, const testing::TempDir& dir) {
  return testing::RunShell(std::string(RAYMATCH_BIN) + " " + args, dir);
}

const char* kScene = R"(name = "tiny"
seed = 7
[source]
type = "cone"
half_angle_deg = 20
[[object]]
type = "sphere"
radius_um = 8
material = "water"
[objective]
focal_length_mm = 10
na = 0.42
[tube_lens]
focal_length_mm = 200
[camera]
pixels = [40, 30]
pixel_pitch_um = 20
[trace]
rays = 200000
[scan]
defocus_um = [-5, 0, 5]
)";

// optics = "mie" and --compare-optics as a user runs them: the wave image's files and sidecar,
// the comparison's files and table; a scene the wave model cannot image is refused at the
// optics key's line.
TEST(SimulateCli, WaveOpticsAndTheComparisonWithRays) {
  testing::TempDir dir;
  std::string text = kScene;
  text.replace(text.find("rays = 200000"), 13,
               "photons_per_pixel = 500\noptics = \"mie\"\n[trace.mie]\nnodes_per_panel = 3");
  const std::string scene = dir.Write("wave.toml", text);
  CliRun r = Raymatch("simulate " + scene + " -o " + (dir / "w") + " --defocus-um 0 -q", dir);
  ASSERT_EQ(r.code, 0) << r.err;
  std::ifstream side(dir / "w/tiny_z+000.00um.json");
  const nlohmann::json j = nlohmann::json::parse(side);
  EXPECT_EQ(j["optics"], "mie");
  EXPECT_GT(j["sampling"]["directions"].get<int>(), 3);
  r = Raymatch("simulate " + scene + " -o " + (dir / "c") + " --defocus-um -5,5 --compare-optics",
               dir);
  ASSERT_EQ(r.code, 0) << r.err;
  std::ifstream so(dir / "stdout.txt");
  const std::string out((std::istreambuf_iterator<char>(so)), std::istreambuf_iterator<char>());
  EXPECT_NE(out.find("chi-square per pixel"), std::string::npos) << out;
  for (const char* f : {"c/tiny_z-005.00um_mie.tif", "c/tiny_z+005.00um_rays.tif",
                        "c/tiny_z+005.00um_z.tif", "c/tiny_z+005.00um_z.png", "c/tiny_optics.csv"})
    EXPECT_TRUE(fs::exists(dir / f)) << f;
  // With optics = "physical" the comparison adds the physical-optics image.
  std::string ptext = kScene;
  ptext.replace(ptext.find("rays = 200000"), 13,
                "photons_per_pixel = 500\noptics = \"physical\"\n[trace.physical]\n"
                "polar_nodes = 1\nazimuths = 2");
  const std::string pscene = dir.Write("phys.toml", ptext);
  r = Raymatch("simulate " + pscene + " -o " + (dir / "p") + " --defocus-um 5 --compare-optics",
               dir);
  ASSERT_EQ(r.code, 0) << r.err;
  for (const char* f : {"p/tiny_z+005.00um_physical.tif", "p/tiny_z+005.00um_z_physical.tif",
                        "p/tiny_z+005.00um_z_physical.png", "p/tiny_z+005.00um_rays.tif"})
    EXPECT_TRUE(fs::exists(dir / f)) << f;
  std::ifstream pcsv(dir / "p/tiny_optics.csv");
  std::string header;
  std::getline(pcsv, header);
  EXPECT_NE(header.find("chi2_physical"), std::string::npos) << header;
  const std::string two =
      dir.Write("two.toml", text +
                                "[[object]]\ntype = \"sphere\"\ncenter_um = [12, 0, 0]\n"
                                "radius_um = 2\nindex = 1.4\n");
  r = Raymatch("simulate " + two + " -o " + (dir / "t"), dir);
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("two.toml:"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("concentric"), std::string::npos) << r.err;
  EXPECT_FALSE(fs::exists(dir / "t"));
}

TEST(SimulateCli, WritesImagesSidecarsAndIndex) {
  testing::TempDir dir;
  const std::string scene = dir.Write("tiny.toml", kScene);
  const CliRun r = Raymatch("simulate " + scene + " -o " + (dir / "out") + " --threads 2", dir);
  ASSERT_EQ(r.code, 0) << r.err;
  for (const char* z : {"-005.00", "+000.00", "+005.00"}) {
    const std::string stem = dir / ("out/tiny_z" + std::string(z) + "um");
    ImageFileInfo info;
    const Image img = ReadImage(stem + ".tif", &info);
    EXPECT_EQ(info.pixel_type, "float");
    EXPECT_EQ(img.width, 40);
    EXPECT_TRUE(fs::exists(stem + ".png"));
    std::ifstream js(stem + ".json");
    const auto j = nlohmann::json::parse(js);
    EXPECT_EQ(j["seed"], 7);
    EXPECT_EQ(j["rays"], 200000);
    uint64_t fates = 0;
    for (auto& [k, v] : j["fates"].items()) fates += v.get<uint64_t>();
    EXPECT_EQ(fates, 200000u);
    double sum = 0;
    for (float v : img.pixels) sum += v;
    EXPECT_EQ(j["hits"].get<double>(), sum);
    EXPECT_NE(j["provenance"]["command_line"].get<std::string>().find("simulate"),
              std::string::npos);
    EXPECT_NE(j["provenance"]["version"].get<std::string>(), "");
  }
  std::ifstream idx(dir / "out/tiny_scan.json");
  EXPECT_EQ(nlohmann::json::parse(idx)["planes"].size(), 3u);
}

TEST(SimulateCli, SameSeedSameImageAcrossThreadCounts) {
  testing::TempDir dir;
  const std::string scene = dir.Write("tiny.toml", kScene);
  ASSERT_EQ(
      Raymatch("simulate " + scene + " -q --no-png --defocus-um 0 --threads 1 -o " + (dir / "a"),
               dir)
          .code,
      0);
  ASSERT_EQ(
      Raymatch("simulate " + scene + " -q --no-png --defocus-um 0 --threads 2 -o " + (dir / "b"),
               dir)
          .code,
      0);
  EXPECT_EQ(ReadImage(dir / "a/tiny_z+000.00um.tif").pixels,
            ReadImage(dir / "b/tiny_z+000.00um.tif").pixels);
}

TEST(SimulateCli, BadSceneGivesLocatedErrorAndNoOutput) {
  testing::TempDir dir;
  std::string bad = kScene;
  bad.replace(bad.find("radius_um = 8"), 13, "radius_um = 0");
  const std::string scene = dir.Write("bad.toml", bad);
  const CliRun r = Raymatch("simulate " + scene + " -o " + (dir / "out"), dir);
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("bad.toml:8:13: error: 'object[0].radius_um': expected a positive number"),
            std::string::npos)
      << r.err;
  EXPECT_FALSE(fs::exists(dir / "out"));
  // Usage errors exit 2.
  EXPECT_EQ(Raymatch("simulate", dir).code, 2);
  EXPECT_EQ(Raymatch("simulate " + (dir / "missing.toml"), dir).code, 2);
}

// Issue 15 defect 2: names rounded to 0.01 um made 48.331 and 48.334 one file (a plane lost
// silently). Distinct positions give distinct files; a repeated position is an error.
TEST(SimulateCli, CloseFocusPositionsGetTheirOwnFiles) {
  testing::TempDir dir;
  const std::string scene = dir.Write("tiny.toml", kScene);
  const CliRun r = Raymatch("simulate " + scene +
                                " -q --no-png --rays 2000 --defocus-um "
                                "48.331,48.334,-0.125,0.1,-10 -o " +
                                (dir / "out"),
                            dir);
  ASSERT_EQ(r.code, 0) << r.err;
  for (const char* z : {"+048.331", "+048.334", "-000.125", "+000.10", "-010.00"})
    EXPECT_TRUE(fs::exists(dir / ("out/tiny_z" + std::string(z) + "um.tif"))) << z;
  std::ifstream idx(dir / "out/tiny_scan.json");
  const auto planes = nlohmann::json::parse(idx)["planes"];
  ASSERT_EQ(planes.size(), 5u);
  std::set<std::string> images;
  for (const auto& p : planes) images.insert(p["image"].get<std::string>());
  EXPECT_EQ(images.size(), 5u);
  std::ifstream csv(dir / "out/tiny_scan.csv");
  std::stringstream text;
  text << csv.rdbuf();
  EXPECT_NE(text.str().find("48.331,"), std::string::npos) << text.str();
  EXPECT_NE(text.str().find("\n-10,tiny_z-010.00um.tif,"), std::string::npos)  // not -1e+01
      << text.str();

  const CliRun twice = Raymatch("simulate " + scene +
                                    " -q --no-png --rays 2000 --defocus-um "
                                    "5,0,5 -o " +
                                    (dir / "dup"),
                                dir);
  EXPECT_EQ(twice.code, 1);
  EXPECT_NE(twice.err.find("focus position 5 um is listed twice"), std::string::npos) << twice.err;
  EXPECT_FALSE(fs::exists(dir / "dup"));
}

// Issue 15 defect 7: the sidecar records the objective's NA, how a water density was chosen and
// the per-order (Debye path class) counts.
TEST(SimulateCli, SidecarRecordsNaDensityAndPathClasses) {
  testing::TempDir dir;
  std::string text = kScene;
  text.replace(text.find("material = \"water\""), 18,
               "material = \"water\"\ntemperature_K = 293.15");
  const std::string scene = dir.Write("tiny.toml", "medium_index = 1.33\n" + text);
  ASSERT_EQ(
      Raymatch("simulate " + scene + " -q --no-png --rays 20000 --defocus-um 0 -o " + (dir / "out"),
               dir)
          .code,
      0);
  std::ifstream js(dir / "out/tiny_z+000.00um.json");
  const auto j = nlohmann::json::parse(js);
  EXPECT_EQ(j["objective"]["na"], 0.42);
  EXPECT_DOUBLE_EQ(j["objective"]["acceptance_sin_theta_in_medium"].get<double>(), 0.42 / 1.33);
  EXPECT_EQ(j["objects"][0]["density_given"], false);
  EXPECT_NE(j["objects"][0]["density"].get<std::string>().find("defaulted"), std::string::npos);
  uint64_t classes = 0;
  ASSERT_EQ(j["path_classes"].size(), 8u);
  for (auto& [k, v] : j["path_classes"].items()) classes += v.get<uint64_t>();
  EXPECT_GT(j["path_classes"]["p1"].get<uint64_t>(), 0u);
  EXPECT_LE(classes, j["counters"]["rays_hitting_objects"].get<uint64_t>());
  EXPECT_GT(classes, 0u);
}

// Issue 22 item 3: with [camera.readout] a plane is also written as the camera's code values
// (uint16), the raw frame a camera would store: per pixel DN = round((counts + read noise) /
// gain + dark). Checked against the counts of the same plane: the mean of DN - counts / gain -
// dark is 0 and its variance (read / gain)^2 + 1/12 (quantisation), within 5 standard errors
// over the 1200 pixels; the sidecar records the model and the clipped pixels.
TEST(SimulateCli, ReadoutWritesCodeValuesLikeARawFrame) {
  testing::TempDir dir;
  std::string text = kScene;
  text.replace(
      text.find("[trace]"), 7,
      "[camera.readout]\ngain_e_per_dn = 2\ndark_dn = 100\nread_noise_e = 6\nbit_depth = 12\n"
      "well_capacity_e = 1e6\n[trace]");
  const std::string scene = dir.Write("tiny.toml", text);
  ASSERT_EQ(
      Raymatch("simulate " + scene + " -q --no-png --defocus-um 0 -o " + (dir / "out"), dir).code,
      0);
  const std::string stem = dir / "out/tiny_z+000.00um";
  ImageFileInfo info;
  const Image dn = ReadImage(stem + "_dn.tif", &info);
  EXPECT_EQ(info.pixel_type, "uint16");
  const Image counts = ReadImage(stem + ".tif");
  ASSERT_EQ(dn.size(), counts.size());
  double m = 0, v = 0;
  for (size_t i = 0; i < dn.size(); ++i) m += dn.pixels[i] - counts.pixels[i] / 2.0 - 100;
  m /= double(dn.size());
  for (size_t i = 0; i < dn.size(); ++i) {
    const double d = dn.pixels[i] - counts.pixels[i] / 2.0 - 100 - m;
    v += d * d;
  }
  v /= double(dn.size() - 1);
  const double var = 9 + 1.0 / 12, n = double(dn.size());
  EXPECT_NEAR(m, 0, 5 * std::sqrt(var / n));
  EXPECT_NEAR(v, var, 5 * var * std::sqrt(2 / (n - 1)));
  std::ifstream js(stem + ".json");
  const auto j = nlohmann::json::parse(js)["code_values"];
  EXPECT_EQ(j["image"], "tiny_z+000.00um_dn.tif");
  EXPECT_EQ(j["bit_depth"], 12);
  EXPECT_EQ(j["saturated_pixels"], 0);
  EXPECT_EQ(j["clipped_low_pixels"], 0);
  std::ifstream idx(dir / "out/tiny_scan.json");
  EXPECT_EQ(nlohmann::json::parse(idx)["planes"][0]["code_values"], "tiny_z+000.00um_dn.tif");
  // Without [camera.readout], photon counts only.
  ASSERT_EQ(Raymatch("simulate " + dir.Write("plain.toml", kScene) +
                         " -q --no-png --defocus-um 0 -o " + (dir / "plain"),
                     dir)
                .code,
            0);
  EXPECT_FALSE(fs::exists(dir / "plain/tiny_z+000.00um_dn.tif"));
}

TEST(SimulateCli, SampleSceneIsValid) {
  testing::TempDir dir;
  const CliRun r = Raymatch("simulate " + std::string(RAYMATCH_SOURCE_DIR) +
                                "/datasets-sample/drop46/scene.toml -q --no-png --rays 20000 "
                                "--defocus-um 0 -o " +
                                (dir / "out"),
                            dir);
  EXPECT_EQ(r.code, 0) << r.err;
}

// `fit` says a model mismatch on stdout and by its exit code (4), so a script can catch it: an
// experiment blurred by a 1 um camera PSF fitted with a model that has none. The same fit with
// the PSF in the model is consistent (exit 0).
TEST(FitCli, ModelMismatchExitsFourAndAConsistentFitZero) {
  testing::TempDir dir;
  auto scene = [](double x, int seed, double psf) {
    std::ostringstream s;
    s << "name = \"drop\"\nseed = " << seed
      << "\n[source]\ntype = \"cone\"\nhalf_angle_deg = 27\n[[object]]\nname = \"drop\"\n"
         "type = \"sphere\"\ncenter_um = ["
      << x
      << ", 0, 0]\nradius_um = 23\nindex = 1.335\n"
         "[objective]\nfocal_length_mm = 10\nna = 0.42\n[tube_lens]\nfocal_length_mm = 200\n"
         "[camera]\npixels = [64, 56]\npixel_pitch_um = 20\n"
      << (psf > 0 ? "psf_sigma_um = " + std::to_string(psf) + "\n" : "")
      << "[trace]\nphotons_per_pixel = 400\n";
    return s.str();
  };
  const std::string truth = dir.Write("truth.toml", scene(0.3, 9, 1.0));
  const CliRun sim =
      Raymatch("simulate " + truth + " -q -o " + (dir / "exp") + " --defocus-um -10", dir);
  ASSERT_EQ(sim.code, 0) << sim.err;
  std::string tif;
  for (const auto& e : fs::directory_iterator(dir / "exp"))
    if (e.path().extension() == ".tif") tif = e.path().string();
  ASSERT_FALSE(tif.empty());
  for (const double psf : {0.0, 1.0}) {
    const std::string name = psf > 0 ? "with" : "without";
    dir.Write(name + ".toml", scene(0, 1, psf));
    const std::string fit = dir.Write(
        name + "_fit.toml",
        "scene = \"" + name + ".toml\"\nseed = 3\n[[image]]\nfile = \"" + tif +
            "\"\ndefocus_um = -10\n[[parameter]]\nkey = \"object.drop.center_um[0]\"\n"
            "lower = -2\nupper = 2\nstep = 0.2\n[[parameter]]\nkey = \"object.drop.radius_um\"\n"
            "lower = 21\nupper = 25\nstep = 0.2\n[uncertainty]\nrepeat_seeds = 0\n"
            "slice_points = 0\n");
    const CliRun r = Raymatch("fit " + fit + " -o " + (dir / name), dir);
    std::ifstream so(dir / "stdout.txt");
    const std::string out{std::istreambuf_iterator<char>(so), {}};
    std::ifstream in(dir / (name + "/fit.json"));
    ASSERT_TRUE(in) << r.err;
    const nlohmann::json j = nlohmann::json::parse(in);
    const bool mismatch = j["goodness_of_fit"]["model_mismatch"].get<bool>();
    EXPECT_EQ(mismatch, psf == 0) << out;
    EXPECT_EQ(r.code, psf == 0 ? 4 : 0) << out << r.err;
    EXPECT_EQ(out.find("WARNING: model mismatch") != std::string::npos, psf == 0) << out;
  }
}

}  // namespace
}  // namespace raymatch

namespace raymatch {
namespace {

// compare / compare-scan exit codes as documented (docs/compare.md): 0 ok/pass, 3 size
// mismatch, 4 file error.
TEST(CompareCli, ExitCodes) {
  testing::TempDir dir;
  const std::string root = std::string(RAYMATCH_SOURCE_DIR) + "/datasets-sample/drop46/";
  // The experiment against itself passes.
  EXPECT_EQ(Raymatch("compare-scan " + root + "scan.csv " + root + "scan.csv --dark " + root +
                         "dark.tif --gain 1.0989 -o " + (dir / "self"),
                     dir)
                .code,
            0);
  EXPECT_TRUE(std::filesystem::exists(dir / "self/report.html"));
  EXPECT_EQ(
      Raymatch("compare " + root + "drop_z+00um.tif " + root + "drop_z+05um.tif -L 4095", dir).code,
      0);
  WriteFloatImage(dir / "tiny.tif", Image(8, 8, 1.f), "");
  EXPECT_EQ(
      Raymatch("compare " + root + "drop_z+00um.tif " + (dir / "tiny.tif") + " -L 4095", dir).code,
      3);
  EXPECT_EQ(
      Raymatch("compare " + root + "drop_z+00um.tif " + (dir / "none.tif") + " -L 4095", dir).code,
      4);
  EXPECT_EQ(Raymatch("compare-scan " + (dir / "none.csv") + " " + root + "scan.csv", dir).code, 4);
  const std::string tiny = dir.Write("tiny.csv", "0,tiny.tif\n");
  EXPECT_EQ(Raymatch("compare-scan " + tiny + " " + root + "scan.csv -o " + (dir / "x"), dir).code,
            3);
}

// Issue 15 defect 7: `-L 0` is a usage error (exit 2, docs/compare.md) whose message says what L
// must be, not CLI11's range with a 300-digit upper bound.
TEST(CompareCli, DataRangeMessageIsShort) {
  testing::TempDir dir;
  const std::string root = std::string(RAYMATCH_SOURCE_DIR) + "/datasets-sample/drop46/";
  for (const char* L : {"0", "-3", "abc"}) {
    const CliRun r =
        Raymatch("compare " + root + "drop_z+00um.tif " + root + "drop_z+05um.tif -L " + L, dir);
    EXPECT_EQ(r.code, 2) << L;
    EXPECT_NE(r.err.find("the data range L must be a number > 0"), std::string::npos) << r.err;
    EXPECT_LT(r.err.size(), 400u) << r.err;
  }
  const CliRun neg = Raymatch(
      "compare-scan " + root + "scan.csv " + root + "scan.csv -L -1 -o " + (dir / "n"), dir);
  EXPECT_EQ(neg.code, 2);
  EXPECT_NE(neg.err.find("the data range L must be a number >= 0"), std::string::npos) << neg.err;
  std::ifstream doc(std::string(RAYMATCH_SOURCE_DIR) + "/docs/compare.md");
  std::stringstream d;
  d << doc.rdbuf();
  EXPECT_NE(d.str().find("**or invalid options or input**"), std::string::npos);
}

// The multi-scale settings reach the measures and are recorded in the JSON; a setting outside
// what cwssim_index/multissim accept is a usage error (exit 2) or a failed comparison.
TEST(CompareCli, MultiscaleSettingsAreUsedAndRecorded) {
  testing::TempDir dir;
  const std::string root = std::string(RAYMATCH_SOURCE_DIR) + "/datasets-sample/drop46/";
  const std::string pair =
      "compare " + root + "drop_z+00um.tif " + root + "drop_z+05um.tif -L 4095 ";
  ASSERT_EQ(Raymatch(pair + "--json " + (dir / "d.json"), dir).code, 0);
  ASSERT_EQ(Raymatch(pair +
                         "--ms-ssim-weights wang2003 --ms-ssim-scales 5 --cw-ssim-orientations 8 "
                         "--cw-ssim-k 0.01 --json " +
                         (dir / "s.json"),
                     dir)
                .code,
            0);
  std::ifstream fd(dir / "d.json"), fs(dir / "s.json");
  const auto d = nlohmann::json::parse(fd), s = nlohmann::json::parse(fs);
  EXPECT_EQ(d["ms_ssim"]["weights"], "matlab");
  EXPECT_EQ(d["ms_ssim"]["scales_used"], 7);  // 160x120: multissim accepts 8 scales
  EXPECT_EQ(d["cw_ssim"]["orientations"], 16);
  EXPECT_EQ(s["ms_ssim"]["weights"], "wang2003");
  EXPECT_EQ(s["ms_ssim"]["scales_used"], 5);
  EXPECT_NEAR(s["ms_ssim"]["per_scale"][0]["weight"].get<double>(), 0.0448 / 1.0001, 1e-12);
  EXPECT_EQ(s["cw_ssim"]["orientations"], 8);
  EXPECT_EQ(s["cw_ssim"]["per_orientation"].size(), 8u);
  EXPECT_EQ(s["cw_ssim"]["k"], 0.01);
  EXPECT_NE(s["cw_ssim"]["value"], d["cw_ssim"]["value"]);
  EXPECT_EQ(Raymatch(pair + "--ms-ssim-weights gaussian", dir).code, 2);
  EXPECT_EQ(Raymatch(pair + "--cw-ssim-orientations 32", dir).code, 2);
  const CliRun too_many = Raymatch(pair + "--ms-ssim-scales 9", dir);
  EXPECT_EQ(too_many.code, 2);
  EXPECT_NE(too_many.err.find("at most 8"), std::string::npos) << too_many.err;
}
}  // namespace
}  // namespace raymatch
