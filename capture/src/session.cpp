// The guided session (session.h). Each kind fills its part of a folder: `pinhole`, `cones` and
// `dark` together make a `calibrate lightfield` folder, `flats` (+ `dark`) a `calibrate
// corrector` folder, `focus-scan` (+ `dark`) a `run` experiment folder. metadata.toml keeps
// what earlier sessions wrote there and is rewritten atomically at the end.
#include "raymatch/capture/session.h"

#include <toml++/toml.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <sstream>

#include "raymatch/capture/frames.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"
#include "raymatch/core/toml_reader.h"

namespace raymatch::capture {

namespace fs = std::filesystem;

SessionKind ParseSessionKind(const std::string& n) {
  if (n == "pinhole") return SessionKind::kPinhole;
  if (n == "cones") return SessionKind::kCones;
  if (n == "flats") return SessionKind::kFlats;
  if (n == "focus-scan") return SessionKind::kFocusScan;
  if (n == "dark") return SessionKind::kDark;
  throw Error("session kind '" + n + "': expected pinhole, cones, flats, focus-scan or dark");
}

namespace {

std::string Num(double v) {
  std::ostringstream os;
  os << std::setprecision(10) << v;
  return os.str();
}

std::string Trim(std::string s) {
  const auto b = s.find_first_not_of(" \t\r\n");
  if (b == std::string::npos) return "";
  return s.substr(b, s.find_last_not_of(" \t\r\n") - b + 1);
}

bool ParseDouble(const std::string& s, double* v) {
  try {
    size_t used = 0;
    *v = std::stod(s, &used);
    return used == s.size() && std::isfinite(*v);
  } catch (...) {
    return false;
  }
}

}  // namespace

std::string Prompter::Ask(const std::string& question, const std::string& fallback) {
  for (;;) {
    *out << question << (fallback.empty() ? "" : " [" + fallback + "]") << ": " << std::flush;
    std::string line;
    bool got = false;
    while (std::getline(*in, line)) {
      if (scripted && !line.empty() && line[0] == '#') continue;
      got = true;
      break;
    }
    if (!got)
      throw Error("no answer for \"" + question + "\"" +
                  (scripted ? " (the scripted answers ran out)" : " (end of input)"));
    line = Trim(line);
    if (scripted) *out << (line.empty() ? "(default)" : line) << "\n";
    if (!line.empty()) return line;
    if (!fallback.empty()) return fallback;
    if (scripted)
      throw Error("\"" + question + "\" has no default: the scripted answer must give a value");
  }
}

double Prompter::AskNumber(const std::string& question, const std::string& fallback, double lo,
                           double hi) {
  for (;;) {
    const std::string a = Ask(question, fallback);
    double v = 0;
    if (ParseDouble(a, &v) && v >= lo && v <= hi) return v;
    const std::string msg = "\"" + a + "\" for \"" + question + "\": expected a number from " +
                            Num(lo) + " to " + Num(hi);
    if (scripted) throw Error(msg);
    *out << msg << "\n";
  }
}

std::vector<double> Prompter::AskList(const std::string& question, const std::string& fallback) {
  for (;;) {
    std::string a = Ask(question, fallback);
    std::replace(a.begin(), a.end(), ',', ' ');
    std::istringstream is(a);
    std::vector<double> v;
    std::string tok;
    bool ok = true;
    while (is >> tok) {
      double x = 0;
      ok = ok && ParseDouble(tok, &x);
      v.push_back(x);
    }
    if (ok && !v.empty()) return v;
    const std::string msg =
        "\"" + a + "\" for \"" + question + "\": expected numbers separated by commas";
    if (scripted) throw Error(msg);
    *out << msg << "\n";
  }
}

void Prompter::WaitFor(const std::string& instruction) {
  Ask(instruction + "; then press Enter", "ready");
}

namespace {

class Session {
 public:
  Session(Camera& cam, const SessionOptions& o, Prompter& ask)
      : cam_(cam), o_(o), ask_(ask), s_(o.settings) {}

