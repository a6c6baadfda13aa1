// The fit file (docs/fit.md) and scene keys: reading, resolving and changing numeric values.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <limits>
#include <optional>
#include <set>
#include <sstream>

#include "binding.h"
#include "raymatch/compare/focus_scan.h"
#include "raymatch/core/calibration_file.h"
#include "raymatch/core/image.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/toml_reader.h"
#include "raymatch/fit/fit.h"
#include "raymatch/simulate/geometry.h"
#include "raymatch/simulate/physical_image.h"
#include "raymatch/simulate/scene.h"

namespace raymatch::fit {

namespace fs = std::filesystem;

const char* ErrorFunctionName(ErrorFunction e) {
  static const char* n[] = {"poisson", "mse", "1-ssim", "1-ms-ssim", "1-cw-ssim"};
  return n[int(e)];
}
const char* MethodName(Method m) {
  static const char* n[] = {"grid", "pattern", "lm"};
  return n[int(m)];
}

const char* StageName(Stage s) {
  static const char* n[] = {"grid",  "poll", "lm",      "polish", "fisher", "final", "repeat",
                            "slice", "best", "profile", "start",  "scan",   "hop"};
  return n[int(s)];
}

const char* StatusName(FitStatus s) {
  static const char* n[] = {"", "converged", "failed", "max_evaluations", "flat"};
  return n[int(s)];
}

namespace internal {

std::vector<KeySegment> SplitKey(const std::string& key) {
  std::vector<KeySegment> out;
  std::stringstream ss(key);
  std::string part;
  while (std::getline(ss, part, '.')) {
    KeySegment s;
    const size_t b = part.find('[');
    if (b != std::string::npos) {
      const size_t e = part.find(']', b);
      if (e != part.size() - 1 || e == b + 1)
        throw Error("key '" + key + "': expected name[index] in '" + part + "'");
      for (size_t k = b + 1; k < e; ++k)
        if (!std::isdigit(static_cast<unsigned char>(part[k])))
          throw Error("key '" + key + "': index in '" + part + "' must be a whole number");
      s.index = std::stoul(part.substr(b + 1, e - b - 1));
      part = part.substr(0, b);
    }
    if (part.empty()) throw Error("key '" + key + "': empty name between dots");
    s.name = part;
    out.push_back(s);
  }
  if (out.empty()) throw Error("empty key");
  return out;
}

}  // namespace internal

using internal::KeySegment;
using internal::SplitKey;

namespace {

/// The numeric keys of a table (with [i] for numeric arrays), for messages.
std::string NumericKeys(const toml::table& t) {
  std::string s;
  for (const auto& [k, v] : t) {
    std::string name(k.str());
    if (v.is_number()) {
    } else if (const toml::array* a = v.as_array(); a && !a->empty() &&
                                                    a->is_homogeneous(toml::node_type::none) &&
                                                    (*a)[0].is_number()) {
      name += "[0.." + std::to_string(a->size() - 1) + "]";
    } else if (v.is_table() || v.is_array_of_tables()) {
      name += v.is_table() ? ".*" : "[i].* or " + name + ".<name>.*";
    } else {
      continue;
    }
    s += (s.empty() ? "" : ", ") + name;
  }
  return s.empty() ? "(none)" : s;
}

/// Where a key's number lives: a table entry or an array element.
struct Slot {
  toml::table* table = nullptr;
  std::string key;
  toml::array* array = nullptr;
  size_t index = 0;
  toml::node* node = nullptr;
};

Slot Resolve(toml::table& root, const std::string& key, const std::string& scene_file) {
  const std::vector<KeySegment> segs = SplitKey(key);
  toml::table* t = &root;
  std::string where = "the scene";
  auto fail = [&](const std::string& why) -> Error {
    return Error(FileLocation{scene_file}, "key '" + key + "': " + why + " (numeric keys of " +
                                               where + ": " + NumericKeys(*t) + ")");
  };
  for (size_t i = 0; i < segs.size(); ++i) {
    const KeySegment& s = segs[i];
    toml::node* n = t->get(s.name);
    if (!n) throw fail("no '" + s.name + "' in " + where);
    const bool last = i + 1 == segs.size();
    if (toml::array* a = n->as_array()) {
      if (a->is_array_of_tables() && !a->empty()) {
        toml::table* next = nullptr;
        std::string label;
        if (s.index) {
          if (*s.index >= a->size())
            throw fail("'" + s.name + "' has " + std::to_string(a->size()) + " entries");
          next = (*a)[*s.index].as_table();
          label = s.name + "[" + std::to_string(*s.index) + "]";
        } else {
          if (last) throw fail("'" + s.name + "' is a list of tables: name one");
          const std::string& want = segs[++i].name;
          std::string names;
          for (auto& e : *a) {
            toml::table* et = e.as_table();
            const auto nm = (*et)["name"].value<std::string>();
            names += (names.empty() ? "" : ", ") + nm.value_or("(unnamed)");
            if (nm && *nm == want) next = et;
          }
          if (!next) throw fail("no " + s.name + " named '" + want + "' (names: " + names + ")");
          if (segs[i].index) throw fail("'" + want + "' is a table, not a list");
          label = s.name + " '" + want + "'";
        }
        if (i + 1 == segs.size()) throw fail("'" + label + "' is a table, not a number");
        t = next;
        where = label;
        continue;
      }
      if (!s.index) throw fail("'" + s.name + "' is a list: give an index, e.g. " + s.name + "[0]");
      if (!last) throw fail("'" + s.name + "[i]' is a number, not a table");
      if (*s.index >= a->size())
        throw fail("'" + s.name + "' has " + std::to_string(a->size()) + " values");
      toml::node& e = (*a)[*s.index];
      if (!e.is_number())
        throw fail("'" + s.name + "[" + std::to_string(*s.index) + "]' is not a number");
      return {nullptr, "", a, *s.index, &e};
    }
    if (s.index) throw fail("'" + s.name + "' is not a list");
    if (toml::table* sub = n->as_table()) {
      if (last) throw fail("'" + s.name + "' is a table, not a number");
      t = sub;
      where = "[" + s.name + "]";
      continue;
    }
    if (!last) throw fail("'" + s.name + "' is a value, not a table");
    if (!n->is_number()) throw fail("'" + s.name + "' is not a number");
    return {t, s.name, nullptr, 0, n};
  }
  throw fail("incomplete key");
}

std::string ResolvePath(const std::string& base_file, const std::string& p) {
  const fs::path q(p);
  return q.is_absolute() ? p : (fs::path(base_file).parent_path() / q).string();
}

}  // namespace

std::string UnitOf(const std::string& key) {
  // The key's last name, without its index: image[0].defocus_um, object.a.rotation_deg[1].
  std::string base = key.substr(key.rfind('.') == std::string::npos ? 0 : key.rfind('.') + 1);
  base = base.substr(0, base.find('['));
  for (const char* u : {"_um", "_mm", "_deg", "_K", "_kg_m3"})
    if (base.size() > std::string(u).size() && base.ends_with(u)) return std::string(u).substr(1);
  return "";
}

std::optional<std::pair<size_t, std::string>> ParseImageKey(const std::string& key, size_t images) {
  const auto segs = SplitKey(key);
  const std::string field = segs.size() == 2 ? segs[1].name : "";
  const bool known = field == "defocus_um" || field == "background_photons" ||
                     field == "background_slope_x" || field == "background_slope_y";
  if (segs.size() != 2 || !segs[0].index || segs[0].name != "image" || !known || segs[1].index ||
      *segs[0].index >= images)
    return std::nullopt;
  return std::pair(*segs[0].index, field);
}

std::string ImageKeysHelp(size_t images) {
  return "image keys are image[i].defocus_um, image[i].background_photons, "
         "image[i].background_slope_x or _y with i < " +
         std::to_string(images);
}

double SceneValue(const toml::table& scene, const std::string& key, const std::string& scene_file) {
  toml::table& t = const_cast<toml::table&>(scene);  // Resolve only reads through the slot here
  const Slot s = Resolve(t, key, scene_file);
  return s.node->value<double>().value();
}

void SetSceneValue(toml::table& scene, const std::string& key, double value,
                   const std::string& scene_file) {
  const Slot s = Resolve(scene, key, scene_file);
  if (s.table) {
    s.table->insert_or_assign(s.key, value);
  } else {
    s.array->replace(s.array->cbegin() + s.index, value);
  }
}

namespace {
constexpr int kMaxGridPoints = 10001;  ///< grid samples per parameter
constexpr double kMaxDefocusUm = 1e5;  ///< |defocus| of an image, and of its bounds when fitted
/// A grid's size for a message (the product of the axes can exceed any integer type).
std::string GridCount(double n) {
  char buf[32];
  std::snprintf(buf, sizeof buf, n < 1e15 ? "%.0f" : "%.3g", n);
  return buf;
}
/// Refuses an experimental image that cannot hold a brightfield experiment: no light
/// at all (a camera that did not fire), a flat level far from the photon count the scene or fit
/// file declares (a wrong gain, dark frame or exposure), or mostly saturated pixels. Each message
/// names the fit file's [[image]] entry and the image file and says what is wrong.
void CheckExperimentImage(const FitImage& fi, double expected_photons_per_pixel,
                          const std::string& expected_from) {
  const Image& im = fi.photons;
  if (im.empty()) throw Error(fi.where, "image " + fi.file + " has no pixels");
  double max = -1e300, sum = 0;
  for (float v : im.pixels) {
    max = std::max(max, double(v));
    sum += v;
  }
  if (!(max > 0))
    throw Error(fi.where, "image " + fi.file + " has no signal: every pixel is " +
                              (max == 0 ? "0" : "0 or below") +
                              " photons after dark subtraction (did the camera fire and the lamp "
                              "light? is the dark frame given as the image?)");
  size_t at_max = 0;
  for (float v : im.pixels) at_max += double(v) >= max * (1 - 1e-6);
  const double saturated = double(at_max) / double(im.size());
  if (saturated > 0.5) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "%.0f %% of its pixels sit at its largest value %.6g",
                  100 * saturated, max);
    throw Error(fi.where,
                "image " + fi.file + " is mostly saturated: " + buf +
                    "; expose it less (or check that it is a camera image, not a constant)");
  }
  // The flat level: mean of the border frame BorderMedian uses (robust at low counts, where the
  // median of Poisson counts is coarse).
  const int bw = std::max(1, std::min(im.width, im.height) / 8);
  double border = 0;
  size_t n = 0;
  for (int y = 0; y < im.height; ++y)
    for (int x = 0; x < im.width; ++x)
      if (x < bw || y < bw || x >= im.width - bw || y >= im.height - bw) border += im.at(x, y), ++n;
  border /= double(std::max<size_t>(n, 1));
  if (!(border > 0))
    throw Error(fi.where,
                "image " + fi.file +
                    " has no light around the object: the mean of its border "
                    "pixels is " +
                    std::to_string(border) +
                    " photons (a brightfield image has a lit background; check the dark frame)");
  constexpr double kLevelFactor = 3;
  if (expected_photons_per_pixel > 0 && (border > kLevelFactor * expected_photons_per_pixel ||
                                         border * kLevelFactor < expected_photons_per_pixel)) {
    char buf[160];
    std::snprintf(buf, sizeof buf,
                  "its flat level (mean of the border pixels) is %.4g photons per pixel, "
                  "%.3g times the %.4g",
                  border, border / expected_photons_per_pixel, expected_photons_per_pixel);
    throw Error(fi.where, "image " + fi.file + " does not match the experiment's photon count: " +
                              buf + " of " + expected_from +
                              " (more than a factor 3 apart); check gain_e_per_dn, "
                              "the dark frame and the exposure, or correct photons_per_pixel");
  }
}

}  // namespace

