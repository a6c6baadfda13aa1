#include "raymatch/calibrate/lightfield.h"

#include <ceres/ceres.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <sstream>

#include "raymatch/calibrate/mrcal_lightfield.h"
#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/provenance.h"

namespace raymatch::calibrate {

namespace fs = std::filesystem;

namespace {

constexpr double kDeg = M_PI / 180;

constexpr double kOutside = -1e300;

double Bilinear(const Image& img, double fx, double fy) {  // fx, fy in pixel-centre units
  const int x0 = int(std::floor(fx)), y0 = int(std::floor(fy));
  if (x0 < 0 || y0 < 0 || x0 + 1 >= img.width || y0 + 1 >= img.height) return kOutside;
  const double ax = fx - x0, ay = fy - y0;
  return (1 - ay) * ((1 - ax) * img.at(x0, y0) + ax * img.at(x0 + 1, y0)) +
         ay * ((1 - ax) * img.at(x0, y0 + 1) + ax * img.at(x0 + 1, y0 + 1));
}

struct CenterResidual {
  double dz, cx, cy;
  template <class T>
  bool operator()(const T* apex, const T* tilt, T* r) const {
    r[0] = T(cx) - (apex[0] + (T(dz) - apex[2]) * tilt[0]);
    r[1] = T(cy) - (apex[1] + (T(dz) - apex[2]) * tilt[1]);
    return true;
  }
};

struct RadiusResidual {
  double dz, radius;
  template <class T>
  bool operator()(const T* apex, const T* tan_half, T* r) const {
    r[0] = T(radius) - (T(dz) - apex[2]) * tan_half[0];
    return true;
  }
};

}  // namespace

void Centroid(const Image& img, double p, double fraction, double* x, double* y, double* rms) {
  const double mx = *std::max_element(img.pixels.begin(), img.pixels.end());
  double w = 0, sx = 0, sy = 0, sxx = 0;
  for (int r = 0; r < img.height; ++r)
    for (int c = 0; c < img.width; ++c) {
      const double v = img.at(c, r);
      if (v < fraction * mx) continue;
      const double px = PixX(c, img.width, p), py = PixY(r, img.height, p);
      w += v, sx += v * px, sy += v * py, sxx += v * (px * px + py * py);
    }
  *x = sx / w, *y = sy / w;
  if (rms) *rms = std::sqrt(std::max(0.0, sxx / w - (*x) * (*x) - (*y) * (*y)));
}

Image ConeToAngularMap(const Image& ph, double p, double dz, double ax, double ay, double az, int n,
                       double extent, double na, std::vector<char>* covered) {
  Image map(n, n);
  if (covered) covered->assign(size_t(n) * n, 0);
  const double h = dz - az;  // plane distance from the apex
  for (int row = 0; row < n; ++row)
    for (int col = 0; col < n; ++col) {
      const double u = (2 * (col + 0.5) / n - 1) * extent, v = (1 - 2 * (row + 0.5) / n) * extent;
      const double s2 = u * u + v * v;
      if (s2 >= na * na || s2 >= 1) continue;
      const double w = std::sqrt(1 - s2);
      const double X = ax + h * u / w, Y = ay + h * v / w;
      const double fx = X / p + ph.width / 2.0 - 0.5, fy = ph.height / 2.0 - 0.5 - Y / p;
      const double e = Bilinear(ph, fx, fy);
      if (e == kOutside) continue;
      // Irradiance on a plane h away -> radiance per du dv: du dv = h^2 / rho^4 dx dy with
      // rho = h / w, so L = E (per um^2) x h^2 / w^4.
      // Signed: dark-subtracted noise must average out in sums (clipping it would bias them).
      map.at(col, row) = float(e / (p * p) * h * h / std::pow(w, 4));
      if (covered) (*covered)[size_t(row) * n + col] = 1;
    }
  return map;
}

namespace {

// Edge of the angular distribution from a map: the (u, v) area of the cells above half the
// plateau (mean of the cells above a quarter of the maximum) gives s_edge = sqrt(A / pi).
double EdgeHalfAngleDeg(const Image& map, double extent) {
  const double mx = *std::max_element(map.pixels.begin(), map.pixels.end());
  double plateau = 0;
  size_t cnt = 0;
  for (float x : map.pixels)
    if (x > 0.25 * mx) plateau += x, ++cnt;
  plateau /= std::max<size_t>(cnt, 1);
  size_t lit = 0;
  for (float x : map.pixels) lit += x > 0.5 * plateau;
  const double cell = (2 * extent / map.width) * (2 * extent / map.height);
  return std::asin(std::min(1.0, std::sqrt(lit * cell / M_PI))) / kDeg;
}

void FillOptics(const LightFieldInput& in, CalibrationData* d) {
  d->objective_focal_mm = in.optics.objective_focal_mm;
  d->working_distance_mm = in.optics.working_distance_mm;
  d->na = in.optics.na;
  d->tube_focal_mm = in.optics.tube_focal_mm;
  d->pixel_pitch_um = in.camera.pixel_pitch_um;
  d->wavelength_um = in.optics.wavelength_um;
  d->field_radius_um = in.field_radius_um;
}

// mrcal path: images from a camera focused at infinity; each pixel is a direction.
LightFieldSummary FromCameraModel(const LightFieldInput& in, const LightFieldOptions& o) {
  LightFieldSummary s;
  Image dark;
  if (!in.dark.empty()) dark = ReadImage(in.dark);
  const Image* dk = dark.empty() ? nullptr : &dark;
  const int n = o.map_size;
  const double extent = o.extent > 0 ? o.extent : std::min(1.0, 1.15 * in.optics.acceptance_sin());
  Image map(n, n);
  std::vector<int> count(size_t(n) * n, 0);
  double max_s = 0;
  for (const std::string& file : in.direction_images) {
    size_t sat = 0;
    const Image ph = LoadPhotons(file, dk, in.camera, &sat);
    if (sat)
      s.warnings.push_back(file + ": " + std::to_string(sat) +
                           " saturated pixels (radiance clipped there)");
    std::vector<char> cov;
    DirectionMapStats st;
    const Image m = DirectionImageToAngularMap(ph, in.camera_model, n, extent, &cov, &st);
    max_s = std::max(max_s, st.max_s);
    const double cell = (2 * extent / n) * (2 * extent / n);
    if (st.median_pixel_area_uv > 0.5 * cell)
      s.warnings.push_back(file + ": camera pixels are coarser than the map cells (" +
                           std::to_string(st.median_pixel_area_uv / cell) +
                           " cells each): lower --map-size or the map has holes");
    for (size_t i = 0; i < m.size(); ++i)
      if (cov[i]) map.pixels[i] += m.pixels[i], ++count[i];
  }
  size_t unmeasured = 0;
  for (size_t i = 0; i < map.size(); ++i) {
    if (count[i]) map.pixels[i] = std::max(0.f, map.pixels[i] / float(count[i]));
    const double u = (2 * (i % n + 0.5) / n - 1) * extent, v = (1 - 2 * (i / n + 0.5) / n) * extent;
    if (u * u + v * v < in.optics.acceptance_sin() * in.optics.acceptance_sin() && !count[i])
      ++unmeasured;
  }
  if (unmeasured)
    s.warnings.push_back(std::to_string(unmeasured) +
                         " directions inside the NA are outside the camera's view (set to 0)");
  s.cone.half_angle_deg = EdgeHalfAngleDeg(map, extent);
  CalibrationData& d = s.data;
  d.angular_map = map;
  d.angular_extent = extent;
  d.na_limit = 0;  // not seen through the objective: not cut at its NA
  d.cone_half_angle_deg = s.cone.half_angle_deg;
  std::ostringstream note;
  note << "measured with a camera focused at infinity (mrcal model " << in.camera_model << ") from "
       << in.direction_images.size() << " image(s), up to direction-cosine radius " << max_s
       << "; not cut by the objective NA";
  d.light_field_note = note.str();
  FillOptics(in, &d);
  d.provenance = ProvenanceJson();
  std::string inputs = FileChecksum(in.camera_model) + " " + in.camera_model;
  for (const std::string& f : in.direction_images) inputs += "; " + FileChecksum(f) + " " + f;
  d.provenance["light_field_inputs"] = inputs;
  return s;
}

}  // namespace

Image SpatialMapFromFlat(const Image& photons, double pixel_um, int bin, double size_um[2],
                         double* lo, double* hi) {
  if (bin < 1) throw Error("flat_bin_px must be >= 1");
  const int nbx = photons.width / bin, nby = photons.height / bin;
  if (nbx < 1 || nby < 1)
    throw Error("the flat-field image is smaller than one bin of " + std::to_string(bin) +
                " pixels");
  const int x0 = (photons.width - nbx * bin) / 2, y0 = (photons.height - nby * bin) / 2;
  Image map(nbx, nby);
  for (int by = 0; by < nby; ++by)
    for (int bx = 0; bx < nbx; ++bx) {
      double sum = 0;
      for (int y = 0; y < bin; ++y)
        for (int x = 0; x < bin; ++x) sum += photons.at(x0 + bx * bin + x, y0 + by * bin + y);
      map.at(bx, by) = float(std::max(0.0, sum / (bin * bin)));
    }
  // Normalise to the mean of the central quarter of the view (relative irradiance).
  double centre = 0;
  int cnt = 0;
  for (int by = nby / 4; by < nby - nby / 4; ++by)
    for (int bx = nbx / 4; bx < nbx - nbx / 4; ++bx) centre += map.at(bx, by), ++cnt;
  centre /= std::max(cnt, 1);
  if (!(centre > 0)) throw Error("the flat-field image has no light in the centre of the view");
  *lo = 1e300, *hi = -1e300;
  for (float& v : map.pixels) {
    v = float(v / centre);
    *lo = std::min(*lo, double(v)), *hi = std::max(*hi, double(v));
  }
  // Beyond the view the simulator continues the edge values (SourceSpec::extend_spatial_map).
  size_um[0] = map.width * bin * pixel_um;
  size_um[1] = map.height * bin * pixel_um;
  return map;
}

namespace {

LightFieldSummary FromCones(const LightFieldInput& in, const LightFieldOptions& o) {
  LightFieldSummary s;
  const double M = in.optics.magnification();
  const double p = in.camera.pixel_pitch_um / M;  // object-plane pixel
  Image dark;
  if (!in.dark.empty()) dark = ReadImage(in.dark);
  const Image* dk = dark.empty() ? nullptr : &dark;
  size_t sat = 0;
  const Image pin = LoadPhotons(in.pinhole, dk, in.camera, &sat);
  if (sat)
    s.warnings.push_back(in.pinhole + ": " + std::to_string(sat) +
                         " saturated pixels (centroid biased; lower the exposure)");
  double rms = 0;
  Centroid(pin, p, 0.1, &s.pinhole_x_um, &s.pinhole_y_um, &rms);
  s.pinhole_diameter_um = 2 * std::sqrt(2.0) * rms;  // uniform disc: rms^2 = R^2 / 2
  std::vector<Image> cones;
  ConeFit& f = s.cone;
  for (const ConeImage& c : in.cones) {
    cones.push_back(LoadPhotons(c.file, dk, in.camera, &sat));
    if (cones.back().width != pin.width || cones.back().height != pin.height)
      throw Error(FileLocation{c.file}, "cone image size differs from the pinhole image");
    if (sat) s.warnings.push_back(c.file + ": " + std::to_string(sat) + " saturated pixels");
    double cx, cy;
    Centroid(cones.back(), p, 0.25, &cx, &cy, nullptr);
    // Edge radius: area above half the plateau (mean of the brightest half of the lit pixels).
    std::vector<float> v = cones.back().pixels;
    std::sort(v.begin(), v.end());
    const double mx = v.back();
    double plateau = 0;
    size_t cnt = 0;
    for (float x : v)
      if (x > 0.25 * mx) plateau += x, ++cnt;
    plateau /= std::max<size_t>(cnt, 1);
    size_t lit = 0;
    for (float x : v) lit += x > 0.5 * plateau;
    f.center_x_um.push_back(cx);
    f.center_y_um.push_back(cy);
    f.radius_um.push_back(std::sqrt(lit * p * p / M_PI));
    const bool touches = [&] {
      const Image& im = cones.back();
      for (int x = 0; x < im.width; ++x)
        if (im.at(x, 0) > 0.5 * plateau || im.at(x, im.height - 1) > 0.5 * plateau) return true;
      for (int y = 0; y < im.height; ++y)
        if (im.at(0, y) > 0.5 * plateau || im.at(im.width - 1, y) > 0.5 * plateau) return true;
      return false;
    }();
    if (touches)
      s.warnings.push_back(
          c.file +
          ": the cone reaches the image border (its radius is underestimated; use a smaller dz)");
  }
  // Joint fit of apex, axis and edge angle (Ceres, Levenberg-Marquardt).
  double apex[3] = {s.pinhole_x_um, s.pinhole_y_um, 0}, tilt[2] = {0, 0}, tan_half[1] = {0.3};
  ceres::Problem prob;
  for (size_t k = 0; k < in.cones.size(); ++k) {
    prob.AddResidualBlock(
        new ceres::AutoDiffCostFunction<CenterResidual, 2, 3, 2>(
            new CenterResidual{in.cones[k].dz_um, f.center_x_um[k], f.center_y_um[k]}),
        nullptr, apex, tilt);
    prob.AddResidualBlock(new ceres::AutoDiffCostFunction<RadiusResidual, 1, 3, 1>(
                              new RadiusResidual{in.cones[k].dz_um, f.radius_um[k]}),
                          nullptr, apex, tan_half);
  }
  // The pinhole's own image fixes the apex laterally (it is the apex at z = apex z).
  prob.AddResidualBlock(new ceres::AutoDiffCostFunction<CenterResidual, 2, 3, 2>(
                            new CenterResidual{0.0, s.pinhole_x_um, s.pinhole_y_um}),
                        nullptr, apex, tilt);
  ceres::Solver::Options so;
  so.max_num_iterations = 100;
  ceres::Solver::Summary sum;
  ceres::Solve(so, &prob, &sum);
  if (!sum.IsSolutionUsable()) throw Error("cone fit did not converge: " + sum.BriefReport());
  f.apex_x_um = apex[0], f.apex_y_um = apex[1], f.apex_z_um = apex[2];
  f.tilt_x = tilt[0], f.tilt_y = tilt[1];
  f.half_angle_deg = std::atan(tan_half[0]) / kDeg;
  double rc = 0, rr = 0;
  for (size_t k = 0; k < in.cones.size(); ++k) {
    const double h = in.cones[k].dz_um - apex[2];
    rc += std::pow(f.center_x_um[k] - apex[0] - h * tilt[0], 2) +
          std::pow(f.center_y_um[k] - apex[1] - h * tilt[1], 2);
    rr += std::pow(f.radius_um[k] - h * tan_half[0], 2);
  }
  f.rms_center_residual_um = std::sqrt(rc / in.cones.size());
  f.rms_radius_residual_um = std::sqrt(rr / in.cones.size());
  // Edge radii are measured to ~0.1 pixel; half a pixel of misfit means the geometry is wrong.
  if (f.rms_radius_residual_um > 0.5 * p)
    s.warnings.push_back("the cone cross-section does not scale with dz (radius residual " +
                         std::to_string(f.rms_radius_residual_um) +
                         " um > half a pixel): check dz_um values");
  const double na_deg = std::asin(in.optics.acceptance_sin()) / kDeg;
  f.cut_by_na = f.half_angle_deg > na_deg - 0.5;
  // Angular map: average of the cone images' radiance (where measured).
  const int n = o.map_size;
  const double extent = o.extent > 0 ? o.extent : std::min(1.0, 1.15 * in.optics.acceptance_sin());
  Image map(n, n);
  std::vector<int> count(size_t(n) * n, 0);
  for (size_t k = 0; k < cones.size(); ++k) {
    std::vector<char> cov;
    const Image m = ConeToAngularMap(cones[k], p, in.cones[k].dz_um, apex[0], apex[1], apex[2], n,
                                     extent, in.optics.acceptance_sin(), &cov);
    for (size_t i = 0; i < m.size(); ++i)
      if (cov[i]) map.pixels[i] += m.pixels[i], ++count[i];
  }
  size_t unmeasured = 0;
  for (size_t i = 0; i < map.size(); ++i) {
    const double u = (2 * (i % n + 0.5) / n - 1) * extent, v = (1 - 2 * (i / n + 0.5) / n) * extent;
    if (u * u + v * v < in.optics.acceptance_sin() * in.optics.acceptance_sin() && !count[i])
      ++unmeasured;
    if (count[i]) map.pixels[i] = std::max(0.f, map.pixels[i] / float(count[i]));  // radiance >= 0
  }
  if (unmeasured)
    s.warnings.push_back(std::to_string(unmeasured) +
                         " directions inside the NA fall outside every cone image (set to 0)");
  std::ostringstream note;
  note << "measured from " << cones.size() << " cone images up to NA " << in.optics.na << " ("
       << na_deg << " deg)";
  if (f.cut_by_na) note << "; the cone edge is cut by the objective NA";
  if (o.extrapolate_to_deg > na_deg) {
    // Mean radiance of the outermost measured ring, continued to the given angle.
    double ring = 0;
    int rn = 0;
    const double s_lo = std::sin((na_deg - 2) * kDeg), s_na = in.optics.acceptance_sin();
    for (size_t i = 0; i < map.size(); ++i) {
      const double u = (2 * (i % n + 0.5) / n - 1) * extent,
                   v = (1 - 2 * (i / n + 0.5) / n) * extent;
      const double sr = std::hypot(u, v);
      if (sr > s_lo && sr < s_na && count[i]) ring += map.pixels[i], ++rn;
    }
    ring /= std::max(rn, 1);
    const double s_to = std::sin(o.extrapolate_to_deg * kDeg);
    for (size_t i = 0; i < map.size(); ++i) {
      const double u = (2 * (i % n + 0.5) / n - 1) * extent,
                   v = (1 - 2 * (i / n + 0.5) / n) * extent;
      const double sr = std::hypot(u, v);
      if (sr >= s_na && sr < s_to) map.pixels[i] = float(ring);
    }
    note << "; beyond it extrapolated flat to " << o.extrapolate_to_deg << " deg";
  } else {
    note << "; zero beyond it (no extrapolation)";
  }
  CalibrationData& d = s.data;
  d.angular_map = map;
  d.angular_extent = extent;
  d.na_limit = in.optics.acceptance_sin();  // a sine in the calibration medium
  d.cone_half_angle_deg = f.half_angle_deg;
  d.light_field_note = note.str();
  FillOptics(in, &d);
  d.provenance = ProvenanceJson();
  std::string inputs = FileChecksum(in.pinhole) + " " + in.pinhole;
  for (const ConeImage& c : in.cones) inputs += "; " + FileChecksum(c.file) + " " + c.file;
  d.provenance["light_field_inputs"] = inputs;
  return s;
}

}  // namespace

LightFieldSummary CalibrateLightField(const LightFieldInput& in, const LightFieldOptions& o) {
  if (o.map_size < 4 || o.map_size > 4096) throw Error("map_size must be in [4, 4096]");
  LightFieldSummary s = in.camera_model.empty() ? FromCones(in, o) : FromCameraModel(in, o);
  if (!in.flat.empty()) {
    Image dark;
    if (!in.dark.empty()) dark = ReadImage(in.dark);
    size_t sat = 0;
    const Image flat = LoadPhotons(in.flat, dark.empty() ? nullptr : &dark, in.camera, &sat);
    if (sat)
      s.warnings.push_back(in.flat + ": " + std::to_string(sat) +
                           " saturated pixels (the spatial map is clipped there)");
    double lo, hi;
    CalibrationData& d = s.data;
    d.spatial_map = SpatialMapFromFlat(flat, in.camera.pixel_pitch_um / in.optics.magnification(),
                                       in.flat_bin_px, d.field_size_um, &lo, &hi);
    std::ostringstream os;
    os.precision(3);
    os << "; spatial map from " << fs::path(in.flat).filename().string() << " (" << in.flat_bin_px
       << " px bins, " << lo << " to " << hi << " of the centre over the view)";
    d.light_field_note += os.str();
    d.provenance["light_field_inputs"] = d.provenance["light_field_inputs"].get<std::string>() +
                                         "; " + FileChecksum(in.flat) + " " + in.flat;
  }
  return s;
}

std::string LightFieldSummary::BriefReport() const {
  std::ostringstream os;
  os.precision(4);
  os << "pinhole at (" << pinhole_x_um << ", " << pinhole_y_um << ") um, apparent diameter "
     << pinhole_diameter_um << " um\ncone: half-angle " << cone.half_angle_deg << " deg"
     << (cone.cut_by_na ? " (cut by the objective NA)" : "") << ", apex z " << cone.apex_z_um
     << " um, axis tilt (" << cone.tilt_x << ", " << cone.tilt_y << "), rms residuals: centre "
     << cone.rms_center_residual_um << " um, radius " << cone.rms_radius_residual_um << " um\n"
     << "light field: " << data.light_field_note << "\n";
  return os.str();  // warnings are separate (apps print them to stderr)
}

}  // namespace raymatch::calibrate
