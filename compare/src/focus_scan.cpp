#include "raymatch/compare/focus_scan.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "raymatch/core/image_io.h"

namespace fs = std::filesystem;

namespace raymatch::compare {

namespace {

Image LoadChecked(const std::string& path) {
  if (!fs::exists(path))
    throw CompareError(FailureKind::kFileError, FileLocation{path}, "file not found");
  try {
    return ReadImage(path);
  } catch (const Error& e) {
    const bool nan = e.message().find("NaN") != std::string::npos;
    throw CompareError(nan ? FailureKind::kInvalidInput : FailureKind::kFileError, e.where(),
                       e.message());
  }
}

}  // namespace

namespace {

// A stack index that cannot be read as one (bad JSON, wrong types, an unparsable or non-finite
// defocus) is a file error (exit 4), naming the file and the line or field.
[[noreturn]] void IndexError(const FileLocation& where, const std::string& message) {
  throw CompareError(FailureKind::kFileError, where, message);
}

// A defocus written as text: the whole field must be a finite number.
bool ParseDefocus(const std::string& text, double* z) {
  std::string t = text;
  while (!t.empty() && (t.back() == ' ' || t.back() == '\t' || t.back() == '\r')) t.pop_back();
  size_t b = 0;
  while (b < t.size() && (t[b] == ' ' || t[b] == '\t')) ++b;
  t = t.substr(b);
  if (t.empty()) return false;
  try {
    size_t used = 0;
    *z = std::stod(t, &used);
    return used == t.size();
  } catch (const std::exception&) {
    return false;
  }
}

void ReadJsonIndex(const std::string& index, std::istream& in, const fs::path& base, Stack* s,
                   std::vector<std::string>* sidecars) {
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(in);
  } catch (const std::exception& e) {
    IndexError(FileLocation{index}, std::string("not valid JSON: ") + e.what());
  }
  const char* shape =
      "expected {\"planes\": [{\"defocus_um\": <number>, \"image\": \"<file>\"}, ...]}";
  if (!j.is_object() || !j.contains("planes") || !j["planes"].is_array())
    IndexError(FileLocation{index}, std::string("no \"planes\" array: ") + shape);
  const nlohmann::json& planes = j["planes"];
  for (size_t i = 0; i < planes.size(); ++i) {
    const nlohmann::json& p = planes[i];
    const std::string field = "planes[" + std::to_string(i) + "]";
    if (!p.is_object()) IndexError(FileLocation{index}, field + " is not an object: " + shape);
    if (!p.contains("defocus_um"))
      IndexError(FileLocation{index}, field + ".defocus_um is missing");
    if (!p.contains("image")) IndexError(FileLocation{index}, field + ".image is missing");
    const nlohmann::json& z = p["defocus_um"];
    if (!z.is_number())
      IndexError(FileLocation{index}, field + ".defocus_um must be a number (micrometres), got " +
                                          std::string(z.type_name()) + " " + z.dump());
    const double dz = z.get<double>();
    if (!std::isfinite(dz)) IndexError(FileLocation{index}, field + ".defocus_um must be finite");
    const nlohmann::json& im = p["image"];
    if (!im.is_string() || im.get<std::string>().empty())
      IndexError(FileLocation{index}, field +
                                          ".image must be a non-empty file name (string), got " +
                                          std::string(im.type_name()) + " " + im.dump());
    s->defocus_um.push_back(dz);
    s->files.push_back((base / im.get<std::string>()).string());
    const auto sc = p.find("sidecar");
    sidecars->push_back(sc != p.end() && sc->is_string() && !sc->get<std::string>().empty()
                            ? (base / sc->get<std::string>()).string()
                            : "");
  }
}

/// Splits a CSV line at its commas (index files hold no quoted fields).
std::vector<std::string> SplitCsv(const std::string& line) {
  std::vector<std::string> out(1);
  for (const char c : line)
    if (c == ',')
      out.emplace_back();
    else
      out.back() += c;
  for (std::string& f : out) {
    while (!f.empty() && (f.back() == ' ' || f.back() == '\r')) f.pop_back();
    while (!f.empty() && f.front() == ' ') f.erase(f.begin());
  }
  return out;
}

/// A CSV index: `defocus_um,file` per line (the file: the rest of the line), or, after a header
/// that names a `defocus_um` and an `image` (or `file`) column (simulate's <stem>_scan.csv),
/// those two columns.
void ReadCsvIndex(const std::string& index, std::istream& in, const fs::path& base, Stack* s,
                  std::vector<std::string>* sidecars) {
  std::string line;
  int n = 0;
  int z_col = -1, file_col = -1, sidecar_col = -1;  // from a header naming its columns
  while (std::getline(in, line)) {
    ++n;
    while (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.empty() || line[0] == '#') continue;
    const size_t comma = line.find(',');
    double z = 0;
    if (file_col >= 0) {
      const std::vector<std::string> f = SplitCsv(line);
      const int need = std::max(z_col, file_col);
      if (int(f.size()) <= need)
        IndexError(FileLocation{index, n, 1},
                   "expected " + std::to_string(need + 1) + " comma-separated columns as the " +
                       "header names, found " + std::to_string(f.size()));
      if (!ParseDefocus(f[size_t(z_col)], &z) || !std::isfinite(z))
        IndexError(FileLocation{index, n, 1}, "the defocus '" + f[size_t(z_col)] +
                                                  "' is not a finite number (micrometres, column " +
                                                  std::to_string(z_col + 1) + ")");
      if (f[size_t(file_col)].empty())
        IndexError(FileLocation{index, n, 1},
                   "no image file in column " + std::to_string(file_col + 1));
      s->defocus_um.push_back(z);
      s->files.push_back((base / f[size_t(file_col)]).string());
      const bool named = sidecar_col >= 0 && int(f.size()) > sidecar_col && !f[sidecar_col].empty();
      sidecars->push_back(named ? (base / f[size_t(sidecar_col)]).string() : "");
      continue;
    }
    const bool number = comma != std::string::npos && ParseDefocus(line.substr(0, comma), &z);
    if (!number) {
      if (n == 1) {  // a header; it may name the columns
        const std::vector<std::string> h = SplitCsv(line);
        for (size_t c = 0; c < h.size(); ++c) {
          if (h[c] == "defocus_um" && z_col < 0) z_col = int(c);
          if ((h[c] == "image" || h[c] == "file") && file_col < 0) file_col = int(c);
          if (h[c] == "sidecar" && sidecar_col < 0) sidecar_col = int(c);
        }
        if (z_col < 0 || file_col < 0) z_col = file_col = -1;  // the plain two-column form
        continue;
      }
      IndexError(FileLocation{index, n, 1},
                 comma == std::string::npos
                     ? "expected 'defocus_um,file', found no comma"
                     : "the defocus '" + line.substr(0, comma) +
                           "' is not a number (expected 'defocus_um,file' in micrometres)");
    }
    if (!std::isfinite(z))
      IndexError(FileLocation{index, n, 1},
                 "the defocus '" + line.substr(0, comma) + "' is not a finite number");
    std::string f = line.substr(comma + 1);
    while (!f.empty() && (f.back() == '\r' || f.back() == ' ')) f.pop_back();
    if (f.empty())
      IndexError(FileLocation{index, n, int(comma) + 2}, "no image file after the defocus");
    s->defocus_um.push_back(z);
    s->files.push_back((base / f).string());
    sidecars->push_back("");
  }
}

/// The object pixel a sidecar records (image.object_pixel_um); 0 when the file does not exist.
double SidecarPixelUm(const std::string& file) {
  if (file.empty() || !fs::exists(file)) return 0;
  std::ifstream in(file);
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(in);
  } catch (const std::exception& e) {
    IndexError(FileLocation{file},
               std::string("the plane's sidecar is not valid JSON: ") + e.what());
  }
  const nlohmann::json* v = nullptr;
  if (j.is_object() && j.contains("image") && j["image"].is_object() &&
      j["image"].contains("object_pixel_um"))
    v = &j["image"]["object_pixel_um"];
  if (!v) return 0;  // a sidecar of another kind: no pixel size
  if (!v->is_number() || !(v->get<double>() > 0) || !std::isfinite(v->get<double>()))
    IndexError(FileLocation{file},
               "image.object_pixel_um must be a positive number (micrometres), got " + v->dump());
  return v->get<double>();
}

}  // namespace

