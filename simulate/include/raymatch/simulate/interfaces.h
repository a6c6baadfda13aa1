#pragma once
// Interface physics: Snell refraction, reflection, dielectric Fresnel coefficients.
//
// Sign convention: `d` is the unit propagation direction of the incoming ray; `n` is the unit
// surface normal on the side the ray arrives from (Dot(d, n) < 0). `eta` = n1 / n2 with n1 the
// index on the incoming side. All functions are branch-light and allocation-free.
#include <algorithm>
#include <cmath>

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

/// Unpolarised reflectance for a ray with incidence cosine cos_i going from n1 into n2;
/// returns 1 beyond the critical angle (total internal reflection).
inline double FresnelReflectance(double n1, double n2, double cos_i) {
  const double eta = n1 / n2;
  const double sin2_t = eta * eta * std::max(0.0, 1.0 - cos_i * cos_i);
  if (sin2_t >= 1.0) return 1.0;
  return Fresnel(n1, n2, cos_i, std::sqrt(1.0 - sin2_t)).R();
}

}  // namespace raymatch::simulate
