#pragma once
// Interface physics: Snell refraction, reflection, dielectric Fresnel coefficients.
//
// Sign convention: `d` is the unit propagation direction of the incoming ray; `n` is the unit
// surface normal on the side the ray arrives from (Dot(d, n) < 0). `eta` = n1 / n2 with n1 the
// index on the incoming side. All functions are branch-light and allocation-free.
#include <algorithm>
#include <cmath>
#include <complex>

#include "raymatch/core/vec.h"

namespace raymatch::simulate {

/// Mirror reflection of `d` about the normal `n` (either orientation).
inline Vec3 Reflect(const Vec3& d, const Vec3& n) { return d - n * (2 * Dot(d, n)); }

/// Snell refraction. Returns false on total internal reflection (n1 sin t1 > n2), leaving
/// `*t` untouched. `cos_i` = -Dot(d, n) > 0. On success `*cos_t` is the transmitted cosine.
inline bool Refract(const Vec3& d, const Vec3& n, double eta, Vec3* t, double* cos_t) {
  const double cos_i = -Dot(d, n);
  const double sin2_t = eta * eta * std::max(0.0, 1.0 - cos_i * cos_i);
  if (sin2_t >= 1.0) return false;
  const double ct = std::sqrt(1.0 - sin2_t);
  *t = d * eta + n * (eta * cos_i - ct);
  *cos_t = ct;
  return true;
}

/// Fresnel amplitude and power coefficients for s and p polarisation (Born & Wolf sign
/// convention for r_p: r_p = (n2 cos_i - n1 cos_t) / (n2 cos_i + n1 cos_t)). cos_i, cos_t >= 0.
struct FresnelCoefficients {
  double rs, rp;                                ///< amplitude reflection coefficients
  double Rs, Rp;                                ///< power reflectances
  double R() const { return 0.5 * (Rs + Rp); }  ///< unpolarised reflectance
};

inline FresnelCoefficients Fresnel(double n1, double n2, double cos_i, double cos_t) {
  FresnelCoefficients f;
  f.rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t);
  f.rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t);
  f.Rs = f.rs * f.rs;
  f.Rp = f.rp * f.rp;
  return f;
}

/// The complex Fresnel amplitude coefficients of a ray with incidence cosine cos_i from n1 into
/// n2, also beyond the critical angle, for fields exp(i (k.r - omega t)) (Born & Wolf sec. 1.5;
/// the same r_p sign as Fresnel): the phase a ray carries across the surface, for physical
/// optics. Beyond the critical angle the transmitted cosine is i sqrt(sin^2 t_t - 1) (the
/// evanescent wave decays away from the surface), |r_s| = |r_p| = 1, and the phases are
/// tan(delta_s / 2) = -sqrt(sin^2 t_i - n^2) / cos t_i and
/// tan(delta_p / 2) = -sqrt(sin^2 t_i - n^2) / (n^2 cos t_i) with n = n2 / n1 (B&W eq. 1.5.58
/// for the principal branch, delta in (-pi, 0]).
struct FresnelAmplitudes {
  std::complex<double> rs, rp, ts, tp;
  bool total = false;  ///< total internal reflection (no transmitted power)
};

inline FresnelAmplitudes ComplexFresnel(double n1, double n2, double cos_i) {
  const double sin2_t = (n1 / n2) * (n1 / n2) * std::max(0.0, 1.0 - cos_i * cos_i);
  FresnelAmplitudes f;
  f.total = sin2_t > 1.0;
  const std::complex<double> ct =
      f.total ? std::complex<double>(0, std::sqrt(sin2_t - 1)) : std::sqrt(1.0 - sin2_t);
  const std::complex<double> a = n1 * cos_i, b = n2 * ct;  // s: n cos of each side
  const std::complex<double> c = n2 * cos_i, d = n1 * ct;  // p: the indices swapped
  f.rs = (a - b) / (a + b), f.ts = 2.0 * a / (a + b);
  f.rp = (c - d) / (c + d), f.tp = 2.0 * a / (c + d);
  return f;
}

/// Unpolarised reflectance for a ray with incidence cosine cos_i going from n1 into n2;
/// returns 1 beyond the critical angle (total internal reflection).
inline double FresnelReflectance(double n1, double n2, double cos_i) {
  const double eta = n1 / n2;
  const double sin2_t = eta * eta * std::max(0.0, 1.0 - cos_i * cos_i);
  if (sin2_t >= 1.0) return 1.0;
  return Fresnel(n1, n2, cos_i, std::sqrt(1.0 - sin2_t)).R();
}

}  // namespace raymatch::simulate
