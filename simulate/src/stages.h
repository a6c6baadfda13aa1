#pragma once
// What the tracer's stages share between the scalar path and the SIMD packet path, apart from
// the stage functions themselves (stages-inl.h): the optics' description, the outcome codes of
// the packet path, limits both paths obey, and the one-lane "vector" the scalar path traces with.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <utility>
#include <vector>

#include "raymatch/core/image.h"
#include "raymatch/simulate/tracer.h"

namespace raymatch::simulate {

struct Scene;

/// Objects a ray can be inside at once (nested objects: a bubble in a drop). One level more
/// ends the ray as lost inside, on both paths.
inline constexpr int kMaxNesting = 16;

/// An ideal thin lens.
struct Lens {
  double z = 0;      ///< plane (um)
  double f = 0;      ///< focal length (um)
  double rim = 0;    ///< rim radius (um), 0 = none
  double power = 0;  ///< 1 / f: a slope changes by -x / f, done as a product (divisions are slow)
};

/// Everything after the objects: corrector zones, ideal lenses with the aperture stop, sensor.
/// MakeOptics gives the planes at defocus 0; `Shifted` moves them by a plane's defocus, and both
/// paths trace with that copy.
struct Optics {
  bool corrector = false;  ///< a corrector stage (no zones: every ray is outside)
  double corrector_z = 0;
  std::vector<double> ring_outer2;  ///< squared outer radii of the zones (um^2), ascending
  std::vector<double> ring_t;       ///< their transmissions
  Lens lenses[3];                   ///< objective (1 or 2) + tube lens
  int num_lenses = 0;
  int stop_after = 0;  ///< the stop plane comes before lens stop_after (after the objective)
  double stop_z = 0, stop_r2 = 0;
  double sensor_z = 0;
  double pitch = 0, inv_pitch = 0, off_x = 0, off_y = 0, sign = -1;
  double psf_sigma_sensor = 0;  ///< Gaussian PSF at the sensor (um), 0 = none (packets: PsfDraws)
  int nx = 0, ny = 0;