Stack ReadStack(const std::string& index) {
  if (!fs::exists(index))
    throw CompareError(FailureKind::kFileError, FileLocation{index}, "stack index not found");
  if (fs::is_directory(index))
    throw CompareError(FailureKind::kFileError, FileLocation{index},
                       "is a folder, not a stack index");
  const fs::path base = fs::path(index).parent_path();
  Stack s;
  std::ifstream in(index);
  if (!in)
    throw CompareError(FailureKind::kFileError, FileLocation{index}, "cannot open the stack index");
  std::vector<std::string> sidecars;
  if (fs::path(index).extension() == ".json")
    ReadJsonIndex(index, in, base, &s, &sidecars);
  else
    ReadCsvIndex(index, in, base, &s, &sidecars);
  if (s.files.empty())
    throw CompareError(FailureKind::kInvalidInput, FileLocation{index}, "the stack is empty");
  for (const auto& f : s.files) {
    s.images.push_back(LoadChecked(f));
    if (s.images.back().width != s.images[0].width || s.images.back().height != s.images[0].height)
      throw CompareError(FailureKind::kSizeMismatch, FileLocation{f},
                         "image size differs from the stack's first image");
  }
  // The pixel size when every plane's sidecar gives the same one.
  for (size_t i = 0; i < sidecars.size(); ++i) {
    const double px = SidecarPixelUm(sidecars[i]);
    if (!(px > 0) || (i > 0 && std::abs(px - s.object_pixel_um) > 1e-9 * px)) {
      s.object_pixel_um = 0;
      break;
    }
    s.object_pixel_um = px;
  }
  return s;
}