  SessionSummary Run() {
    const fs::path folder = o_.folder;
    metadata_path_ = folder / "metadata.toml";
    CheckOutputPath(folder / "probe.tif");  // folder exists (created) and is writable
    if (fs::exists(metadata_path_)) meta_ = ParseTomlFile(metadata_path_.string());
    ValidateSettings(cam_.info(), s_);
    *ask_.out << "Camera: " << cam_.info().id << " (" << cam_.info().model << "), "
              << cam_.info().raw_format << ", " << cam_.info().bit_depth << "-bit\n";
    CameraAndOptics();
    switch (o_.kind) {
      case SessionKind::kPinhole:
        Pinhole();
        break;
      case SessionKind::kCones:
        Cones();
        break;
      case SessionKind::kFlats:
        Flats();
        break;
      case SessionKind::kFocusScan:
        FocusScan();
        break;
      case SessionKind::kDark:
        Dark();
        break;
    }
    std::ostringstream os;
    os << "# Written by `raymatch capture session` (docs/capture.md); frames' sidecars (.json)\n"
       << "# record exposure, gain, black level and time of each image.\n"
       << meta_ << "\n";
    WriteTextFileAtomic(metadata_path_, os.str());
    summary_.metadata = metadata_path_.string();
    *ask_.out << "wrote " << metadata_path_.string() << "\n";
    return summary_;
  }

 private:
  // [camera] and [optics]: asked once per folder (datasheet values), then kept.
  void CameraAndOptics() {
    const nlohmann::json& ds = cam_.info().datasheet;
    auto def = [&](const char* key) {
      return ds.contains(key) ? Num(ds[key].get<double>()) : std::string();
    };
    if (!meta_.contains("camera")) {
      *ask_.out << "Camera datasheet values for metadata.toml [camera]:\n";
      toml::table c;
      c.insert("pixel_pitch_um",
               ask_.AskNumber("sensor pixel pitch (um)", def("pixel_pitch_um"), 0.1, 1000));
      c.insert("bit_depth",
               int64_t(ask_.AskNumber("data bits per pixel", def("bit_depth"), 1, 32)));
      const double gain = ask_.AskNumber("electrons per code value at analogue gain 1",
                                         def("gain_e_per_dn"), 1e-4, 1e6);
      // The folder's images are converted with one gain: the datasheet value at this analogue gain.
      c.insert("gain_e_per_dn", gain / s_.analogue_gain);
      c.insert("well_capacity_e",
               ask_.AskNumber("full-well capacity (electrons)", def("well_capacity_e"), 1, 1e9));
      c.insert("read_noise_e",
               ask_.AskNumber("read noise (electrons rms)", def("read_noise_e"), 0, 1e6));
      meta_.insert("camera", std::move(c));
    }
    if (!meta_.contains("optics")) {
      *ask_.out << "Microscope optics for metadata.toml [optics]:\n";
      toml::table t;
      t.insert("objective_focal_mm",
               ask_.AskNumber("objective focal length (mm)", def("objective_focal_mm"), 0.1, 1000));
      t.insert("na", ask_.AskNumber("objective NA", def("na"), 0.001, 1.6));
      t.insert("working_distance_mm",
               ask_.AskNumber("working distance (mm)", def("working_distance_mm"), 0.01, 1000));
      t.insert("tube_focal_mm",
               ask_.AskNumber("tube lens focal length (mm)", def("tube_focal_mm"), 1, 10000));
      t.insert(
          "wavelength_um",
          ask_.AskNumber("wavelength (um)",
                         def("wavelength_um").empty() ? "0.462" : def("wavelength_um"), 0.2, 2.0));
      meta_.insert("optics", std::move(t));
    }
    const toml::table& c = *meta_["camera"].as_table();
    e_per_dn_ = c["gain_e_per_dn"].value<double>().value_or(1.0);
    well_e_ = c["well_capacity_e"].value<double>().value_or(0.0);
    bits_ = int(c["bit_depth"].value<int64_t>().value_or(16));
    if (!(well_e_ > 0)) well_e_ = e_per_dn_ * double((int64_t(1) << bits_) - 1);
  }

  double PinholeDiameter() {
    const std::string def = meta_.contains("pinhole_diameter_um")
                                ? Num(meta_["pinhole_diameter_um"].value<double>().value_or(2))
                                : "2";
    const double d = ask_.AskNumber("pinhole diameter (um)", def, 0.01, 1000);
    meta_.insert_or_assign("pinhole_diameter_um", d);
    return d;
  }

