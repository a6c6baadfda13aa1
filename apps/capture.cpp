// raymatch capture list|frames|session: record images from the microscope's camera into the
// folders `calibrate` and `run` read (docs/capture.md). Thin: options -> capture library.
#include <unistd.h>

#include <fstream>
#include <iostream>

#include "commands.h"
#include "raymatch/capture/camera.h"
#include "raymatch/capture/frames.h"
#include "raymatch/capture/session.h"
#include "raymatch/core/error.h"

namespace raymatch::apps {

namespace {

// "--roi X,Y,W,H" in sensor pixels.
void AddSettings(CLI::App* c, capture::CaptureSettings* s, std::vector<int>* roi,
                 std::string* bayer) {
  c->add_option("--exposure-us", s->exposure_us, "Exposure time in microseconds (us)")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  c->add_option("--gain", s->analogue_gain,
                "Analogue gain as a factor (1 = unity gain; no digital gain)")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  c->add_option("--roi", *roi,
                "Region of interest in sensor pixels: X,Y,WIDTH,HEIGHT (top-left corner, size)")
      ->delimiter(',')
      ->expected(4);
  c->add_option(
       "--bayer", *bayer,
       "Colour sensors: mosaic (raw CFA as recorded, default), bin (2x2 sums, half size),\n"
       "or one channel plane p0|p1|p2|p3 (half size; pixel (0,0),(1,0),(0,1),(1,1) of each cell)")
      ->check(CLI::IsMember({"mosaic", "bin", "p0", "p1", "p2", "p3"}));
}

void ApplyRoiBayer(capture::CaptureSettings* s, const std::vector<int>& roi,
                   const std::string& bayer) {
  if (roi.size() == 4) s->roi = {roi[0], roi[1], roi[2], roi[3]};
  if (bayer == "bin")
    s->bayer = capture::BayerMode::kBin;
  else if (bayer.size() == 2 && bayer[0] == 'p')
    s->bayer = capture::BayerMode(int(capture::BayerMode::kPlane0) + (bayer[1] - '0'));
}

std::string Range(double lo, double hi, const std::string& unit) {
  if (hi <= 0) return "not reported";
  std::ostringstream os;
  os << lo << " to " << hi << unit;
  return os.str();
}

}  // namespace

void RegisterCapture(CLI::App& app, int* exit_code) {
  CLI::App* cap = app.add_subcommand(
      "capture",
      "Record raw images from the microscope's camera (libcamera, V4L2, or the simulated camera\n"
      "sim:SCENE.toml) into the folders `calibrate` and `run` read (docs/capture.md).\n"
      "Units: exposure in microseconds (us), analogue gain as a factor, ROI in sensor pixels.");
  cap->require_subcommand(1);

  CLI::App* list = cap->add_subcommand(
      "list", "List the cameras found (model, sensor, formats, ranges); exit 0 also when none");
  list->callback([exit_code] {
    *exit_code = RunGuarded([&] {
      std::vector<std::string> notes;
      const auto cams = capture::ListCameras(&notes);
      for (const auto& n : notes) std::cerr << "note: " << n << "\n";
      if (cams.empty()) {
        std::cout << "no camera found\n";
        return 0;
      }
      for (const auto& c : cams) {
        std::cout << c.id << "\n  model: " << c.model << "\n  sensor: " << c.width << " x "
                  << c.height << " pixels";
        if (c.pixel_pitch_um > 0) std::cout << ", " << c.pixel_pitch_um << " um pitch";
        std::cout << "\n  pixel formats:";
        for (const auto& f : c.pixel_formats) std::cout << " " << f << ";";
        std::cout << "\n  raw capture format: " << (c.raw_format.empty() ? "none" : c.raw_format)
                  << " (" << c.bit_depth
                  << "-bit)\n  exposure: " << Range(c.exposure_min_us, c.exposure_max_us, " us")
                  << "\n  analogue gain: " << Range(c.gain_min, c.gain_max, "") << "\n";
        if (!c.notes.empty()) std::cout << "  note: " << c.notes << "\n";
      }
      return 0;
    });
  });

  struct FramesOpts {
    std::string camera = "auto", output;
    capture::FramesOptions o;
    std::vector<int> roi;
    std::string bayer = "mosaic";
  };
  auto fo = std::make_shared<FramesOpts>();
  CLI::App* fr = cap->add_subcommand(
      "frames",
      "Capture N raw frames (no auto exposure, no auto gain, no white balance, full bit depth)\n"
      "to DIR/NAME.tif (N > 1: NAME_0000.tif ..., or their float mean with --mean), each TIFF\n"
      "with a JSON sidecar. Exit codes: 0 ok, 1 error (no camera, bad request, cannot write).");
  fr->add_option("--camera", fo->camera,
                 "Camera id from `capture list`, sim:SCENE.toml, or auto (the first found)")
      ->capture_default_str();
  fr->add_option("-o,--output", fo->output, "Output file DIR/NAME.tif (the folder is created)")
      ->required();
  fr->add_option("-n,--count", fo->o.count, "Number of frames")
      ->capture_default_str()
      ->check(CLI::Range(1, 100000));
  fr->add_flag("--mean", fo->o.mean,
               "Write the mean of the frames (32-bit float TIFF) instead of each frame");
  fr->add_flag("--dark", fo->o.dark,
               "Also capture dark frames (asks to block the light): NAME_dark.tif");
  AddSettings(fr, &fo->o.settings, &fo->roi, &fo->bayer);
  fr->callback([fo, exit_code] {
    *exit_code = RunGuarded([&] {
      ApplyRoiBayer(&fo->o.settings, fo->roi, fo->bayer);
      fo->o.output = fo->output;
      capture::CheckOutputPath(fo->o.output);  // before opening the camera: fail fast
      auto cam = capture::OpenCamera(fo->camera);
      for (const auto& p : capture::CaptureFramesToFiles(*cam, fo->o, std::cin, std::cout))
        std::cout << "wrote " << p << "\n";
      return 0;
    });
  });

  struct SessionOpts {
    std::string kind, camera = "auto", answers;
    capture::SessionOptions o;
    std::vector<int> roi;
    std::string bayer = "mosaic";
  };
  auto so = std::make_shared<SessionOpts>();
  CLI::App* se = cap->add_subcommand(
      "session",
      "Guided capture of a calibration or experiment folder: KIND = pinhole, cones, flats,\n"
      "focus-scan or dark. Asks you to set the stage, captures, shows the signal level and\n"
      "clipping, suggests the exposure for --target-signal, and writes FOLDER/metadata.toml so\n"
      "that `raymatch calibrate` / `run` read it unedited. pinhole + cones + dark into one folder\n"
      "make a `calibrate lightfield` folder; flats + dark a `calibrate corrector` folder.\n"
      "Non-interactive: --answers FILE, or answers on stdin when it is not a terminal (one per\n"
      "line, blank = default).");
  se->add_option("kind", so->kind, "pinhole | cones | flats | focus-scan | dark")
      ->required()
      ->check(CLI::IsMember({"pinhole", "cones", "flats", "focus-scan", "dark"}));
  se->add_option("-o,--output", so->o.folder,
                 "Output folder (created; its metadata.toml is extended)")
      ->required();
  se->add_option("--camera", so->camera, "Camera id from `capture list`, sim:SCENE.toml, or auto")
      ->capture_default_str();
  se->add_option("--answers", so->answers, "Scripted answers, one per line (blank = default)")
      ->check(CLI::ExistingFile);
  se->add_option("--average", so->o.average,
                 "Frames averaged per image (>1: 32-bit float mean TIFFs)")
      ->capture_default_str()
      ->check(CLI::Range(1, 10000));
  se->add_option("--target-signal", so->o.target_signal,
                 "Exposure suggestions aim at this fraction of the well")
      ->capture_default_str()
      ->check(CLI::Range(0.01, 0.99));
  AddSettings(se, &so->o.settings, &so->roi, &so->bayer);
  se->callback([so, exit_code] {
    *exit_code = RunGuarded([&] {
      ApplyRoiBayer(&so->o.settings, so->roi, so->bayer);
      so->o.kind = capture::ParseSessionKind(so->kind);
      std::ifstream file;
      capture::Prompter ask;
      ask.out = &std::cout;
      if (!so->answers.empty()) {
        file.open(so->answers);
        if (!file) throw Error(so->answers + ": cannot open the answers file");
        ask.in = &file;
        ask.scripted = true;
      } else {
        ask.in = &std::cin;
        ask.scripted = !isatty(STDIN_FILENO);
      }
      auto cam = capture::OpenCamera(so->camera);
      const auto s = capture::RunSession(*cam, so->o, ask);
      std::cout << "session done: " << s.files.size() << " images in " << so->o.folder << "\n";
      return 0;
    });
  });
}

}  // namespace raymatch::apps
