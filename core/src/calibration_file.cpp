#include "raymatch/core/calibration_file.h"

#include <cmath>
#include <filesystem>
#include <sstream>

#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/toml_reader.h"

namespace fs = std::filesystem;

namespace raymatch {

namespace {

constexpr const char* kFormat = "raymatch-calibration-1";

std::string List(const std::vector<double>& v) {
  std::ostringstream os;
  os.precision(10);
  os << "[";
  for (size_t i = 0; i < v.size(); ++i) os << (i ? ", " : "") << v[i];
  os << "]";
  return os.str();
}

std::string Quote(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    if (c == '"' || c == '\\') out += '\\';
    if (c == '\n') {
      out += "\\n";
      continue;
    }
    out += c;
  }
  return out + "\"";
}

}  // namespace

void WriteCalibrationFile(const std::string& path, const CalibrationData& d) {
  EnsureDirectory(fs::path(path).parent_path());
  std::ostringstream os;
  os.precision(12);
  os << "# raymatch calibration file (docs/calibration-format.md)\nformat = \"" << kFormat
     << "\"\n\n[provenance]\n";
  for (auto& [k, v] : d.provenance.items())
    os << k << " = " << Quote(v.is_string() ? v.get<std::string>() : v.dump()) << "\n";
  os << "\n[optics]\nobjective_focal_mm = " << d.objective_focal_mm
     << "\nworking_distance_mm = " << d.working_distance_mm << "\nna = " << d.na
     << "\ntube_focal_mm = " << d.tube_focal_mm << "\npixel_pitch_um = " << d.pixel_pitch_um
     << "\nwavelength_um = " << d.wavelength_um << "\n";
  // Both files are written to temporaries first and committed only when both are complete,
  // so that a failure leaves the previous calibration (or nothing) in place.
  std::vector<std::pair<fs::path, fs::path>> sides;  // (temporary, final)
  auto sidecar = [&](const std::string& suffix, const Image& img, const std::string& what) {
    const std::string side = fs::path(path).stem().string() + suffix;
    const fs::path fin = fs::path(path).parent_path() / side;
    sides.emplace_back(TemporaryPathFor(fin), fin);
    WriteFloatImage(sides.back().first.string(), img, what);
    return side;
  };
  try {
    if (d.has_light_field()) {
      const std::string side =
          sidecar(".angular.tif", d.angular_map,
                  "raymatch calibration: angular radiance over direction cosines");
      os << "\n[light_field]\nangular_map = " << Quote(side)
         << "   # float32 TIFF: columns u, rows v (top = +extent)\nangular_extent = "
         << d.angular_extent << "\nfield_radius_um = " << d.field_radius_um
         << "   # uniform disc at the object plane; 0 = not measured (simulator sizes "
            "it)\nna_limit = "
         << d.na_limit << "   # the map is cut at this NA (0 = not cut)\ncone_half_angle_deg = "
         << d.cone_half_angle_deg << "\nnote = " << Quote(d.light_field_note) << "\n";
      if (d.edge_half_angle_deg > 0)
        os << "edge_half_angle_deg = " << d.edge_half_angle_deg
           << "   # beyond na_limit: soft edge, "
           << "half radiance here (calibrate sphere)\nedge_width_deg = " << d.edge_width_deg
           << "   # (1 - tanh((theta - edge) / width)) / 2\nedge_tilt_deg = [" << d.edge_tilt_deg[0]
           << ", " << d.edge_tilt_deg[1]
           << "]   # the edge's axis: direction cosines (sin x, sin y)\n";
      if (!d.spatial_map.empty()) {
        const std::string sp =
            sidecar(".spatial.tif", d.spatial_map,
                    "raymatch calibration: relative irradiance at the object plane");
        os << "spatial_map = " << Quote(sp)
           << "   # float32 TIFF: columns x, rows y (top = +y), relative irradiance\nfield_size_um "
              "= ["
           << d.field_size_um[0] << ", " << d.field_size_um[1]
           << "]   # the map's rectangle, centred on the axis\n";
      }
    }
  } catch (...) {
    for (auto& [tmp, fin] : sides) DiscardTemporary(tmp);
    throw;
  }
  if (d.psf_sigma_um > 0)
    os << "\n[camera]\npsf_sigma_um = " << d.psf_sigma_um
       << "   # Gaussian PSF sigma at the object plane (calibrate sphere)\n";
  if (!d.key_sigma.empty()) {
    os << "\n[uncertainty]   # 1 sigma of calibrated values, by the fit key they set "
          "(calibrate sphere; a fit's prior = \"calibration\")\n";
    for (const auto& [key, sigma] : d.key_sigma) os << Quote(key) << " = " << sigma << "\n";
  }
  if (d.has_corrector()) {
    os << "\n[corrector]\ndistance_mm = " << d.corrector_distance_mm
       << "\nring_outer_mm = " << List(d.ring_outer_mm)
       << "\ntransmissions = " << List(d.transmissions)
       << "\ntransmission_sigma = " << List(d.transmission_sigma) << "\n";
  }
  const fs::path toml_tmp = TemporaryPathFor(path);
  try {
    WriteTextFileAtomic(toml_tmp, os.str());
    for (auto& [tmp, fin] : sides) CommitTemporary(tmp, fin);
    CommitTemporary(toml_tmp, path);
  } catch (...) {
    for (auto& [tmp, fin] : sides) DiscardTemporary(tmp);
    DiscardTemporary(toml_tmp);
    throw;
  }
}