Image PrepareExperiment(const Image& raw, const PrepareOptions& o, const Image* dark,
                        const Image* flat) {
  auto crop = [&](const Image& img, const std::string& what) {
    if (!o.roi) return img;
    const auto [x0, y0, w, h] = *o.roi;
    if (x0 < 0 || y0 < 0 || w <= 0 || h <= 0 || x0 + w > img.width || y0 + h > img.height)
      throw CompareError(FailureKind::kSizeMismatch,
                         "ROI " + std::to_string(x0) + "," + std::to_string(y0) + " " +
                             std::to_string(w) + "x" + std::to_string(h) + " does not fit the " +
                             what + " (" + std::to_string(img.width) + "x" +
                             std::to_string(img.height) + ")");
    Image c(w, h);
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) c.at(x, y) = img.at(x0 + x, y0 + y);
    return c;
  };
  Image img = crop(raw, "image");
  if (dark) {
    const Image d = crop(*dark, "dark frame");
    if (d.width != img.width || d.height != img.height)
      throw CompareError(FailureKind::kSizeMismatch, "dark frame size differs from the image");
    for (size_t i = 0; i < img.size(); ++i) img.pixels[i] -= d.pixels[i];
  }
  if (flat) {
    const Image f = crop(*flat, "flat field");
    if (f.width != img.width || f.height != img.height)
      throw CompareError(FailureKind::kSizeMismatch, "flat field size differs from the image");
    const double mean = ComputeStats(f).mean;
    if (!(mean > 0)) throw CompareError(FailureKind::kInvalidInput, "flat field is blank");
    for (size_t i = 0; i < img.size(); ++i)
      img.pixels[i] = f.pixels[i] > 0 ? float(img.pixels[i] * mean / f.pixels[i]) : 0.f;
  }
  for (float& v : img.pixels) v = float(v * o.gain_e_per_dn);
  return img;
}

const char* MeasureName(Measure m) {
  switch (m) {
    case Measure::kMse:
      return "mse";
    case Measure::kSsim:
      return "ssim";
    case Measure::kMsSsim:
      return "ms_ssim";
    case Measure::kCwSsim:
      return "cw_ssim";
    case Measure::kPoissonChi2:
      return "poisson_chi2";
  }
  return "?";
}

bool HigherIsBetter(Measure m) {
  return m == Measure::kSsim || m == Measure::kMsSsim || m == Measure::kCwSsim;
}

