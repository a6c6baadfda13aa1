#include "raymatch/calibrate/zemax_source.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <iterator>
#include <limits>

#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"
#include "raymatch/core/provenance.h"
#include "raymatch/core/rng.h"

namespace raymatch::calibrate {

namespace {

constexpr size_t kHeaderBytes = 208;

// Explicit little-endian byte order, whatever the host (the format is little-endian).
class ByteWriter {
 public:
  void U32(uint32_t v) {
    for (int i = 0; i < 4; ++i) bytes.push_back(char((v >> (8 * i)) & 0xff));
  }
  void I32(int32_t v) { U32(uint32_t(v)); }
  void F32(float f) {
    uint32_t v;
    std::memcpy(&v, &f, 4);
    U32(v);
  }
  std::string bytes;
};

class ByteReader {
 public:
  ByteReader(const std::string& b, const std::string& file) : b_(b), file_(file) {}
  uint32_t U32() {
    if (pos_ + 4 > b_.size())
      throw Error(FileLocation{file_}, "truncated at byte " + std::to_string(pos_));
    uint32_t v = 0;
    for (int i = 0; i < 4; ++i) v |= uint32_t(uint8_t(b_[pos_ + i])) << (8 * i);
    pos_ += 4;
    return v;
  }
  int32_t I32() { return int32_t(U32()); }
  float F32() {
    const uint32_t v = U32();
    float f;
    std::memcpy(&f, &v, 4);
    return f;
  }
  /// A float that must be finite (NaN or Inf is an error naming its byte and `what`).
  float FiniteF32(const std::string& what) {
    const size_t at = pos_;
    const float f = F32();
    if (!std::isfinite(f))
      throw Error(FileLocation{file_},
                  "byte " + std::to_string(at) + ": " + what + " is not a finite number");
    return f;
  }
  std::string Chars(size_t n) {
    std::string s = b_.substr(pos_, n);
    pos_ += n;
    return s.substr(0, s.find('\0'));
  }
  size_t pos() const { return pos_; }

