// The simulated camera: raymatch's own tracer renders what the stage shows (pinhole, focus,
// iris, lamp, objects), then the camera model turns photo-electrons into code values.
//
// Same lamp for every frame: the ray count is proportional to the exposure, the field area (the
// pinhole's or the open field's) and the source power the iris lets through, so relative
// exposures, iris series and pinhole/flat ratios come out as a real lamp would give them. The
// flat-field scale is [sim_camera] photons_per_us: photo-electrons per pixel per microsecond in
// the open field with the iris open. Frame k traces plane k's ray streams and draws its read
// noise from stream 0x80000000 + k: the same scene, seed and sequence of requests give the
// same frames, bit for bit.
#include <cmath>
#include <sstream>

#include "backends.h"
#include "raymatch/capture/sensor_model.h"
#include "raymatch/core/error.h"
#include "raymatch/core/provenance.h"
#include "raymatch/core/toml_reader.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/tracer.h"

namespace raymatch::capture::internal {

namespace {

using simulate::Scene;
using simulate::SourceType;

constexpr double kDeg = M_PI / 180;

class SimCamera : public Camera {
 public:
  explicit SimCamera(const std::string& path) {
    toml::table root = ParseTomlFile(path);
    const toml::node* node = root.get("sim_camera");
    if (!node || !node->is_table())
      throw Error(FileLocation{path},
                  "sim camera: missing table [sim_camera] (the camera model: photons_per_us, "
                  "bit_depth, gain_e_per_dn, black_level_dn, read_noise_e, well_capacity_e; "
                  "docs/capture.md)");
    const toml::table sub = *node->as_table();
    TomlReader r(sub, path, "sim_camera");
    info_.model = r.String("model", "raymatch simulated camera");
    model_.bit_depth = int(r.Integer("bit_depth", 12, 1, 16));
    model_.gain_e_per_dn = r.Positive("gain_e_per_dn", 1.0);
    model_.black_level_dn = r.InRange("black_level_dn", 0, model_.max_dn(), 64);
    model_.read_noise_e = r.InRange("read_noise_e", 0, 1e4, 6);
    model_.well_capacity_e = r.Positive("well_capacity_e", 4500.0);
    photons_per_us_ = r.Positive("photons_per_us");
    info_.exposure_min_us = r.Positive("exposure_min_us", 1.0);
    info_.exposure_max_us = r.Positive("exposure_max_us", 1e7);
    info_.gain_min = r.Positive("gain_min", 1.0);
    info_.gain_max = r.Positive("gain_max", 16.0);
    if (r.Has("temperature_c")) temperature_c_ = r.InRange("temperature_c", -100, 150, 20);
    const bool has_seed = r.Has("seed");
    const int64_t seed = r.Integer("seed", 1, 0, INT64_MAX);
    r.Finish();
    if (info_.exposure_min_us > info_.exposure_max_us)
      throw Error(r.Where("exposure_min_us"),
                  "'sim_camera.exposure_min_us' is above exposure_max_us");
    if (info_.gain_min > info_.gain_max)
      throw Error(r.Where("gain_min"), "'sim_camera.gain_min' is above gain_max");
    model_.Validate();
    root.erase("sim_camera");
    scene_ = simulate::LoadScene(root, path);
    if (has_seed) scene_.trace.seed = uint64_t(seed);
    objects_ = scene_.objects;
    scene_.objects.clear();
    scene_.defocus_um = {0.0};  // the stage sets the focus; a [scan] in the file is not used

    info_.id = "sim:" + path;
    info_.backend = "sim";
    info_.width = scene_.camera.nx;
    info_.height = scene_.camera.ny;
    info_.pixel_pitch_um = scene_.camera.pixel_pitch_um;
    info_.raw_format = "R16";
    info_.bit_depth = model_.bit_depth;
    info_.pixel_formats = {"R16 (mono, " + std::to_string(model_.bit_depth) + "-bit data)"};
    std::ostringstream notes;
    notes << "renders " << path << " (source " << SourceName() << ") with raymatch's tracer; "
          << photons_per_us_ << " e-/pixel/us in the open flat field";
    info_.notes = notes.str();
    const auto& o = scene_.optics;
    info_.datasheet = {{"pixel_pitch_um", scene_.camera.pixel_pitch_um},
                       {"bit_depth", model_.bit_depth},
                       {"gain_e_per_dn", model_.gain_e_per_dn},
                       {"well_capacity_e", model_.well_capacity_e},
                       {"read_noise_e", model_.read_noise_e},
                       {"objective_focal_mm", o.objective_focal_mm},
                       {"na", o.na},
                       {"working_distance_mm", o.working_distance_mm},
                       {"tube_focal_mm", o.tube_focal_mm},
                       {"wavelength_um", scene_.wavelength_um}};

    // The open flat field: hits per pixel per ray, field area and source power.
    const simulate::Simulator base(scene_);
    base.RaysForPhotonTarget(1.0, &hits_per_pixel_per_ray_);
    if (!(hits_per_pixel_per_ray_ > 0))
      throw Error(FileLocation{path}, "sim camera: no ray of the open field reaches the sensor");
    base_area_um2_ = FieldArea(base);
    base_power_ = SourcePower(scene_.source);
    // The objects (meshes, index fields) are traced only in frames with the objects in view:
    // build them once now so that an unusable mesh is refused when the camera opens, before a
    // capture makes its output folder.
    if (!objects_.empty()) {
      Scene with_objects = scene_;
      with_objects.objects = objects_;
      const simulate::Simulator check(with_objects);
    }
  }