namespace {

double Median(std::vector<float> v) {
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

Image Shift(const Image& img, double dx, double dy) {
  cv::Mat src(img.height, img.width, CV_32F, const_cast<float*>(img.pixels.data())), dst;
  const cv::Mat m = (cv::Mat_<double>(2, 3) << 1, 0, dx, 0, 1, dy);
  cv::warpAffine(src, dst, m, src.size(), cv::INTER_LINEAR, cv::BORDER_REPLICATE);
  Image out(img.width, img.height);
  std::copy(dst.begin<float>(), dst.end<float>(), out.pixels.begin());
  return out;
}

constexpr double kShiftSignificance = 3.0;

struct Registration {
  std::array<double, 2> shift{};  ///< to apply to `a` (Shift(a, x, y) ~ b)
  std::array<double, 2> sigma{};  ///< shot-noise standard error
};

/// Sub-pixel shift of `a` onto `b` with its shot-noise standard error. Whole pixels come from
/// phase correlation; the fraction from Lucas-Kanade least-squares steps, s += M^-1 sum(g r),
/// r = shifted a - b, g the central-difference gradient of (shifted a + b)/2. Central
/// differences never use the pixel of r, so white noise does not bias s (an MSE search
/// over interpolated shifts does: interpolation averages noise away and pulls the minimum
/// towards half pixels). Pixel variances are Poisson, a for the experiment in photons and
/// scale x b for a simulation scaled by `scale`; Cov(s) = M_s^-1 (sum g g^T var r) M_s^-1 with
/// M_s = M minus the gradient's own noise (Kay, Fundamentals of Statistical Signal
/// Processing: Estimation, 1993, ch. 8, least squares).
Registration Register(const Image& a0, const Image& b, double scale) {
  Registration reg;
  cv::Mat ma(a0.height, a0.width, CV_32F, const_cast<float*>(a0.pixels.data()));
  cv::Mat mb(b.height, b.width, CV_32F, const_cast<float*>(b.pixels.data()));
  cv::Mat win;
  cv::createHanningWindow(win, ma.size(), CV_32F);
  cv::Mat a64, b64, w64;
  ma.convertTo(a64, CV_64F);
  mb.convertTo(b64, CV_64F);
  win.convertTo(w64, CV_64F);
  const cv::Point2d d = cv::phaseCorrelate(b64, a64, w64);  // shift of a relative to b
  double sx = std::round(-d.x), sy = std::round(-d.y);
  const int w = a0.width, h = a0.height;
  double m[3], gn[2], gr[2], c[3];
  // Lucas-Kanade iterations from the whole-pixel shift. With linear interpolation the noise of
  // the shifted image enters g (at x +- 1) and r (at x) with weights that cancel, so the step
  // stays unbiased by noise.
  for (int it = 0; it < 4; ++it) {
    const Image a = sx == 0 && sy == 0 ? a0 : Shift(a0, sx, sy);
    const int margin = 2 + static_cast<int>(std::ceil(std::max(std::abs(sx), std::abs(sy))));
    std::fill(m, m + 3, 0.0), std::fill(gn, gn + 2, 0.0), std::fill(gr, gr + 2, 0.0),
        std::fill(c, c + 3, 0.0);
    auto var = [&](int x, int y) {  // variance of one pixel of a and of b
      return std::max(0.0, double(a.at(x, y))) + scale * std::max(0.0, double(b.at(x, y)));
    };
    for (int y = margin; y < h - margin; ++y)
      for (int x = margin; x < w - margin; ++x) {
        const double gx =
            0.25 * (a.at(x + 1, y) + b.at(x + 1, y) - a.at(x - 1, y) - b.at(x - 1, y));
        const double gy =
            0.25 * (a.at(x, y + 1) + b.at(x, y + 1) - a.at(x, y - 1) - b.at(x, y - 1));
        const double r = double(a.at(x, y)) - b.at(x, y), vr = var(x, y);
        m[0] += gx * gx, m[1] += gx * gy, m[2] += gy * gy;
        gn[0] += (var(x + 1, y) + var(x - 1, y)) / 16;  // noise of gx: (a+b)/2 differenced, / 2
        gn[1] += (var(x, y + 1) + var(x, y - 1)) / 16;
        gr[0] += gx * r, gr[1] += gy * r;
        c[0] += gx * gx * vr, c[1] += gx * gy * vr, c[2] += gy * gy * vr;
      }
    // a(x - s) ~ a(x) - s.grad: least squares of r ~ s.g gives M s = sum(g r). Gauss-Newton
    // with the signal part of M (the gradient's own noise only slows the steps down) where it
    // is positive definite.
    double q0 = m[0] - gn[0], q1 = m[1], q2 = m[2] - gn[1];
    if (!(q0 > 0 && q2 > 0 && q0 * q2 - q1 * q1 > 0)) q0 = m[0], q1 = m[1], q2 = m[2];
    const double det = q0 * q2 - q1 * q1;
    if (!(det > 0)) break;
    const double s0 = (q2 * gr[0] - q1 * gr[1]) / det;
    const double s1 = (q0 * gr[1] - q1 * gr[0]) / det;
    sx += std::clamp(s0, -1.0, 1.0), sy += std::clamp(s1, -1.0, 1.0);
    if (std::abs(s0) < 1e-3 && std::abs(s1) < 1e-3) break;
  }
  reg.shift = {sx, sy};
  // Covariance with the signal part of M (the noise part carries no information about s).
  const double p0 = m[0] - gn[0], p1 = m[1], p2 = m[2] - gn[1];
  const double ds = p0 * p2 - p1 * p1;
  if (!(p0 > 0 && p2 > 0 && ds > 0)) {
    reg.sigma = {std::numeric_limits<double>::infinity(), std::numeric_limits<double>::infinity()};
    return reg;
  }
  const double i0 = p2 / ds, i1 = -p1 / ds, i2 = p0 / ds;  // M_s^-1
  // Diagonal of M_s^-1 C M_s^-1.
  const double v0 = i0 * (i0 * c[0] + i1 * c[1]) + i1 * (i0 * c[1] + i1 * c[2]);
  const double v1 = i1 * (i1 * c[0] + i2 * c[1]) + i2 * (i1 * c[1] + i2 * c[2]);
  reg.sigma = {std::sqrt(std::max(0.0, v0)), std::sqrt(std::max(0.0, v1))};
  return reg;
}

int Nearest(const std::vector<double>& zs, double z) {
  int best = 0;
  for (size_t j = 1; j < zs.size(); ++j)
    if (std::abs(zs[j] - z) < std::abs(zs[best] - z)) best = int(j);
  return best;
}

}  // namespace

std::string FocusScanResult::RegistrationSummary() const {
  if (!registration_run) return "registration off: no shift applied";
  auto axis = [&](int k) {
    char buf[160];
    if (!std::isfinite(shift_sigma_px[k]))
      std::snprintf(buf, sizeof buf, "%s: none applied (no measurable gradient)", k ? "y" : "x");
    else if (shift_applied[k])
      std::snprintf(buf, sizeof buf, "%s: %.3f +- %.3f px applied", k ? "y" : "x", shift_px[k],
                    shift_sigma_px[k]);
    else
      std::snprintf(buf, sizeof buf, "%s: none applied (%.3f +- %.3f px is within 3 sigma)",
                    k ? "y" : "x", shift_estimate_px[k], shift_sigma_px[k]);
    return std::string(buf);
  };
  return "registration " + axis(0) + "; " + axis(1);
}

FocusScanResult RunFocusScan(const Stack& exp, const Stack& sim, const FocusScanOptions& o) {
  if (exp.images.empty() || sim.images.empty())
    throw CompareError(FailureKind::kInvalidInput, "a focus stack is empty");
  FocusScanResult r;
  r.object_pixel_um = o.object_pixel_um > 0     ? o.object_pixel_um
                      : sim.object_pixel_um > 0 ? sim.object_pixel_um
                                                : exp.object_pixel_um;
  r.exp_defocus_um = exp.defocus_um;
  r.sim_defocus_um = sim.defocus_um;
  Image dark, flat;
  if (!o.prepare.dark_file.empty()) dark = LoadChecked(o.prepare.dark_file);
  if (!o.prepare.flat_file.empty()) flat = LoadChecked(o.prepare.flat_file);
  for (const Image& e : exp.images)
    r.exp_images.push_back(PrepareExperiment(e, o.prepare, dark.empty() ? nullptr : &dark,
                                             flat.empty() ? nullptr : &flat));
  r.sim_images = sim.images;
  const Image& e0 = r.exp_images[0];
  if (e0.width != r.sim_images[0].width || e0.height != r.sim_images[0].height)
    throw CompareError(FailureKind::kSizeMismatch,
                       "experiment images are " + std::to_string(e0.width) + "x" +
                           std::to_string(e0.height) + " after preparation, simulation images " +
                           std::to_string(r.sim_images[0].width) + "x" +
                           std::to_string(r.sim_images[0].height) + "; crop with an ROI");
  // Bring the simulation to the experiment's background level (exposure), then register.
  if (o.normalize_background) {
    const double me = Median(r.exp_images[exp.images.size() / 2].pixels);
    const double ms =
        Median(r.sim_images[Nearest(sim.defocus_um, exp.defocus_um[exp.images.size() / 2])].pixels);
    if (!(ms > 0) || !(me > 0))
      throw CompareError(FailureKind::kInvalidInput, "blank images: cannot match exposures");
    r.sim_scale = me / ms;
    for (Image& s : r.sim_images)
      for (float& v : s.pixels) v = float(v * r.sim_scale);
  }
  if (o.register_shift) {
    const size_t k = exp.images.size() / 2;
    const Registration reg = Register(
        r.exp_images[k], r.sim_images[Nearest(sim.defocus_um, exp.defocus_um[k])], r.sim_scale);
    r.registration_run = true;
    r.shift_estimate_px = reg.shift;
    r.shift_sigma_px = reg.sigma;
    for (int axis = 0; axis < 2; ++axis) {
      // Applied only when significant against the shot noise (3 sigma: a spurious shift in
      // fewer than 0.3 % of noise-only pairs per axis).
      r.shift_applied[axis] = std::isfinite(reg.sigma[axis]) &&
                              std::abs(reg.shift[axis]) > kShiftSignificance * reg.sigma[axis];
      r.shift_px[axis] = r.shift_applied[axis] ? reg.shift[axis] : 0.0;
    }
    if (r.shift_px[0] != 0 || r.shift_px[1] != 0)
      for (Image& e : r.exp_images) e = Shift(e, r.shift_px[0], r.shift_px[1]);
  }
  double L = o.data_range;
  if (L <= 0) {
    for (const auto* v : {&r.exp_images, &r.sim_images})
      for (const Image& img : *v) L = std::max(L, ComputeStats(img).max);
  }
  if (!(L > 0)) throw CompareError(FailureKind::kInvalidInput, "all images are blank");
  r.data_range = L;
  MsSsimOptions mo = o.ms_ssim;
  mo.data_range = L;
  mo.num_scales = MsSsimScalesFor(mo, e0.width, e0.height);
  const int cw_max = MaxCwSsimLevel(e0.width, e0.height);
  CwSsimOptions cwo = o.cw_ssim;
  cwo.data_range = L;
  cwo.level = CwSsimLevelFor(cwo, e0.width, e0.height);
  r.ms_ssim = mo;
  r.cw_ssim = cwo;
  const size_t ne = r.exp_images.size(), ns = r.sim_images.size();
  for (Measure m : o.measures) {
    MeasureScan ms;
    ms.measure = m;
    ms.matrix.assign(ne, std::vector<double>(ns, 0));
    std::vector<CwSsimBands> eb, sb;
    if (m == Measure::kCwSsim) {
      for (const Image& e : r.exp_images) eb.push_back(ComputeCwSsimBands(e, cwo, cwo.level));
      for (const Image& s : r.sim_images) sb.push_back(ComputeCwSsimBands(s, cwo, cwo.level));
    }
    for (size_t i = 0; i < ne; ++i)
      for (size_t j = 0; j < ns; ++j) {
        const Image &a = r.exp_images[i], &b = r.sim_images[j];
        double v = 0;
        switch (m) {
          case Measure::kMse:
            v = MeanSquaredError(a, b);
            break;
          case Measure::kSsim: {
            SsimOptions so;
            so.data_range = L;
            v = Ssim(a, b, so).ssim;
            break;
          }
          case Measure::kMsSsim:
            v = MsSsim(a, b, mo).ms_ssim;
            break;
          case Measure::kCwSsim:
            v = CwSsimFromBands(eb[i], sb[j], cwo, cwo.level, cw_max).cw_ssim;
            break;
          case Measure::kPoissonChi2:
            v = PoissonMeasures(a, b).chi2_per_pixel;
            break;
        }
        ms.matrix[i][j] = v;
      }
    ms.passes = true;
    for (size_t i = 0; i < ne; ++i) {
      int best = 0;
      for (size_t j = 1; j < ns; ++j) {
        const double v = ms.matrix[i][j], bv = ms.matrix[i][best];
        if (HigherIsBetter(m) ? v > bv : v < bv) best = int(j);
      }
      ms.best.push_back(best);
      ms.expected.push_back(Nearest(sim.defocus_um, exp.defocus_um[i]));
      if (std::abs(best - ms.expected.back()) > 1) ms.passes = false;
    }
    r.measures.push_back(std::move(ms));
  }
  int primary = 0, failed = 0;
  std::string failed_names;
  for (MeasureScan& ms : r.measures)
    if (std::count(o.primary.begin(), o.primary.end(), ms.measure)) {
      ms.primary = true;
      ++primary;
      if (!ms.passes)
        ++failed,
            failed_names += std::string(failed_names.empty() ? "" : ", ") + MeasureName(ms.measure);
    }
  r.verdict = failed == 0 ? Verdict::kPass : failed < primary ? Verdict::kWarning : Verdict::kFail;
  r.message = failed == 0 ? "all primary measures pass the focus-scan test"
                          : "focus-scan test failed for: " + failed_names;
  return r;
}

nlohmann::json FocusScanResult::ToJson() const {
  nlohmann::json ms = nlohmann::json::array();
  for (const MeasureScan& m : measures) {
    nlohmann::json best = nlohmann::json::array();
    for (size_t i = 0; i < m.best.size(); ++i)
      best.push_back({{"experiment_defocus_um", exp_defocus_um[i]},
                      {"best_simulation_defocus_um", sim_defocus_um[m.best[i]]},
                      {"expected_simulation_defocus_um", sim_defocus_um[m.expected[i]]}});
    ms.push_back({{"measure", MeasureName(m.measure)},
                  {"higher_is_better", HigherIsBetter(m.measure)},
                  {"passes", m.passes},
                  {"matrix", m.matrix},
                  {"best_matches", best}});
  }
  return {{"verdict", verdict == Verdict::kPass      ? "pass"
                      : verdict == Verdict::kWarning ? "warning"
                                                     : "fail"},
          {"message", message},
          {"data_range", data_range},
          {"registration_shift_px", shift_px},
          {"registration",
           {{"run", registration_run},
            {"applied", {shift_applied[0], shift_applied[1]}},
            {"estimate_px", shift_estimate_px},
            {"sigma_px",
             {std::isfinite(shift_sigma_px[0]) ? nlohmann::json(shift_sigma_px[0])
                                               : nlohmann::json(nullptr),
              std::isfinite(shift_sigma_px[1]) ? nlohmann::json(shift_sigma_px[1])
                                               : nlohmann::json(nullptr)}},
            {"rule", "a shift is applied on an axis only where |estimate| > 3 sigma (shot noise)"},
            {"summary", RegistrationSummary()}}},
          {"simulation_scale", sim_scale},
          {"object_pixel_um",
           object_pixel_um > 0 ? nlohmann::json(object_pixel_um) : nlohmann::json(nullptr)},
          {"ms_ssim_scales", ms_ssim.num_scales},
          {"ms_ssim_weights", MsSsimWeightsName(ms_ssim.weights)},
          {"ms_ssim_sigma_px", ms_ssim.sigma},
          {"cw_ssim_level", cw_ssim.level},
          {"cw_ssim_orientations", cw_ssim.orientations},
          {"cw_ssim_k", cw_ssim.k},
          {"experiment_defocus_um", exp_defocus_um},
          {"simulation_defocus_um", sim_defocus_um},
          {"measures", ms}};
}

}  // namespace raymatch::compare
