// Mie coefficients, efficiencies and amplitudes against published values.
//
// Sources: W. J. Wiscombe's MIEV0 test cases (NCAR TN-140+STR 1979, "Mie scattering
// calculations"; the answers of his test driver MVTstNew.f, block CHEKMI, computed at 14 digits,
// printed to 7), and Bohren & Huffman's BHMIE example (appendix A: m = 1.55, radius 0.525 um,
// wavelength 0.6328 um). Wiscombe writes an absorbing index m = n - ik and his S1, S2 are the
// complex conjugates of Bohren & Huffman's (m = n + ik), which raymatch uses: the expected S
// values below are conjugated. The tolerance is the printed digits: half a unit in the 7th
// significant digit (5e-7 relative, 1e-6 allowed for the rounding of both sides).
#include "raymatch/simulate/mie.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <utility>

namespace raymatch::simulate {
namespace {

constexpr double kPrinted = 1e-6;  // relative: 7 printed significant digits

struct EfficiencyCase {
  double n, k, x, q_ext, q_sca, g_q_sca;  // g_q_sca: Wiscombe's GQSC = g x Qsca (0: not printed)
};

// MVTstNew.f, TestQE / TestQS / TestGQ (cases 5-19 that are dielectric or absorbing spheres).
const EfficiencyCase kWiscombe[] = {
    {0.75, 0, 0.099, 7.417859e-06, 7.417859e-06, 0},
    {0.75, 0, 0.101, 8.033542e-06, 8.033542e-06, 0},
    {0.75, 0, 10, 2.232265, 2.232265, 0},
    {0.75, 0, 1000, 1.997908, 1.997908, 0},
    {1.33, 1e-5, 1, 9.395198e-02, 9.392330e-02, 0},
    {1.33, 1e-5, 100, 2.101321, 2.096594, 0},
    {1.5, 1, 0.055, 1.014910e-01, 1.131687e-05, 0},
    {1.5, 1, 0.056, 1.033467e-01, 1.216311e-05, 0},
    {1.5, 1, 1, 2.336321, 6.634538e-01, 0},
    {1.5, 1, 100, 2.097502, 1.283697, 0},
    {1.5, 1, 10000, 2.004368, 1.236574, 0},
    {10, 10, 1, 2.532993, 2.049405, 0},
    {10, 10, 100, 2.071124, 1.836785, 0},
    {1.33, 1e-5, 10000, 2.004089, 1.723857, 0},
    // MIEV0.f's own self-test (TESTMI): x = 10, m = 1.5 - 0.1i, GQSC = 1.139235.
    {1.5, 0.1, 10, 2.459791, 1.235144, 1.139235},
};

TEST(Mie, EfficienciesMatchWiscombesTestCases) {
  for (const auto& c : kWiscombe) {
    const MieEfficiencies e = Efficiencies(ComputeMie({c.n, c.k}, c.x));
    SCOPED_TRACE("m = " + std::to_string(c.n) + " + " + std::to_string(c.k) +
                 "i, x = " + std::to_string(c.x));
    EXPECT_NEAR(e.q_ext, c.q_ext, kPrinted * c.q_ext);
    EXPECT_NEAR(e.q_sca, c.q_sca, kPrinted * c.q_sca);
    if (c.g_q_sca > 0) EXPECT_NEAR(e.g * e.q_sca, c.g_q_sca, kPrinted * c.g_q_sca);
  }
}

// Non-absorbing m = 1.5 up to x = 5000 (Wiscombe's tech note, as printed to 7 digits in the
// POLARIS code's transcription of TN-140 p. A22): Qext and g. These need up to 5000 + 4.05 *
// 5000^(1/3) + 2 = 5071 terms: the downward recurrence and the upward Riccati-Bessel
// recurrence must both stay stable that far.
TEST(Mie, LargeSizeParametersStayStable) {
  const struct {
    double x, q, g;
  } kCases[] = {{10, 2.881999, 0.742913},
                {100, 2.094388, 0.818246},
                {1000, 2.013945, 0.827882},
                {5000, 2.008650, 0.829592}};
  for (const auto& c : kCases) {
    const MieCoefficients mc = ComputeMie({1.5, 0}, c.x);
    EXPECT_EQ(mc.terms(), MieTerms(c.x));
    const MieEfficiencies e = Efficiencies(mc);
    EXPECT_NEAR(e.q_ext, c.q, kPrinted * c.q) << "x = " << c.x;
    EXPECT_NEAR(e.q_sca, c.q, kPrinted * c.q) << "x = " << c.x;
    EXPECT_NEAR(e.g, c.g, 1.5e-6) << "x = " << c.x;
  }
  EXPECT_EQ(MieTerms(5000), 5071);
}

TEST(Mie, BohrenHuffmanExample) {
  const double x = 2 * M_PI * 0.525 / 0.6328;  // 5.21282 ("5.213" in print)
  const MieCoefficients c = ComputeMie({1.55, 0}, x);
  const MieEfficiencies e = Efficiencies(c);
  EXPECT_NEAR(e.q_ext, 3.10543, 5e-6);
  EXPECT_NEAR(e.q_sca, 3.10543, 5e-6);
  EXPECT_NEAR(e.q_back, 2.92534, 5e-6);
  // Appendix A's table: S11 / S11(0) and POL = -S12 / S11 (6 printed digits).
  auto s11 = [&](double deg, double* pol) {
    const MieAmplitudes s = Amplitudes(c, deg * M_PI / 180);
    const double a = std::norm(s.s1), b = std::norm(s.s2);
    *pol = (a - b) / (a + b);  // S12 = (|S2|^2 - |S1|^2) / 2
    return (a + b) / 2;
  };
  double pol0;
  const double ref = s11(0, &pol0);
  const struct {
    double deg, s11, pol;
  } kRows[] = {{9, 0.785390, -0.459811e-02},
               {36, 0.355355e-01, -0.534997},
               {54, 0.574313e-01, 0.477927e-01},
               {90, 0.124601e-01, 0.230462},
               {180, 0.383189e-01, 0}};
  for (const auto& r : kRows) {
    double pol;
    EXPECT_NEAR(s11(r.deg, &pol) / ref, r.s11, 5e-6 * r.s11) << r.deg << " deg";  // 6 digits
    EXPECT_NEAR(pol, r.pol, 2e-6) << r.deg << " deg";
  }
}

// Amplitudes in Wiscombe's convention (MVTstNew.f TestS1/TestS2), conjugated to Bohren and
// Huffman's.
TEST(Mie, AmplitudesMatchWiscombesTables) {
  const struct {
    double n, k, x, deg;
    Complex s1, s2;  // Wiscombe's values
  } kRows[] = {
      {1.5, 1, 1, 0, {5.840802e-01, 1.905153e-01}, {5.840802e-01, 1.905153e-01}},
      {1.5, 1, 1, 30, {5.657020e-01, 1.871997e-01}, {5.001610e-01, 1.456112e-01}},
      {1.5, 1, 1, 60, {5.175251e-01, 1.784426e-01}, {2.879639e-01, 4.105398e-02}},
      {1.5, 1, 1, 90, {4.563396e-01, 1.671665e-01}, {3.622847e-02, -6.182646e-02}},
      {1.5, 1, 1, 180, {3.488438e-01, 1.468286e-01}, {-3.488438e-01, -1.468286e-01}},
      {0.75, 0, 10, 0, {5.580662e+01, -9.758097e+00}, {5.580662e+01, -9.758097e+00}},
      {0.75, 0, 10, 30, {-7.672879e+00, 1.087317e+01}, {-1.092923e+01, 9.629667e+00}},
      {0.75, 0, 10, 60, {3.587894e+00, -1.756177e+00}, {3.427411e+00, 8.082691e-02}},
      {0.75, 0, 10, 90, {-1.785905e+00, -5.232828e-02}, {-5.148748e-01, -7.027288e-01}},
      // MIEV0.f's self-test: x = 10, m = 1.5 - 0.1i at mu = -0.7660444 (140 deg).
      {1.5, 0.1, 10, 140, {-0.1548380, -1.128972}, {0.05669755, 0.5425681}},
  };
  for (const auto& r : kRows) {
    const MieAmplitudes s = Amplitudes(ComputeMie({r.n, r.k}, r.x), r.deg * M_PI / 180);
    // 7 printed digits of the larger amplitude (a sum's rounding scales with its largest terms;
    // MIEV0's self-test row is 1.3e-6 of |S2| off in Re S2).
    const double tol1 = 2e-6 * std::max(std::abs(r.s1), std::abs(r.s2)), tol2 = tol1;
    SCOPED_TRACE("m = " + std::to_string(r.n) + ", x = " + std::to_string(r.x) + ", angle " +
                 std::to_string(r.deg));
    EXPECT_NEAR(std::abs(s.s1 - std::conj(r.s1)), 0, tol1) << s.s1;
    EXPECT_NEAR(std::abs(s.s2 - std::conj(r.s2)), 0, tol2) << s.s2;
  }
}

// The optical theorem ties the forward amplitude to extinction: Q_ext = 4 Re S(0) / x^2
// (Bohren and Huffman eq. 4.76), an identity between two different sums.
TEST(Mie, OpticalTheoremHolds) {
  for (double x : {0.3, 3.0, 30.0, 313.0}) {
    const MieCoefficients c = ComputeMie({1.33, 0.002}, x);
    EXPECT_NEAR(4 * Amplitudes(c, 0).s1.real() / (x * x), Efficiencies(c).q_ext, 1e-10) << x;
  }
}

// The scattered power is the integral of (|S1|^2 + |S2|^2) / 2 over the sphere, / k^2: Q_sca =
// 2 / x^2 integral_0^pi (|S1|^2 + |S2|^2) / 2 sin theta d theta, integrated here on the table
// (so the table's interpolation is tested too) by Simpson's rule on a grid much finer than
// the amplitudes' oscillation.
TEST(Mie, TableIntegratesToTheScatteringEfficiency) {
  for (double x : {5.0, 120.0}) {
    const MieCoefficients c = ComputeMie({1.4, 0}, x);
    const MieTable t(c, M_PI);
    const int n = 200000;
    const double h = M_PI / n;
    double sum = 0;
    for (int i = 0; i <= n; ++i) {
      const MieAmplitudes s = t.At(i * h);
      const double f = (std::norm(s.s1) + std::norm(s.s2)) / 2 * std::sin(i * h);
      sum += f * (i == 0 || i == n ? 1 : (i % 2 ? 4 : 2));
    }
    const double q = 2 / (x * x) * sum * h / 3;
    EXPECT_NEAR(q, Efficiencies(c).q_sca, 2e-6 * q) << x;
  }
}

TEST(Mie, TableInterpolatesTheAmplitudes) {
  const MieCoefficients c = ComputeMie({1.33, 0}, 313);
  const MieTable t(c, 1.2);
  const double s0 = std::abs(Amplitudes(c, 0).s1);
  double worst = 0;
  for (double th = 0.0003; th < 1.2; th += 0.0173) {
    const MieAmplitudes a = t.At(th), b = Amplitudes(c, th);
    worst = std::max({worst, std::abs(a.s1 - b.s1), std::abs(a.s2 - b.s2)});
  }
  EXPECT_LT(worst, 1e-5 * s0);  // (x step)^4 with step 0.05 / x
}

TEST(Mie, RejectsImpossibleInput) {
  EXPECT_THROW(ComputeMie({1.33, 0}, 0), std::invalid_argument);
  EXPECT_THROW(ComputeMie({1.33, -0.1}, 1), std::invalid_argument);
  EXPECT_THROW(ComputeCoatedMie({1, 0}, 0, {1.33, 0}, 10), std::invalid_argument);
  EXPECT_THROW(ComputeCoatedMie({1, 0}, 11, {1.33, 0}, 10), std::invalid_argument);
  EXPECT_THROW(ComputeCoatedMie({1, -0.1}, 5, {1.33, 0}, 10), std::invalid_argument);
}

// Coated spheres. Published: the water sphere coated with soot of W. Yang, Appl. Opt. 42, 1710
// (2003) (core m 1.33, shell 1.59 + 0.66i, the shell 1 % of the volume: x_core = 0.99^(1/3) x),
// as computed by scattnlay (O. Pena and U. Pal, Comput. Phys. Commun. 180, 2348 (2009), its
// test02 output, printed to 5 decimals). Columns: x, Qext, Qsca, Qback. (That output's g, from
// its radiation-pressure efficiency, is 2-10 % below the g of these coefficients, which
// Bohren and Huffman's closed form at 60 digits also gives: 0.22747 at x = 1.1, 0.74470 at
// 10.1; g is checked against the closed form below.)
TEST(CoatedMie, MatchesTheSootCoatedWaterDropOfYangAndScattnlay) {
  const struct {
    double x, q_ext, q_sca, q_back;
  } kRows[] = {{1.1, 0.14896, 0.13070, 0.10194},
               {10.1, 2.11652, 1.91869, 0.21450},
               {50.1, 2.02546, 1.57718, 0.38868},
               {99.85, 2.09451, 1.50760, 0.78482}};
  constexpr double kFiveDecimals = 6e-6;  // half a unit of the 5th decimal, and our rounding
  for (const auto& r : kRows) {
    const MieEfficiencies e =
        Efficiencies(ComputeCoatedMie({1.33, 0}, std::cbrt(0.99) * r.x, {1.59, 0.66}, r.x));
    SCOPED_TRACE("x = " + std::to_string(r.x));
    EXPECT_NEAR(e.q_ext, r.q_ext, kFiveDecimals);
    EXPECT_NEAR(e.q_sca, r.q_sca, kFiveDecimals);
    EXPECT_NEAR(e.q_back, r.q_back, kFiveDecimals);
  }
}

// Transparent coated spheres of this microscope's kind against Bohren and Huffman's closed form
// (sec. 8.1, eqs. 8.1-8.2) evaluated at 60 digits with mpmath's Bessel functions
// (tests/simulate/data/coated_mie_reference.py prints these): efficiencies and S1, S2 to 12
// digits, here to 1e-9 relative (the double-precision recursion over up to 342 terms).
TEST(CoatedMie, MatchesTheClosedFormAtHighPrecision) {
  const struct {
    Complex m_core;
    double x_core;
    Complex m_shell;
    double x, q_ext, q_sca, q_back, g;
    Complex s1_10, s2_10, s1_90, s2_90;  // at 10 and 90 degrees
  } kCases[] = {
      // an air bubble in a water drop in air
      {{1, 0},
       20,
       {1.333, 0},
       50,
       2.49059432207,
       2.49059432207,
       0.599683208468,
       0.870066782122,
       {18.3117071001, -47.6078760114},
       {19.1060007376, -46.2923680494},
       {2.88976533844, -6.49831749057},
       {-7.90356462669, 1.84587559456}},
      // the sample's 46 um drop (size parameter 313) with a bubble of a third of its radius
      {{1, 0},
       100,
       {1.33885, 0},
       313,
       1.98937038699,
       1.98937038699,
       0.7141738317,
       0.856347539079,
       {136.939808431, 230.691766799},
       {194.067994876, 220.898021427},
       {-5.58426113019, -15.3160812433},
       {15.3955587351, -0.820767053106}},
      // a cell in water: an absorbing nucleus (1.39 + 0.001i) in cytoplasm (1.37)
      {{1.39 / 1.335, 0.001},
       8,
       {1.37 / 1.335, 0},
       30,
       1.12540396957,
       1.12378474603,
       0.000147169325322,
       0.994846969413,
       {-3.81319561201, 40.982310357},
       {-3.59954176703, 40.6399121899},
       {-0.855513909835, 0.344237487061},
       {-0.0928761845306, 0.0169352507675}},
  };
  constexpr double kRel = 1e-9;
  for (const auto& c : kCases) {
    SCOPED_TRACE("x_core " + std::to_string(c.x_core) + ", x " + std::to_string(c.x));
    const MieCoefficients mc = ComputeCoatedMie(c.m_core, c.x_core, c.m_shell, c.x);
    EXPECT_EQ(mc.terms(), MieTerms(c.x));
    const MieEfficiencies e = Efficiencies(mc);
    EXPECT_NEAR(e.q_ext, c.q_ext, kRel * c.q_ext);
    EXPECT_NEAR(e.q_sca, c.q_sca, kRel * c.q_sca);
    EXPECT_NEAR(e.q_back, c.q_back, kRel * c.q_back);
    EXPECT_NEAR(e.g, c.g, kRel);
    const MieAmplitudes a10 = Amplitudes(mc, 10 * M_PI / 180), a90 = Amplitudes(mc, M_PI / 2);
    EXPECT_LT(std::abs(a10.s1 - c.s1_10), kRel * std::abs(c.s1_10));
    EXPECT_LT(std::abs(a10.s2 - c.s2_10), kRel * std::abs(c.s2_10));
    EXPECT_LT(std::abs(a90.s1 - c.s1_90), kRel * std::abs(c.s1_90));
    EXPECT_LT(std::abs(a90.s2 - c.s2_90), kRel * std::abs(c.s2_90));
  }
}

// Up to x = 5000 (a 370 um drop in air with a bubble): a lossless coated sphere removes exactly
// what it scatters, term by term (Re a_n = |a_n|^2), which a recursion that lost its stability
// would break by order 1; the efficiencies are near 2 (the extinction paradox). Measured: the
// worst term is off by 2.3e-11 at x = 1000 and 2.7e-8 at x = 5000 (round-off that Q_n carries
// over the terms that reach the core; a homogeneous sphere stays at 3e-16).
TEST(CoatedMie, LargeSizeParametersStayStable) {
  for (auto [x, tol] : {std::pair{1000.0, 1e-9}, std::pair{5000.0, 1e-6}}) {
    const MieCoefficients c = ComputeCoatedMie({1, 0}, 0.4 * x, {1.333, 0}, x);
    double worst = 0;
    for (int n = 0; n < c.terms(); ++n)
      worst = std::max({worst, std::abs(c.a[n].real() - std::norm(c.a[n])),
                        std::abs(c.b[n].real() - std::norm(c.b[n]))});
    EXPECT_LT(worst, tol) << "x = " << x;
    const MieEfficiencies e = Efficiencies(c);
    EXPECT_NEAR(e.q_ext, e.q_sca, tol) << "x = " << x;
    EXPECT_NEAR(e.q_ext, 2, 0.05) << "x = " << x;
  }
}

// The limits that make a coated sphere a homogeneous one: the same index inside and out; a core
// that fills the shell; a shell matched to the medium (then the core alone scatters: the same
// cross sections, x_core^2 Q, over the core's own terms).
TEST(CoatedMie, ReducesToTheHomogeneousSphere) {
  auto same = [](const MieCoefficients& a, const MieCoefficients& b, double tol) {
    ASSERT_EQ(a.terms(), b.terms());
    for (int n = 0; n < a.terms(); ++n) {
      EXPECT_LT(std::abs(a.a[n] - b.a[n]), tol) << "a_" << n + 1;
      EXPECT_LT(std::abs(a.b[n] - b.b[n]), tol) << "b_" << n + 1;
    }
  };
  for (double x : {3.0, 60.0, 400.0}) {
    SCOPED_TRACE("x = " + std::to_string(x));
    same(ComputeCoatedMie({1.392, 0}, 0.4 * x, {1.392, 0}, x), ComputeMie({1.392, 0}, x), 1e-11);
    same(ComputeCoatedMie({1.2, 0.01}, x, {1.6, 0}, x), ComputeMie({1.2, 0.01}, x), 1e-11);
    const MieEfficiencies core = Efficiencies(ComputeMie({0.75, 0}, 0.5 * x));
    const MieEfficiencies coated = Efficiencies(ComputeCoatedMie({0.75, 0}, 0.5 * x, {1, 0}, x));
    EXPECT_NEAR(coated.q_sca * x * x, core.q_sca * 0.25 * x * x, 1e-9 * core.q_sca * x * x);
    EXPECT_NEAR(coated.q_ext * x * x, core.q_ext * 0.25 * x * x, 1e-9 * core.q_ext * x * x);
  }
}

}  // namespace
}  // namespace raymatch::simulate
