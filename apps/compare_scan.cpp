// raymatch compare-scan: the focus-scan test between an experimental and a simulated stack.
#include <iostream>

#include "commands.h"
#include "compare_common.h"
#include "raymatch/compare/focus_scan.h"

namespace raymatch::apps {

namespace {

struct ScanCliOptions {
  std::string experiment, simulation, output = "compare-out";
  compare::FocusScanOptions scan;
  std::vector<int> roi;
  bool no_register = false, no_normalize = false;
};

int RunScanCompare(ScanCliOptions o) {
  if (!o.roi.empty()) {
    if (o.roi.size() != 4)
      throw compare::CompareError(compare::FailureKind::kInvalidInput,
                                  "--roi needs x,y,width,height");
    o.scan.prepare.roi = std::array<int, 4>{o.roi[0], o.roi[1], o.roi[2], o.roi[3]};
  }
  o.scan.register_shift = !o.no_register;
  o.scan.normalize_background = !o.no_normalize;
  const compare::Stack e = compare::ReadStack(o.experiment);
  const compare::Stack s = compare::ReadStack(o.simulation);
  const compare::FocusScanResult r = compare::RunFocusScan(e, s, o.scan);
  const std::string report = compare::WriteFocusScanReport(r, o.output, "raymatch focus-scan test");
  std::cout << "raymatch compare-scan: " << r.message << "\n";
  for (const auto& m : r.measures) {
    std::cout << "  " << compare::MeasureName(m.measure) << (m.passes ? "  pass  " : "  FAIL  ");
    for (size_t i = 0; i < m.best.size(); ++i) std::cout << r.sim_defocus_um[m.best[i]] << " ";
    std::cout << "(best simulated z per experimental z)\n";
  }
  std::cout << "  report: " << report << "\n";
  return static_cast<int>(r.verdict);
}

}  // namespace

void RegisterCompareScan(CLI::App& app, int* exit_code) {
  auto o = std::make_shared<ScanCliOptions>();
  CLI::App* sub = app.add_subcommand(
      "compare-scan",
      "Focus-scan test: every experimental plane against every simulated plane for MSE, SSIM,\n"
      "MS-SSIM, CW-SSIM and Poisson chi-square; passes when each best match is the same defocus\n"
      "within one step. Stacks: CSV 'defocus_um,file' or the simulator's <name>_scan.json.\n"
      "Writes JSON, CSV, PNG heatmaps, a montage and report.html.\n"
      "Exit: 0 pass, 1 some primary measures fail, 2 all fail or invalid options/input,\n"
      "3 size mismatch, 4 file error.");
  sub->add_option("experiment", o->experiment, "Experimental stack index (.csv or .json)")
      ->required();
  sub->add_option("simulation", o->simulation, "Simulated stack index (.csv or .json)")->required();
  sub->add_option("-o,--output", o->output, "Output directory")->capture_default_str();
  sub->add_option("--dark", o->scan.prepare.dark_file, "Dark frame subtracted from the experiment");
  sub->add_option("--flat", o->scan.prepare.flat_file,
                  "Flat field (dark-subtracted) for the experiment");
  sub->add_option("--gain", o->scan.prepare.gain_e_per_dn, "Photons (electrons) per code value")
      ->capture_default_str();
  sub->add_option("--roi", o->roi, "Crop x,y,width,height (pixels) before comparing")
      ->delimiter(',');
  sub->add_option("-L,--data-range", o->scan.data_range,
                  "Dynamic range L in photons (default: the largest pixel of both stacks)")
      ->check(DataRangeCheck(true));
  AddMultiscaleOptions(sub, &o->scan.ms_ssim, &o->scan.cw_ssim);
  sub->add_flag("--no-register", o->no_register, "Skip sub-pixel registration");
  sub->add_option("--pixel-um", o->scan.object_pixel_um,
                  "The camera pixel at the object plane in micrometres, for the report's axes "
                  "(default: from the planes' sidecars, simulate's image.object_pixel_um; axes in "
                  "pixels when they give none)")
      ->check(CLI::PositiveNumber);
  sub->add_flag("--no-normalize", o->no_normalize,
                "Do not scale the simulation to the experiment's background");
  sub->callback(
      [o, exit_code] { *exit_code = RunCompareGuarded([&] { return RunScanCompare(*o); }); });
}

}  // namespace raymatch::apps
