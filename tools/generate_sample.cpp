// Generates datasets-sample/: a synthetic but experiment-like calibration and measurement set
// with recorded ground truth (datasets-sample/README.md). Usage:
//   build/release/tools/generate_sample OUTDIR [--quick] [--seed N] [--drop-radius-um R]
//                                              [--psf-sigma-um S]
// --quick: 1/16 of the photons (for the golden pipeline test); same geometry and truth.
// --drop-radius-um, --psf-sigma-um: another truth for the drop's radius and the camera's PSF,
// with the metadata unchanged (nominal diameter 46 um), so that the pipeline starts away from
// the truth as it does with a real drop.
//
// What makes it realistic, beyond the simulator's physics: a light field that is not an ideal
// cone (soft edge beyond the objective NA, radial and azimuthal non-uniformity, tilted axis),
// angle-dependent losses (corrector truth), a diffraction-limited PSF, camera gain, read noise,
// dark offset and 12-bit quantisation stored in 16-bit files, an exposure and a drop position
// the pipeline must recover. The pipeline reads only the images and the per-folder metadata.
#include <CLI/CLI.hpp>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <sstream>

#include "raymatch/core/atomic_file.h"
#include "raymatch/core/camera_readout.h"
#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/provenance.h"
#include "raymatch/simulate/shapes.h"
#include "raymatch/simulate/tracer.h"
#include "raymatch/simulate/water.h"

namespace fs = std::filesystem;
using namespace raymatch;
using namespace raymatch::simulate;

namespace {

constexpr double kDeg = M_PI / 180;

struct Truth {
  // Illumination: radiance vs angle theta from the (tilted) cone axis, in direction cosines.
  double edge_deg = 25.5, edge_width_deg = 1.2;  // soft edge beyond asin(NA) = 24.8 deg
  double radial_rise = 0.10;                     // L ~ 1 + rise (theta/edge)^2
  double azimuthal = 0.06, azimuth_deg = 40;     // L ~ 1 + a (sin t / sin edge) cos(phi - az)
  double tilt_deg = 0.8, tilt_azimuth_deg = 120;
  std::vector<double> iris_deg = {3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 30};  // flats
  std::vector<double> corrector = {1, 0.998, 0.995, 0.99, 0.982, 0.97, 0.95, 0.92, 0.88};
  // Camera (a 12-bit high-speed camera, 10 um pixels).
  double well_e = 4500, gain_e_per_dn = 4500.0 / 4095, read_noise_e = 6, dark_dn = 64;
  double signal = 0.56;                       // flat-field exposure (fraction of the well)
  double psf_sigma_um = 0.21 * 0.462 / 0.42;  // diffraction-limited (Gaussian approx.)
  int nx = 160, ny = 120;
  double pitch_um = 10;
  // The drop and the merging drops.
  double radius_um = 23.0, temperature_K = 293.15;
  Vec3 drop_center_um{1.3, -0.7, 0.8};
  double merging_tilt_deg = 12, merging_defocus_um = 6;  // merging/merging_tilted.tif
  std::vector<double> defocus_um = {-20, -15, -10, -5, 0, 5, 10, 15, 20};
  std::vector<double> cone_dz_um = {20, 30, 40};
  double pinhole_diameter_um = 2.0;
};

double Radiance(const Truth& t, double u, double v, double iris_deg) {
  // Rotate (u, v) into the tilted cone's frame (small-angle: shift in direction cosines).
  const double tu = std::sin(t.tilt_deg * kDeg) * std::cos(t.tilt_azimuth_deg * kDeg);
  const double tv = std::sin(t.tilt_deg * kDeg) * std::sin(t.tilt_azimuth_deg * kDeg);
  const double du = u - tu, dv = v - tv;
  const double s = std::hypot(du, dv);
  if (s >= 1) return 0;
  const double theta = std::asin(s) / kDeg, phi = std::atan2(dv, du);
  const double edge = 0.5 * (1 - std::tanh((theta - t.edge_deg) / t.edge_width_deg));
  const double iris = 0.5 * (1 - std::tanh((std::asin(std::hypot(u, v)) / kDeg - iris_deg) / 0.4));
  return edge * iris * (1 + t.radial_rise * std::pow(theta / t.edge_deg, 2)) *
         (1 + t.azimuthal * s / std::sin(t.edge_deg * kDeg) * std::cos(phi - t.azimuth_deg * kDeg));
}

Image AngularMap(const Truth& t, double iris_deg) {
  const int n = 128;
  const double ext = 0.5;
  Image m(n, n);
  for (int y = 0; y < n; ++y)
    for (int x = 0; x < n; ++x) {
      double sum = 0;  // 4x4 supersampling per cell
      for (int a = 0; a < 4; ++a)
        for (int b = 0; b < 4; ++b) {
          const double u = (2 * (x + (a + 0.5) / 4) / n - 1) * ext;
          const double v = (1 - 2 * (y + (b + 0.5) / 4) / n) * ext;
          sum += Radiance(t, u, v, iris_deg);
        }
      m.at(x, y) = float(sum / 16);
    }
  return m;
}

Scene BaseScene(const Truth& t, double iris_deg, bool corrector) {
  Scene s;
  s.name = "truth";
  s.wavelength_um = 0.462;
  s.source.type = SourceType::kLightField;
  s.source.angular_map = AngularMap(t, iris_deg);
  s.source.angular_extent = 0.5;
  s.optics.objective_focal_mm = 10;
  s.optics.na = 0.42;
  s.optics.working_distance_mm = 20;
  s.optics.tube_focal_mm = 200;
  if (corrector) {
    s.optics.corrector.enabled = true;
    s.optics.corrector.transmissions = t.corrector;
  }
  s.camera.nx = t.nx;
  s.camera.ny = t.ny;
  s.camera.pixel_pitch_um = t.pitch_um;
  s.camera.psf_sigma_um = t.psf_sigma_um;
  s.trace.partial_reflection = PartialReflection::kUnpolarized;
  return s;
}

/// Photon counts -> camera code values: read noise (electrons), gain, dark offset, 12 bits.
Image Expose(const Truth& t, const Image& photons, uint64_t seed, uint32_t stream) {
  CameraReadout cam;
  cam.gain_e_per_dn = t.gain_e_per_dn, cam.dark_dn = t.dark_dn, cam.read_noise_e = t.read_noise_e;
  cam.well_capacity_e = t.well_e, cam.bit_depth = 12;
  return ToCodeValues(photons, cam, seed, stream);
}

class Writer {
 public:
  Writer(fs::path root, uint64_t seed) : root_(std::move(root)), seed_(seed) {}
  void Image16(const std::string& rel, const Image& photons, const std::string& what) {
    const fs::path p = root_ / rel;
    EnsureDirectory(p.parent_path());
    WriteUint16Image(p.string(), Expose(truth, photons, seed_, stream_++),
                     "raymatch synthetic sample: " + what + " (12-bit data in 16-bit file)");
    std::cout << "  " << rel << "\n";
  }
  Truth truth;