std::array<double, 2> ReadEdgeTiltDeg(TomlReader& table, const std::string& key) {
  const std::vector<double> t = table.Numbers(key, 2, 2);
  if (!(std::abs(t[0]) <= 10 && std::abs(t[1]) <= 10))
    table.Fail(key, "expected [x, y] in degrees, each within 10 (the tilt of the edge's axis)");
  return {t[0], t[1]};
}

CalibrationData ReadCalibrationFile(const std::string& path) {
  const toml::table t = ParseTomlFile(path);
  TomlReader r(t, path, "");
  CalibrationData d;
  if (r.String("format") != kFormat) r.Fail("format", std::string("expected \"") + kFormat + "\"");
  if (r.Has("provenance")) {
    TomlReader p = r.Table("provenance");
    for (auto& [k, v] : *t["provenance"].as_table())
      d.provenance[std::string(k.str())] = p.String(std::string(k.str()));
    p.Finish();
  }
  TomlReader o = r.Table("optics");
  d.objective_focal_mm = o.Positive("objective_focal_mm");
  d.working_distance_mm = o.Positive("working_distance_mm");
  d.na = o.InRange("na", 0, 1, 0, true, true);
  d.tube_focal_mm = o.Positive("tube_focal_mm");
  d.pixel_pitch_um = o.Positive("pixel_pitch_um");
  d.wavelength_um = o.InRange("wavelength_um", 0.2, 2.0, 0.462);
  o.Finish();
  if (r.Has("light_field")) {
    TomlReader l = r.Table("light_field");
    const std::string side = (fs::path(path).parent_path() / l.String("angular_map")).string();
    try {
      d.angular_map = ReadImage(side);
      d.sidecar_files.push_back(side);
    } catch (const Error& e) {
      l.Fail("angular_map", e.what());
    }
    for (float v : d.angular_map.pixels)
      if (v < 0) l.Fail("angular_map", "negative radiance in the map");
    d.angular_extent = l.InRange("angular_extent", 0, 1, 0, true, false);
    d.field_radius_um = l.Number("field_radius_um", 0);
    if (d.field_radius_um < 0) l.Fail("field_radius_um", "expected >= 0");
    d.na_limit = l.InRange("na_limit", 0, 1, 0);
    d.cone_half_angle_deg = l.InRange("cone_half_angle_deg", 0, 90, 0);
    d.light_field_note = l.String("note", "");
    if (l.Has("edge_half_angle_deg") || l.Has("edge_width_deg")) {
      if (!(d.na_limit > 0))
        l.Fail("edge_half_angle_deg", "a soft edge beyond the NA needs na_limit > 0");
      d.edge_half_angle_deg = l.InRange("edge_half_angle_deg", 1, 85, 0, true, true);
      d.edge_width_deg = l.InRange("edge_width_deg", 0.01, 20, 0, true, true);
      if (!l.Has("edge_width_deg")) l.Fail("edge_width_deg", "required with edge_half_angle_deg");
      if (!l.Has("edge_half_angle_deg"))
        l.Fail("edge_half_angle_deg", "required with edge_width_deg");
      if (l.Has("edge_tilt_deg")) d.edge_tilt_deg = ReadEdgeTiltDeg(l, "edge_tilt_deg");
    }
    if (l.Has("spatial_map") || l.Has("field_size_um")) {
      const std::string sp = (fs::path(path).parent_path() / l.String("spatial_map")).string();
      try {
        d.spatial_map = ReadImage(sp);
        d.sidecar_files.push_back(sp);
      } catch (const Error& e) {
        l.Fail("spatial_map", e.what());
      }
      double sum = 0;
      for (float v : d.spatial_map.pixels) {
        if (!(v >= 0) || !std::isfinite(v)) l.Fail("spatial_map", "expected finite values >= 0");
        sum += v;
      }
      if (!(sum > 0)) l.Fail("spatial_map", "the map is all zero");
      const auto fsz = l.Numbers("field_size_um", 2, 2);
      if (!(fsz[0] > 0) || !(fsz[1] > 0))
        l.Fail("field_size_um", "expected two positive sizes (width, height)");
      d.field_size_um[0] = fsz[0], d.field_size_um[1] = fsz[1];
    }
    l.Finish();
  }
  if (r.Has("camera")) {
    TomlReader c = r.Table("camera");
    d.psf_sigma_um = c.InRange("psf_sigma_um", 0, 100, 0);
    c.Finish();
  }
  if (r.Has("uncertainty")) {
    TomlReader u = r.Table("uncertainty");
    for (const auto& [k, v] : *t["uncertainty"].as_table()) {
      const std::string key(k.str());
      d.key_sigma[key] = u.Positive(key);
    }
    u.Finish();
  }
  if (r.Has("corrector")) {
    TomlReader c = r.Table("corrector");
    d.corrector_distance_mm = c.Positive("distance_mm");
    d.ring_outer_mm = c.Numbers("ring_outer_mm", 1, 64);
    d.transmissions = c.Numbers("transmissions", 1, 64);
    d.transmission_sigma = c.Numbers("transmission_sigma", 1, 64);
    if (d.transmissions.size() != d.ring_outer_mm.size() ||
        d.transmission_sigma.size() != d.ring_outer_mm.size())
      c.Fail("transmissions",
             "ring_outer_mm, transmissions and transmission_sigma need equal lengths");
    for (double v : d.transmissions)
      if (v < 0 || v > 1.5) c.Fail("transmissions", "expected values in [0, 1.5]");
    c.Finish();
  }
  r.Finish();
  return d;
}

}  // namespace raymatch