  // Captures; shows level and clipping; suggests an exposure; retakes until the user keeps it.
  FrameSet Expose(const std::string& what, bool peak) {
    for (int attempt = 0; attempt < 30; ++attempt) {
      FrameSet set = CaptureSet(cam_, s_, o_.average, o_.average > 1);
      const Frame& f = set.frames.back();
      const double black = f.black_level_dn.value_or(0);
      const double max_dn = double((int64_t(1) << f.bit_depth) - 1);
      const SignalLevel lv = MeasureSignal(set.image, black, max_dn, e_per_dn_, well_e_);
      const double level = peak ? lv.peak_fraction : lv.median_fraction;
      const bool clipped = peak ? lv.clipped_fraction > 0 : lv.clipped_fraction > 1e-3;
      const double suggest =
          SuggestExposure(s_.exposure_us, level, clipped, o_.target_signal, cam_.info());
      *ask_.out << std::fixed << std::setprecision(1) << "  " << what << " at " << s_.exposure_us
                << " us: signal median " << 100 * lv.median_fraction << " %, peak "
                << 100 * lv.peak_fraction << " % of the well; clipped " << std::setprecision(3)
                << 100 * lv.clipped_fraction << " % of pixels" << (clipped ? " (CLIPPED)" : "")
                << std::defaultfloat << "\n"
                << "  suggested exposure for " << 100 * o_.target_signal
                << " % of the well: " << suggest << " us\n";
      if (auto_adjust_) {
        if (!clipped && std::abs(level / o_.target_signal - 1) < 0.1) return set;
        if (suggest == s_.exposure_us) {  // at the camera's exposure limit
          *ask_.out << "  (the camera's exposure limit: kept)\n";
          return set;
        }
        s_.exposure_us = suggest;
        continue;
      }
      const std::string a = ask_.Ask(
          "  keep (Enter), retake at the suggestion (s), adjust automatically (a), or a new "
          "exposure in us",
          "keep");
      if (a == "keep" || a == "k") return set;
      if (a == "s") {
        s_.exposure_us = suggest;
      } else if (a == "a") {
        auto_adjust_ = true;
        s_.exposure_us = suggest;
      } else {
        double v = 0;
        if (!ParseDouble(a, &v)) {
          if (ask_.scripted)
            throw Error("answer \"" + a + "\": expected Enter, s, a or an exposure in us");
          continue;
        }
        s_.exposure_us = v;
      }
      ValidateSettings(cam_.info(), s_);
    }
    throw Error(what + ": no exposure kept after 30 frames");
  }

  void Save(const std::string& name, const FrameSet& set, const std::string& what) {
    const fs::path p = fs::path(o_.folder) / name;
    WriteFrameSet(p, set, FrameSidecar(cam_.info(), set, what));
    summary_.files.push_back(p.string());
    *ask_.out << "  wrote " << p.string() << "\n";
  }

  void Pinhole() {
    StageState st;
    st.pinhole = true;
    st.pinhole_diameter_um = PinholeDiameter();
    ask_.WaitFor("Put the pinhole at the object plane and focus on it (dz = 0), lamp on");
    cam_.SetStage(st);
    auto_adjust_ = false;
    Save("pinhole.tif", Expose("pinhole", true), "pinhole in focus");
    meta_.insert_or_assign("pinhole", "pinhole.tif");
  }

  void Cones() {
    StageState st;
    st.pinhole = true;
    st.pinhole_diameter_um = PinholeDiameter();
    const std::vector<double> dz =
        ask_.AskList("focus positions beyond the pinhole, dz (um, two or more)", "20, 30, 40");
    toml::array cones;
    auto_adjust_ = false;
    for (double d : dz) {
      ask_.WaitFor("Move the focus " + Num(d) + " um beyond the pinhole (towards the camera)");
      st.focus_um = d;
      cam_.SetStage(st);
      const std::string name = "cone_dz" + Num(d) + ".tif";
      Save(name, Expose("cone dz " + Num(d) + " um", true),
           "light cone, focus " + Num(d) + " um beyond the pinhole");
      cones.push_back(toml::table{{"file", name}, {"dz_um", d}});
    }
    meta_.insert_or_assign("cone", std::move(cones));
  }

