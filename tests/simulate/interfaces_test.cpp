// Interface physics against closed forms (Born & Wolf ch. 1.5).
#include "raymatch/simulate/interfaces.h"

#include <gtest/gtest.h>

#include <complex>

#include "raymatch/simulate/water.h"

namespace raymatch::simulate {
namespace {

constexpr double kPi = 3.14159265358979323846;

TEST(Fresnel, NormalIncidence) {
  // R = ((n-1)/(n+1))^2 = 0.04 for n = 1.5; same from either side.
  EXPECT_NEAR(FresnelReflectance(1.0, 1.5, 1.0), 0.04, 1e-15);
  EXPECT_NEAR(FresnelReflectance(1.5, 1.0, 1.0), 0.04, 1e-15);
  EXPECT_NEAR(FresnelReflectance(1.0, 1.333, 1.0), std::pow(0.333 / 2.333, 2), 1e-15);
}

TEST(Fresnel, BrewsterAngleHasNoPReflection) {
  for (double n2 : {1.333, 1.5, 2.4}) {
    const double tb = std::atan(n2 / 1.0);  // tan(tB) = n2/n1
    const double ci = std::cos(tb), ct = std::sqrt(1 - std::pow(std::sin(tb) / n2, 2));
    const FresnelCoefficients f = Fresnel(1.0, n2, ci, ct);
    EXPECT_NEAR(f.rp, 0.0, 1e-14) << n2;
    EXPECT_GT(f.Rs, 0.01);
  }
}

TEST(Fresnel, TotalInternalReflectionBeyondCriticalAngle) {
  const double n1 = 1.5, n2 = 1.0, tc = std::asin(n2 / n1);
  const Vec3 n(0, 0, -1);  // faces a ray travelling +z
  for (double dt : {-1e-6, 1e-6}) {
    const double t = tc + dt;
    const Vec3 d(std::sin(t), 0, std::cos(t));
    Vec3 out;
    double cos_t;
    const bool refracted = Refract(d, n, n1 / n2, &out, &cos_t);
    EXPECT_EQ(refracted, dt < 0) << "angle offset " << dt;
    if (dt > 0) EXPECT_DOUBLE_EQ(FresnelReflectance(n1, n2, std::cos(t)), 1.0);
  }
}

// R + T = 1 with T from the transmission amplitudes t_s = 2 n1 ci / (n1 ci + n2 ct),
// t_p = 2 n1 ci / (n2 ci + n1 ct) and the power factor n2 ct / (n1 ci): an independent formula.
TEST(Fresnel, EnergyIsConserved) {
  for (double n2 : {1.2, 1.333, 1.5, 2.0})
    for (double ti = 0; ti < kPi / 2; ti += 0.05) {
      for (auto [a, b] : {std::pair{1.0, n2}, std::pair{n2, 1.0}}) {
        const double ci = std::cos(ti), s2 = std::pow(a / b * std::sin(ti), 2);
        if (s2 >= 1) continue;
        const double ct = std::sqrt(1 - s2);
        const double ts = 2 * a * ci / (a * ci + b * ct), tp = 2 * a * ci / (b * ci + a * ct);
        const double T = b * ct / (a * ci) * 0.5 * (ts * ts + tp * tp);
        EXPECT_NEAR(Fresnel(a, b, ci, ct).R() + T, 1.0, 1e-13) << a << "->" << b << " " << ti;
      }
    }
}

// The complex amplitudes below the critical angle are the real ones (and the transmission
// amplitudes of the test above); beyond it the reflection is total (`total`), |r| = 1 with B&W's
// phases (eq. 1.5.58), and just past the critical angle the phases start from 0 (continuity).
TEST(Fresnel, ComplexAmplitudesAreTheRealOnesAndTheTotalReflectionPhases) {
  for (double n2 : {1.0, 1.333, 1.5})
    for (double ti = 0; ti < kPi / 2; ti += 0.01)
      for (auto [a, b] : {std::pair{1.0, n2}, std::pair{1.5, n2 / 1.6}}) {
        const double ci = std::cos(ti), s2 = std::pow(a / b * std::sin(ti), 2);
        const FresnelAmplitudes c = ComplexFresnel(a, b, ci);
        ASSERT_EQ(c.total, s2 > 1) << a << "->" << b << " " << ti;
        if (s2 <= 1) {
          const double ct = std::sqrt(1 - s2);
          const FresnelCoefficients f = Fresnel(a, b, ci, ct);
          // (To rounding: the two compute cos t_t from sin^2 in other orders, and near the
          // critical angle its square root amplifies the difference.)
          EXPECT_NEAR(std::abs(c.rs - f.rs), 0, 1e-12);
          EXPECT_NEAR(std::abs(c.rp - f.rp), 0, 1e-12);
          EXPECT_NEAR(std::abs(c.ts - 2 * a * ci / (a * ci + b * ct)), 0, 1e-12);
          EXPECT_NEAR(std::abs(c.tp - 2 * a * ci / (b * ci + a * ct)), 0, 1e-12);
          EXPECT_EQ(c.rs.imag(), 0.0);
          continue;
        }
        const double n = b / a, root = std::sqrt(std::sin(ti) * std::sin(ti) - n * n);
        EXPECT_NEAR(std::abs(c.rs), 1, 1e-14);
        EXPECT_NEAR(std::abs(c.rp), 1, 1e-14);
        EXPECT_NEAR(std::arg(c.rs), -2 * std::atan(root / ci), 1e-13) << ti;
        EXPECT_NEAR(std::arg(c.rp), -2 * std::atan(root / (n * n * ci)), 1e-13) << ti;
      }
  const double n1 = 1.5, n2 = 1.0, tc = std::asin(n2 / n1);
  const FresnelAmplitudes past = ComplexFresnel(n1, n2, std::cos(tc + 1e-9));
  EXPECT_TRUE(past.total);
  EXPECT_LT(std::abs(std::arg(past.rs)), 1e-3);
  EXPECT_LT(std::abs(std::arg(past.rp)), 1e-3);
}

// Fresnel's rhomb (Born & Wolf sec. 1.5.4): in glass of n = 1.51 the phase difference between
// p and s after total reflection is 45 degrees at 48 deg 37' and 54 deg 37' of incidence, so two
// reflections at 54 deg 37' turn linear light at 45 degrees into circular light. The difference
// follows tan(delta / 2) = cos t sqrt(sin^2 t - n^2) / sin^2 t (eq. 1.5.60), here from the
// amplitudes; the angles are the book's to a minute of arc (3e-4 rad).
TEST(Fresnel, TotalReflectionPhaseDifferenceIsFresnelsRhomb) {
  auto difference = [](double t) {
    const FresnelAmplitudes c = ComplexFresnel(1.51, 1.0, std::cos(t));
    return std::arg(c.rp / c.rs);
  };
  const double deg = kPi / 180;
  for (double t : {(48 + 37.0 / 60) * deg, (54 + 37.0 / 60) * deg}) {
    const double n = 1 / 1.51, s2 = std::sin(t) * std::sin(t);
    EXPECT_NEAR(std::tan(std::abs(difference(t)) / 2), std::cos(t) * std::sqrt(s2 - n * n) / s2,
                1e-13);
    // 45 degrees within what a minute of arc changes it (d delta / d theta < 2 here).
    EXPECT_NEAR(std::abs(difference(t)), 45 * deg, 2 * deg / 60) << t / deg;
  }
}

TEST(Snell, RoundTripRestoresDirectionAndObeysSnell) {
  const Vec3 n = Normalize(Vec3(0.3, -0.2, -1));
  for (double a = 0.05; a < 1.4; a += 0.1) {
    const Vec3 d = Normalize(-n + Vec3(std::sin(a), 0.4 * std::sin(a), 0) * 1.0);
    Vec3 t, back;
    double ct, ct2;
    ASSERT_TRUE(Refract(d, n, 1.0 / 1.5, &t, &ct));
    EXPECT_NEAR(Length(t), 1.0, 1e-14);
    // n1 sin t1 = n2 sin t2
    const double s1 = Length(Cross(d, n)), s2 = Length(Cross(t, n));
    EXPECT_NEAR(1.0 * s1, 1.5 * s2, 1e-14);
    // Leave through a parallel surface: back into index 1, same direction as before.
    ASSERT_TRUE(Refract(t, n, 1.5 / 1.0, &back, &ct2));
    EXPECT_NEAR(Length(back - d), 0.0, 1e-14);
  }
}

TEST(Water, IapwsReleaseCheckValue) {
  // IAPWS R9-97 test value: T = 298.15 K, rho = 997.047435 kg/m^3, 0.5893 um -> 1.33285819.
  const WaterIndex w = WaterRefractiveIndex(298.15, 997.047435, 0.5893);
  EXPECT_NEAR(w.n, 1.33285819, 5e-9);
  EXPECT_TRUE(w.in_range);
  EXPECT_FALSE(WaterRefractiveIndex(298.15, 1100, 0.5893).in_range);  // strong shock
}

TEST(Water, TanakaDensity) {
  // Tanaka et al. 2001, Table: 4 degC maximum ~999.975, 20 degC 998.2067, 25 degC 997.0470.
  EXPECT_NEAR(WaterDensityTanaka(293.15), 998.2067, 2e-3);
  EXPECT_NEAR(WaterDensityTanaka(298.15), 997.0470, 2e-3);
  EXPECT_GT(WaterDensityTanaka(277.13), WaterDensityTanaka(283.15));
}

}  // namespace
}  // namespace raymatch::simulate
