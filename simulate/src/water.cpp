#include "raymatch/simulate/water.h"

#include <cmath>

namespace raymatch::simulate {

WaterIndex WaterRefractiveIndex(double T, double rho, double lambda_um) {
  constexpr double a0 = 0.244257733, a1 = 9.74634476e-3, a2 = -3.73234996e-3, a3 = 2.68678472e-4,
                   a4 = 1.58920570e-3, a5 = 2.45934259e-3, a6 = 0.900704920, a7 = -1.66626219e-2;
  constexpr double lam_uv = 0.2292020, lam_ir = 5.432937;
  const double rr = rho / 1000.0, tr = T / 273.15, lr = lambda_um / 0.589, l2 = lr * lr;
  const double rhs = a0 + a1 * rr + a2 * tr + a3 * l2 * tr + a4 / l2 + a5 / (l2 - lam_uv * lam_uv) +
                     a6 / (l2 - lam_ir * lam_ir) + a7 * rr * rr;
  const double A = rr * rhs;
  WaterIndex out;
  out.n = std::sqrt((1 + 2 * A) / (1 - A));
  out.in_range =
      T >= 261.15 && T <= 773.15 && rho >= 0 && rho <= 1060 && lambda_um >= 0.2 && lambda_um <= 1.1;
  return out;
}

double WaterDensityTanaka(double T) {
  constexpr double a1 = -3.983035, a2 = 301.797, a3 = 522528.9, a4 = 69.34881, a5 = 999.974950;
  const double t = T - 273.15;
  return a5 * (1 - (t + a1) * (t + a1) * (t + a2) / (a3 * (t + a4)));
}

}  // namespace raymatch::simulate