 private:
  const std::string& b_;
  std::string file_;
  size_t pos_ = 0;
};

}  // namespace

double ZemaxUnitUm(int32_t u) {
  switch (u) {
    case 0:
      return 1e6;
    case 1:
      return 25400;
    case 2:
      return 1e4;
    case 3:
      return 304800;
    case 4:
      return 1e3;
  }
  throw Error("Zemax source file: dimension units " + std::to_string(u) +
              " (expected 0 m, 1 in, 2 cm, 3 ft or 4 mm)");
}

void WriteZemaxSourceFile(const std::string& path, const ZemaxSourceFile& f) {
  const ZemaxSourceHeader& h = f.header;
  if (h.identifier != 1010) throw Error(FileLocation{path}, "Zemax source identifier must be 1010");
  if (h.ray_format != 0 && h.ray_format != 2)
    throw Error(FileLocation{path}, "Zemax ray format must be 0 (flux only) or 2 (spectral)");
  if (h.description.size() > 99)
    throw Error(FileLocation{path}, "Zemax description longer than 99 characters");
  ZemaxUnitUm(h.dimension_units);
  if (f.rays.size() > UINT32_MAX)
    throw Error(FileLocation{path}, "too many rays for a Zemax source file");
  ByteWriter w;
  w.I32(h.identifier);
  w.U32(uint32_t(f.rays.size()));
  std::string desc = h.description;
  desc.resize(100, '\0');
  w.bytes += desc;
  for (float v : {h.source_flux, h.ray_set_flux, h.wavelength_um, h.inclination_begin,
                  h.inclination_end, h.azimuth_begin, h.azimuth_end})
    w.F32(v);
  w.I32(h.dimension_units);
  for (const auto* a : {&h.location, &h.rotation, &h.scale})
    for (float v : *a) w.F32(v);
  for (float v : h.unused) w.F32(v);
  w.I32(h.ray_format);
  w.I32(h.flux_type);
  for (int32_t v : h.reserved) w.I32(v);
  RAYMATCH_CHECK(w.bytes.size() == kHeaderBytes);
  w.bytes.reserve(kHeaderBytes + f.rays.size() * 32);
  for (const ZemaxRay& r : f.rays) {
    for (float v : {r.x, r.y, r.z, r.l, r.m, r.n, r.flux}) w.F32(v);
    if (h.ray_format == 2) w.F32(r.wavelength_um);
  }
  EnsureDirectory(std::filesystem::path(path).parent_path());
  const auto tmp = TemporaryPathFor(path);
  {
    std::ofstream out(tmp, std::ios::binary);
    out.write(w.bytes.data(), std::streamsize(w.bytes.size()));
    out.close();
    if (!out) {
      DiscardTemporary(tmp);
      throw Error(FileLocation{path}, "cannot write the Zemax source file");
    }
  }
  CommitTemporary(tmp, path);
}

ZemaxSourceFile ReadZemaxSourceFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(FileLocation{path}, "cannot open the Zemax source file");
  const std::string b((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (b.size() < kHeaderBytes)
    throw Error(FileLocation{path}, "file of " + std::to_string(b.size()) +
                                        " bytes is shorter than the 208-byte Zemax header");
  ByteReader r(b, path);
  ZemaxSourceFile f;
  ZemaxSourceHeader& h = f.header;
  h.identifier = r.I32();
  if (h.identifier != 1010)
    throw Error(FileLocation{path},
                "byte 0: identifier " + std::to_string(h.identifier) +
                    ", expected 1010 (not a Zemax binary source file, or big-endian)");
  h.num_rays = r.U32();
  h.description = r.Chars(100);
  for (float* v : {&h.source_flux, &h.ray_set_flux, &h.wavelength_um, &h.inclination_begin,
                   &h.inclination_end, &h.azimuth_begin, &h.azimuth_end})
    *v = r.FiniteF32("header value");
  h.dimension_units = r.I32();
  try {
    ZemaxUnitUm(h.dimension_units);
  } catch (const Error& e) {
    throw Error(FileLocation{path}, "byte 136: " + e.message());
  }
  for (auto* a : {&h.location, &h.rotation, &h.scale})
    for (float& v : *a) v = r.F32();
  for (float& v : h.unused) v = r.F32();
  h.ray_format = r.I32();
  h.flux_type = r.I32();
  for (int32_t& v : h.reserved) v = r.I32();
  if (h.ray_format != 0 && h.ray_format != 2)
    throw Error(FileLocation{path}, "byte 192: ray format " + std::to_string(h.ray_format) +
                                        " (supported: 0 flux only, 2 spectral)");
  const size_t per = h.ray_format == 2 ? 32 : 28;
  const size_t expect = kHeaderBytes + size_t(h.num_rays) * per;
  if (b.size() != expect)
    throw Error(FileLocation{path}, "file has " + std::to_string(b.size()) +
                                        " bytes; the header's " + std::to_string(h.num_rays) +
                                        " rays of " + std::to_string(per) + " bytes need " +
                                        std::to_string(expect));
  f.rays.resize(h.num_rays);
  // Every ray value must be finite and every flux non-negative: a NaN or a negative weight
  // would turn the angular map's field radius (a flux-weighted RMS) into NaN.
  for (size_t k = 0; k < f.rays.size(); ++k) {
    ZemaxRay& ray = f.rays[k];
    const std::string what = "ray " + std::to_string(k);
    for (float* v : {&ray.x, &ray.y, &ray.z, &ray.l, &ray.m, &ray.n, &ray.flux})
      *v = r.FiniteF32(what);
    if (h.ray_format == 2) ray.wavelength_um = r.FiniteF32(what);
    if (ray.flux < 0)
      throw Error(FileLocation{path}, "byte " +
                                          std::to_string(r.pos() - (h.ray_format == 2 ? 8 : 4)) +
                                          ": " + what + " has a negative flux");
  }
  return f;
}

ZemaxSourceFile SampleZemaxSource(const CalibrationData& cal, const ZemaxExportOptions& o) {
  if (!cal.has_light_field()) throw Error("the calibration has no light field to export");
  const double radius_um = o.field_radius_um > 0 ? o.field_radius_um : cal.field_radius_um;
  if (!(radius_um > 0))
    throw Error("no field radius: the calibration leaves it automatic; give one (field_radius_um)");
  if (o.num_rays == 0 || o.num_rays > UINT32_MAX) throw Error("num_rays must be in [1, 2^32)");
  const Image& m = cal.angular_map;
  const int nx = m.width, ny = m.height;
  const double ext = cal.angular_extent;
  // Cells whose whole square lies beyond |(u,v)| = 1 carry no physical directions.
  std::vector<double> cdf(m.size() + 1, 0.0);
  for (size_t i = 0; i < m.size(); ++i) {
    const double u0 = (2.0 * (i % nx) / nx - 1) * ext, v0 = (1 - 2.0 * (i / nx + 1) / ny) * ext;
    const double du = 2 * ext / nx, dv = 2 * ext / ny;
    const double cu = std::clamp(0.0, u0, u0 + du), cv = std::clamp(0.0, v0, v0 + dv);
    const bool reachable = cu * cu + cv * cv < 1;
    cdf[i + 1] = cdf[i] + (reachable ? std::max(0.0, double(m.pixels[i])) : 0.0);
  }
  if (!(cdf.back() > 0)) throw Error("the angular map is zero everywhere: nothing to sample");
  const double unit = ZemaxUnitUm(o.dimension_units);
  ZemaxSourceFile f;
  ZemaxSourceHeader& h = f.header;
  h.description = "raymatch light field (separable: uniform disc x angular map)";
  h.source_flux = float(o.flux);
  h.ray_set_flux = float(o.flux);
  h.wavelength_um = float(cal.wavelength_um > 0 ? cal.wavelength_um : 0.462);
  h.inclination_end = float(std::asin(std::min(1.0, ext * std::sqrt(2.0))) * 180 / M_PI);
  h.dimension_units = o.dimension_units;
  f.rays.resize(o.num_rays);
  const float flux = float(o.flux / double(o.num_rays));
  for (uint64_t k = 0; k < o.num_rays; ++k) {
    RayRng rng(o.seed, 0, k);
    ZemaxRay& r = f.rays[k];
    // Position: uniform in the disc (rejection keeps it exact and simple).
    double x, y;
    do {
      x = 2 * rng.Uniform() - 1, y = 2 * rng.Uniform() - 1;
    } while (x * x + y * y >= 1);
    double u, v;
    do {
      const double t = rng.Uniform() * cdf.back();
      const size_t i = size_t(std::upper_bound(cdf.begin(), cdf.end(), t) - cdf.begin()) - 1;
      const size_t c = std::min(i, m.size() - 1);
      u = (2 * ((c % nx) + rng.Uniform()) / nx - 1) * ext;
      v = (1 - 2 * ((c / nx) + rng.Uniform()) / ny) * ext;
    } while (u * u + v * v >= 1);
    r.x = float(x * radius_um / unit), r.y = float(y * radius_um / unit), r.z = 0;
    r.l = float(u), r.m = float(v), r.n = float(std::sqrt(1 - u * u - v * v));
    r.flux = flux;
    r.wavelength_um = h.wavelength_um;
  }
  return f;
}

ZemaxImportSummary AngularMapFromZemax(const ZemaxSourceFile& f, const ZemaxImportOptions& o) {
  if (o.map_size < 2) throw Error("map_size must be >= 2");
  ZemaxImportSummary s;
  const double unit = ZemaxUnitUm(f.header.dimension_units);
  double ext = o.extent;
  if (!(ext > 0)) {
    for (const ZemaxRay& r : f.rays) {
      const double norm = std::sqrt(double(r.l) * r.l + double(r.m) * r.m + double(r.n) * r.n);
      if (r.n > 0 && norm > 0 &&
          std::isfinite(norm))  // the same normalisation as the binning below
        ext = std::max({ext, std::abs(r.l / norm), std::abs(r.m / norm)});
    }
    ext = std::min(1.0, ext * 1.02);
  }
  if (!(ext > 0)) throw Error("no forward rays (n > 0) in the Zemax source");
  const int n = o.map_size;
  Image map(n, n);
  std::vector<double> acc(size_t(n) * n, 0.0);
  double w_sum = 0, r2_sum = 0;
  for (const ZemaxRay& r : f.rays) {
    const double norm = std::sqrt(double(r.l) * r.l + double(r.m) * r.m + double(r.n) * r.n);
    if (!(r.n > 0) || !(norm > 0) || !std::isfinite(norm) || !(r.flux >= 0) ||
        !std::isfinite(r.flux) || !std::isfinite(r.x) || !std::isfinite(r.y)) {
      ++s.rays_skipped;
      continue;
    }
    // Direction cosines are normalised defensively (Zemax writes unit vectors).
    const double u = r.l / norm, v = r.m / norm;
    const double fc = std::floor((u / ext + 1) / 2 * n), fr = std::floor((1 - v / ext) / 2 * n);
    if (!(fc >= 0 && fc < n && fr >= 0 && fr < n)) {  // compared as doubles: no out-of-range cast
      ++s.rays_skipped;
      continue;
    }
    const int col = int(fc), row = int(fr);
    acc[size_t(row) * n + col] += r.flux;
    const double x = r.x * unit, y = r.y * unit;
    w_sum += r.flux, r2_sum += r.flux * (x * x + y * y);
    ++s.rays_used;
  }
  if (!(w_sum > 0)) throw Error("the Zemax source carries no flux in forward rays");
  const double cell = (2 * ext / n) * (2 * ext / n);
  for (size_t i = 0; i < acc.size(); ++i) {
    const double radiance = std::max(0.0, acc[i]) / cell;
    if (!(radiance <= std::numeric_limits<float>::max()))  // the map is float32: no Inf
      throw Error("the Zemax rays' radiance " + std::to_string(radiance) +
                  " exceeds the float range of the angular map (fluxes too large: rescale them)");
    map.pixels[i] = float(radiance);
  }
  if (s.rays_skipped)
    s.warnings.push_back(std::to_string(s.rays_skipped) +
                         " rays skipped (backward, zero or outside the map)");
  s.data.angular_map = map;
  s.data.angular_extent = ext;
  s.data.field_radius_um = std::sqrt(2 * r2_sum / w_sum);
  s.data.wavelength_um = f.header.wavelength_um;
  s.data.light_field_note = "imported from a Zemax source file (" + std::to_string(s.rays_used) +
                            " rays): " + f.header.description;
  return s;
}

ZemaxImportSummary ImportZemaxLightField(const ZemaxSourceFile& file, const ZemaxImportOptions& o,
                                         const CalibrationData& base,
                                         const std::string& source_path) {
  ZemaxImportSummary s = AngularMapFromZemax(file, o);
  CalibrationData d = base;
  d.angular_map = s.data.angular_map;
  d.angular_extent = s.data.angular_extent;
  d.field_radius_um = s.data.field_radius_um;
  d.na_limit = 0;
  d.cone_half_angle_deg = 0;
  d.light_field_note = s.data.light_field_note;
  nlohmann::json prov = ProvenanceJson();
  for (auto& [k, v] : base.provenance.items())
    if (!prov.contains(k) && k != "light_field_inputs") prov[k] = v;
  if (!source_path.empty())
    prov["light_field_inputs"] = FileChecksum(source_path) + " " + source_path;
  d.provenance = prov;
  s.data = d;
  return s;
}

NdArray ZemaxRayList(const ZemaxSourceFile& f, uint64_t* skipped) {
  const double unit = ZemaxUnitUm(f.header.dimension_units);
  NdArray a;
  uint64_t skip = 0;
  for (const ZemaxRay& r : f.rays) {
    if (!(r.n > 0) || !(r.flux >= 0) || !(double(r.l) * r.l + double(r.m) * r.m < 1) ||
        !std::isfinite(r.flux) || !std::isfinite(r.x) || !std::isfinite(r.y)) {
      ++skip;
      continue;
    }
    a.values.insert(a.values.end(),
                    {r.x * unit, r.y * unit, double(r.l), double(r.m), double(r.flux)});
  }
  a.shape = {a.values.size() / 5, 5};
  if (skipped) *skipped = skip;
  if (a.values.empty()) throw Error("the Zemax source file has no ray travelling towards +z");
  return a;
}

}  // namespace raymatch::calibrate