  /// This optics with every plane moved by `defocus` (um).
  Optics Shifted(double defocus) const {
    Optics o = *this;
    o.corrector_z += defocus;
    for (int l = 0; l < num_lenses; ++l) o.lenses[l].z += defocus;
    o.stop_z += defocus;
    o.sensor_z += defocus;
    return o;
  }
};

/// The scene's optics at defocus 0.
Optics MakeOptics(const Scene& s);

// What the image models without rays (wave_image.cpp, physical_image.cpp) share.

/// The object-plane point of the sensor position (col, row) in pixels (pixel centres at +0.5):
/// the inverse of the tracer's sensor stage (camera offset, flip, magnification); `sensor_sign`
/// is the optics' sign times the magnification.
std::pair<double, double> SensorToObject(const CameraSpec& cam, double sensor_sign, double col,
                                         double row);

/// Light from an object of radius `radius_um` whose centre lies `dz` before the focal plane
/// reaches that plane within rho_light of its axis; the window adds `margin` for the pupil's
/// diffraction tails (periodic wrap-around): `margin_um`, or 0 for 8 um + 8 lambda / NA.
struct WaveWindow {
  double rho_light, margin;
};
WaveWindow WaveWindowFor(const Scene& s, double margin_um, double radius_um, double dz);

/// The flat field's photons per pixel an image model without rays is scaled to: [trace]
/// photons_per_pixel, or with a ray count instead the ray model's flat field of that many rays.
double FlatFieldPhotons(const Scene& s);

/// Pixel sub-samples per side: `setting`, or 0 for a spacing of at most lambda_medium / (8 s_na)
/// on a pixel `pixel_object_um` wide at the object.
int PixelSubsamples(int setting, double pixel_object_um, double lambda_medium, double s_na);

/// The corrector's zones as angles: the ray model's zones (MakeOptics: radii at the corrector
/// plane) seen from the focal plane's axis point, r = d tan(theta), as outer edges in sin(theta)
/// with their intensity transmissions (empty without a corrector).
struct CorrectorZones {
  std::vector<double> s, t;
  /// The transmission of light at sin(theta) = `sin_theta` (1 without a corrector; 0 beyond
  /// the last zone).
  double At(double sin_theta) const {
    if (s.empty()) return 1;
    for (size_t i = 0; i < s.size(); ++i)
      if (sin_theta <= s[i]) return t[i];
    return 0;
  }
};
CorrectorZones CorrectorZonesOf(const Scene& scene);

/// A light field's angular density over direction cosines (u, v), as the image models without
/// rays sample it: the measured map, continued beyond the NA under the fitted edge where one is
/// set (ContinuedMap), zero outside it and beyond sin(theta) = 1; `breaks`, the radii in
/// sin(theta) where it changes abruptly (the map's NA limit and the edge ring inside it);
/// `s_max`, the largest sin(theta) the map spans (below 0.999), and `reach`, the largest its
/// non-zero cells reach.
struct AngularDensity {
  std::shared_ptr<const Image> map;
  double extent = 0, pu = 0;
  std::vector<double> breaks;
  double s_max = 0, reach = 0;
  double operator()(double u, double v) const {
    if (u * u + v * v >= 1) return 0.0;
    const int x = int(std::floor((u + extent) / pu)), y = int(std::floor((extent - v) / pu));
    if (x < 0 || y < 0 || x >= map->width || y >= map->height) return 0.0;
    return double(map->at(x, y));
  }
};
AngularDensity LightFieldDensity(const SourceSpec& ss);

/// A light field's spatial map as an envelope of the image (the image models without rays):
/// its value at an object-plane point (1 without a map; 0 beyond it unless it extends).
struct SpatialEnvelope {
  Image map;
  double x0 = 0, y0 = 0, w = 0, h = 0;
  bool clamp = false;
  bool empty() const { return map.empty(); }
  double At(double x, double y) const {
    if (map.empty()) return 1;
    const double fx = (x - x0) / w + 0.5, fy = 0.5 - (y - y0) / h;
    int cx = int(std::floor(fx * map.width)), cy = int(std::floor(fy * map.height));
    if (!clamp && (cx < 0 || cy < 0 || cx >= map.width || cy >= map.height)) return 0;
    cx = std::clamp(cx, 0, map.width - 1);
    cy = std::clamp(cy, 0, map.height - 1);
    return map.at(cx, cy);
  }
  /// Its mean over the sensor's pixel centres (1 without a map): the flat field's mean over
  /// the sensor stays the photon target when the image is scaled by it.
  double MeanOverSensor(const CameraSpec& cam, double sensor_sign) const;
};
SpatialEnvelope SpatialEnvelopeOf(const Scene& scene);

/// A soft edge's tail (radiance falling as exp(-2 (theta - edge) / width)) reaches to the end of
/// a light field's map with radiances of 1e-12 and less, and each direction there would cost a
/// field: the outermost rings of illumination directions that together carry less than this
/// share of the source's power are left out (their light, direct or scattered, is that share
/// of the image's or less).
inline constexpr double kTailPower = 1e-9;

/// Of rings of directions given as (sin theta, power), the sin theta from which on (>=) the
/// outermost ones together carry less than kTailPower of the power (2: none).
double TailStart(std::vector<std::pair<double, double>> rings);

/// Whether the packet path can trace a scene, and if not, why (Simulator::Effects lists it).
struct PacketSupport {
  bool ok = false;
  const char* reason = "";  ///< why not: a short phrase
};

namespace packet {
// What became of a lane of the packet path (Rays::out): a pixel index (>= 0), a fate's code
// (FateCode: minus the fate's number), or one of the two codes after the fates.
constexpr double FateCode(Fate f) { return -static_cast<double>(static_cast<int>(f)); }
inline constexpr double kScalar = -double(kNumFates);    ///< trace on the scalar path
inline constexpr double kNear = -double(kNumFates + 1);  ///< split mode: meets the split sphere
/// The fates the packet stages give (the others come from the scalar path only).
inline constexpr Fate kPacketFates[] = {Fate::kOutsideNa,         Fate::kMissedSensor,
                                        Fate::kAbsorbedCorrector, Fate::kInteractionCap,
                                        Fate::kEscaped,           Fate::kLostInside};
}  // namespace packet

namespace stages {

/// One lane: the scalar path's instantiation of the stages (stages-inl.h). A vector type of the
/// same shape (stages-inl.h, VecLanes) gives the packet path's.
struct ScalarLanes {
  using V = double;
  using M = bool;
  using I = int64_t;  ///< integer lanes (indices) beside V
  using MI = bool;
  static constexpr bool kOneLane = true;
  static V Set(double x) { return x; }
  static V Add(V a, V b) { return a + b; }
  static V Sub(V a, V b) { return a - b; }
  static V Mul(V a, V b) { return a * b; }
  static V Div(V a, V b) { return a / b; }
  static V Neg(V a) { return -a; }
  static V Sqrt(V a) { return std::sqrt(a); }
  static V Floor(V a) { return std::floor(a); }
  static M Lt(V a, V b) { return a < b; }
  static M Le(V a, V b) { return a <= b; }
  static M Gt(V a, V b) { return a > b; }
  static M Ge(V a, V b) { return a >= b; }
  static M Eq(V a, V b) { return a == b; }
  static V Select(M m, V a, V b) { return m ? a : b; }
  static M And(M a, M b) { return a && b; }
  static M Or(M a, M b) { return a || b; }
  static M AndNot(M not_a, M b) { return !not_a && b; }
  static M Not(M a) { return !a; }
  static M False() { return false; }
  static M True() { return true; }
  static bool None(M m) { return !m; }
  /// Whether a stage may stop here because every lane is settled: one lane stops as soon as
  /// its fate is known; vectors run every lane to the end of the stage (no branch).
  static bool Stop(M settled) { return settled; }
  // Integer lanes.
  static I ISet(int64_t x) { return x; }
  static I IAdd(I a, I b) { return a + b; }
  static I ISub(I a, I b) { return a - b; }
  static MI ILt(I a, I b) { return a < b; }
  static MI IGt(I a, I b) { return a > b; }
  static MI IEq(I a, I b) { return a == b; }
  static I ISelect(MI m, I a, I b) { return m ? a : b; }
  static MI IAnd(MI a, MI b) { return a && b; }
  static MI ToIMask(M m) { return m; }
  static M ToMask(MI m) { return m; }
  static bool INone(MI m) { return !m; }
  static I ToInt(V x) { return static_cast<int64_t>(x); }  ///< truncation
  static V ToDouble(I x) { return static_cast<double>(x); }
  static V Gather(const double* p, I i) { return p[i]; }
  template <class G>
  static I GatherI(const G* p, I i) {
    return p[i];
  }
};

}  // namespace stages
}  // namespace raymatch::simulate
