#include "raymatch/calibrate/inputs.h"

#include <cmath>
#include <filesystem>
#include <utility>

#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/toml_reader.h"

namespace fs = std::filesystem;

namespace raymatch::calibrate {

namespace {

std::string Existing(TomlReader& r, const std::string& key, const std::string& folder) {
  const std::string p = (fs::path(folder) / r.String(key)).string();
  if (!fs::exists(p)) r.Fail(key, "file not found: " + p);
  return p;
}

void ReadCommon(TomlReader& r, CameraInfo* cam, OpticsInfo* opt) {
  TomlReader c = r.Table("camera");
  cam->pixel_pitch_um = c.Positive("pixel_pitch_um");
  cam->bit_depth = int(c.Integer("bit_depth", 16, 1, 32));
  cam->gain_e_per_dn = c.Positive("gain_e_per_dn", 1.0);
  cam->well_capacity_e = c.Positive("well_capacity_e", 0.0);
  cam->read_noise_e = c.Number("read_noise_e", 0.0);
  c.Finish();
  TomlReader o = r.Table("optics");
  opt->objective_focal_mm = o.Positive("objective_focal_mm");
  if (!o.Has("na"))
    o.Fail("na", "required: numerical aperture NA = n sin(theta), 0 < NA < medium_index");
  opt->medium_index = o.InRange("medium_index", 1.0, 3.0, 1.0);
  opt->na = o.InRange("na", 0, 3, 0, true, true);
  if (opt->na >= opt->medium_index)
    o.Fail("na", "NA = n sin(theta) must be below medium_index = " +
                     std::to_string(opt->medium_index) + " (docs/conventions.md)");
  opt->working_distance_mm = o.Positive("working_distance_mm", opt->objective_focal_mm);
  opt->tube_focal_mm = o.Positive("tube_focal_mm");
  opt->wavelength_um = o.InRange("wavelength_um", 0.2, 2.0, 0.462);
  // A microscope's lengths: a value beyond 10 m (e.g. a mistyped 9e18) would be accepted here
  // and only fail, far from this file, when the calibrated scene is traced.
  for (const auto& [key, v] :
       {std::pair<const char*, double>{"objective_focal_mm", opt->objective_focal_mm},
        {"working_distance_mm", opt->working_distance_mm},
        {"tube_focal_mm", opt->tube_focal_mm}})
    if (v > 1e4) o.Fail(key, "expected at most 10000 mm (10 m) for a microscope");
  o.Finish();
}

}  // namespace

LightFieldInput ReadLightFieldInput(const std::string& folder) {
  const std::string path = (fs::path(folder) / "metadata.toml").string();
  const toml::table t = ParseTomlFile(path);
  TomlReader r(t, path, "");
  LightFieldInput in;
  in.folder = folder;
  if (r.Has("dark")) in.dark = Existing(r, "dark", folder);
  in.field_radius_um = r.Number("field_radius_um", 0.0);
  if (in.field_radius_um < 0) r.Fail("field_radius_um", "expected >= 0 (0 = not measured)");
  if (r.Has("flat")) {
    in.flat = Existing(r, "flat", folder);
    in.flat_bin_px = int(r.Integer("flat_bin_px", 8, 1, 1024));
    if (in.field_radius_um > 0)
      r.Fail("flat", "give either field_radius_um (uniform disc) or flat (spatial map), not both");
  }
  if (r.Has("camera_model")) {
    // mrcal path: a camera focused at infinity; no pinhole, no defocus series.
    in.camera_model = Existing(r, "camera_model", folder);
    if (r.Has("cone") || r.Has("pinhole"))
      r.Fail("camera_model",
             "give either camera_model with [[direction]] images or pinhole with [[cone]] images, "
             "not both");
    for (TomlReader& c : r.Tables("direction")) {
      in.direction_images.push_back(Existing(c, "file", folder));
      c.Finish();
    }
    if (in.direction_images.empty())
      throw Error(r.Where("camera_model"),
                  "camera_model needs at least one [[direction]] image (file = ...)");
  } else {
    in.pinhole = Existing(r, "pinhole", folder);
    in.pinhole_diameter_um = r.Positive("pinhole_diameter_um");
    for (TomlReader& c : r.Tables("cone")) {
      ConeImage ci;
      ci.file = Existing(c, "file", folder);
      ci.dz_um = c.Positive("dz_um");
      c.Finish();
      in.cones.push_back(ci);
    }
    if (in.cones.size() < 2)
      throw Error(r.Where(), "need at least two [[cone]] images at different dz_um (got " +
                                 std::to_string(in.cones.size()) + ")");
    for (size_t i = 0; i < in.cones.size(); ++i)
      for (size_t j = i + 1; j < in.cones.size(); ++j)
        if (in.cones[i].dz_um == in.cones[j].dz_um)
          throw Error(r.Where(),
                      "two cone images share dz_um = " + std::to_string(in.cones[i].dz_um));
  }
  ReadCommon(r, &in.camera, &in.optics);
  r.Finish();
  return in;
}

FlatFieldInput ReadFlatFieldInput(const std::string& folder) {
  const std::string path = (fs::path(folder) / "metadata.toml").string();
  const toml::table t = ParseTomlFile(path);
  TomlReader r(t, path, "");
  FlatFieldInput in;
  in.folder = folder;
  if (r.Has("dark")) in.dark = Existing(r, "dark", folder);
  in.pinhole_diameter_um = r.Positive("pinhole_diameter_um");
  for (TomlReader& f : r.Tables("flat")) {
    FlatImage fi;
    fi.file = Existing(f, "file", folder);
    fi.cone = Existing(f, "cone", folder);
    fi.cone_dz_um = f.Positive("cone_dz_um");
    fi.exposure = f.Positive("exposure", 1.0);
    fi.cone_exposure = f.Positive("cone_exposure", 1.0);
    f.Finish();
    in.flats.push_back(fi);
  }
  if (in.flats.size() < 2) throw Error(r.Where(), "need at least two [[flat]] entries");
  ReadCommon(r, &in.camera, &in.optics);
  r.Finish();
  return in;
}

Image LoadPhotons(const std::string& file, const Image* dark, const CameraInfo& cam,
                  size_t* saturated) {
  Image img = ReadImage(file);
  const double sat = std::pow(2.0, cam.bit_depth) - 1;
  size_t n = 0;
  for (float v : img.pixels) n += v >= sat;
  if (saturated) *saturated = n;
  if (dark) {
    if (dark->width != img.width || dark->height != img.height)
      throw Error(FileLocation{file}, "image is " + std::to_string(img.width) + "x" +
                                          std::to_string(img.height) + " but the dark frame is " +
                                          std::to_string(dark->width) + "x" +
                                          std::to_string(dark->height));
    for (size_t i = 0; i < img.size(); ++i) img.pixels[i] -= dark->pixels[i];
  }
  double mx = -1e300;
  for (float& v : img.pixels) {
    v = float(v * cam.gain_e_per_dn);
    mx = std::max(mx, double(v));
  }
  if (!(mx > 5 * std::max(cam.read_noise_e, 1.0)))
    throw Error(FileLocation{file},
                "image is blank (no pixel above the dark level + 5 read-noise sigmas)");
  return img;
}

}  // namespace raymatch::calibrate
