#include "raymatch/simulate/scan.h"

#include <algorithm>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <memory>
#include <set>
#include <sstream>
#include <type_traits>

#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/provenance.h"
#include "raymatch/simulate/geometry.h"
#include "raymatch/simulate/physical_image.h"
#include "raymatch/simulate/water.h"
#include "raymatch/simulate/wave_image.h"

namespace fs = std::filesystem;

namespace raymatch::simulate {

std::string PlaneStem(const std::string& name, double defocus_um) {
  const double z = defocus_um == 0 ? 0.0 : defocus_um;  // no "-0.00"
  // Two decimals as long as they name the value exactly; otherwise as many more as it takes
  // for the name to read back as the same double, so distinct planes never share a file.
  char buf[64];
  for (int digits = 2; digits <= 17; ++digits) {
    std::snprintf(buf, sizeof buf, "%+0*.*f", digits + 5, digits, z);
    if (std::strtod(buf, nullptr) == z) break;
  }
  return name + "_z" + buf + "um";
}

// Shortest text that reads back as the same double (the CSV index and messages).
static std::string FormatDefocus(double z) {
  char buf[64];
  // The shortest form that reads back exactly, plain where it is no longer (-10, not -1e+01).
  const auto r = std::to_chars(buf, buf + sizeof buf, z);
  return std::string(buf, r.ptr);
}

static const char* PrName(PartialReflection p) {
  return p == PartialReflection::kOff           ? "off"
         : p == PartialReflection::kUnpolarized ? "unpolarized"
                                                : "polarized";
}

namespace {

/// An object's index over the spectrum: mean, least and largest at 2000 quantiles, or why it is
/// monochromatic. `water`: the object's water density field at other wavelengths as the tracer
/// uses it (Simulator::WaterMapOf), or null.
nlohmann::json OverTheSpectrum(const ObjectSpec& o, const Scene& s, const WaterMapTable* water) {
  const SpectrumSpec& sp = s.source.spectrum;
  const int K = 2000;  // the spectrum's quantile midpoints
  if (o.index_field && water) {
    const IndexField& f = *o.index_field;
    double lo = 1e300, hi = -1e300;
    for (int k = 0; k < K; ++k) {
      const AffineIndexMap m = water->At(sp.Sample((k + 0.5) / K));
      lo = std::min(lo, m.offset + m.scale * f.min_n),
      hi = std::max(hi, m.offset + m.scale * f.max_n);
    }
    return {{"traced",
             "each ray near the object sees the density grid's IAPWS R9-97 index at its own "
             "wavelength (an affine map of the grid's index at wavelength_um)"},
            {"min_index", lo},
            {"max_index", hi},
            {"map_max_error", water->max_error()}};
  }
  if (o.index_field)
    return "monochromatic: an index field at wavelength_um (only water density grids follow "
           "the wavelength)";
  if (o.dispersion.law == DispersionLaw::kNone)
    return "monochromatic: a constant index (no dispersion law)";
  double sum = 0, lo = 1e300, hi = -1e300;
  for (int k = 0; k < K; ++k) {
    const double n = o.dispersion.IndexAt(sp.Sample((k + 0.5) / K));
    sum += n, lo = std::min(lo, n), hi = std::max(hi, n);
  }
  return {{"mean_index", sum / K}, {"min_index", lo}, {"max_index", hi}};
}

/// The sidecar's "spectrum" block.
nlohmann::json SpectrumJson(const Scene& s) {
  const SpectrumSpec& sp = s.source.spectrum;
  nlohmann::json j_sp = {{"type", SpectrumTypeName(sp.type)},
                         {"mean_um", sp.mean_um()},
                         {"traced", s.is_spectral() ? "each ray near an object draws its wavelength"
                                                    : "monochromatic: no object has a "
                                                      "dispersion law"}};
  if (sp.type == SpectrumType::kGaussian) j_sp["center_um"] = sp.center_um;
  if (sp.type == SpectrumType::kGaussian) j_sp["fwhm_um"] = sp.fwhm_um;
  if (sp.type == SpectrumType::kLines) j_sp["wavelengths_um"] = sp.wavelengths_um;
  if (sp.type == SpectrumType::kLines) j_sp["weights"] = sp.weights;
  if (sp.type == SpectrumType::kFile) j_sp["file"] = sp.file;
  return j_sp;
}

/// The sidecar's "exposure" block (motion during the pulse).
nlohmann::json ExposureJson(const Scene& s) {
  const ExposureSpec& e = s.exposure;
  nlohmann::json ex = {
      {"pulse", PulseName(e.shape)},  // not "shape": tifffile reads a description
                                      // with a "shape" key as its own array metadata
      {"max_offset_us", e.max_offset_us()},
      {"convention",
       "objects' center_um is their position at the pulse's centre (top-hat: midpoint; "
       "Gaussian: peak, drawn within +-3 FWHM; file: power-weighted mean time)"}};
  if (e.shape == PulseShape::kTopHat) ex["duration_us"] = e.duration_us;
  if (e.shape == PulseShape::kGaussian) ex["fwhm_us"] = e.fwhm_us;
  if (e.shape == PulseShape::kFile) ex["file"] = e.file;
  return ex;
}

}  // namespace

/// The sidecar's objective block (both image models).
static nlohmann::json ObjectiveJson(const Scene& s) {
  return {{"na", s.optics.na},
          {"acceptance_sin_theta_in_medium", AcceptanceSin(s)},
          {"na_convention", "NA = medium_index x sin(theta_max) (docs/conventions.md)"},
          {"focal_length_mm", s.optics.objective_focal_mm},
          {"model", s.optics.model == ObjectiveModel::kSingle ? "single" : "two_lens"}};
}

/// The sidecar's image block (both image models).
static nlohmann::json ImageJson(const Scene& s, const Image& counts) {
  const PixelStats st = ComputeStats(counts);
  return {{"width", counts.width},
          {"height", counts.height},
          {"mean_counts", st.mean},
          {"max_counts", st.max},
          {"object_pixel_um", s.camera.pixel_pitch_um / std::abs(Magnification(s.optics))},
          {"magnification", Magnification(s.optics)},
          {"orientation",
           s.camera.flip ? "upright: +x right, +y up (inversion undone)" : "raw sensor: inverted"}};
}

nlohmann::json PlaneMetadata(const Simulator& sim, const PlaneResult& r, uint32_t plane_index) {
  const Scene& s = sim.scene();
  nlohmann::json fates = nlohmann::json::object();
  for (int i = 0; i < kNumFates; ++i) fates[FateName(Fate(i))] = r.counters.fates[i];
  nlohmann::json objects = nlohmann::json::array();
  for (size_t i = 0; i < s.objects.size(); ++i) {
    const ObjectSpec& o = s.objects[i];
    nlohmann::json obj = {{"name", o.name}, {"index", o.index}, {"material", o.material}};
    if (!o.density_source.empty()) {
      obj["density_kg_m3"] = o.density_kg_m3;
      obj["density"] = o.density_source == "given"
                           ? "given (density_kg_m3 in the scene)"
                           : "defaulted (Tanaka et al. 2001, Metrologia 38:301, at temperature_K)";
      obj["density_given"] = o.density_source == "given";
    }
    if (s.source.spectrum.type != SpectrumType::kNone)
      obj["over_the_spectrum"] = OverTheSpectrum(o, s, sim.WaterMapOf(int(i)));
    if (s.has_motion()) {  // each object's own motion (the exposure block: the pulse)
      const Vec3& v = o.velocity_um_per_us;
      obj["velocity_um_per_us"] = {v.x, v.y, v.z};
      obj["path_um"] = 2 * o.SweepUm(s.exposure.max_offset_us());
    }
    objects.push_back(obj);
  }
  // Debye path classes of the first departure from the first object hit: p = 0 reflected
  // externally, p >= 1 transmitted after p - 1 internal reflections (the last class: p >= 7).
  nlohmann::json path_classes = nlohmann::json::object();
  for (int k = 0; k < kNumPathClasses; ++k) {
    const std::string key = k == 0                     ? "p0_reflected"
                            : k == kNumPathClasses - 1 ? "p" + std::to_string(k) + "_or_more"
                                                       : "p" + std::to_string(k);
    path_classes[key] = r.counters.path_class[k];
  }
  nlohmann::json j = {
      {"provenance", ProvenanceJson()},
      {"scene_file", s.file},
      {"scene_checksum_fnv1a64", s.file.empty() ? "" : FileChecksum(s.file)},
      {"units", {{"pixel_values", "ray hits (photon counts)"}, {"lengths", "micrometres"}}},
      {"defocus_um", r.defocus_um},
      {"defocus_convention",
       "z of the objective's focal plane; + = focal plane moved downstream (towards the camera)"},
      {"seed", s.trace.seed},
      {"plane_index", plane_index},
      {"rays", r.rays},
      {"hits", r.counters.fates[int(Fate::kDetected)]},
      {"fates", fates},
      {"seconds", r.seconds},
      {"threads", r.threads},
      {"mpi_ranks", r.ranks},
      {"simd", r.simd ? std::string(SimdTarget()) + " packets (Google Highway)"
                      : "off (one ray at a time)"},
      {"rays_per_second", r.seconds > 0 ? r.rays / r.seconds : 0.0},
      {"effects", sim.Effects()},
      {"partial_reflection", PrName(s.trace.partial_reflection)},
      {"objective", ObjectiveJson(s)},
      {"path_classes", path_classes},
      {"counters",
       {{"interface_events", r.counters.interface_events},
        {"fresnel_evaluations", r.counters.fresnel_evaluations},
        {"corrector_tests", r.counters.corrector_tests},
        {"mesh_queries", r.counters.mesh_queries},
        {"rays_hitting_objects", r.counters.rays_hitting_objects},
        {"grin_segments", r.counters.grin_segments},
        {"grin_steps", r.counters.grin_steps},
        {"grin_uniform_steps", r.counters.grin_uniform_steps},
        {"motion_draws", r.counters.motion_draws},
        {"wavelength_draws", r.counters.wavelength_draws}}},
      {"image", ImageJson(s, r.counts)},
      {"wavelength_um", s.wavelength_um},
      {"medium_index", s.medium_index},
      {"objects", objects},
  };
  if (s.source.spectrum.type != SpectrumType::kNone) j["spectrum"] = SpectrumJson(s);
  if (s.has_motion()) j["exposure"] = ExposureJson(s);
  return j;
}

void CheckPlanePositions(const Scene& scene) {
  std::set<std::string> stems;
  for (double dz : scene.defocus_um)
    if (!stems.insert(PlaneStem(scene.name, dz)).second)
      throw Error(FileLocation{scene.file},
                  "focus position " + FormatDefocus(dz) +
                      " um is listed twice in defocus_um; each plane needs its own position");
}

bool CodeValues(const Scene& scene, const Image& counts, uint32_t plane_index, Image* code_values,
                nlohmann::json* entry) {
  if (!scene.camera.readout) return false;
  const CameraReadout& c = *scene.camera.readout;
  ReadoutCounts n;
  *code_values = ToCodeValues(counts, c, scene.trace.seed, kReadoutStream + plane_index, &n);
  *entry = {{"gain_e_per_dn", c.gain_e_per_dn},
            {"dark_dn", c.dark_dn},
            {"read_noise_e", c.read_noise_e},
            {"well_capacity_e", c.well_capacity_e},
            {"bit_depth", c.bit_depth},
            {"saturated_pixels", n.saturated},
            {"clipped_low_pixels", n.clipped_low},
            {"model",
             "counts as photoelectrons, clipped at the full well, + Gaussian read noise, / gain + "
             "dark level, rounded, clipped to [0, 2^bits - 1]"}};
  return true;
}

/// The scene file's name of a shape (as ReadObject reads it; revolutions and volume fractions
/// are meshes by then).
const char* ShapeName(ShapeType t) {
  switch (t) {
    case ShapeType::kSphere:
      return "sphere";
    case ShapeType::kEllipsoid:
      return "ellipsoid";
    case ShapeType::kBox:
      return "box";
    case ShapeType::kMesh:
      return "mesh";
  }
  return "";
}

/// One plane of an image model without rays (the exact wave image, physical optics): the
/// expected image, its Poisson photon counts and the sidecar.
template <class Imager>
PlaneResult ExpectedImagePlane(const Imager& mie, const char* optics, const char* model, double dz,
                               uint32_t plane_index, const RunControl& control,
                               nlohmann::json* meta) {
  const auto t0 = std::chrono::steady_clock::now();
  const Scene& s = mie.scene();
  PlaneResult r;
  r.defocus_um = dz;
  const int threads = control.threads > 0 ? control.threads : s.trace.threads;
  Image expected;
  if constexpr (std::is_same_v<Imager, PhysicalImager>)
    expected = mie.Expected(dz, threads, control.progress, control.label);
  else
    expected = mie.Expected(dz, threads);
  r.counts = PoissonSample(expected, s.trace.seed, plane_index);
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  nlohmann::json objects = nlohmann::json::array();
  for (const ObjectSpec& o : s.objects)
    objects.push_back({{"name", o.name},
                       {"type", ShapeName(o.shape)},
                       {"center_um", {o.center_um.x, o.center_um.y, o.center_um.z}},
                       {"radius_um", o.radius_um},
                       {"index", o.index},
                       {"absorption_index", o.absorption_index},
                       {"material", o.material}});
  *meta = {
      {"provenance", ProvenanceJson()},
      {"scene_file", s.file},
      {"scene_checksum_fnv1a64", s.file.empty() ? "" : FileChecksum(s.file)},
      {"units", {{"pixel_values", "photon counts"}, {"lengths", "micrometres"}}},
      {"optics", optics},
      {"model", model},
      {"sampling", mie.sampling().ToJson()},
      {"defocus_um", dz},
      {"defocus_convention",
       "z of the objective's focal plane; + = focal plane moved downstream (towards the camera)"},
      {"seed", s.trace.seed},
      {"plane_index", plane_index},
      {"photons_per_pixel_target", s.trace.photons_per_pixel},
      {"seconds", r.seconds},
      {"effects", mie.Effects()},
      {"objective", ObjectiveJson(s)},
      {"image", ImageJson(s, r.counts)},
      {"wavelength_um", s.wavelength_um},
      {"medium_index", s.medium_index},
      {"objects", objects},
  };
  return r;
}

PlaneResult MiePlane(const MieImager& mie, double dz, uint32_t plane_index,
                     const RunControl& control, nlohmann::json* meta) {
  return ExpectedImagePlane(
      mie, "mie",
      "exact wave image: Mie scattering of each illumination plane wave (unpolarised), "
      "partially coherent Koehler imaging through an aplanatic objective, Poisson photon "
      "counts of the expected image (docs/wave-optics.md)",
      dz, plane_index, control, meta);
}

PlaneResult PhysicalPlane(const PhysicalImager& phys, double dz, uint32_t plane_index,
                          const RunControl& control, nlohmann::json* meta) {
  return ExpectedImagePlane(
      phys, "physical",
      "physical optics: each illumination plane wave's angular spectrum behind the objects "
      "from rays that carry their field (Kirchhoff's shadow plus ray tubes on every Fresnel "
      "branch), imaged through an aplanatic objective, intensities summed over directions "
      "and polarisations, Poisson photon counts of the expected image "
      "(docs/physical-optics.md)",
      dz, plane_index, control, meta);
}

ScanSummary RunScan(const Scene& scene, const ScanOptions& opt) {
  const auto t0 = std::chrono::steady_clock::now();
  CheckPlanePositions(scene);
  // Every input (meshes, index fields, ray lists, the calibration) is read and checked while the
  // simulator is built, before the output folder is made: a refused input leaves no folder.
  const bool mie_optics = scene.trace.optics == ImageOptics::kMie;
  const bool physical = scene.trace.optics == ImageOptics::kPhysical;
  const bool wave = mie_optics || physical;
  std::unique_ptr<Simulator> sim_ptr;
  std::unique_ptr<MieImager> mie;
  std::unique_ptr<PhysicalImager> phys;
  if (mie_optics)
    mie = std::make_unique<MieImager>(scene);
  else if (physical)
    phys = std::make_unique<PhysicalImager>(scene);
  else
    sim_ptr = std::make_unique<Simulator>(scene);
  EnsureDirectory(opt.output_dir);
  ScanSummary sum;
  sum.index_json = (fs::path(opt.output_dir) / (scene.name + "_scan.json")).string();
  sum.index_csv = (fs::path(opt.output_dir) / (scene.name + "_scan.csv")).string();
  // The index describes one complete scan: a previous scan's index goes before the first plane
  // is written and the new one comes after the last, so an interrupted or failed scan leaves
  // no index listing planes it did not write (or planes of two different scans).
  RemoveStaleOutput(sum.index_json);
  RemoveStaleOutput(sum.index_csv);
  sum.effects = mie ? mie->Effects() : phys ? phys->Effects() : sim_ptr->Effects();
  if (wave) {
    sum.rays_per_image = 0;  // no rays: the expected image, then Poisson photon counts
  } else if (opt.rays) {
    sum.rays_per_image = *opt.rays;
  } else if (scene.trace.rays > 0) {
    sum.rays_per_image = scene.trace.rays;
  } else {
    sum.rays_per_image =
        sim_ptr->RaysForPhotonTarget(scene.trace.photons_per_pixel, &sum.hits_per_pixel_per_ray);
  }
  nlohmann::json planes = nlohmann::json::array();
  std::ostringstream csv;
  csv << "defocus_um,image,png,sidecar,rays,hits,mean_counts,seconds\n";
  for (size_t i = 0; i < scene.defocus_um.size(); ++i) {
    const double dz = scene.defocus_um[i];
    RunControl ctl = opt.control;
    char label[64];
    std::snprintf(label, sizeof label, "plane %zu/%zu z=%+.2f um", i + 1, scene.defocus_um.size(),
                  dz);
    ctl.label = label;
    PlaneResult r;
    nlohmann::json meta;
    if (mie) {
      r = MiePlane(*mie, dz, static_cast<uint32_t>(i), ctl, &meta);
    } else if (phys) {
      r = PhysicalPlane(*phys, dz, static_cast<uint32_t>(i), ctl, &meta);
    } else {
      r = sim_ptr->TracePlane(dz, static_cast<uint32_t>(i), sum.rays_per_image, ctl);
      meta = PlaneMetadata(*sim_ptr, r, static_cast<uint32_t>(i));
    }
    const std::string stem = PlaneStem(scene.name, dz);
    ScanPlaneOutput out;
    out.defocus_um = dz;
    out.image = (fs::path(opt.output_dir) / (stem + ".tif")).string();
    out.sidecar = (fs::path(opt.output_dir) / (stem + ".json")).string();
    Image code_values;
    nlohmann::json readout;
    if (CodeValues(scene, r.counts, static_cast<uint32_t>(i), &code_values, &readout)) {
      out.code_values = (fs::path(opt.output_dir) / (stem + "_dn.tif")).string();
      readout["image"] = fs::path(out.code_values).filename().string();
      meta["code_values"] = readout;
    }
    const std::string description = meta.dump();  // the TIFFs' ImageDescription
    WriteFloatImage(out.image, r.counts, description);
    if (!out.code_values.empty()) WriteUint16Image(out.code_values, code_values, description);
    WriteTextFileAtomic(out.sidecar, meta.dump(2) + "\n");
    if (opt.write_png) {
      out.png = (fs::path(opt.output_dir) / (stem + ".png")).string();
      std::vector<float> v = r.counts.pixels;
      std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
      WritePngPreview(out.png, r.counts, 0.0, std::max(1.0, 2.0 * v[v.size() / 2]));
    }
    out.mean_counts = ComputeStats(r.counts).mean;
    out.seconds = r.seconds;
    planes.push_back(
        {{"defocus_um", dz},
         {"image", fs::path(out.image).filename().string()},
         {"png", out.png.empty() ? "" : fs::path(out.png).filename().string()},
         {"sidecar", fs::path(out.sidecar).filename().string()},
         {"code_values",
          out.code_values.empty() ? "" : fs::path(out.code_values).filename().string()}});
    csv << FormatDefocus(dz) << "," << fs::path(out.image).filename().string() << ","
        << (out.png.empty() ? "" : fs::path(out.png).filename().string()) << ","
        << fs::path(out.sidecar).filename().string() << "," << r.rays << ","
        << r.counters.fates[int(Fate::kDetected)] << "," << out.mean_counts << "," << r.seconds
        << "\n";
    sum.planes.push_back(out);
  }
  sum.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const nlohmann::json index = {{"provenance", ProvenanceJson()},
                                {"scene_file", scene.file},
                                {"name", scene.name},
                                {"rays_per_image", sum.rays_per_image},
                                {"photons_per_pixel_target", scene.trace.photons_per_pixel},
                                {"effects", sum.effects},
                                {"optics", ImageOpticsName(scene.trace.optics)},
                                {"seconds", sum.seconds},
                                {"planes", planes}};
  WriteTextFileAtomic(sum.index_json, index.dump(2) + "\n");
  WriteTextFileAtomic(sum.index_csv, csv.str());
  return sum;
}

std::vector<OpticsComparisonPlane> CompareOptics(const Scene& scene, const ScanOptions& opt) {
  CheckPlanePositions(scene);
  if (!(scene.trace.photons_per_pixel > 0))
    throw Error(FileLocation{scene.file},
                "--compare-optics needs [trace] photons_per_pixel (or --photons-per-pixel): the "
                "difference is measured in units of that shot noise");
  Scene wave_scene = scene, ray_scene = scene;
  wave_scene.trace.optics = ImageOptics::kMie;
  ray_scene.trace.optics = ImageOptics::kRays;
  const MieImager mie(wave_scene);  // throws for scenes without an exact wave image
  const Simulator sim(ray_scene);
  std::unique_ptr<PhysicalImager> phys;
  if (scene.trace.optics == ImageOptics::kPhysical) phys = std::make_unique<PhysicalImager>(scene);
  const uint64_t rays = sim.RaysForPhotonTarget(scene.trace.photons_per_pixel);
  EnsureDirectory(opt.output_dir);
  std::vector<OpticsComparisonPlane> out;
  std::ostringstream csv;
  csv << "defocus_um,chi2_per_pixel,max_abs_z,wave_image,ray_image,z_image"
      << (phys ? ",chi2_physical,max_abs_z_physical,physical_image,z_physical_image" : "") << "\n";
  for (size_t i = 0; i < scene.defocus_um.size(); ++i) {
    const double dz = scene.defocus_um[i];
    RunControl ctl = opt.control;
    const Image wave = mie.Expected(dz, ctl.threads > 0 ? ctl.threads : scene.trace.threads);
    const Image ray = sim.TracePlane(dz, static_cast<uint32_t>(i), rays, ctl).counts;
    OpticsComparisonPlane p;
    p.defocus_um = dz;
    // z = (image - wave) / sqrt(wave) with its mean square and largest magnitude.
    auto against_wave = [&](const Image& a, double* chi2, double* max_abs) {
      Image z(wave.width, wave.height);
      double sum = 0;
      for (size_t q = 0; q < wave.size(); ++q) {
        const double e = std::max(double(wave.pixels[q]), 1.0);
        const double v = (double(a.pixels[q]) - wave.pixels[q]) / std::sqrt(e);
        z.pixels[q] = float(v);
        sum += v * v;
        *max_abs = std::max(*max_abs, std::abs(v));
      }
      *chi2 = sum / double(wave.size());
      return z;
    };
    const Image z = against_wave(ray, &p.chi2_per_pixel, &p.max_abs_z);
    Image physical, z_physical;
    if (phys) {
      physical = phys->Expected(dz, ctl.threads > 0 ? ctl.threads : scene.trace.threads,
                                ctl.progress, "physical optics");
      z_physical = against_wave(physical, &p.chi2_physical, &p.max_abs_z_physical);
      p.physical = true;
    }
    const std::string stem = PlaneStem(scene.name, dz);
    const fs::path dir(opt.output_dir);
    p.wave_image = (dir / (stem + "_mie.tif")).string();
    p.ray_image = (dir / (stem + "_rays.tif")).string();
    p.z_image = (dir / (stem + "_z.tif")).string();
    const nlohmann::json meta = {
        {"provenance", ProvenanceJson()},
        {"scene_file", scene.file},
        {"defocus_um", dz},
        {"photons_per_pixel", scene.trace.photons_per_pixel},
        {"rays_per_image", rays},
        {"mie_sampling", mie.sampling().ToJson()},
        {"z", "(rays - wave) / sqrt(wave): the difference in units of the shot noise"},
        {"chi2_per_pixel", p.chi2_per_pixel}};
    WriteFloatImage(p.wave_image, wave, meta.dump());
    WriteFloatImage(p.ray_image, ray, meta.dump());
    WriteFloatImage(p.z_image, z, meta.dump());
    auto preview = [&](const Image& zi, const std::string& path) {
      Image shifted = zi;
      for (float& v : shifted.pixels) v += 5.0f;  // z = -5 .. 5 on the preview's 0 .. 10
      WritePngPreview(path, shifted, 0.0, 10.0);
    };
    if (opt.write_png) preview(z, p.z_png = (dir / (stem + "_z.png")).string());
    csv << FormatDefocus(dz) << "," << p.chi2_per_pixel << "," << p.max_abs_z << ","
        << fs::path(p.wave_image).filename().string() << ","
        << fs::path(p.ray_image).filename().string() << ","
        << fs::path(p.z_image).filename().string();
    if (phys) {
      nlohmann::json pm = meta;
      pm["physical_sampling"] = phys->sampling().ToJson();
      pm["z"] =
          "(physical - wave) / sqrt(wave): the physical image's difference in units of the "
          "shot noise (it has no noise itself)";
      pm["chi2_per_pixel"] = p.chi2_physical;
      p.physical_image = (dir / (stem + "_physical.tif")).string();
      p.z_physical_image = (dir / (stem + "_z_physical.tif")).string();
      WriteFloatImage(p.physical_image, physical, pm.dump());
      WriteFloatImage(p.z_physical_image, z_physical, pm.dump());
      if (opt.write_png) preview(z_physical, (dir / (stem + "_z_physical.png")).string());
      csv << "," << p.chi2_physical << "," << p.max_abs_z_physical << ","
          << fs::path(p.physical_image).filename().string() << ","
          << fs::path(p.z_physical_image).filename().string();
    }
    csv << "\n";
    out.push_back(p);
  }
  WriteTextFileAtomic((fs::path(opt.output_dir) / (scene.name + "_optics.csv")).string(),
                      csv.str());
  return out;
}

}  // namespace raymatch::simulate