 private:
  fs::path root_;
  uint64_t seed_;
  uint32_t stream_ = 1000;
};

Image Trace(const Scene& s, double defocus, uint64_t rays, uint32_t plane) {
  RunControl ctl;
  ctl.progress = false;
  return Simulator(s).TracePlane(defocus, plane, rays, ctl).counts;
}

std::string Join(const std::vector<double>& v) {
  std::ostringstream os;
  for (size_t i = 0; i < v.size(); ++i) os << (i ? ", " : "") << v[i];
  return os.str();
}

const char* kCameraToml = R"([camera]
pixel_pitch_um = 10        # sensor pixel pitch
bit_depth = 12             # data bits (stored in 16-bit files)
gain_e_per_dn = 1.0989011  # electrons per code value (datasheet)
well_capacity_e = 4500     # full-well capacity (datasheet)
read_noise_e = 6           # datasheet

[optics]
objective_focal_mm = 10
na = 0.42
working_distance_mm = 20
tube_focal_mm = 200
wavelength_um = 0.462
)";

}  // namespace

int main(int argc, char** argv) {
  SetCommandLine(argc, argv);
  CLI::App app{"Generate the raymatch synthetic sample data set (datasets-sample/)."};
  std::string out;
  bool quick = false;
  uint64_t seed = 20261122;
  app.add_option("outdir", out, "Output directory")->required();
  app.add_flag("--quick", quick, "1/16 of the photons (golden tests)");
  app.add_option("--seed", seed, "Random seed");
  Truth truth;
  app.add_option("--drop-radius-um", truth.radius_um,
                 "The drop's true radius in um (the metadata's nominal diameter stays 46 um)")
      ->check(CLI::Range(15.0, 30.0))
      ->capture_default_str();
  app.add_option("--psf-sigma-um", truth.psf_sigma_um,
                 "The camera PSF's true Gaussian sigma at the object in um")
      ->check(CLI::Range(0.0, 2.0))
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  try {
    Writer w(out, seed);
    w.truth = truth;
    const Truth& t = w.truth;
    const double scale = quick ? 1.0 / 16 : 1.0;
    const double photons = t.signal * t.well_e;
    uint32_t plane = 0;

    // --- Light field: pinhole in focus, then the cone at dz downstream; darks.
    std::cout << "light field\n";
    Scene ph = BaseScene(t, 90, false);
    ph.source.field_radius_um = t.pinhole_diameter_um / 2;
    ph.source.field_shape = FieldShape::kDisc;
    w.Image16("lightfield/pinhole.tif", Trace(ph, 0, uint64_t(3.5e4), plane++),
              "pinhole in focus");  // ~2500 e- peak
    for (double dz : t.cone_dz_um) {
      const double area_px = M_PI * std::pow(dz * std::tan(std::asin(0.42)), 2) / 0.25;
      w.Image16("lightfield/cone_dz" + std::to_string(int(dz)) + ".tif",
                Trace(ph, dz, uint64_t(0.5 * photons * area_px * scale), plane++),
                "light cone, focus " + std::to_string(dz) + " um beyond the pinhole");
    }
    w.Image16("lightfield/dark.tif", Image(t.nx, t.ny), "dark frame");
    std::ofstream(fs::path(out) / "lightfield/metadata.toml")
        << "# Pinhole and light-cone images for `raymatch calibrate lightfield`.\n"
        << "pinhole = \"pinhole.tif\"\npinhole_diameter_um = " << t.pinhole_diameter_um
        << "\ndark = \"dark.tif\"\n"
        << "# The illumination is uniform over the view here; a non-uniform one would be measured\n"
        << "# with a flat field (flat = \"../flatfield/flat_iris30deg.tif\", "
           "docs/calibration.md).\n\n"
        <<
        [&] {
          std::string s;
          for (double dz : t.cone_dz_um)
            s += "[[cone]]\nfile = \"cone_dz" + std::to_string(int(dz)) +
                 ".tif\"\ndz_um = " + std::to_string(int(dz)) + "   # focus beyond the pinhole\n\n";
          return s;
        }()
        << kCameraToml;

    // --- Flat-field iris series with corrector losses; each iris with its cone image.
    std::cout << "flat fields\n";
    const double open_sum = [&] {
      double s = 0;
      for (float v : AngularMap(t, 90).pixels) s += v;
      return s;
    }();
    Scene flat_open = BaseScene(t, 90, true);
    const uint64_t rays_open = Simulator(flat_open).RaysForPhotonTarget(photons * scale);
    std::string iris_toml;
    for (double iris : t.iris_deg) {
      Scene f = BaseScene(t, iris, true);
      double sum = 0;
      for (float v : f.source.angular_map.pixels) sum += v;
      const uint64_t rays = uint64_t(rays_open * sum / open_sum);  // same lamp, iris blocks light
      const std::string tag = "iris" + std::to_string(int(iris)) + "deg";
      w.Image16("flatfield/flat_" + tag + ".tif", Trace(f, 0, rays, plane++), "flat field " + tag);
      // The cone through the pinhole. The corrector fit needs the relative amount of light of
      // each iris, so the lamp is the same for all and the exposure time is recorded: a narrow
      // cone is exposed longer (1, 2, 5, 10, ...x) so its mean over the lit disc is at least
      // ~1/3 of the well (as an experimenter would; read noise would otherwise dominate).
      Scene c = BaseScene(t, iris, false);
      c.source.field_radius_um = t.pinhole_diameter_um / 2;
      const double open_px = M_PI * std::pow(30 * std::tan(24.8 * kDeg), 2) / 0.25;
      const double lit_px =
          M_PI *
          std::pow(30 * std::tan(std::min(iris, 24.8) * kDeg) + t.pinhole_diameter_um / 2, 2) /
          0.25;
      const double per_px = 0.25 * photons * open_px * sum / open_sum / lit_px;
      int exposure = 1;
      for (int e : {2, 5, 10, 20, 50, 100})
        if (e * per_px < 0.35 * t.well_e) exposure = e;
      w.Image16("flatfield/cone_" + tag + ".tif",
                Trace(c, 30, uint64_t(exposure * 0.25 * photons * open_px * scale * sum / open_sum),
                      plane++),
                "cone for " + tag + " (relative exposure " + std::to_string(exposure) + ")");
      iris_toml += "[[flat]]\nfile = \"flat_" + tag + ".tif\"\ncone = \"cone_" + tag +
                   ".tif\"\ncone_dz_um = 30\ncone_exposure = " + std::to_string(exposure) +
                   "   # relative to the flat fields' exposure (same lamp)\n\n";
    }
    w.Image16("flatfield/dark.tif", Image(t.nx, t.ny), "dark frame");
    std::ofstream(fs::path(out) / "flatfield/metadata.toml")
        << "# Flat fields (no object) at several illumination apertures, each with the image of\n"
        << "# its light cone through a pinhole (same lamp; cone_exposure = relative exposure "
           "time), for\n"
        << "# `raymatch calibrate corrector`.\n"
        << "dark = \"dark.tif\"\npinhole_diameter_um = " << t.pinhole_diameter_um << "\n\n"
        << iris_toml << kCameraToml;

    // --- The experiment: a 46 um water drop, focus scan.
    std::cout << "drop focus scan\n";
    Scene drop = BaseScene(t, 90, true);
    ObjectSpec o;
    o.shape = ShapeType::kSphere;
    o.radius_um = t.radius_um;
    o.center_um = t.drop_center_um;
    o.index = WaterRefractiveIndex(t.temperature_K, WaterDensityTanaka(t.temperature_K), 0.462).n;
    drop.objects = {o};
    drop.defocus_um = t.defocus_um;
    // Exposure of the drop images: the flat-field level of this very scene (its source field is
    // larger than the flat field's, because it must cover the drop and the defocus range).
    const uint64_t rays_drop = Simulator(drop).RaysForPhotonTarget(photons * scale);
    std::string csv = "defocus_um,file\n";
    for (size_t i = 0; i < t.defocus_um.size(); ++i) {
      char name[64];
      std::snprintf(name, sizeof name, "drop_z%+03dum.tif", int(t.defocus_um[i]));
      w.Image16(std::string("drop46/") + name, Trace(drop, t.defocus_um[i], rays_drop, plane++),
                "46 um water drop, defocus " + std::to_string(t.defocus_um[i]) + " um");
      csv += std::to_string(int(t.defocus_um[i])) + "," + name + "\n";
    }
    w.Image16("drop46/dark.tif", Image(t.nx, t.ny), "dark frame");
    std::ofstream(fs::path(out) / "drop46/scan.csv") << csv;
    std::ofstream(fs::path(out) / "drop46/metadata.toml")
        << "# Focus scan of a free-falling water drop (nominal diameter 46 um, 20 degC).\n"
        << "scan = \"scan.csv\"          # defocus_um,file (+ = focal plane towards the camera)\n"
        << "dark = \"dark.tif\"\nobject = \"water drop\"\nnominal_diameter_um = 46\n"
        << "temperature_K = 293.15\n\n"
        << kCameraToml;

    // --- Merging drops: a revolved two-lobe outline, axis horizontal in the image.
    std::cout << "merging drops\n";
    Outline outline;
    for (int i = 0; i <= 240; ++i) {
      const double z = -30 + 56.0 * i / 240;  // lobes: R 18 at z = -10, R 14 at z = +12
      const double r1 = 18 * 18 - (z + 10) * (z + 10), r2 = 14 * 14 - (z - 12) * (z - 12);
      const double neck = 9.0;  // smoothed neck radius
      double r = std::sqrt(std::max({r1, r2, 0.0}));
      if (z > -2 && z < 6) r = std::max(r, neck);
      outline.push_back({i == 0 || i == 240 ? 0.0 : r, z});
    }
    const TriangleMesh mesh = RevolveOutline(outline, 128);
    {
      std::ostringstream obj;
      obj << "# merging drops: revolved outline, axis = local z, micrometres\n";
      for (const Vec3& v : mesh.vertices) obj << "v " << v.x << " " << v.y << " " << v.z << "\n";
      for (const auto& tri : mesh.triangles)
        obj << "f " << tri[0] + 1 << " " << tri[1] + 1 << " " << tri[2] + 1 << "\n";
      EnsureDirectory(fs::path(out) / "merging");
      WriteTextFileAtomic(fs::path(out) / "merging/merging_drops.obj", obj.str());
    }
    Scene merge = BaseScene(t, 90, true);
    ObjectSpec m;
    m.shape = ShapeType::kMesh;
    m.mesh = std::make_shared<TriangleMesh>(mesh);
    m.rotation_deg = {0, 90, 0};  // local z -> world x: the axis runs horizontally
    m.index = o.index;
    merge.objects = {m};
    w.Image16("merging/merging_z+00um.tif",
              Trace(merge, 0, Simulator(merge).RaysForPhotonTarget(photons * scale), plane++),
              "merging drops");
    w.Image16("merging/dark.tif", Image(t.nx, t.ny), "dark frame");
    // The same drops tilted out of the image plane and defocused: the fit demo of the paper's
    // Fig. 9 (grid scan of defocus and tilt). Written after every other image, so their noise
    // streams and planes are unchanged.
    Scene tilted = merge;
    tilted.objects[0].rotation_deg = {0, 90 - t.merging_tilt_deg, 0};
    tilted.defocus_um = {t.merging_defocus_um};
    w.Image16("merging/merging_tilted.tif",
              Trace(tilted, t.merging_defocus_um,
                    Simulator(tilted).RaysForPhotonTarget(photons * scale), plane++),
              "merging drops tilted " + std::to_string(t.merging_tilt_deg) + " deg, defocus " +
                  std::to_string(t.merging_defocus_um) + " um");
    std::ofstream(fs::path(out) / "merging/metadata.toml")
        << "# Two merging water drops in focus; their shape as a mesh (from a CFD-like model).\n"
        << "image = \"merging_z+00um.tif\"\ndefocus_um = 0\ndark = \"dark.tif\"\n"
        << "mesh = \"merging_drops.obj\"     # micrometres; axis = local z\n"
        << "mesh_rotation_deg = [0, 90, 0]   # local z -> image x\n\n"
        << kCameraToml;

    // --- Ground truth (never read by the pipeline).
    std::ostringstream tr;
    tr << "# Ground truth of the synthetic sample; the pipeline never reads this file.\n"
       << "generator = \"tools/generate_sample.cpp\"\nseed = " << seed
       << "\nquick = " << (quick ? "true" : "false") << "\ncommand_line = \"" << CommandLine()
       << "\"\n\n"
       << "[light_field]\nedge_half_angle_deg = " << t.edge_deg
       << "\nedge_width_deg = " << t.edge_width_deg << "\nradial_rise = " << t.radial_rise
       << "\nazimuthal_amplitude = " << t.azimuthal << "\nazimuth_deg = " << t.azimuth_deg
       << "\ntilt_deg = " << t.tilt_deg << "\ntilt_azimuth_deg = " << t.tilt_azimuth_deg
       << "\nmeasured_cut_deg = " << std::asin(0.42) / kDeg << "   # objective NA\n\n"
       << "[corrector]\ntransmissions = [" << Join(t.corrector) << "]\n"
       << "ring_outer_mm = \"default: 9 equal-width zones to 1.02 x WD tan(asin NA)\"\n\n"
       << "[camera]\nsignal = " << t.signal << "\nphotons_per_pixel = " << photons * scale
       << "\ngain_e_per_dn = " << t.gain_e_per_dn << "\nread_noise_e = " << t.read_noise_e
       << "\ndark_dn = " << t.dark_dn << "\npsf_sigma_um = " << t.psf_sigma_um << "\n\n"
       << "[drop]\nradius_um = " << t.radius_um << "\ncenter_um = [" << t.drop_center_um.x << ", "
       << t.drop_center_um.y << ", " << t.drop_center_um.z << "]\nindex = " << o.index
       << "\n# best-matching simulated defocus for experimental defocus d: d - center z\n\n"
       << "[merging_tilted]\nimage = \"merging/merging_tilted.tif\"\ntilt_deg = "
       << t.merging_tilt_deg << "   # axis tilted out of the image plane: mesh rotation_deg = [0, "
       << 90 - t.merging_tilt_deg << ", 0]\ndefocus_um = " << t.merging_defocus_um << "\n";
    WriteTextFileAtomic(fs::path(out) / "truth.toml", tr.str());
    std::cout << "done: " << out << "\n";
  } catch (const Error& e) {
    std::cerr << "generate_sample: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