  void Flats() {
    StageState st;
    const double pin = PinholeDiameter();
    std::vector<double> iris =
        ask_.AskList("iris half-angles (deg), narrow to wide", "5, 10, 15, 20, 25");
    std::sort(iris.begin(), iris.end());
    const double dz = ask_.AskNumber("cone focus beyond the pinhole, dz (um)", "30", 1, 10000);
    // One flat exposure for the series (relative exposure 1), set at the widest iris.
    ask_.WaitFor("Take the pinhole out, focus at 0, open the iris to " + Num(iris.back()) + " deg");
    st.iris_deg = iris.back();
    cam_.SetStage(st);
    auto_adjust_ = false;
    FrameSet widest = Expose("flat field, iris " + Num(iris.back()) + " deg", false);
    const double flat_us = s_.exposure_us;
    double cone_us = flat_us;
    toml::array flats;
    bool cone_auto = false;
    for (double a : iris) {
      const std::string tag = "iris" + Num(a) + "deg";
      FrameSet flat;
      if (a == iris.back()) {
        flat = std::move(widest);
      } else {
        ask_.WaitFor("Flat field: pinhole out, focus at 0, iris " + Num(a) + " deg");
        st = StageState{};
        st.iris_deg = a;
        cam_.SetStage(st);
        s_.exposure_us = flat_us;
        flat = CaptureSet(cam_, s_, o_.average, o_.average > 1);
      }
      Save("flat_" + tag + ".tif", flat, "flat field, iris " + Num(a) + " deg");
      ask_.WaitFor("Cone: pinhole in, focus " + Num(dz) + " um beyond it, iris " + Num(a) +
                   " deg (same lamp)");
      st = StageState{};
      st.pinhole = true;
      st.pinhole_diameter_um = pin;
      st.focus_um = dz;
      st.iris_deg = a;
      cam_.SetStage(st);
      s_.exposure_us = cone_us;
      auto_adjust_ = cone_auto;
      Save("cone_" + tag + ".tif", Expose("cone, iris " + Num(a) + " deg", true),
           "cone through the pinhole, iris " + Num(a) + " deg, focus " + Num(dz) + " um beyond it");
      cone_auto = auto_adjust_;  // "a" once: the rest of the series adjusts too
      cone_us = s_.exposure_us;
      flats.push_back(toml::table{{"file", "flat_" + tag + ".tif"},
                                  {"cone", "cone_" + tag + ".tif"},
                                  {"cone_dz_um", dz},
                                  {"cone_exposure", cone_us / flat_us}});
    }
    meta_.insert_or_assign("pinhole_diameter_um", pin);
    meta_.insert_or_assign("flat", std::move(flats));
  }

  void FocusScan() {
    const std::vector<double> z = ask_.AskList(
        "focus positions (um, + = focal plane towards the camera)", "-20, -10, 0, 10, 20");
    if (!meta_.contains("nominal_diameter_um"))
      meta_.insert("nominal_diameter_um",
                   ask_.AskNumber("nominal object diameter (um)", "", 0.01, 1e6));
    if (!meta_.contains("temperature_K"))
      meta_.insert("temperature_K", ask_.AskNumber("temperature (K)", "293.15", 261.15, 773.15));
    StageState st;
    st.objects = true;
    std::string csv = "defocus_um,file\n";
    auto_adjust_ = false;
    for (size_t i = 0; i < z.size(); ++i) {
      ask_.WaitFor("Set the focus to " + Num(z[i]) + " um");
      st.focus_um = z[i];
      cam_.SetStage(st);
      char name[64];
      std::snprintf(name, sizeof name, "scan_z%+07.2fum.tif", z[i]);
      FrameSet set =
          i == 0 ? Expose("focus " + Num(z[i]) + " um", false)
                 : CaptureSet(cam_, s_, o_.average, o_.average > 1);  // one exposure for the scan
      Save(name, set, "focus scan, defocus " + Num(z[i]) + " um");
      csv += Num(z[i]) + "," + name + "\n";
    }
    WriteTextFileAtomic(fs::path(o_.folder) / "scan.csv", csv);
    meta_.insert_or_assign("scan", "scan.csv");
  }

  void Dark() {
    s_.exposure_us = ask_.AskNumber("dark frame exposure (us; the longest used in this folder)",
                                    Num(s_.exposure_us), 1e-3, 1e9);
    ValidateSettings(cam_.info(), s_);
    ask_.WaitFor("Block the light (lamp off or shutter closed)");
    StageState st;
    st.lamp_on = false;
    cam_.SetStage(st);
    FrameSet set = CaptureSet(cam_, s_, o_.average, o_.average > 1);
    const Frame& f = set.frames.back();
    const SignalLevel lv =
        MeasureSignal(set.image, 0, double((int64_t(1) << f.bit_depth) - 1), e_per_dn_, well_e_);
    *ask_.out << "  dark median " << lv.median_fraction * well_e_ / e_per_dn_ << " DN\n";
    Save("dark.tif", set, "dark frame");
    meta_.insert_or_assign("dark", "dark.tif");
  }

  Camera& cam_;
  const SessionOptions& o_;
  Prompter& ask_;
  CaptureSettings s_;
  toml::table meta_;
  fs::path metadata_path_;
  SessionSummary summary_;
  double e_per_dn_ = 1, well_e_ = 1;
  int bits_ = 16;
  bool auto_adjust_ = false;
};

}  // namespace

SessionSummary RunSession(Camera& cam, const SessionOptions& o, Prompter& ask) {
  if (o.average < 1)
    throw Error("--average " + std::to_string(o.average) + ": expected at least 1");
  if (!(o.target_signal > 0 && o.target_signal < 1))
    throw Error("--target-signal " + Num(o.target_signal) +
                ": expected a fraction of the well in (0, 1)");
  return Session(cam, o, ask).Run();
}

}  // namespace raymatch::capture