FitSpec LoadFitSpec(const std::string& path) { return LoadFitSpec(path, ""); }

namespace {
FitSpec LoadFitFile(const std::string& path, const std::string& scene_override,
                    const std::string& calibration_override, bool ray_start_fit);
}  // namespace

FitSpec LoadFitSpec(const std::string& path, const std::string& scene_override,
                    const std::string& calibration_override) {
  return LoadFitFile(path, scene_override, calibration_override, false);
}

double FitSpec::RaysPerPhoton() const {
  return exact_images() ? std::numeric_limits<double>::infinity()
                        : rays.ray_factor * rays.fractions.back();
}

namespace {

/// The fit file's scene (with its calibration and optics written in), checked: the scene as
/// loaded, f's scene, scene_file, calibration_file and what an exact image model sets.
simulate::Scene ReadSceneAndOptics(TomlReader& r, const std::string& path,
                                   const std::string& scene_override,
                                   const std::string& calibration_override, bool ray_start_fit,
                                   FitSpec* f_out) {
  FitSpec& f = *f_out;
  if (!scene_override.empty()) {
    f.scene_file = scene_override;
    r.String("scene", "");
  } else {
    f.scene_file = ResolvePath(path, r.String("scene"));
    if (!fs::is_regular_file(f.scene_file))
      r.Fail("scene", (fs::is_directory(f.scene_file) ? "is a folder, not a scene file: "
                                                      : "scene file not found: ") +
                          f.scene_file);
  }
  f.scene = ParseTomlFile(f.scene_file);
  if (!calibration_override.empty()) {
    f.calibration_file = fs::absolute(calibration_override).string();
    r.String("calibration", "");
  } else if (r.Has("calibration")) {
    f.calibration_file = fs::absolute(ResolvePath(path, r.String("calibration"))).string();
  }
  if (!f.calibration_file.empty()) f.scene.insert_or_assign("calibration", f.calibration_file);
  // The fit file's choice of image model replaces the scene's; a ray start fit's is the rays.
  std::string optics = r.Has("optics") ? r.Choice("optics", {"rays", "mie", "physical"}) : "";
  if (ray_start_fit) optics = "rays";
  if (!optics.empty()) {
    if (!f.scene.contains("trace")) f.scene.insert("trace", toml::table{});
    toml::table& trace = *f.scene["trace"].as_table();
    trace.insert_or_assign("optics", optics);
    if (ray_start_fit) {
      trace.erase("mie");
      trace.erase("physical");
    }
  }
  const simulate::Scene scene = simulate::LoadScene(f.scene, f.scene_file);  // checks it
  f.optics = simulate::ImageOpticsName(scene.trace.optics);
  if (scene.trace.optics == simulate::ImageOptics::kPhysical) {
    if (const std::string why = simulate::PhysicalUnsupportedReason(scene); !why.empty())
      throw Error(FileLocation{f.scene_file}, why);
  }
  if (scene.trace.optics != simulate::ImageOptics::kRays) {
    // An image model without simulation noise: one level, the two derivative sets the
    // uncertainties need (any two sets are the same images), no repeats with other ray streams;
    // [rays] may still set them.
    f.rays.fractions = {1.0};
    f.rays.jacobian_seeds = 2;
    f.repeat_seeds = 0;
    // The profile-likelihood paths score with the ray streams' derivative sets and are not yet
    // right for an exact model (an interval beside its own estimate): curvature sigmas only,
    // unless [uncertainty] profile asks.
    f.profile = ProfileMode::kNever;
  }
  // Mesh files are read when a simulator is built: check them now (the meshes are cached, so
  // the fit reads each file once), before anything runs or is written.
  if (std::any_of(scene.objects.begin(), scene.objects.end(), [](const simulate::ObjectSpec& o) {
        return o.shape == simulate::ShapeType::kMesh;
      })) {
    const simulate::Geometry check(scene.objects);
  }
  return scene;
}

/// One [[image]]: its files read and prepared (photons, the pixels left out), checked against
/// the scene's camera.
FitImage ReadFitImage(TomlReader& im, const std::string& path, const simulate::Scene& scene) {
  FitImage fi;
  fi.where = im.Where();
  fi.file = ResolvePath(path, im.String("file"));
  fi.defocus_um = im.Number("defocus_um");
  if (!(std::abs(fi.defocus_um) <= kMaxDefocusUm))
    im.Fail("defocus_um", "expected a focus position within +-1e5 um (10 cm)");
  if (im.Has("dark")) fi.dark_file = ResolvePath(path, im.String("dark"));
  fi.gain_e_per_dn = im.Positive("gain_e_per_dn", 1.0);
  fi.read_noise_e = im.InRange("read_noise_e", 0, 1e4, 0);
  fi.saturation_dn = im.InRange("saturation_dn", 0, 1e9, 0);
  im.Finish();
  Image raw, dark;
  try {
    raw = ReadImage(fi.file);
    if (!fi.dark_file.empty()) dark = ReadImage(fi.dark_file);
  } catch (const Error& err) {
    throw Error(fi.where, err.what());
  }
  compare::PrepareOptions prep;
  prep.dark_file = fi.dark_file;
  prep.gain_e_per_dn = fi.gain_e_per_dn;
  try {
    fi.photons = compare::PrepareExperiment(raw, prep, dark.empty() ? nullptr : &dark, nullptr);
  } catch (const Error& err) {  // e.g. a dark frame of another size: name both files
    throw Error(fi.where, "image " + fi.file +
                              (fi.dark_file.empty() ? "" : " with dark frame " + fi.dark_file) +
                              ": " + err.message());
  }
  // Saturated pixels (at or above saturation_dn) and, with a dark frame (an offset above 0),
  // pixels clipped at 0 carry no count the Poisson model can describe: left out.
  if (fi.saturation_dn > 0 || !dark.empty()) {
    fi.usable = Image(raw.width, raw.height, 1.0f);
    for (size_t p = 0; p < raw.size(); ++p)
      if ((fi.saturation_dn > 0 && raw.pixels[p] >= fi.saturation_dn) ||
          (!dark.empty() && raw.pixels[p] <= 0)) {
        fi.usable.pixels[p] = 0;
        ++fi.excluded_pixels;
      }
    if (fi.excluded_pixels == 0) fi.usable = Image();
  }
  if (fi.photons.width != scene.camera.nx || fi.photons.height != scene.camera.ny)
    throw Error(fi.where, "image " + fi.file + " is " + std::to_string(fi.photons.width) + " x " +
                              std::to_string(fi.photons.height) +
                              " pixels; the scene's camera has " + std::to_string(scene.camera.nx) +
                              " x " + std::to_string(scene.camera.ny));
  return fi;
}

/// A [[parameter]]'s prior: "calibration" (the calibration file's value and sigma, the file read
/// once into cal) or [mean, sigma].
void ReadPrior(TomlReader& p, const toml::table& t, const FitSpec& f, double current,
               std::optional<CalibrationData>& cal, Parameter* q_out) {
  Parameter& q = *q_out;
  if (p.Has("prior") && f.error != ErrorFunction::kPoisson)
    p.Fail("prior", "a prior adds to the Poisson deviance: it needs error = \"poisson\"");
  if (p.Has("prior")) {
    if (const auto s = t["parameter"][f.parameters.size()]["prior"].value<std::string>()) {
      if (*s != "calibration")
        p.Fail("prior", "expected \"calibration\" or [mean, sigma] (a Gaussian prior)");
      if (f.calibration_file.empty())
        p.Fail("prior", "prior = \"calibration\" needs a calibration file (key calibration)");
      if (!cal) cal = ReadCalibrationFile(f.calibration_file);
      const auto it = cal->key_sigma.find(q.key);
      if (it == cal->key_sigma.end())
        p.Fail("prior", "the calibration " + f.calibration_file + " gives no uncertainty for '" +
                            q.key + "' (its [uncertainty] table, written by `raymatch " +
                            "calibrate sphere`, holds the keys that calibration fitted; files "
                            "from older versions lack it: run it again)");
      q.prior_mean = current, q.prior_sigma = it->second, q.prior_from = "calibration";
      p.String("prior");
    } else {
      const std::vector<double> m = p.Numbers("prior", 2, 2);
      if (!(m[1] > 0) || !std::isfinite(m[0]) || !std::isfinite(m[1]))
        p.Fail("prior", "expected [mean, sigma] with sigma > 0 (a Gaussian prior)");
      q.prior_mean = m[0], q.prior_sigma = m[1], q.prior_from = "fit file";
    }
  }
}

/// One [[parameter]]: its key bound against the scene (an edge or PSF that the calibration
/// gives is written into f's scene so it can be set), its range, step, grid points and prior.
Parameter ReadParameter(TomlReader& p, const toml::table& t, const simulate::Scene& scene,
                        std::set<std::string>* keys_io, std::optional<CalibrationData>* cal,
                        FitSpec* f_out) {
  FitSpec& f = *f_out;
  std::set<std::string>& keys = *keys_io;
  Parameter q;
  q.where = p.Where();
  q.key = p.String("key");
  if (!keys.insert(q.key).second) p.Fail("key", "parameter '" + q.key + "' is given twice");
  // What the key sets, resolved against the scene once (binding.h; the model binds it
  // against its own copy the same way).
  internal::Binding bound;
  try {
    bound = internal::Bind(q.key, scene, f.images.size());
  } catch (const Error& err) {
    p.Fail("key", err.what());
  }
  using Kind = internal::Binding::Kind;
  // A coated sphere's wave image needs its two spheres concentric and moving together.
  if (scene.trace.optics == simulate::ImageOptics::kMie && scene.objects.size() == 2 &&
      bound.kind == Kind::kObject &&
      (bound.field == internal::Binding::Field::kCenter ||
       q.key.find(".velocity_um_per_us") != std::string::npos))
    p.Fail("key", "'" + q.key +
                      "' moves one sphere of a coated sphere off the other's centre, which the "
                      "wave model (optics = \"mie\") cannot image; fit its radii and indices");
  // The calibration's edge and PSF as keys of a scene that takes them from the calibration:
  // written into the scene's tables with the calibration's values, so they can be set.
  if (bound.kind == Kind::kEdge && !f.scene.contains("light_field_edge") &&
      !(scene.source.edge_half_angle_deg > 0))
    p.Fail("key", "'" + q.key +
                      "' needs the light field's edge beyond the NA: a [light_field_edge] "
                      "table in the scene, or a calibration with one (`raymatch calibrate "
                      "sphere`; in a pipeline, [calibration] sphere)");
  if (bound.kind == Kind::kEdge && !f.scene.contains("light_field_edge")) {
    toml::array tilt{scene.source.edge_tilt_deg[0], scene.source.edge_tilt_deg[1]};
    f.scene.insert_or_assign("light_field_edge",
                             toml::table{{"half_angle_deg", scene.source.edge_half_angle_deg},
                                         {"width_deg", scene.source.edge_width_deg},
                                         {"tilt_deg", std::move(tilt)}});
  }
  if (bound.kind == Kind::kPsf && f.scene["camera"].as_table() &&
      !f.scene["camera"].as_table()->contains("psf_sigma_um"))
    f.scene["camera"].as_table()->insert_or_assign("psf_sigma_um", scene.camera.psf_sigma_um);
  double current = 0;
  if (!bound.InScene()) {
    // image[i].defocus_um: the defocus of one of this file's images; image[i].background_*:
    // an additive background of its expected image (photons per pixel; slopes per pixel).
    if (bound.kind == Kind::kDefocus) {
      current = f.images[bound.image].defocus_um;
      if (!(std::abs(p.Number("lower")) <= kMaxDefocusUm &&
            std::abs(p.Number("upper")) <= kMaxDefocusUm))
        p.Fail("lower", "focus positions lie within +-1e5 um (10 cm)");
    }
  } else {
    try {
      current = SceneValue(f.scene, q.key, f.scene_file);
    } catch (const Error& err) {
      p.Fail("key", err.what());
    }
  }
  q.lower = p.Number("lower");
  q.upper = p.Number("upper");
  if (!(q.upper > q.lower)) p.Fail("upper", "must be greater than lower");
  q.start = p.Number("start", current);
  if (q.start < q.lower || q.start > q.upper) {
    std::ostringstream m;
    m << "start value " << q.start << (p.Has("start") ? "" : " (the scene's value)")
      << " lies outside [lower, upper] = [" << q.lower << ", " << q.upper << "]";
    p.Fail(p.Has("start") ? "start" : "key", m.str());
  }
  if (!std::isfinite(q.upper - q.lower)) p.Fail("upper", "upper - lower must be a finite number");
  q.step = p.Positive("step", (q.upper - q.lower) / 10);
  q.points = static_cast<int>(p.Integer("points", 0, 2, kMaxGridPoints));
  if (q.points == 0) {  // grid samples from the step (used by method grid and bench fit-grid)
    // In double first: a tiny step over a wide range must not overflow the int.
    const double n = std::floor((q.upper - q.lower) / q.step + 1e-9) + 1;
    if (!(n <= kMaxGridPoints))
      p.Fail("step", "gives " + std::to_string(n) + " grid points from lower to upper; at most " +
                         std::to_string(kMaxGridPoints) + " (give a larger step or points)");
    q.points = static_cast<int>(n);
  }
  q.unit = UnitOf(q.key);
  ReadPrior(p, t, f, current, *cal, &q);
  p.Finish();
  return q;
}

/// [rays]: the ray budget, fractions, binning and the estimator's switches.
void ReadRays(TomlReader ry, FitSpec* f_out) {
  FitSpec& f = *f_out;
  f.rays.ray_factor = ry.InRange("ray_factor", kMinRayFactor, kMaxRayFactor, 1);
  if (ry.Has("fractions")) {
    f.rays.fractions = ry.Numbers("fractions", 1, 32);
    for (double v : f.rays.fractions)
      if (!(v > 0 && v <= 1)) ry.Fail("fractions", "ray fractions must lie in (0, 1]");
    if (!std::is_sorted(f.rays.fractions.begin(), f.rays.fractions.end()))
      ry.Fail("fractions", "give the fractions coarse to fine (ascending)");
  }
  f.rays.common_random_numbers = ry.Bool("common_random_numbers", true);
  f.rays.photons_per_pixel = ry.Positive("photons_per_pixel", 0.0);
  f.rays.reuse_background = ry.Bool("reuse_background", true);
  f.rays.fit_exposure = ry.Bool("fit_exposure", true);
  f.rays.finite_ray_correction = ry.Bool("finite_ray_correction", true);
  f.rays.smooth_polish = ry.Bool("smooth_polish", true);
  f.rays.polish = ry.Bool("polish", false);
  f.rays.jacobian_seeds = int(
      ry.Integer("jacobian_seeds", f.rays.jacobian_seeds, kMinJacobianSeeds, kMaxJacobianSeeds));
  if (ry.Has("binning")) {
    for (double b : ry.Numbers("binning", f.rays.fractions.size(), f.rays.fractions.size())) {
      if (!(b >= 1 && b <= 64 && b == std::floor(b)))
        ry.Fail("binning", "expected whole numbers in [1, 64], one per ray fraction");
      f.rays.binning.push_back(int(b));
    }
  }
  ry.Finish();
}

/// [uncertainty]: repeats, Cramer-Rao bound, slices and profile-likelihood intervals.
void ReadUncertainty(TomlReader u, FitSpec* f_out) {
  FitSpec& f = *f_out;
  f.repeat_seeds = static_cast<int>(u.Integer("repeat_seeds", f.repeat_seeds, 0, kMaxRepeatSeeds));
  if (f.repeat_seeds == 1) u.Fail("repeat_seeds", "0 (none) or at least 2 repeated fits");
  f.cramer_rao = u.Bool("cramer_rao", true);
  f.slice_points = static_cast<int>(u.Integer("slice_points", 7, 0, 1001));
  if (u.Has("profile")) {
    const std::string profile = u.Choice("profile", {"auto", "always", "never"});
    f.profile = profile == "always"  ? ProfileMode::kAlways
                : profile == "never" ? ProfileMode::kNever
                                     : ProfileMode::kAuto;
  }
  f.profile_correlation = u.InRange("profile_correlation", 0, 1, 0.9);
  u.Finish();
}

/// [search]: a ray-model start fit, scanned parameters and a hop (for lm and pattern).
void ReadSearch(TomlReader sr, const std::string& path, const std::string& scene_override,
                const std::string& calibration_override, bool ray_start_fit, FitSpec* f_out) {
  FitSpec& f = *f_out;
  const std::string start = sr.Choice("start", {"parameters", "rays"}, "parameters");
  std::vector<std::string> scan;
  if (sr.Has("scan")) scan = sr.Strings("scan");
  const std::string hop_key = sr.String("hop", "");
  const double hop_step = sr.Number("hop_step", 0.0);
  if (!ray_start_fit) {
    if (f.method == Method::kGrid && (start == "rays" || !scan.empty() || !hop_key.empty()))
      sr.Fail(start == "rays" ? "start"
              : !scan.empty() ? "scan"
                              : "hop",
              "method = \"grid\" evaluates every point already: [search] is for lm and pattern");
    if (start == "rays") {
      if (!f.exact_images())
        sr.Fail("start",
                "start = \"rays\" fits the ray model first, before a wave model (optics = "
                "\"mie\" or \"physical\"); this fit's model is the rays already");
      f.start_fit = std::make_shared<const FitSpec>(
          LoadFitFile(path, scene_override, calibration_override, true));
    }
    // The index of a [search] entry's parameter, or an error listing the fit's parameters.
    auto parameter = [&](const std::string& field, const std::string& key) {
      size_t i = 0;
      while (i < f.parameters.size() && f.parameters[i].key != key) ++i;
      if (i == f.parameters.size()) {
        std::string names;
        for (const Parameter& q : f.parameters) names += (names.empty() ? "" : ", ") + q.key;
        sr.Fail(field,
                "'" + key + "' is not a [[parameter]] of this fit (they are: " + names + ")");
      }
      return i;
    };
    for (const std::string& key : scan) {
      const size_t i = parameter("scan", key);
      if (std::find(f.scan.begin(), f.scan.end(), i) != f.scan.end())
        sr.Fail("scan", "'" + key + "' is listed twice");
      f.scan.push_back(i);
    }
    if (!hop_key.empty()) {
      const Parameter& p = f.parameters[parameter("hop", hop_key)];
      if (!(hop_step > 0))
        sr.Fail("hop_step", "hop = \"" + hop_key + "\" needs hop_step > 0 (in its units)");
      if (hop_step >= p.upper - p.lower)
        sr.Fail("hop_step", "a hop of " + std::to_string(hop_step) +
                                " leaves the parameter's bounds [" + std::to_string(p.lower) +
                                ", " + std::to_string(p.upper) + "]");
      f.hop = int(&p - f.parameters.data());
      f.hop_step = hop_step;
    } else if (hop_step != 0) {
      sr.Fail("hop_step", "hop_step needs hop = \"<key>\" (the parameter to hop along)");
    }
  }
  sr.Finish();
}

/// `ray_start_fit`: the ray model's fit of a [search] start = "rays" (the scene's and the fit
/// file's optics replaced by rays, search only, no [search] stages of its own).
FitSpec LoadFitFile(const std::string& path, const std::string& scene_override,
                    const std::string& calibration_override, bool ray_start_fit) {
  const toml::table t = ParseTomlFile(path);
  TomlReader r(t, path, "");
  FitSpec f;
  f.file = path;
  const simulate::Scene scene =
      ReadSceneAndOptics(r, path, scene_override, calibration_override, ray_start_fit, &f);
  f.seed = static_cast<uint64_t>(r.Integer("seed", 1, 0, INT64_MAX));
  const std::string m = r.Choice("method", {"grid", "pattern", "lm"}, "lm");
  f.method = m == "grid"      ? Method::kGrid
             : m == "pattern" ? Method::kPattern
                              : Method::kLevenbergMarquardt;
  const std::string e =
      r.Choice("error", {"poisson", "mse", "ssim", "ms-ssim", "cw-ssim"}, "poisson");
  f.error = e == "poisson"   ? ErrorFunction::kPoisson
            : e == "mse"     ? ErrorFunction::kMse
            : e == "ssim"    ? ErrorFunction::kSsim
            : e == "ms-ssim" ? ErrorFunction::kMsSsim
                             : ErrorFunction::kCwSsim;
  f.max_evaluations = static_cast<int>(r.Integer("max_evaluations", 2000, 1, 10000000));
  f.threads = static_cast<int>(r.Integer("threads", 0, 0, 4096));

  for (TomlReader im : r.Tables("image")) f.images.push_back(ReadFitImage(im, path, scene));
  if (f.images.empty())
    r.Fail("image", "missing: give at least one [[image]] with file and defocus_um");

  std::set<std::string> keys;
  std::optional<CalibrationData> cal;  // read when a prior names it
  for (TomlReader p : r.Tables("parameter"))
    f.parameters.push_back(ReadParameter(p, t, scene, &keys, &cal, &f));
  if (f.parameters.empty())
    r.Fail("parameter", "missing: give at least one [[parameter]] with key, lower and upper");
  double grid_points = 1;
  for (const Parameter& q : f.parameters) grid_points *= std::max(q.points, 1);
  if (f.method == Method::kGrid) {
    if (grid_points > f.max_evaluations)
      r.Fail("method", "the grid has " + GridCount(grid_points) +
                           " points, more than max_evaluations (" +
                           std::to_string(f.max_evaluations) + ")");
  }

  if (r.Has("rays")) ReadRays(r.Table("rays"), &f);
  if (r.Has("uncertainty")) ReadUncertainty(r.Table("uncertainty"), &f);
  if (r.Has("search"))
    ReadSearch(r.Table("search"), path, scene_override, calibration_override, ray_start_fit, &f);
  if (ray_start_fit) {  // its optimum is the main fit's start: the estimator without extras
    f.repeat_seeds = 0;
    f.slice_points = 0;
    f.cramer_rao = false;
    f.profile = ProfileMode::kNever;
  }
  r.Finish();
  // The images against the scene's photon count ([trace] photons_per_pixel, or signal x
  // well_capacity). A fit file's [rays] photons_per_pixel replaces it as the count the fit traces
  // for (some fits trace more rays than the experiment had photons): then only the checks that
  // need no photon count apply.
  const double expected = f.rays.photons_per_pixel > 0 ? 0 : scene.trace.photons_per_pixel;
  for (const FitImage& fi : f.images) CheckExperimentImage(fi, expected, f.scene_file + " [trace]");
  return f;
}

}  // namespace

}  // namespace raymatch::fit