  const CameraInfo& info() const override { return info_; }
  bool simulated() const override { return true; }
  void SetStage(const StageState& s) override { stage_ = s; }

  Frame Capture(const CaptureSettings& settings) override {
    ValidateSettings(info_, settings);
    const uint32_t index = frame_index_++;
    Frame f;
    f.pixel_format = info_.raw_format;
    f.bit_depth = model_.bit_depth;
    f.exposure_us = settings.exposure_us;
    f.analogue_gain = settings.analogue_gain;
    f.black_level_dn = model_.black_level_dn;
    f.temperature_c = temperature_c_;
    f.sensor_timestamp_ns = int64_t(index) * 1000000;  // simulated clock, 1 ms per frame
    Image electrons(info_.width, info_.height);
    uint64_t rays = 0;
    if (stage_.lamp_on) {
      Scene s = scene_;
      if (stage_.objects) s.objects = objects_;
      s.defocus_um = {stage_.focus_um};  // the automatic field covers this focus
      if (stage_.pinhole) {
        // Images through the pinhole are rendered without the corrector stage: calibrate
        // corrector takes the cone images as the illumination's light per zone before the
        // losses the flat fields show (docs/calibration.md; tools/generate_sample.cpp does the
        // same). docs/capture.md says so.
        s.optics.corrector.enabled = false;
        if (!(stage_.pinhole_diameter_um > 0))
          throw Error("sim camera: pinhole diameter " + std::to_string(stage_.pinhole_diameter_um) +
                      " um: expected > 0");
        s.source.field_shape = simulate::FieldShape::kDisc;
        s.source.field_radius_um = stage_.pinhole_diameter_um / 2;
      }
      if (stage_.iris_deg > 0) ApplyIris(&s.source, stage_.iris_deg);
      const simulate::Simulator sim(s);
      const double photons = photons_per_us_ * settings.exposure_us;
      const double ratio = FieldArea(sim) / base_area_um2_ * SourcePower(s.source) / base_power_;
      rays = uint64_t(std::llround(photons / hits_per_pixel_per_ray_ * ratio));
      simulate::RunControl ctl;
      electrons = sim.TracePlane(stage_.focus_um, index, rays, ctl).counts;
    }
    f.dn = CropRoi(ExposeSensor(model_, electrons, settings.analogue_gain, scene_.trace.seed,
                                0x80000000u + index),
                   settings.roi);
    f.timestamp_utc = UtcTimestamp();
    ApplyBayerMode(&f, settings.bayer, false, 0);
    f.extra = {{"simulated", true},
               {"scene", scene_.file},
               {"seed", scene_.trace.seed},
               {"frame_index", index},
               {"rays", rays},
               {"stage",
                {{"lamp_on", stage_.lamp_on},
                 {"pinhole", stage_.pinhole},
                 {"pinhole_diameter_um", stage_.pinhole_diameter_um},
                 {"focus_um", stage_.focus_um},
                 {"iris_deg", stage_.iris_deg},
                 {"objects", stage_.objects}}},
               {"camera_model",
                {{"gain_e_per_dn", model_.gain_e_per_dn},
                 {"black_level_dn", model_.black_level_dn},
                 {"read_noise_e", model_.read_noise_e},
                 {"well_capacity_e", model_.well_capacity_e},
                 {"bit_depth", model_.bit_depth},
                 {"photons_per_us", photons_per_us_}}}};
    return f;
  }

