#include "raymatch/simulate/scene.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <sstream>

#include "raymatch/core/array_io.h"
#include "raymatch/core/calibration_file.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/toml_reader.h"
#include "raymatch/simulate/physical_image.h"
#include "raymatch/simulate/shapes.h"
#include "raymatch/simulate/water.h"
#include "raymatch/simulate/wave_image.h"

namespace fs = std::filesystem;

namespace raymatch::simulate {

namespace {

std::string Resolve(const std::string& scene_file, const std::string& p) {
  const fs::path path(p);
  if (path.is_absolute()) return p;
  return (fs::path(scene_file).parent_path() / path).lexically_normal().string();
}

/// A file the scene names, resolved against the scene file and recorded in its input_files.
std::string Input(Scene& s, const std::string& p) {
  std::string f = Resolve(s.file, p);
  s.input_files.push_back(f);
  return f;
}

Image ReadMap(TomlReader& r, const std::string& key, const std::string& scene_file,
              std::string* resolved) {
  *resolved = Resolve(scene_file, r.String(key));
  Image img;
  try {
    img = ReadImage(*resolved);
  } catch (const Error& e) {
    r.Fail(key, e.what());
  }
  double sum = 0;
  for (float v : img.pixels) {
    if (v < 0) r.Fail(key, "map has negative values (radiance must be >= 0)");
    sum += v;
  }
  if (!(sum > 0)) r.Fail(key, "map is blank (all zero)");
  return img;
}

void ReadField(TomlReader& r, SourceSpec& s) {
  const std::string shape = r.Choice("field_shape", {"disc", "rect"}, "disc");
  s.field_shape = shape == "disc" ? FieldShape::kDisc : FieldShape::kRect;
  if (s.field_shape == FieldShape::kDisc) {
    s.field_radius_um = r.Positive("field_radius_um", 0.0);
  } else {
    const auto v = r.Numbers("field_size_um", 2, 2);
    if (!(v[0] > 0 && v[1] > 0)) r.Fail("field_size_um", "expected two positive sizes");
    s.field_size_um = {v[0], v[1]};
  }
  const auto c = r.Vec3("field_center_um", {0, 0, 0});
  s.field_center_um = {c[0], c[1], 0};
}

/// [source] spectrum = { type = "gaussian", center_um, fwhm_um } | { type = "lines",
/// wavelengths_um, weights } | { file = "led.csv" } (wavelength_um, power[, efficiency]).
SpectrumSpec ReadSpectrum(TomlReader r, const std::string& scene_file) {
  SpectrumSpec s;
  const std::string type = r.Choice("type", {"gaussian", "lines", "file"}, "file");
  if (type == "gaussian") {
    s.type = SpectrumType::kGaussian;
    s.center_um = r.InRange("center_um", 0.2, 2.0, 0);
    s.fwhm_um = r.InRange("fwhm_um", 0, 0.2, 0, true);
    if (!r.Has("center_um") || !r.Has("fwhm_um"))
      r.Fail(r.Has("center_um") ? "fwhm_um" : "center_um",
             "required: center_um (0.2-2 um) and fwhm_um (up to 0.2 um)");
  } else if (type == "lines") {
    s.type = SpectrumType::kLines;
    s.wavelengths_um = r.Numbers("wavelengths_um", 1, 1000);
    s.weights = r.Numbers("weights", s.wavelengths_um.size(), s.wavelengths_um.size());
    double sum = 0;
    for (size_t k = 0; k < s.weights.size(); ++k) {
      if (!(s.wavelengths_um[k] >= 0.2 && s.wavelengths_um[k] <= 2.0))
        r.Fail("wavelengths_um", "expected wavelengths from 0.2 to 2 um");
      if (!(s.weights[k] >= 0)) r.Fail("weights", "expected weights >= 0");
      sum += s.weights[k];
    }
    if (!(sum > 0)) r.Fail("weights", "expected a positive weight");
    for (double& w : s.weights) w /= sum;
  } else {
    s.type = SpectrumType::kFile;
    s.file = Resolve(scene_file, r.String("file"));
    try {
      s.table = ReadPiecewiseLinearCsv(s.file, "wavelength_um,relative_power[,efficiency]");
    } catch (const Error& e) {
      r.Fail("file", e.what());
    }
    if (!(s.table.x.front() >= 0.2 && s.table.x.back() <= 2.0))
      r.Fail("file", "wavelengths from 0.2 to 2 um expected in " + s.file);
  }
  r.Finish();
  return s;
}

SourceSpec ReadSource(TomlReader r, const std::string& file) {
  SourceSpec s;
  if (r.Has("spectrum")) s.spectrum = ReadSpectrum(r.Table("spectrum"), file);
  const std::string type =
      r.Choice("type", {"collimated", "cone", "point", "lightfield", "ray_list"});
  if (type == "collimated") {
    s.type = SourceType::kCollimated;
    ReadField(r, s);
    s.tilt_deg = r.InRange("tilt_deg", 0, 89, 0);
    s.azimuth_deg = r.Number("azimuth_deg", 0);
  } else if (type == "cone") {
    s.type = SourceType::kCone;
    ReadField(r, s);
    s.half_angle_deg = r.InRange("half_angle_deg", 0, 89, 0, true, false);
    if (!r.Has("half_angle_deg")) r.Fail("half_angle_deg", "required for a cone source");
  } else if (type == "point") {
    s.type = SourceType::kPoint;
    const auto p = r.Vec3("position_um");
    s.position_um = {p[0], p[1], p[2]};
    s.half_angle_deg = r.InRange("half_angle_deg", 0, 90, 90, true, false);
  } else if (type == "ray_list") {
    s.type = SourceType::kRayList;
    s.ray_file = Resolve(file, r.String("file"));
    NdArray a;
    try {
      a = ReadNpy(s.ray_file);
    } catch (const Error& e) {
      r.Fail("file", e.what());
    }
    if (a.shape.size() != 2 || a.shape[1] != 5 || a.shape[0] < 1)
      r.Fail("file", "expected a .npy array of shape (N, 5): x_um, y_um, u, v, weight per ray");
    double total = 0;
    for (size_t i = 0; i < a.shape[0]; ++i) {
      const double* v = &a.values[5 * i];
      for (int k = 0; k < 5; ++k)
        if (!std::isfinite(v[k]))
          r.Fail("file", "ray " + std::to_string(i) + " has a NaN or Inf value");
      if (v[2] * v[2] + v[3] * v[3] >= 1)
        r.Fail("file", "ray " + std::to_string(i) + ": direction cosines need u^2 + v^2 < 1");
      if (v[4] < 0) r.Fail("file", "ray " + std::to_string(i) + ": negative weight");
      total += v[4];
      s.rays.push_back({v[0], v[1], v[2], v[3], v[4]});
    }
    if (!(total > 0)) r.Fail("file", "all ray weights are zero");
  } else {
    s.type = SourceType::kLightField;
    ReadField(r, s);
    s.angular_map = ReadMap(r, "angular_map", file, &s.angular_map_file);
    s.angular_extent = r.InRange("angular_extent", 0, 1, 0, true, false);
    if (!r.Has("angular_extent"))
      r.Fail("angular_extent", "required: half-width of the map in direction cosines, (0, 1]");
    if (r.Has("spatial_map")) {
      if (s.field_shape != FieldShape::kRect)
        r.Fail("spatial_map", "a spatial map needs field_shape = \"rect\" and field_size_um");
      s.spatial_map = ReadMap(r, "spatial_map", file, &s.spatial_map_file);
    }
  }
  r.Finish();
  return s;
}

/// A dispersion law instead of a constant index: cauchy = [A, B, ...] (n = A + B / l^2 + ...)
/// or sellmeier_b + sellmeier_c_um2 (n^2 = 1 + sum B l^2 / (l^2 - C)), l in um.
bool ReadDispersionLaw(TomlReader& r, const Scene& scene, ObjectSpec& o) {
  const bool cauchy = r.Has("cauchy"), sellmeier = r.Has("sellmeier_b");
  if (!cauchy && !sellmeier) {
    if (r.Has("sellmeier_c_um2")) r.Fail("sellmeier_c_um2", "give sellmeier_b too");
    return false;
  }
  for (const char* k : {"index", "material"})
    if (r.Has(k)) r.Fail(k, "give one of index, material, cauchy or sellmeier_b/_c_um2");
  if (cauchy && sellmeier) r.Fail("sellmeier_b", "give either cauchy or sellmeier_b, not both");
  Dispersion& d = o.dispersion;
  std::ostringstream os;
  os.precision(8);
  if (cauchy) {
    d.law = DispersionLaw::kCauchy;
    d.coefficients = r.Numbers("cauchy", 1, 6);
    os << "Cauchy (n = A + B/l^2 + ...; l in um)";
  } else {
    d.law = DispersionLaw::kSellmeier;
    d.sellmeier_b = r.Numbers("sellmeier_b", 1, 6);
    d.sellmeier_c_um2 = r.Numbers("sellmeier_c_um2", d.sellmeier_b.size(), d.sellmeier_b.size());
    os << "Sellmeier (n^2 = 1 + sum B l^2/(l^2 - C); l in um)";
  }
  // The index over the illumination's wavelengths: each must be a real index above 1.
  std::vector<double> ls = {scene.wavelength_um};
  const SpectrumSpec& sp = scene.source.spectrum;
  if (sp.type == SpectrumType::kLines) ls = sp.wavelengths_um;
  if (sp.type == SpectrumType::kGaussian)
    ls = {sp.Sample(0), sp.Sample(0.5), sp.Sample(std::nextafter(1.0, 0.0))};
  if (sp.type == SpectrumType::kFile) ls = {sp.table.x.front(), sp.table.x.back()};
  for (double l : ls) {
    const double n = d.IndexAt(l);
    if (!(n >= 1.0 && n <= 5.0))
      r.Fail(cauchy ? "cauchy" : "sellmeier_b", "gives n = " + std::to_string(n) + " at " +
                                                    std::to_string(l) +
                                                    " um, within the spectrum (expected 1 to 5)");
  }
  o.index = d.IndexAt(scene.wavelength_um);
  os << ": n=" << o.index << " at " << scene.wavelength_um << " um";
  o.material = os.str();
  return true;
}

void ReadMaterial(TomlReader& r, const Scene& scene, ObjectSpec& o) {
  o.absorption_index = r.InRange("absorption_index", 0.0, 10.0, 0.0);
  if (ReadDispersionLaw(r, scene, o)) return;
  if (r.Has("index") && r.Has("material"))
    r.Fail("material", "give either 'index' or 'material', not both");
  if (r.Has("index")) {
    o.index = r.InRange("index", 1.0, 5.0, 1.0);
    o.material = "constant index";
    r.Number("temperature_K", 0), r.Number("density_kg_m3", 0);  // mark; checked below
    if (r.Has("temperature_K") || r.Has("density_kg_m3"))
      r.Fail(r.Has("temperature_K") ? "temperature_K" : "density_kg_m3",
             "only meaningful with material = \"water\"");
    return;
  }
  if (!r.Has("material")) r.Fail("index", "missing: give 'index = <n>' or 'material = \"water\"'");
  r.Choice("material", {"water"});
  const double T = r.InRange("temperature_K", 261.15, 773.15, 293.15);
  double rho;
  if (r.Has("density_kg_m3")) {
    rho = r.InRange("density_kg_m3", 0, 2000, 998, true, false);
    o.density_source = "given";
  } else {
    if (T < 273.15 || T > 313.15)
      r.Fail("temperature_K", "outside 273.15-313.15 K the density must be given (density_kg_m3)");
    rho = WaterDensityTanaka(T);
    o.density_source = "defaulted";
  }
  o.density_kg_m3 = rho;
  o.dispersion.law = DispersionLaw::kWater;
  o.dispersion.temperature_K = T;
  o.dispersion.density_kg_m3 = rho;
  const WaterIndex w = WaterRefractiveIndex(T, rho, scene.wavelength_um);
  o.index = w.n;
  std::ostringstream os;
  os.precision(8);
  os << "water (IAPWS R9-97, T=" << T << " K, rho=" << rho
     << " kg/m^3, lambda=" << scene.wavelength_um << " um): n=" << w.n;
  o.material = os.str();
}

/// `perturbation_scale` of a grid: its difference from a reference multiplied,
/// v' = ref + s (v - ref), in the grid's own quantity (density before IAPWS R9-97, or index). The
/// reference: `reference_density_kg_m3` / `reference_index`, else the grid's mean on the object's
/// surface (spheres: 1024 points of a Fibonacci lattice). s = 1 leaves the grid as it is.
void ScalePerturbation(TomlReader& r, IndexField* f, const ObjectSpec& o, bool density) {
  const std::string ref_key = density ? "reference_density_kg_m3" : "reference_index";
  const std::string other = density ? "reference_index" : "reference_density_kg_m3";
  if (r.Has(other))
    r.Fail(other,
           std::string("a ") + (density ? "density" : "index") + " grid's reference is " + ref_key);
  const double s = r.Number("perturbation_scale", 1.0);
  if (!(std::abs(s) <= 1e6)) r.Fail("perturbation_scale", "expected a finite number within +-1e6");
  const bool given = r.Has(ref_key);
  double ref = given ? r.Positive(ref_key) : 0;
  if (s == 1) return;  // bit for bit the grid as given
  std::string from = "given";
  if (!given) {
    if (o.shape != ShapeType::kSphere)
      r.Fail("perturbation_scale",
             "give " + ref_key +
                 ": the default reference (the grid's mean on the surface) is "
                 "defined for spheres");
    const int n = 1024;
    double sum = 0;
    for (int k = 0; k < n; ++k) {  // Fibonacci lattice: equal areas on the sphere
      const double z = 1 - (2 * k + 1) / double(n), rho = std::sqrt(1 - z * z);
      const double phi = k * M_PI * (3 - std::sqrt(5.0));
      sum += f->Index(Vec3(rho * std::cos(phi), rho * std::sin(phi), z) * o.radius_um);
    }
    ref = sum / n;
    from = "the grid's mean on the sphere's surface";
  }
  for (double& v : f->values) v = ref + s * (v - ref);
  std::ostringstream d;
  d << "difference from " << ref << (density ? " kg/m^3" : "") << " (" << from << ") x " << s
    << "; ";
  f->description = d.str();
}

std::shared_ptr<const IndexField> ReadIndexField(TomlReader r, Scene& scene, const ObjectSpec& o) {
  auto f = std::make_shared<IndexField>();
  const std::string type =
      r.Choice("type", {"luneburg", "fisheye", "parabolic", "linear_n2", "grid_rz", "grid_3d"});
  if (type == "luneburg") {
    f->type = IndexFieldType::kLuneburg;
    f->n0 = r.Positive("n0", scene.medium_index);
    f->radius_um = r.Positive("radius_um", o.shape == ShapeType::kSphere ? o.radius_um : 0.0);
    if (!(f->radius_um > 0)) r.Fail("radius_um", "required unless the object is a sphere");
    f->description = "Luneburg n = n0 sqrt(2 - (r/R)^2)";
  } else if (type == "fisheye") {
    f->type = IndexFieldType::kFishEye;
    f->n0 = r.Positive("n0");
    f->radius_um = r.Positive("radius_um");
    f->description = "Maxwell fish-eye n = n0 / (1 + (r/a)^2)";
  } else if (type == "parabolic") {
    f->type = IndexFieldType::kParabolic;
    f->n0 = r.Positive("n0");
    f->g_per_um = r.Positive("g_per_um");
    f->description = "parabolic n^2 = n0^2 (1 - g^2 (x^2 + y^2))";
  } else if (type == "linear_n2") {
    f->type = IndexFieldType::kLinearN2;
    f->n0 = r.Positive("n0");
    const auto k = r.Vec3("k_per_um");
    f->k_per_um = {k[0], k[1], k[2]};
    f->description = "linear n^2 = n0^2 + k . p";
  } else {
    const bool rz = type == "grid_rz";
    f->type = rz ? IndexFieldType::kGridRZ : IndexFieldType::kGrid3D;
    const std::string file = Input(scene, r.String("file"));
    const std::string dataset = r.String("dataset", "");
    NdArray a;
    try {
      a = ReadArrayFile(file, dataset);
    } catch (const Error& e) {
      r.Fail("file", e.what());
    }
    const size_t dims = rz ? 2 : 3;
    if (a.shape.size() != dims)
      r.Fail("file", std::string("expected a ") +
                         (rz ? "2D array [nz][nr]" : "3D array [nz][ny][nx]") + ", got " +
                         std::to_string(a.shape.size()) + " dimensions");
    for (size_t i = 0; i < a.size(); ++i)
      if (!std::isfinite(a.values[i]))
        r.Fail("file", "grid value " + std::to_string(i) + " (flat C-order index) is NaN or Inf");
    const auto sp = r.Numbers("spacing_um", dims, dims);
    for (double v : sp)
      if (!(v > 0)) r.Fail("spacing_um", "spacings must be positive");
    std::vector<double> org(dims, 0.0);
    if (r.Has("origin_um"))
      org = r.Numbers("origin_um", dims, dims);
    else
      r.Number("origin_um", 0);
    if (rz) {
      f->nz = int(a.shape[0]), f->nx = int(a.shape[1]), f->ny = 1;
      f->spacing_um = {sp[0], 1, sp[1]};
      f->origin_um = {org[0], 0, org[1]};
      if (org[0] < 0) r.Fail("origin_um", "the radius of the first sample must be >= 0");
    } else {
      f->nz = int(a.shape[0]), f->ny = int(a.shape[1]), f->nx = int(a.shape[2]);
      f->spacing_um = {sp[0], sp[1], sp[2]};
      f->origin_um = {org[0], org[1], org[2]};
    }
    const std::string quantity = r.Choice("quantity", {"index", "density"}, "index");
    f->values = std::move(a.values);
    ScalePerturbation(r, f.get(), o, quantity == "density");
    if (quantity == "density") {
      std::vector<double> temps;
      double T = 293.15;
      if (r.Has("temperature_file")) {
        NdArray t;
        try {
          t = ReadArrayFile(Input(scene, r.String("temperature_file")), dataset);
        } catch (const Error& e) {
          r.Fail("temperature_file", e.what());
        }
        if (t.size() != f->values.size())
          r.Fail("temperature_file", "must have the same shape as the density grid");
        temps = std::move(t.values);
      } else {
        T = r.InRange("temperature_K", 200, 800, 293.15);
      }
      // A subsample of the grid's states (at most ~4096, every k-th value) for rays of other
      // wavelengths under a spectrum (WaterMapTable).
      auto states = std::make_shared<IndexField::WaterStates>();
      states->wavelength_um = scene.wavelength_um;
      const size_t every = std::max<size_t>(1, f->values.size() / 4096);
      size_t out_of_range = 0;
      for (size_t i = 0; i < f->values.size(); ++i) {
        const double Ti = temps.empty() ? T : temps[i];
        if (i % every == 0)
          states->density_kg_m3.push_back(f->values[i]), states->temperature_K.push_back(Ti);
        const WaterIndex w = WaterRefractiveIndex(Ti, f->values[i], scene.wavelength_um);
        out_of_range += !w.in_range;
        f->values[i] = w.n;
      }
      f->water = std::move(states);
      if (out_of_range)
        scene.warnings.push_back(r.Where("file").ToString() + ": " + std::to_string(out_of_range) +
                                 " grid values lie outside the IAPWS R9-97 range (0-1060 kg/m^3, "
                                 "261-773 K); the formula is extrapolated there");
      f->description += "water density grid -> IAPWS R9-97 index";
    } else {
      r.Number("temperature_K", 0), r.String("temperature_file", "");
      f->description += "index grid";
      for (double v : f->values)
        if (!(v > 0)) r.Fail("file", "refractive indices must be positive");
    }
    f->description += std::string(rz ? " n(r, z) " : " n(x, y, z) ") + file;
  }
  // A rotation about the object's centre (after the scaling, whose default reference, the mean
  // on a sphere's surface, then does not depend on it).
  if (r.Has("rotation_deg")) {
    const auto a = r.Vec3("rotation_deg");
    for (double v : a)
      if (!(std::abs(v) <= 360)) r.Fail("rotation_deg", "expected three angles within +-360 deg");
    f->rotated = true;
    f->rotation = RotationFromEulerDeg(a[0], a[1], a[2]);
    f->rotation_t = f->rotation.Transposed();
    std::ostringstream d;
    d << ", rotated [" << a[0] << ", " << a[1] << ", " << a[2] << "] deg";
    f->description += d.str();
  }
  r.Finish();
  // Range for reports: sample the analytic fields at the centre; grids exactly.
  if (!f->values.empty()) {
    f->min_n = *std::min_element(f->values.begin(), f->values.end());
    f->max_n = *std::max_element(f->values.begin(), f->values.end());
  } else {
    f->min_n = f->max_n = f->Index(Vec3());
  }
  return f;
}

ObjectSpec ReadObject(TomlReader r, Scene& scene, int i) {
  ObjectSpec o;
  o.where = r.Where();
  o.name = r.String("name", "object" + std::to_string(i));
  const std::string type =
      r.Choice("type", {"sphere", "ellipsoid", "box", "mesh", "revolution", "volume_fraction"});
  const auto c = r.Vec3("center_um", {0, 0, 0});
  o.center_um = {c[0], c[1], c[2]};
  const auto v = r.Vec3("velocity_um_per_us", {0, 0, 0});
  o.velocity_um_per_us = {v[0], v[1], v[2]};
  auto read_axes = [&](const char* key) {
    const auto v = r.Vec3(key);
    if (!(v[0] > 0 && v[1] > 0 && v[2] > 0)) r.Fail(key, "expected three positive lengths");
    o.semi_axes_um = {v[0], v[1], v[2]};
  };
  auto read_rot = [&] {
    const auto v = r.Vec3("rotation_deg", {0, 0, 0});
    o.rotation_deg = {v[0], v[1], v[2]};
  };
  if (type == "sphere") {
    o.shape = ShapeType::kSphere;
    o.radius_um = r.Positive("radius_um");
  } else if (type == "ellipsoid") {
    o.shape = ShapeType::kEllipsoid;
    read_axes("semi_axes_um");
    read_rot();
  } else if (type == "box") {
    o.shape = ShapeType::kBox;
    const auto v = r.Vec3("size_um");
    if (!(v[0] > 0 && v[1] > 0 && v[2] > 0)) r.Fail("size_um", "expected three positive lengths");
    o.semi_axes_um = {v[0] / 2, v[1] / 2, v[2] / 2};
    read_rot();
  } else if (type == "revolution") {
    o.shape = ShapeType::kMesh;
    const int given = r.Has("outline_rz_um") + r.Has("outline_file") + r.Has("outline_image");
    if (given != 1)
      r.Fail("outline_rz_um", "give exactly one of outline_rz_um, outline_file, outline_image");
    Outline outline;
    try {
      if (r.Has("outline_rz_um")) {
        for (const auto& row : r.NumberRows("outline_rz_um", 2))
          outline.push_back({row[0], row[1]});
        o.shape_description = "revolved outline (" + std::to_string(outline.size()) + " points)";
      } else if (r.Has("outline_file")) {
        const std::string f = Input(scene, r.String("outline_file"));
        outline = ReadOutlineCsv(f);
        o.shape_description = "revolved outline from " + f;
      } else {
        const std::string f = Input(scene, r.String("outline_image"));
        SilhouetteOptions so;
        so.pixel_um = r.Positive("pixel_um");
        so.threshold = r.InRange("threshold", 0, 1, 0.5, true, true);
        so.vertical_axis = r.Choice("axis", {"vertical", "horizontal"}, "vertical") == "vertical";
        so.axis_px = r.Number("axis_px", -1);
        so.smooth_px = r.InRange("smooth_px", 0, 100, 1.5);
        double axis = 0;
        outline = OutlineFromSilhouette(ReadImage(f), so, &axis);
        o.shape_description =
            "revolved silhouette of " + f + " (axis at " + std::to_string(axis) + " px)";
      }
    } catch (const Error& e) {
      if (!e.where().file.empty() && e.where().file != scene.file) throw;
      r.Fail(r.Has("outline_rz_um")  ? "outline_rz_um"
             : r.Has("outline_file") ? "outline_file"
                                     : "outline_image",
             e.message());
    }
    const int segments = static_cast<int>(r.Integer("segments", 256, 8, 65536));
    o.mesh = std::make_shared<TriangleMesh>(RevolveOutline(outline, segments));
    read_rot();
  } else if (type == "volume_fraction") {
    o.shape = ShapeType::kMesh;
    const std::string f = Input(scene, r.String("file"));
    NdArray a;
    try {
      a = ReadArrayFile(f, r.String("dataset", ""));
    } catch (const Error& e) {
      r.Fail("file", e.what());
    }
    const auto sp = r.Numbers("spacing_um", 3, 3);
    const auto org =
        r.Has("origin_um") ? r.Numbers("origin_um", 3, 3) : std::vector<double>{0, 0, 0};
    if (!(sp[0] > 0 && sp[1] > 0 && sp[2] > 0)) r.Fail("spacing_um", "spacings must be positive");
    const double iso = r.InRange("iso", 0, 1, 0.5, true, true);
    try {
      o.mesh = std::make_shared<TriangleMesh>(
          MeshFromVolumeFraction(a, {sp[0], sp[1], sp[2]}, {org[0], org[1], org[2]}, iso));
    } catch (const Error& e) {
      r.Fail("file", e.message());
    }
    o.shape_description = "iso-surface " + std::to_string(iso) + " of " + f;
    read_rot();
  } else {
    o.shape = ShapeType::kMesh;
    o.mesh_file = Input(scene, r.String("file"));
    if (!fs::exists(o.mesh_file)) r.Fail("file", "mesh file not found: " + o.mesh_file);
    o.mesh_scale_um = r.Positive("scale_um", 1.0);
    read_rot();
  }
  if (r.Has("index_field")) {
    if (r.Has("index") || r.Has("material"))
      r.Fail("index_field", "an object with an index field takes no 'index' or 'material'");
    o.index_field = ReadIndexField(r.Table("index_field"), scene, o);
    o.index = o.index_field->Index(Vec3());
    o.material = o.index_field->description;
  } else {
    ReadMaterial(r, scene, o);
  }
  r.Finish();
  return o;
}

void ReadCorrector(TomlReader& top, OpticsSpec* out) {
  OpticsSpec& o = *out;
  if (top.Has("corrector")) {
    TomlReader c = top.Table("corrector");
    o.corrector.enabled = true;
    o.corrector.distance_mm = c.Positive("distance_mm", 0.0);
    o.corrector.transmissions = c.Numbers("transmissions", 1, 64);
    for (double t : o.corrector.transmissions)
      if (t < 0 || t > 1) c.Fail("transmissions", "each transmission must be in [0, 1]");
    if (c.Has("ring_outer_mm")) {
      o.corrector.ring_outer_mm = c.Numbers("ring_outer_mm", 1, 64);
      if (o.corrector.ring_outer_mm.size() != o.corrector.transmissions.size())
        c.Fail("ring_outer_mm", "needs one outer radius per transmission value");
      double prev = 0;
      for (double r : o.corrector.ring_outer_mm) {
        if (!(r > prev)) c.Fail("ring_outer_mm", "radii must be positive and ascending");
        prev = r;
      }
    }
    c.Finish();
  }
}

OpticsSpec ReadOptics(TomlReader& top, double medium_index) {
  OpticsSpec o;
  TomlReader obj = top.Table("objective");
  const std::string model = obj.Choice("model", {"single", "two_lens"}, "single");
  o.model = model == "single" ? ObjectiveModel::kSingle : ObjectiveModel::kTwoLens;
  o.objective_focal_mm = obj.Positive("focal_length_mm");
  // NA = n sin(theta) with n the scene's medium (dry: 1, water dipping: 1.33), so NA < n.
  if (!obj.Has("na"))
    obj.Fail("na", "required: numerical aperture NA = n sin(theta), 0 < NA < medium_index");
  o.na = obj.InRange("na", 0, 3, 0, true, true);
  if (o.na >= medium_index)
    obj.Fail("na", "NA = n sin(theta) must be below the medium's index n = medium_index = " +
                       std::to_string(medium_index) + " (docs/conventions.md)");
  if (o.model == ObjectiveModel::kTwoLens) {
    o.working_distance_mm = obj.Positive("working_distance_mm");
    o.back_focal_mm = obj.Positive("back_focal_distance_mm");
    const double f = o.objective_focal_mm;
    const double d = f - o.back_focal_mm * o.working_distance_mm / f;
    if (!(d > 0))
      obj.Fail("back_focal_distance_mm",
               "gives a non-positive lens separation d = f - BFD*WD/f; expected BFD < f^2/WD");
    if (o.back_focal_mm == f || o.working_distance_mm == f)
      obj.Fail("working_distance_mm", "WD = f or BFD = f makes one lens power infinite");
  } else {
    o.working_distance_mm = obj.Positive("working_distance_mm", o.objective_focal_mm);
  }
  obj.Finish();
  TomlReader tube = top.Table("tube_lens");
  o.tube_focal_mm = tube.Positive("focal_length_mm");
  o.tube_distance_mm = tube.Positive("distance_mm", 150);
  tube.Finish();
  ReadCorrector(top, &o);
  return o;
}

}  // namespace

/// The calibration's light field as a source: its spatial map over its rectangle when it has
/// one, else a uniform disc field (automatic radius unless the file gives one).
SourceSpec CalibratedSource(const CalibrationData& c, const std::string& file) {
  SourceSpec s;
  s.type = SourceType::kLightField;
  s.field_shape = FieldShape::kDisc;
  s.field_radius_um = c.field_radius_um;
  s.angular_map = c.angular_map;
  s.angular_extent = c.angular_extent;
  s.angular_map_file = file;
  s.map_na_limit = c.na_limit;
  s.edge_half_angle_deg = c.edge_half_angle_deg;
  s.edge_width_deg = c.edge_width_deg;
  s.edge_tilt_deg = c.edge_tilt_deg;
  if (!c.spatial_map.empty()) {
    s.field_shape = FieldShape::kRect;
    s.field_size_um = {c.field_size_um[0], c.field_size_um[1]};
    s.spatial_map = c.spatial_map;
    s.spatial_map_file = file;
    s.extend_spatial_map = true;
  }
  return s;
}

double AcceptanceSin(const Scene& s) { return s.optics.na / s.medium_index; }

double Magnification(const OpticsSpec& o) { return -o.tube_focal_mm / o.objective_focal_mm; }

Scene LoadScene(const std::string& path) { return LoadScene(ParseTomlFile(path), path); }

/// [camera]: pixels, pitch (default the calibration's), offset, sensor shift, flip, PSF, read-out.
void ReadCamera(TomlReader r, const CalibrationData* cal, CameraSpec* c) {
  const auto px = r.Numbers("pixels", 2, 2);
  if (px[0] < 1 || px[1] < 1 || px[0] > 65536 || px[1] > 65536 || px[0] != std::floor(px[0]) ||
      px[1] != std::floor(px[1]))
    r.Fail("pixels", "expected two whole numbers in [1, 65536] (columns, rows)");
  c->nx = static_cast<int>(px[0]);
  c->ny = static_cast<int>(px[1]);
  c->pixel_pitch_um = r.Positive("pixel_pitch_um", cal ? cal->pixel_pitch_um : 0.0);
  if (!(c->pixel_pitch_um > 0)) r.Positive("pixel_pitch_um");  // required: report it
  if (r.Has("offset_um")) {
    const auto v = r.Numbers("offset_um", 2, 2);
    c->offset_um = {v[0], v[1]};
  }
  c->sensor_shift_mm = r.Number("sensor_shift_mm", 0);
  c->flip = r.Bool("flip", true);
  c->psf_sigma_um = r.InRange("psf_sigma_um", 0, 100, c->psf_sigma_um);
  if (r.Has("readout")) {
    TomlReader ro = r.Table("readout");
    CameraReadout readout;
    readout.gain_e_per_dn = ro.Positive("gain_e_per_dn");
    readout.bit_depth = static_cast<int>(ro.Integer("bit_depth", 12, 1, 16));
    readout.dark_dn = ro.InRange("dark_dn", 0, readout.max_code(), 0);
    readout.read_noise_e = ro.InRange("read_noise_e", 0, 1e6, 0);
    readout.well_capacity_e = ro.InRange("well_capacity_e", 0, 1e12, 0);
    ro.Finish();
    c->readout = readout;
  }
  r.Finish();
}

/// [exposure] and the objects' velocities: a moving object needs a pulse to move during.
void ReadMotion(TomlReader& r, const std::string& path, Scene* s) {
  if (r.Has("exposure")) {
    TomlReader e = r.Table("exposure");
    const std::string shape = e.Choice("shape", {"tophat", "gaussian", "file"}, "tophat");
    if (shape == "tophat") {
      s->exposure.shape = PulseShape::kTopHat;
      s->exposure.duration_us = e.Positive("duration_us");
    } else if (shape == "gaussian") {
      s->exposure.shape = PulseShape::kGaussian;
      s->exposure.fwhm_us = e.Positive("fwhm_us");
    } else {
      const std::string file = Input(*s, e.String("file"));
      try {
        s->exposure = TabulatedExposure(file);
      } catch (const Error& err) {
        e.Fail("file", err.what());
      }
    }
    e.Finish();
  }
  for (const ObjectSpec& o : s->objects)
    if (Dot(o.velocity_um_per_us, o.velocity_um_per_us) > 0 &&
        s->exposure.shape == PulseShape::kNone)
      throw Error(o.where, "object '" + o.name +
                               "' has a velocity_um_per_us but the scene has no [exposure] "
                               "table (shape = \"tophat\" with duration_us, \"gaussian\" "
                               "with fwhm_us, or \"file\")");
}

/// How far an object reaches from its centre: a sphere's radius, the length of the other
/// shapes' semi-axes; 0 for a mesh (its vertices say).
static double ObjectExtentUm(const ObjectSpec& o) {
  return o.shape == ShapeType::kSphere ? o.radius_um
         : o.shape == ShapeType::kMesh ? 0
                                       : Length(o.semi_axes_um);
}

/// Values that load but are unlikely to be what was meant: a sphere smaller than the wavelength
/// under the ray model (a radius written in mm?) or an object wider than the camera's view.
static void PlausibilityWarnings(Scene* s) {
  const double m = s->optics.objective_focal_mm > 0 ? std::abs(Magnification(s->optics)) : 0;
  const double view_um =
      m > 0 ? std::max(s->camera.nx, s->camera.ny) * s->camera.pixel_pitch_um / m : 0;
  auto num = [](double v) {
    std::ostringstream o;
    o << v;
    return o.str();
  };
  for (const ObjectSpec& o : s->objects) {
    if (o.shape == ShapeType::kSphere && o.radius_um < s->wavelength_um &&
        s->trace.optics != ImageOptics::kMie)
      s->warnings.push_back(o.where.ToString() + ": object '" + o.name +
                            "': radius_um = " + num(o.radius_um) + " is below the wavelength (" +
                            num(s->wavelength_um) +
                            " um): a sub-wavelength sphere, which rays do not describe (a radius "
                            "meant in mm?)");
    const double width = 2 * ObjectExtentUm(o);
    if (view_um > 0 && width > 2 * view_um)
      s->warnings.push_back(o.where.ToString() + ": object '" + o.name + "' is " + num(width) +
                            " um wide, more than twice the camera's view (" + num(view_um) +
                            " um at the object): the image shows only part of it");
  }
}

/// [trace.mie]: the wave image's sampling.
static void ReadMieSettings(TomlReader mr, MieSettings* m_out) {
  MieSettings& m = *m_out;
  m.nodes_per_panel = static_cast<int>(mr.Integer("nodes_per_panel", m.nodes_per_panel, 1, 64));
  m.panel_width = mr.InRange("panel_width", 1e-4, 1.0, m.panel_width);
  m.harmonics = static_cast<int>(mr.Integer("harmonics", m.harmonics, 0, 256));
  m.oversample = mr.InRange("oversample", 1.0, 8.0, m.oversample);
  m.margin_um = mr.InRange("margin_um", 0.0, 1000.0, m.margin_um);
  m.window_um = mr.InRange("window_um", 0.0, 100000.0, m.window_um);
  m.spectrum_nodes = static_cast<int>(mr.Integer("spectrum_nodes", m.spectrum_nodes, 1, 256));
  m.spectrum_interleave =
      static_cast<int>(mr.Integer("spectrum_interleave", m.spectrum_interleave, 1, 1024));
  m.motion_nodes = static_cast<int>(mr.Integer("motion_nodes", m.motion_nodes, 1, 256));
  m.pixel_subsamples = static_cast<int>(mr.Integer("pixel_subsamples", m.pixel_subsamples, 0, 64));
  mr.Finish();
}

/// [trace.physical]: the physical-optics image's sampling.
static void ReadPhysicalSettings(TomlReader pr, PhysicalSettings* p_out) {
  PhysicalSettings& p = *p_out;
  p.polar_nodes = static_cast<int>(pr.Integer("polar_nodes", p.polar_nodes, 1, 64));
  p.azimuths = static_cast<int>(pr.Integer("azimuths", p.azimuths, 1, 256));
  p.oversample = pr.InRange("oversample", 1.0, 8.0, p.oversample);
  p.margin_um = pr.InRange("margin_um", 0.0, 1000.0, p.margin_um);
  p.window_um = pr.InRange("window_um", 0.0, 100000.0, p.window_um);
  p.pixel_subsamples = static_cast<int>(pr.Integer("pixel_subsamples", p.pixel_subsamples, 0, 64));
  p.ray_spacing_um = pr.InRange("ray_spacing_um", 0.0, 100.0, p.ray_spacing_um);
  p.refine_levels = static_cast<int>(pr.Integer("refine_levels", p.refine_levels, 0, 12));
  p.max_cell_steps = pr.InRange("max_cell_steps", 0.05, 100.0, p.max_cell_steps);
  p.max_events = static_cast<int>(pr.Integer("max_events", p.max_events, 0, 8));
  p.spectrum_nodes = static_cast<int>(pr.Integer("spectrum_nodes", p.spectrum_nodes, 1, 256));
  p.motion_nodes = static_cast<int>(pr.Integer("motion_nodes", p.motion_nodes, 1, 256));
  pr.Finish();
}

/// [trace]: the ray or photon count, partial reflection, limits, gradient-index integration
/// and the image model.
static void ReadTrace(TomlReader tr, Scene* s_out) {
  Scene& s = *s_out;
  s.trace.rays = static_cast<uint64_t>(tr.Integer("rays", 0, 0, int64_t(1) << 50));
  s.trace.photons_per_pixel = tr.Positive("photons_per_pixel", 0.0);
  if (tr.Has("rays") && tr.Has("photons_per_pixel"))
    tr.Fail("photons_per_pixel", "give either 'rays' or 'photons_per_pixel', not both");
  if (tr.Has("signal") || tr.Has("well_capacity")) {
    if (tr.Has("rays") || tr.Has("photons_per_pixel"))
      tr.Fail("signal", "give 'signal' and 'well_capacity' instead of rays/photons_per_pixel");
    const double signal = tr.InRange("signal", 0, 1, 0, true, false);
    const double well = tr.Positive("well_capacity");
    s.trace.photons_per_pixel = signal * well;
  } else {
    tr.Number("signal", 0), tr.Number("well_capacity", 0);
  }
  const std::string pr =
      tr.Choice("partial_reflection", {"off", "unpolarized", "polarized"}, "unpolarized");
  s.trace.partial_reflection = pr == "off"           ? PartialReflection::kOff
                               : pr == "unpolarized" ? PartialReflection::kUnpolarized
                                                     : PartialReflection::kPolarized;
  s.trace.max_interactions = static_cast<int>(tr.Integer("max_interactions", 100, 1, 100000));
  s.trace.threads = static_cast<int>(tr.Integer("threads", 0, 0, 4096));
  s.trace.grin.tolerance_um = tr.Positive("grin_tolerance_um", s.trace.grin.tolerance_um);
  s.trace.grin.max_step_um = tr.Positive("grin_max_step_um", 0.0);
  s.trace.grin.max_steps =
      static_cast<int>(tr.Integer("grin_max_steps", s.trace.grin.max_steps, 1, 1000000000));
  s.trace.grin.uniform_tolerance =
      tr.InRange("grin_uniform_tolerance", -1.0, 1e-3, s.trace.grin.uniform_tolerance);
  s.trace.grin.cell_steps = tr.Bool("grin_cell_steps", s.trace.grin.cell_steps);
  const std::string optics = tr.Choice("optics", {"rays", "mie", "physical"}, "rays");
  s.trace.optics = optics == "mie"        ? ImageOptics::kMie
                   : optics == "physical" ? ImageOptics::kPhysical
                                          : ImageOptics::kRays;
  if (tr.Has("mie")) {
    ReadMieSettings(tr.Table("mie"), &s.trace.mie);
    if (s.trace.optics != ImageOptics::kMie)
      tr.Fail("mie", "[trace.mie] sets the wave image's sampling: it needs optics = \"mie\"");
  }
  if (tr.Has("physical")) {
    ReadPhysicalSettings(tr.Table("physical"), &s.trace.physical);
    if (s.trace.optics != ImageOptics::kPhysical)
      tr.Fail("physical",
              "[trace.physical] sets the physical-optics image's sampling: it needs optics = "
              "\"physical\"");
  }
  tr.Finish();
}

Scene LoadScene(const toml::table& t, const std::string& path) {
  Scene s;
  s.file = path;
  TomlReader r(t, path, "");
  s.name = r.String("name", fs::path(path).stem().string());
  for (char c : s.name)
    if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-' || c == '.'))
      r.Fail("name", "used in file names: letters, digits, '_', '-' and '.' only");
  // A calibration file supplies the light field, corrector and optics; tables in the scene
  // override its parts (docs/scene-format.md).
  std::optional<CalibrationData> cal;
  std::string cal_file;
  if (r.Has("calibration")) {
    cal_file = Input(s, r.String("calibration"));
    try {
      cal = ReadCalibrationFile(cal_file);
    } catch (const Error& e) {
      r.Fail("calibration", e.what());
    }
  }
  s.wavelength_um = r.InRange("wavelength_um", 0.2, 2.0, cal ? cal->wavelength_um : 0.462);
  s.medium_index = r.InRange("medium_index", 1.0, 3.0, 1.0);
  s.trace.seed = static_cast<uint64_t>(r.Integer("seed", 1, 0, INT64_MAX));
  // A [source] table with only a spectrum keeps the calibration's light field.
  const bool spectrum_only = r.Has("source") && cal && cal->has_light_field() &&
                             !r.Table("source").Has("type") && r.Table("source").Has("spectrum");
  if (!spectrum_only && (r.Has("source") || !cal || !cal->has_light_field())) {
    s.source = ReadSource(r.Table("source"), path);
  } else {
    s.source = CalibratedSource(*cal, cal_file);
    if (spectrum_only) {
      TomlReader src = r.Table("source");
      s.source.spectrum = ReadSpectrum(src.Table("spectrum"), path);
      src.Finish();
    }
  }
  if (cal)
    s.input_files.insert(s.input_files.end(), cal->sidecar_files.begin(), cal->sidecar_files.end());
  for (const std::string* f : {&s.source.ray_file, &s.source.angular_map_file,
                               &s.source.spatial_map_file, &s.source.spectrum.file})
    if (!f->empty()) s.input_files.push_back(*f);
  // With a spectrum, indices are quoted at its mean unless wavelength_um is given.
  if (s.source.spectrum.type != SpectrumType::kNone && !r.Has("wavelength_um"))
    s.wavelength_um = s.source.spectrum.mean_um();
  if (r.Has("light_field_edge")) {
    TomlReader e = r.Table("light_field_edge");
    if (!(s.source.type == SourceType::kLightField && s.source.map_na_limit > 0))
      e.Fail("half_angle_deg",
             "the edge continues a calibrated light field cut at the objective's NA "
             "(a calibration file with na_limit > 0 and no [source] table)");
    const double na_deg = std::asin(s.source.map_na_limit) * 180 / M_PI;
    s.source.edge_half_angle_deg = e.InRange("half_angle_deg", na_deg - 10, na_deg + 10, 0);
    s.source.edge_width_deg = e.InRange("width_deg", 0.05, 5, 0);
    if (!e.Has("half_angle_deg") || !e.Has("width_deg"))
      e.Fail(e.Has("half_angle_deg") ? "width_deg" : "half_angle_deg",
             "required: half_angle_deg (degrees, within 10 of the NA's " + std::to_string(na_deg) +
                 ") and width_deg (degrees, 0.05-5)");
    if (e.Has("tilt_deg")) s.source.edge_tilt_deg = ReadEdgeTiltDeg(e, "tilt_deg");
    e.Finish();
  }
  if (cal && cal->psf_sigma_um > 0) s.camera.psf_sigma_um = cal->psf_sigma_um;
  int i = 0;
  for (TomlReader& o : r.Tables("object")) s.objects.push_back(ReadObject(o, s, i++));
  if (r.Has("objective") || !cal) {
    s.optics = ReadOptics(r, s.medium_index);
  } else {
    s.optics.model = ObjectiveModel::kSingle;
    s.optics.objective_focal_mm = cal->objective_focal_mm;
    s.optics.na = cal->na;
    if (s.optics.na >= s.medium_index)
      r.Fail("calibration", "the calibration's NA " + std::to_string(cal->na) +
                                " is not below medium_index " + std::to_string(s.medium_index) +
                                " (NA = n sin(theta), docs/conventions.md)");
    s.optics.working_distance_mm = cal->working_distance_mm;
    s.optics.tube_focal_mm = cal->tube_focal_mm;
    if (r.Has("tube_lens"))
      r.Fail("tube_lens", "give [objective] too, or neither (both come from the calibration)");
    ReadCorrector(r, &s.optics);
  }
  if (cal && cal->has_corrector() && !r.Has("corrector")) {
    s.optics.corrector.enabled = true;
    s.optics.corrector.distance_mm = cal->corrector_distance_mm;
    s.optics.corrector.ring_outer_mm = cal->ring_outer_mm;
    s.optics.corrector.transmissions = cal->transmissions;
  }

  ReadCamera(r.Table("camera"), cal ? &*cal : nullptr, &s.camera);

  if (r.Has("trace")) ReadTrace(r.Table("trace"), &s);
  for (const ObjectSpec& o : s.objects)
    if (o.absorption_index > 0 && s.trace.optics != ImageOptics::kMie)
      throw Error(o.where, "object '" + o.name +
                               "': absorption_index needs [trace] optics = "
                               "\"mie\" (the ray model does not absorb)");
  if (s.trace.rays == 0 && s.trace.photons_per_pixel == 0) s.trace.rays = 1000000;

  ReadMotion(r, path, &s);
  if (s.trace.optics != ImageOptics::kRays) {
    const std::string why = s.trace.optics == ImageOptics::kMie ? MieUnsupportedReason(s)
                                                                : PhysicalUnsupportedReason(s);
    if (!why.empty()) r.Table("trace").Fail("optics", why);
  }

  if (r.Has("scan")) {
    TomlReader sc = r.Table("scan");
    s.defocus_um = sc.Numbers("defocus_um", 1, 10000);
    sc.Finish();
  }
  r.Finish();
  ValidateScene(s);
  PlausibilityWarnings(&s);
  std::vector<std::string> once;
  for (std::string& f : s.input_files)
    if (std::find(once.begin(), once.end(), f) == once.end()) once.push_back(std::move(f));
  s.input_files = std::move(once);
  return s;
}

const char* ImageOpticsName(ImageOptics o) {
  return o == ImageOptics::kMie ? "mie" : o == ImageOptics::kPhysical ? "physical" : "rays";
}

bool Scene::has_motion() const {
  if (exposure.shape == PulseShape::kNone) return false;
  for (const ObjectSpec& o : objects)
    if (Dot(o.velocity_um_per_us, o.velocity_um_per_us) > 0) return true;
  return false;
}

bool Scene::is_spectral() const {
  if (source.spectrum.type == SpectrumType::kNone) return false;
  for (const ObjectSpec& o : objects)
    if (o.dispersion.law != DispersionLaw::kNone || (o.index_field && o.index_field->water))
      return true;
  return false;
}

void ValidateScene(const Scene& s) {
  const FileLocation where{s.file};
  const double f_mm = s.optics.objective_focal_mm;
  // The first optical surface: the corrector or the objective's first lens.
  double first_plane_um = 1e300;
  for (double dz : s.defocus_um) {
    const double front =
        (s.optics.model == ObjectiveModel::kTwoLens ? s.optics.working_distance_mm : f_mm) * 1e3;
    double corr = s.optics.corrector.enabled && s.optics.corrector.distance_mm > 0
                      ? s.optics.corrector.distance_mm * 1e3
                      : front;
    first_plane_um = std::min(first_plane_um, dz + std::min(front, corr));
  }
  for (const ObjectSpec& o : s.objects) {
    const double extent = ObjectExtentUm(o);
    if (o.center_um.z + extent + o.SweepUm(s.exposure.max_offset_us()) >= first_plane_um)
      throw Error(o.where, "object '" + o.name +
                               "' reaches the objective or corrector plane; move it or the focus");
  }
  if (s.source.type == SourceType::kPoint && s.source.position_um.z >= first_plane_um)
    throw Error(where, "the point source lies beyond the objective");
}

}  // namespace raymatch::simulate
