// raymatch compare: similarity of two images (MSE, PSNR, SSIM, MS-SSIM, CW-SSIM, Poisson).
#include <iostream>
#include <nlohmann/json.hpp>

#include "commands.h"
#include "compare_common.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/image_io.h"

namespace raymatch::apps {

namespace {

struct CompareCliOptions {
  std::string a, b, json;
  double data_range = 0;
  compare::MsSsimOptions ms;
  compare::CwSsimOptions cw;
  double fail_below = -1;  // MS-SSIM threshold for exit code 2
};

int RunCompare(const CompareCliOptions& o) {
  auto load = [](const std::string& p) {
    try {
      return ReadImage(p);
    } catch (const Error& e) {
      const bool nan = e.message().find("NaN") != std::string::npos;
      throw compare::CompareError(
          nan ? compare::FailureKind::kInvalidInput : compare::FailureKind::kFileError, e.where(),
          e.message());
    }
  };
  const Image a = load(o.a), b = load(o.b);
  compare::CheckComparable(a, b, o.a + " vs " + o.b);
  const double L = o.data_range;
  compare::SsimOptions so;
  so.data_range = L;
  compare::MsSsimOptions mo = o.ms;
  mo.data_range = L;
  compare::CwSsimOptions co = o.cw;
  co.data_range = L;
  const auto ssim = compare::Ssim(a, b, so);
  const auto ms = compare::MsSsim(a, b, mo);
  const auto cw = compare::CwSsim(a, b, co);
  const auto po = compare::PoissonMeasures(a, b);
  nlohmann::json scales = nlohmann::json::array();
  for (const auto& s : ms.scales)
    scales.push_back({{"width", s.width},
                      {"height", s.height},
                      {"weight", s.weight},
                      {"cs", s.cs},
                      {"ssim", s.ssim}});
  const nlohmann::json j = {{"a", o.a},
                            {"b", o.b},
                            {"data_range", L},
                            {"mse", compare::MeanSquaredError(a, b)},
                            {"psnr_db", compare::PeakSignalToNoiseRatio(a, b, L)},
                            {"ssim", ssim.ssim},
                            {"ms_ssim",
                             {{"value", ms.ms_ssim},
                              {"scales_used", ms.num_scales},
                              {"max_scales", ms.max_scales},
                              {"weights", compare::MsSsimWeightsName(mo.weights)},
                              {"sigma_px", mo.sigma},
                              {"per_scale", scales}}},
                            {"cw_ssim",
                             {{"value", cw.cw_ssim},
                              {"level", cw.level},
                              {"max_level", cw.max_level},
                              {"orientations", co.orientations},
                              {"k", co.k},
                              {"window_px", co.window},
                              {"per_orientation", cw.per_orientation}}},
                            {"poisson",
                             {{"chi2_per_pixel", po.chi2_per_pixel},
                              {"deviance_per_pixel", po.deviance_per_pixel},
                              {"clamped_pixels", po.clamped_pixels}}}};
  std::cout << j.dump(2) << "\n";
  if (!o.json.empty()) WriteTextFileAtomic(o.json, j.dump(2) + "\n");
  return o.fail_below >= 0 && ms.ms_ssim < o.fail_below ? kFail : kOk;
}

}  // namespace

void RegisterCompare(CLI::App& app, int* exit_code) {
  auto o = std::make_shared<CompareCliOptions>();
  CLI::App* sub = app.add_subcommand(
      "compare",
      "Compare two images: MSE, PSNR, SSIM (as MATLAB ssim), MS-SSIM (as MATLAB multissim),\n"
      "CW-SSIM (Sampat 2009) and Poisson chi-square/deviance per pixel. Prints JSON.\n"
      "Exit: 0 ok, 2 below --fail-below or invalid options/input, 3 size mismatch, 4 file error.");
  sub->add_option("a", o->a, "First image (e.g. experiment)")->required();
  sub->add_option("b", o->b, "Second image (e.g. simulation)")->required();
  sub->add_option("-L,--data-range", o->data_range,
                  "Dynamic range L in pixel units (e.g. 4095 for 12-bit data in 16-bit files)")
      ->required()
      ->check(DataRangeCheck(false));
  AddMultiscaleOptions(sub, &o->ms, &o->cw);
  sub->add_option("--json", o->json, "Also write the JSON to this file");
  sub->add_option("--fail-below", o->fail_below,
                  "Exit 2 when MS-SSIM (dimensionless, 1 = identical) is below this value");
  sub->callback([o, exit_code] { *exit_code = RunCompareGuarded([&] { return RunCompare(*o); }); });
}

}  // namespace raymatch::apps