 private:
  std::string SourceName() const {
    switch (scene_.source.type) {
      case SourceType::kCone:
        return "cone";
      case SourceType::kLightField:
        return "lightfield";
      case SourceType::kCollimated:
        return "collimated";
      case SourceType::kPoint:
        return "point";
      case SourceType::kRayList:
        return "ray_list";
    }
    return "?";
  }

  static double FieldArea(const simulate::Simulator& sim) {
    const auto& src = sim.scene().source;
    if (src.field_shape == simulate::FieldShape::kRect)
      return src.field_size_um[0] * src.field_size_um[1];
    return M_PI * sim.field_radius_um() * sim.field_radius_um();
  }

  // Power of the source per unit field area, arbitrary units common to one source type.
  static double SourcePower(const simulate::SourceSpec& src) {
    if (src.type == SourceType::kCone) return std::pow(std::sin(src.half_angle_deg * kDeg), 2);
    if (src.type == SourceType::kLightField) {
      double sum = 0;
      for (float v : src.angular_map.pixels) sum += v;
      return sum;
    }
    return 1;
  }

  // The iris limits the illumination to `iris_deg` from the axis (a hard edge; the light the
  // iris blocks is simply missing, the lamp stays the same).
  static void ApplyIris(simulate::SourceSpec* src, double iris_deg) {
    if (src->type == SourceType::kCone) {
      src->half_angle_deg = std::min(src->half_angle_deg, iris_deg);
    } else if (src->type == SourceType::kLightField) {
      const int n = src->angular_map.width, m = src->angular_map.height;
      const double e = src->angular_extent, s = std::sin(iris_deg * kDeg);
      for (int y = 0; y < m; ++y)
        for (int x = 0; x < n; ++x) {
          const double u = (2 * (x + 0.5) / n - 1) * e, v = (1 - 2 * (y + 0.5) / m) * e;
          if (std::hypot(u, v) > s) src->angular_map.at(x, y) = 0;
        }
    } else {
      throw Error("sim camera: an iris needs a cone or lightfield source");
    }
  }

  CameraInfo info_;
  SensorModel model_;
  Scene scene_;
  std::vector<simulate::ObjectSpec> objects_;
  double photons_per_us_ = 0, hits_per_pixel_per_ray_ = 0, base_area_um2_ = 0, base_power_ = 1;
  std::optional<double> temperature_c_;
  StageState stage_;
  uint32_t frame_index_ = 0;
};

}  // namespace

std::unique_ptr<Camera> OpenSimCamera(const std::string& scene_path) {
  if (scene_path.empty())
    throw Error("camera 'sim:': expected sim:SCENE.toml (a scene file with a [sim_camera] table)");
  return std::make_unique<SimCamera>(scene_path);
}

}  // namespace raymatch::capture::internal
